"""Depth scenes of the simulator: 3-D planes under rigid camera and object motions, their closed-form
flow and depth against independent formulas and finite differences, occlusion by the nearest surface,
the ground truth against the events (brightness constancy, the sharpness of the exactly warped
events), the issue-22 test case, the files, and bad input."""

from __future__ import annotations

import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi import metrics
from cmax_taichi import sim as sm
from cmax_taichi.sim.depth import plane_layer, rectangle_alpha
from cmax_taichi.sim.rigid import PlaneMotion, RigidMotion
from cmax_taichi.testing import reference as ref

CAM = sm.default_camera((346, 260))


def _grid(W=346, H=260, step=23):
    yy, xx = np.mgrid[0:H:step, 0:W:step].astype(np.float64)
    return xx.ravel(), yy.ravel()


def test_velocity_of_a_static_plane_is_the_classic_rigid_flow():
    """At t = 0 (camera frame = world frame) the flow of a static plane is the textbook rigid flow
    u = (-f V_x + x~ V_z) / Z + x~ y~ / f w_x - (f + x~^2 / f) w_y + y~ w_z (and v likewise)."""
    V, w = np.array([0.7, -0.3, 0.4]), np.array([0.2, -0.5, 0.3])
    motion = PlaneMotion((0.2, -0.1, 1.0), 3.0, camera=RigidMotion(V, w))
    x, y = _grid()
    Z = motion.depth(0.0, x, y, CAM)
    n = np.array(motion.normal)
    rx, ry = (x - CAM.cx) / CAM.fx, (y - CAM.cy) / CAM.fy
    np.testing.assert_allclose(Z, 3.0 / (n[0] * rx + n[1] * ry + n[2]), rtol=1e-12)
    f = CAM.fx
    xt, yt = x - CAM.cx, y - CAM.cy
    u = (-f * V[0] + xt * V[2]) / Z + xt * yt / f * w[0] - (f + xt**2 / f) * w[1] + yt * w[2]
    v = (-f * V[1] + yt * V[2]) / Z + (f + yt**2 / f) * w[0] - xt * yt / f * w[1] - xt * w[2]
    np.testing.assert_allclose(motion.velocity(0.0, x, y, CAM), np.stack([u, v]), rtol=1e-10, atol=1e-9)


@pytest.mark.parametrize("t", [0.0, 0.13, 0.4])
def test_velocity_is_the_derivative_of_the_exact_motion(t):
    """Camera and surface both translating and turning (about their pivots): the closed-form velocity
    equals the central difference of the homographies, and the homography's scale is the depth."""
    cam_motion = RigidMotion((0.5, 0.2, 0.6), (0.1, -0.3, 0.25), pivot=(0.1, 0.0, 0.5))
    own = RigidMotion((-0.4, 0.1, -0.2), (0.3, 0.2, 1.1), pivot=(0.2, 0.1, 2.0))
    motion = PlaneMotion((0.1, 0.2, 1.0), 2.0, camera=cam_motion, surface=own)
    x, y = _grid()
    h = 1e-5
    pts = np.stack([x, y, np.ones_like(x)])

    def moved(dt):
        q = motion.matrix(t + dt, CAM) @ np.linalg.solve(motion.matrix(t, CAM), pts)
        return q[:2] / q[2]

    numeric = (moved(h) - moved(-h)) / (2 * h)
    np.testing.assert_allclose(motion.velocity(t, x, y, CAM), numeric, rtol=1e-6, atol=1e-5)
    # G(t) [x0, y0, 1] = Z(t) / Z(0) [x_t, y_t, 1]
    x0, y0 = x, y
    q = motion.matrix(t, CAM) @ np.stack([x0, y0, np.ones_like(x0)])
    xt, yt = q[0] / q[2], q[1] / q[2]
    np.testing.assert_allclose(q[2], motion.depth(t, xt, yt, CAM) / motion.depth(0.0, x0, y0, CAM), rtol=1e-9)


