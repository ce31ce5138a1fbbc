"""The event simulator: threshold model, exact ground truth against the core's warps, labels,
determinism, sensor effects, file layout and bad input."""

from __future__ import annotations

import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi import sim as sm
from cmax_taichi.sim.motions import default_theta
from cmax_taichi.testing.reference_warps import REFERENCE_WARPS

SMALL = (96, 72)
IDEAL = dict(threshold_sigma=0.0, refractory=0.0, noise_rate=0.0, contrast_threshold=0.3)
#: every registered model with a float64 NumPy twin (all built-ins): its exact motion is derived from it
WARPS = [w for w in cm.warp_names() if w in REFERENCE_WARPS]
SEGMENT = 0.08  # s, the window of a window-normalised model (mitrokhin4 with an angle); ignored by others


def _signed_thresholds(sim: sm.Simulator, rec: sm.SimulatedRecording) -> np.ndarray:
    xi, yi = rec.x.astype(int), rec.y.astype(int)
    return np.where(rec.p > 0, sim.c_pos[yi, xi], -sim.c_neg[yi, xi])


def _integrate(sim: sm.Simulator, rec: sm.SimulatedRecording) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel: (log-intensity change over the recording) - (sum of the events' signed thresholds),
    and the threshold that bounds it."""
    W, H = rec.sensor_size
    L0, _ = sim.render(rec.t_start)
    L1, _ = sim.render(rec.t_end)
    acc = np.zeros((H, W))
    np.add.at(acc, (rec.y.astype(int), rec.x.astype(int)), _signed_thresholds(sim, rec))
    resid = (L1 - L0) - acc
    return resid, np.where(resid > 0, sim.c_pos, sim.c_neg)


@pytest.mark.parametrize("sigma", [0.0, 0.1])
def test_events_of_a_pixel_integrate_to_its_log_intensity_change(sigma):
    scene = sm.warp_scene("se2", sensor_size=SMALL)
    sim = sm.Simulator(scene, sm.SimulatorConfig(**{**IDEAL, "threshold_sigma": sigma}))
    rec = sim.run(0.05)
    assert len(rec) > 5000
    resid, bound = _integrate(sim, rec)
    assert np.all(np.abs(resid) < bound + 1e-9)
    assert np.all((rec.t > 0.0) & (rec.t <= 0.05))
    assert set(np.unique(rec.labels)) == {0}
    if sigma:
        assert 0.07 < np.std(sim.c_pos) / 0.3 < 0.13


def test_several_thresholds_in_one_render_step_give_several_interpolated_events():
    # coarse renders: changes span several thresholds per step
    config = sm.SimulatorConfig(**IDEAL, step_px=20.0, step_log_change=50.0, max_step=0.01, min_step=1e-3)
    scene = sm.warp_scene("translation2", theta=(400.0, 0.0), sensor_size=SMALL)
    sim = sm.Simulator(scene, config)
    rec = sim.run(0.05)
    assert sim.n_steps == 5
    resid, bound = _integrate(sim, rec)
    assert np.all(np.abs(resid) < bound + 1e-9)
    # events of one pixel within one step have distinct interpolated times, strictly inside the step
    key = rec.y * SMALL[0] + rec.x
    step = np.floor(rec.t / 0.01 - 1e-9)
    _, counts = np.unique(np.stack([key, step]), axis=1, return_counts=True)
    assert counts.max() >= 3
    assert len(np.unique(rec.t)) > 0.9 * len(rec)


@pytest.mark.usefixtures("f64")  # the core's dense flow to 1e-8 px: whatever precision ran before
@pytest.mark.parametrize("warp", WARPS)
def test_ground_truth_motion_is_undone_by_the_core_warp(warp):
    """The displacement of the simulated motion over [t_a, t_b] equals the core's dense flow of the
    warp with theta_at(t_a), matched at the end positions (docs/FORMULAS.md, "Dense flow")."""
    W, H = SMALL
    cam = sm.default_camera(SMALL)
    motion = sm.Motion(warp, default_theta(warp), segment=SEGMENT)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    starts = (0.0, 0.037, 0.2)  # any window start: the truth is exact for every window of SEGMENT s
    for t_a in starts:
        for dt in (0.01, SEGMENT):
            theta = motion.theta_at(t_a)
            flow = cm.dense_flow(warp, theta, SMALL, camera=cam, duration=SEGMENT, dt=dt)
            # a point at the end position x was at y = x - flow(x) at t_a
            y0, y1 = xx - flow[0], yy - flow[1]
            D = motion.matrix(t_a + dt, cam) @ np.linalg.inv(motion.matrix(t_a, cam))
            q = np.tensordot(D, np.stack([y0, y1, np.ones_like(y0)]), axes=1)
            np.testing.assert_allclose(q[0] / q[2], xx, atol=1e-8)
            np.testing.assert_allclose(q[1] / q[2], yy, atol=1e-8)
            assert np.abs(flow).max() > 0.3


def test_forward_motion_parameters_grow_as_the_plane_approaches():
    m = sm.Motion("zoom1", (0.8,))
    assert m.theta_at(0.5)[0] == pytest.approx(0.8 / (1 - 0.4))
    m4 = sm.Motion("mitrokhin4", (10.0, -5.0, 0.5, 0.0))
    np.testing.assert_allclose(m4.theta_at(1.0), [20.0, -10.0, 1.0, 0.0], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("warp", WARPS)
def test_true_parameters_give_a_sharper_iwe_than_identity(warp):
    scene = sm.warp_scene(warp, sensor_size=SMALL, segment=SEGMENT)
    rec = sm.simulate(scene, SEGMENT, contrast_threshold=0.3, noise_rate=0.0)
    prob = cm.ContrastMaximization(rec.events(), warp, camera=scene.camera, t_ref=0.0)
    theta = rec.theta_at(0.0)
    value = prob.value(theta)
    assert value > 1.08 * prob.value(np.zeros_like(theta))
    # and it is (about) the best along the ray through the true parameters
    assert value >= max(prob.value(0.7 * theta), prob.value(1.3 * theta))


def test_labels_and_flow_follow_the_objects():
    from scipy import ndimage

    scene = sm.multi_object_scene((160, 120), n_objects=3, seed=1)
    rec = sm.simulate(scene, 0.06, contrast_threshold=0.3, noise_rate=2.0)
    labels = set(np.unique(rec.labels).tolist())
    assert labels == {-1, 0, 1, 2, 3}
    for t in (0.015, 0.045):
        _, label_map = rec.simulator.render(t)
        near = np.abs(rec.t - t) < 1e-3
        xi, yi = rec.x.astype(int), rec.y.astype(int)
        for k in (1, 2, 3):
            grown = ndimage.binary_dilation(label_map == k, np.ones((3, 3)))
            sel = near & (rec.labels == k)
            assert sel.sum() > 20
            assert np.all(grown[yi[sel], xi[sel]]), f"object {k} events outside the object"
        inner = ndimage.binary_erosion(label_map > 0, np.ones((3, 3)))
        sel = near & (rec.labels == 0)
        assert not np.any(inner[yi[sel], xi[sel]]), "background events inside an object"
        # the dense flow moves each pixel with the layer in front of it
        flow = rec.flow(t, t + 0.01)
        for k in range(4):
            m = label_map == k
            yy, xx = np.nonzero(m)
            expected = rec.displacement(t, t + 0.01, xx, yy, layer=k)
            np.testing.assert_allclose(flow[:, m], expected, atol=1e-12)


def test_same_seed_same_events_other_seed_other_events():
    scene = sm.warp_scene("translation2", sensor_size=SMALL)
    settings = dict(noise_rate=5.0, hot_pixel_fraction=0.002, threshold_sigma=0.05)
    a = sm.simulate(scene, 0.03, seed=3, **settings)
    b = sm.simulate(scene, 0.03, seed=3, **settings)
    c = sm.simulate(scene, 0.03, seed=4, **settings)
    for name in ("x", "y", "t", "p", "labels"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert len(a) != len(c) or not np.array_equal(a.t, c.t)


def test_noise_hot_pixels_and_refractory_period():
    W, H = SMALL
    scene = sm.warp_scene("translation2", sensor_size=SMALL)
    rec = sm.simulate(scene, 0.05, noise_rate=20.0, hot_pixel_fraction=0.001, hot_pixel_rate=1000.0)
    noise = rec.labels == -1
    expected = 20.0 * W * H * 0.05 + round(0.001 * W * H) * 1000.0 * 0.05
    assert abs(noise.sum() - expected) < 5 * np.sqrt(expected)
    # refractory: no pixel reports two scene events closer than the period
    rec = sm.simulate(scene, 0.05, refractory=4e-3, noise_rate=0.0, contrast_threshold=0.1)
    key = rec.y * W + rec.x
    order = np.lexsort((rec.t, key))
    same = np.diff(key[order]) == 0
    gaps = np.diff(rec.t[order])[same]
    assert gaps.size > 100 and gaps.min() >= 4e-3 - 1e-12


def test_write_and_read_the_mvsec_layout(tmp_path):
    import h5py

    scene = sm.multi_object_scene((120, 90), n_objects=2, seed=0)
    rec = sm.simulate(scene, 0.1)
    h5, npz = rec.write(tmp_path, "sim", frame_rate=32.0)
    assert h5.name == "sim_data.hdf5" and npz.name == "sim_gt_flow_dist.npz"
    with h5py.File(h5, "r") as f:
        ev = f["davis/left/events"][()]
        assert ev.shape == (len(rec), 4) and ev.dtype == np.float64
        np.testing.assert_array_equal(ev[:, 2], rec.t)
        assert set(np.unique(ev[:, 3])) == {-1.0, 1.0}
        np.testing.assert_array_equal(f["davis/left/labels"][()], rec.labels)
        assert f["davis/left"].attrs["fx"] == scene.camera.fx
        assert f["ground_truth"].attrs["warp"] == "translation2"
        assert f["ground_truth/theta"].shape == (4, 2)
        assert f["ground_truth/layers/1"].attrs["warp"] == scene.layers[1].motion.warp
    d = np.load(npz)
    ts = d["timestamps"]
    np.testing.assert_allclose(ts, np.arange(4) / 32.0)
    assert d["x_flow_dist"].shape == (4, 90, 120)
    flow = rec.flow(ts[1], ts[2])
    np.testing.assert_allclose(d["x_flow_dist"][1], flow[0], atol=1e-5)
    np.testing.assert_allclose(d["y_flow_dist"][1], flow[1], atol=1e-5)
    data = sm.read_simulation(h5)
    assert len(data.events) == len(rec) and data.warp == "translation2"
    assert data.flow.shape == (4, 2, 90, 120)
    # the dataset reader opens it too, with the intrinsics, and accumulates the flow over 2 frames
    from cmax_taichi.io import open_recording

    with open_recording(h5, sensor_size=(120, 90)) as r:
        assert r.format == "mvsec" and r.n_events == len(rec)
        assert r.camera.fx == scene.camera.fx
        acc = r.flow(ts[0], ts[2])
    exact = rec.flow(ts[0], ts[2])
    assert np.nanmedian(np.abs(acc - exact)) < 0.05


def test_indoor_flying_preset_has_mvsec_like_rates():
    rec = sm.simulate_preset("indoor_flying", duration=0.13)
    assert rec.sensor_size == (346, 260)
    n = np.count_nonzero(rec.t < 0.125)
    assert 20_000 < n < 45_000, n
    mag = np.hypot(*rec.flow(0.0, 0.125))  # dt = 4 frames at 32 Hz
    assert 2.0 < mag.mean() < 8.0


def test_scaled_preset_keeps_the_flow_relative_to_the_image():
    full = sm.preset_scene("driving")
    half = sm.preset_scene("driving", scale=0.5)
    assert half.sensor_size == (173, 130)
    np.testing.assert_allclose(
        half.layers[0].motion.theta, np.array(full.layers[0].motion.theta) * [0.5, 0.5, 1, 1]
    )
    f_full = cm.dense_flow("mitrokhin4", full.layers[0].motion.theta, full.sensor_size, duration=0.1, dt=0.1)
    f_half = cm.dense_flow("mitrokhin4", half.layers[0].motion.theta, half.sensor_size, duration=0.1, dt=0.1)
    ratio = np.abs(f_half).max() / np.abs(f_full).max()
    assert 0.45 < ratio < 0.55


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: sm.SimulatorConfig(contrast_threshold=0.0), "contrast_threshold"),
        (lambda: sm.SimulatorConfig(threshold_sigma=-0.1), "threshold_sigma"),
        (lambda: sm.SimulatorConfig(refractory=float("nan")), "refractory"),
        (lambda: sm.SimulatorConfig(hot_pixel_fraction=2.0), "hot_pixel_fraction"),
        (lambda: sm.SimulatorConfig(min_step=1.0, max_step=0.1), "min_step"),
        (lambda: sm.SimulatorConfig(seed=-1), "seed must be a whole number >= 0, got -1"),
        (lambda: sm.Motion("zoom1", (1.0, 2.0)), "takes 1 parameter"),
        (lambda: sm.Motion("nope", (1.0,)), "nope"),
        (lambda: sm.Motion("mitrokhin4", (1.0, 2.0, 0.1, 0.5)), "segment"),
        (lambda: sm.warp_scene("zoom1", sensor_size=(4, 4)), "at least 8x8"),
        (lambda: sm.warp_scene("translation2", texture="unknown"), "valid textures"),
        (lambda: sm.Layer(np.full((4, 4), 2.0), sm.Motion("translation2", (1, 1))), r"in \[0, 1\]"),
        (lambda: sm.preset_scene("mars"), "valid presets"),
        (lambda: sm.preset_scene("driving", scale=0.0), "scale"),
        (lambda: sm.simulate(sm.warp_scene("zoom1", (2.0,), sensor_size=SMALL), 0.5), "reaches the plane"),
        (lambda: sm.simulate(sm.warp_scene("translation2", sensor_size=SMALL), -1.0), "duration"),
    ],
)
def test_bad_parameters_give_clear_errors(make, message):
    with pytest.raises((ValueError, KeyError, TypeError), match=message):
        make()


def test_docs_simulator_example_runs(tmp_path, monkeypatch):
    """The example of docs/simulator.md runs as written."""
    import re
    from pathlib import Path

    page = Path(__file__).resolve().parents[1] / "docs" / "simulator.md"
    section = page.read_text().split("# Event simulator", 1)
    if len(section) < 2:
        pytest.fail("docs/simulator.md has no 'Event simulator' section")
    code = re.search(r"```python\n(.*?)```", section[1], re.S).group(1)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, str(page), "exec"), namespace)  # noqa: S102 - our own docs
    prob, theta = namespace["prob"], namespace["theta"]
    assert prob.value(theta) > 1.05 * prob.value(np.zeros(4))
    assert namespace["flow"].shape == (2, 180, 240)
    assert namespace["h5_path"].exists() and namespace["flow_path"].exists()