def _two_planes(first_near: bool) -> sm.Scene:
    """A finite near plane (1.5 m) over an infinite far one (5 m), listed in either order."""
    m = RigidMotion((0.8, 0.1, 0.0))
    near = plane_layer(
        sm.load_texture("mri")[::2, ::2],
        CAM,
        centre=(0.2, 0.0, 1.5),
        camera_motion=m,
        finite=True,
        name="near",
    )
    far = plane_layer(
        sm.load_texture("grace_hopper"), CAM, centre=(0.0, 0.0, 5.0), camera_motion=m, name="far"
    )
    layers = [near, far] if first_near else [far, near]
    return sm.Scene((346, 260), layers, camera=CAM)


def test_the_nearest_surface_is_drawn_and_followed_whatever_the_layer_order():
    renders = []
    for first_near in (True, False):
        scene = _two_planes(first_near)
        sim = sm.Simulator(scene, sm.SimulatorConfig(noise_rate=0.0))
        rec = sim.run(0.002)
        L, label = sim.render(0.001)
        near_index = 0 if first_near else 1
        near = scene.layers[near_index]
        h, w = near.texture.shape
        # the pixels whose ray meets the near texture (well inside it) show the near plane
        yy, xx = np.mgrid[0:260, 0:346].astype(np.float64)
        X = np.linalg.solve(
            sim.layer_matrix(near_index, 0.001), np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)])
        )
        u, v = X[0] / X[2], X[1] / X[2]
        inner = ((u > 2) & (v > 2) & (u < w - 3) & (v < h - 3)).reshape(260, 346)
        assert inner.sum() > 10000
        assert np.all(label[inner] == near_index)
        depth = rec.depth(0.001)
        np.testing.assert_allclose(depth[inner], 1.5, rtol=1e-9)
        assert np.nanmin(depth[label == 1 - near_index]) == pytest.approx(5.0)
        vel = rec.velocity(0.001)
        np.testing.assert_allclose(vel[0][inner], -CAM.fx * 0.8 / 1.5, rtol=1e-6)
        flow = rec.flow(0.001, 0.011)
        np.testing.assert_allclose(flow[0][inner], -CAM.fx * 0.8 / 1.5 * 0.01, rtol=1e-6)
        renders.append(L)
    # the same picture either way
    np.testing.assert_allclose(renders[0], renders[1], atol=1e-9)


def _first_window(name: str):
    """``(recording, t0, t1)`` of a preset's first window (depth_example), checked against its recording."""
    example = sm.depth_example(name)
    rec, t0, t1 = example.recording, example.t0, example.t1
    assert (t0, t1) == (0.02, 0.02 + sm.DEPTH_PRESETS[name].window)
    np.testing.assert_array_equal(example.flow, rec.flow(t0, t1))
    assert len(example.events) == len(example.labels) == len(rec.events(t0, np.nextafter(t1, 1.0)))
    return rec, t0, t1


@pytest.fixture(scope="module")
def planes():
    """The issue-22 scene: 'planes', 346x260, its first window."""
    return _first_window("planes")


def test_planes_preset_is_the_issue_test_case(planes):
    """346x260, displacement over the window within 5-15 px, the flow varying by more than 30%."""
    rec, t0, t1 = planes
    assert rec.sensor_size == (346, 260)
    disp = np.hypot(*rec.flow(t0, t1))
    assert np.isfinite(disp).all()  # every pixel sees a surface
    lo, hi = np.percentile(disp, [1, 99])
    assert lo >= 5.0 and hi <= 15.0, (lo, hi)
    assert hi / lo >= 1.3 * 1.3  # far more than 30% across the image
    n = len(rec.events(t0, t1))
    assert 30_000 <= n <= 120_000
    # the three planes are all seen and all produce events
    assert set(np.unique(rec.label_map(t0))) == {0, 1, 2}
    assert all(np.count_nonzero(rec.label_slice(t0, t1) == k) > 5000 for k in range(3))


@pytest.fixture(scope="module")
def corridor():
    """The smooth 3-D scene of the dense flow's accuracy target: 'corridor', 346x260, its first window."""
    return _first_window("corridor")


def test_corridor_preset_fits_the_issue_criterion(corridor):
    """346x260, every pixel sees a surface, 5-15 px over the window, more than 30% of variation, all
    three surfaces seen and producing events."""
    rec, t0, t1 = corridor
    assert rec.sensor_size == (346, 260)
    disp = np.hypot(*rec.flow(t0, t1))
    assert np.isfinite(disp).all()
    lo, hi = disp.min(), disp.max()
    assert lo >= 5.0 and hi <= 15.0, (lo, hi)
    assert hi / lo >= 1.3 * 1.3
    assert 60_000 <= len(rec.events(t0, t1)) <= 200_000
    assert set(np.unique(rec.label_map(t0))) == {0, 1, 2}
    assert all(np.count_nonzero(rec.label_slice(t0, t1) == k) > 5000 for k in range(3))


def test_corridor_truth_is_the_closed_form_of_a_sideways_camera(corridor):
    """The far wall (depth 3 m, parallel to the motion) moves by ``-f V T / Z`` exactly; every pixel
    keeps its depth along x-translation, so the flow depends on the row alone up to the slight vertical
    motion; the floor, nearer, moves faster than the wall at every column."""
    rec, t0, t1 = corridor
    T = t1 - t0
    flow, label = rec.flow(t0, t1), rec.label_map(t0)
    wall = label == 0
    np.testing.assert_allclose(flow[0][wall], -CAM.fx * 1.0 * T / 3.0, rtol=1e-9)
    np.testing.assert_allclose(flow[1][wall], -CAM.fy * 0.15 * T / 3.0, rtol=1e-9)
    np.testing.assert_allclose(rec.depth(t0)[wall], 3.0, rtol=1e-9)
    np.testing.assert_allclose(flow[0], np.broadcast_to(flow[0][:, :1], flow[0].shape), atol=1e-9)  # per row
    floor_rows = np.flatnonzero((label == 1).all(axis=1))
    assert floor_rows.size > 20 and np.all(np.abs(flow[0][floor_rows]) > CAM.fx * T / 3.0)


def test_corridor_is_seeded():
    a = sm.simulate_depth("corridor", duration=0.03, scale=0.25)
    b = sm.simulate_depth("corridor", duration=0.03, scale=0.25)
    c = sm.simulate_depth("corridor", duration=0.03, scale=0.25, seed=1)
    assert len(a) > 100
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.p, b.p)
    assert len(a) != len(c) or not np.array_equal(a.t, c.t)


def _variance(W, H, xw, yw):
    ok = np.isfinite(xw) & np.isfinite(yw)
    return float(ref.gaussian_blur(ref.bilinear_votes(xw[ok], yw[ok], np.ones(ok.sum()), W, H), 1.0).var())


def test_exactly_warped_events_are_sharper_than_any_global_translation(planes):
    """The events moved to t_ref by the exact motion of their surface give a sharper IWE than the best
    global warp (translation2, maximized), overall and on every surface's own events; a flow that
    one global warp cannot represent: its AEE against the truth stays above 1.5 px."""
    rec, t0, t1 = planes
    W, H = rec.sensor_size
    t_ref = 0.5 * (t0 + t1)
    ev = rec.events(t0, t1)
    labels = rec.label_slice(t0, t1)
    xe, ye = rec.warp_events(t_ref, t0, t1)
    assert np.isnan(xe[labels < 0]).all() and np.isfinite(xe[labels >= 0]).all()
    prob = cm.ContrastMaximization(ev, warp="translation2", t_ref=t_ref)
    theta = cm.maximize(prob).theta
    dt = ev.t - t_ref
    xg, yg = ev.x - dt * theta[0], ev.y - dt * theta[1]
    assert _variance(W, H, xe, ye) > 1.03 * _variance(W, H, xg, yg)
    for k in range(3):
        s = labels == k
        assert _variance(W, H, xe[s], ye[s]) > _variance(W, H, xg[s], yg[s]), f"surface {k}"
    # the exact warp is sharper than the identity by far, and than the exact flow scaled by +-10%
    J_exact = _variance(W, H, xe, ye)
    assert J_exact > 1.5 * _variance(W, H, ev.x, ev.y)
    ok = labels >= 0
    for s in (0.9, 1.1):
        xs = ev.x[ok] + s * (xe[ok] - ev.x[ok])
        ys = ev.y[ok] + s * (ye[ok] - ev.y[ok])
        assert J_exact > _variance(W, H, xs, ys)
    gt = rec.flow(t0, t1)
    pred = metrics.flow_from_warp("translation2", theta, (W, H), dt=t1 - t0)
    assert metrics.flow_error(pred, gt, metrics.event_mask(ev))["AEE"] > 1.5


def test_rendered_images_move_with_the_ground_truth_flow(planes):
    """Brightness constancy: the render at t1 sampled at x + flow(x) is the render at t0 at x (where
    the same surface is seen at both ends), to the interpolation error of the pixel-sampled images."""
    from scipy.ndimage import map_coordinates

    rec, t0, t1 = planes
    L0, lab0 = rec.simulator.render(t0)
    L1, lab1 = rec.simulator.render(t1)
    flow = rec.flow(t0, t1)
    H, W = L0.shape
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    xe, ye = xx + flow[0], yy + flow[1]
    moved = map_coordinates(L1, [ye, xe], order=1, mode="nearest")
    end_label = lab1[np.clip(np.rint(ye).astype(int), 0, H - 1), np.clip(np.rint(xe).astype(int), 0, W - 1)]
    same = (lab0 == end_label) & (xe > 1) & (xe < W - 2) & (ye > 1) & (ye < H - 2)
    assert same.mean() > 0.8
    residual = np.median(np.abs(moved - L0)[same])
    still = np.median(np.abs(L1 - L0)[same])
    assert residual < 0.15 * still


@pytest.mark.parametrize("window", ["planes", "corridor"])
def test_the_displacement_is_the_velocity_integrated_along_the_trajectories(window, request):
    rec, t0, t1 = request.getfixturevalue(window)
    cam = rec.camera
    for k, layer in enumerate(rec.scene.layers):
        mask = rec.label_map(t0) == k
        yy, xx = np.nonzero(mask)
        xx, yy = xx[::97].astype(np.float64), yy[::97].astype(np.float64)
        x, y = xx.copy(), yy.copy()
        n = 40
        h = (t1 - t0) / n
        for i in range(n):  # RK4 on dx/dt = velocity of the surface at (x, t)
            t = t0 + i * h
            k1 = layer.motion.velocity(t, x, y, cam)
            k2 = layer.motion.velocity(t + h / 2, x + h / 2 * k1[0], y + h / 2 * k1[1], cam)
            k3 = layer.motion.velocity(t + h / 2, x + h / 2 * k2[0], y + h / 2 * k2[1], cam)
            k4 = layer.motion.velocity(t + h, x + h * k3[0], y + h * k3[1], cam)
            x = x + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            y = y + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        np.testing.assert_allclose(
            rec.displacement(t0, t1, xx, yy, layer=k), np.stack([x - xx, y - yy]), atol=1e-7
        )


def test_events_integrate_to_the_log_intensity_change_in_a_depth_scene():
    scene = sm.depth_scene("object", scale=0.3)
    sim = sm.Simulator(scene, sm.SimulatorConfig(threshold_sigma=0.0, refractory=0.0, noise_rate=0.0))
    rec = sim.run(0.03)
    assert len(rec) > 1000 and set(np.unique(rec.labels)) == {0, 1}
    W, H = rec.sensor_size
    L0, _ = sim.render(0.0)
    L1, _ = sim.render(0.03)
    acc = np.zeros((H, W))
    xi, yi = rec.x.astype(int), rec.y.astype(int)
    np.add.at(acc, (yi, xi), np.where(rec.p > 0, sim.c_pos[yi, xi], -sim.c_neg[yi, xi]))
    resid = (L1 - L0) - acc
    assert np.all(np.abs(resid) < np.where(resid > 0, sim.c_pos, sim.c_neg) + 1e-9)


def test_same_seed_same_events_and_presets_are_seeded():
    a = sm.simulate_depth("room", duration=0.004, scale=0.25)
    b = sm.simulate_depth("room", duration=0.004, scale=0.25)
    c = sm.simulate_depth("room", duration=0.004, scale=0.25, seed=1)
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.x, b.x)
    assert len(a) != len(c) or not np.array_equal(a.t, c.t)


def test_write_and_read_a_depth_scene(tmp_path):
    from cmax_taichi.io import open_recording

    rec = sm.simulate_depth("object", duration=0.07, scale=0.25)
    h5, npz = rec.write(tmp_path, "object", frame_rate=40.0)
    data = sm.read_simulation(h5)
    assert data.warp == "" and data.gt_theta.shape == (len(data.gt_t), 0)
    assert data.flow.shape[1:] == (2, rec.sensor_size[1], rec.sensor_size[0])
    np.testing.assert_allclose(data.flow[0], rec.flow(0.0, 0.025), atol=1e-4)
    with open_recording(h5, format="mvsec", sensor_size=rec.sensor_size) as mv:
        gt = mv.flow(0.0, 0.025)  # one frame: the npz frame as written
        np.testing.assert_allclose(gt, rec.flow(0.0, 0.025), atol=1e-4)
    import h5py

    with h5py.File(h5) as f:
        np.testing.assert_allclose(f["davis/left/image_raw_ts"][()], data.gt_t)
        assert "normal" in f["ground_truth/layers/1"].attrs["plane"]


def test_rectangle_alpha_is_zero_on_the_border_and_one_inside():
    a = rectangle_alpha(5, 6)
    assert a[0].max() == 0 and a[:, -1].max() == 0 and a[1:-1, 1:-1].min() == 1


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: PlaneMotion((0, 0, 1), 0.0), "distance"),
        (lambda: PlaneMotion((0, 0, 0), 1.0), "zero vector"),
        (lambda: PlaneMotion((0, 0, 1), 1.0, camera="fast"), "RigidMotion"),
        (lambda: RigidMotion((1.0, np.nan, 0.0)), "finite"),
        (lambda: plane_layer(np.ones((4, 4)), CAM, centre=(0, 0, -1.0)), "in front"),
        (lambda: plane_layer(np.ones((4, 4)), CAM, centre=(0, 0, 2.0), normal=(1, 0, 0)), "passes through"),
        (
            lambda: sm.simulate(
                sm.Scene(
                    (64, 48),
                    [
                        plane_layer(
                            np.ones((8, 8)), CAM, centre=(0, 0, 1.0), camera_motion=RigidMotion((0, 0, 2.0))
                        )
                    ],
                    camera=CAM,
                ),
                1.0,
            ),
            "comes within",
        ),
        (
            lambda: sm.Scene(
                (64, 48),
                [
                    sm.Layer(np.ones((8, 8)), sm.Motion("translation2", (1.0, 0.0))),
                    plane_layer(np.ones((8, 8)), CAM, centre=(0, 0, 1.0)),
                ],
            ),
            "not a mixture",
        ),
        (lambda: sm.depth_scene("garden"), "valid depth scenes"),
        (lambda: sm.simulate_depth("planes", duration=0.01, scale=0.2, flux=1.0), "unknown simulator"),
        (lambda: sm.Layer(np.ones((4, 4)), PlaneMotion((0, 0, 1), 1.0)), "placement"),
        (lambda: sm.simulate_depth("object", 0.01, scale=0.2).theta_at(0.0), "no warp parameters"),
    ],
)
def test_bad_depth_input_gives_clear_errors(make, message):
    with pytest.raises((ValueError, TypeError), match=message):
        make()


def test_docs_depth_example_runs():
    """The depth example of docs/simulator.md runs as written."""
    import re
    from pathlib import Path

    page = Path(__file__).resolve().parents[1] / "docs" / "simulator.md"
    section = page.read_text().split("## Scenes with depth", 1)
    assert len(section) == 2, "docs/simulator.md has no 'Scenes with depth' section"
    code = re.search(r"```python\n(.*?)```", section[1], re.S).group(1)
    namespace: dict = {}
    exec(compile(code, str(page), "exec"), namespace)  # noqa: S102 - our own docs
    assert namespace["gt"].shape == (2, 260, 346) and namespace["speed"].shape == (2, 260, 346)
    assert np.isfinite(namespace["xw"]).mean() > 0.98  # noise events (0.1 Hz per pixel) have no surface
