"""The coarse-to-fine dense flow solver (cmax_taichi/flow/solver.py), its sequences and its command:
recovery of a spatially varying flow on a small simulated scene, determinism to the last bit, warm
starts, the image pyramid, bad options, and ``cmax-taichi flow`` end to end."""

from __future__ import annotations

import csv
import json
import time

import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi.flow import DenseFlowEstimator, FlowGrid, FlowResult, estimate_flow, iter_flow
from cmax_taichi.flow.solver import auto_scales, dithered
from cmax_taichi.metrics import event_mask, flow_error
from cmax_taichi.testing.flow_scenes import depth_scene

#: a small box-room scene: 3-7 px over the window, the flow varying by a factor 2 across the image
SENSOR = (120, 90)
REGS = {"deformation": 1.0, "curvature": 0.1}


@pytest.fixture(scope="module")
def scene():
    return depth_scene(SENSOR, duration=0.05, displacement=(4.0, 1.5), n_events=8000, seed=2)


def _aee(result: FlowResult, scene) -> float:
    return flow_error(result.displacement(), scene.displacement(), event_mask(scene.events))["AEE"]


def test_recovers_a_varying_flow_and_beats_a_translation(f64, scene):
    res = estimate_flow(scene.events, grid=(4, 4), levels=2, regularizers=REGS, references="middle")
    assert res.grid == FlowGrid(*SENSOR, 4, 4)
    assert res.nodes.shape == (5, 5, 2) and np.all(np.isfinite(res.nodes))
    assert [lv.grid.nx for lv in res.levels] == [2, 4] and res.n_evaluations > 10
    aee = _aee(res, scene)
    truth = scene.displacement()
    best_constant = np.nanmedian(truth.reshape(2, -1), axis=1)[:, None, None] * np.ones_like(truth)
    constant = flow_error(best_constant, truth, event_mask(scene.events))["AEE"]
    assert aee < 0.6 * constant and aee < 1.0, (aee, constant)
    assert res.flow(layout="hwc").shape == (*SENSOR[::-1], 2)
    np.testing.assert_allclose(res.displacement(), res.flow(res.duration))


def test_dither_spreads_integer_coordinates_over_their_pixel(scene):
    ev = scene.events
    assert np.array_equal(ev.x, np.floor(ev.x))  # the scene's events are on the pixel grid
    d = dithered(ev)
    assert np.array_equal(d.t, ev.t) and np.array_equal(d.p, ev.p) and d.sensor_size == ev.sensor_size
    assert np.abs(d.x - ev.x).max() <= 0.5 and np.abs(d.y - ev.y).max() <= 0.5
    assert d.x.min() >= 0 and d.x.max() <= SENSOR[0] - 1 and d.y.min() >= 0 and d.y.max() <= SENSOR[1] - 1
    assert 0.25 < np.std(d.x - ev.x) < 0.32  # uniform over the pixel: 1 / sqrt(12)
    np.testing.assert_array_equal(dithered(ev).y, d.y)  # seeded
    assert dithered(d) is d  # fractional coordinates (undistorted events): unchanged


def test_dither_comes_after_the_undistortion_table(scene):
    """Raw events with a distorted camera: undistorted through the per-pixel table, then dithered; events
    already undistorted (fractional coordinates) are not."""
    camera = cm.Camera(100.0, 100.0, 59.5, 44.5, dist=(0.05, 0.0, 0.0, 0.0, 0.0))
    plain = scene.events.undistort(camera)
    prepared = DenseFlowEstimator((4, 4), levels=2, camera=camera)._prepare(scene.events)
    assert prepared.undistorted and len(prepared) == len(plain)
    assert np.abs(prepared.x - plain.x).max() <= 0.5 and np.std(prepared.y - plain.y) > 0.25
    undithered = DenseFlowEstimator((4, 4), levels=2, camera=camera, dither=False)._prepare(scene.events)
    np.testing.assert_array_equal(undithered.x, plain.x)
    assert DenseFlowEstimator((4, 4), levels=2)._prepare(plain) is plain


def test_dither_removes_the_pull_of_small_components_to_zero(f64):
    """Events on the pixel grid make the IWE sharpest at zero displacement along each axis: without
    the dither a 0.7 px vertical component over the window comes out as 0."""
    sc = depth_scene(SENSOR, duration=0.05, displacement=(4.0, 0.5), n_events=8000, seed=2)
    truth, mask = sc.displacement(), event_mask(sc.events)
    errors = {}
    for dither in (False, True):
        res = estimate_flow(sc.events, grid=(4, 4), levels=2, regularizers=REGS, dither=dither)
        d = res.displacement()
        errors[dither] = (flow_error(d, truth, mask)["AEE"], float(np.mean((d - truth)[1][mask])))
    assert np.mean(truth[1][mask]) > 0.6
    assert errors[False][1] < -0.6 and abs(errors[True][1]) < 0.15, errors
    assert errors[True][0] < 0.5 * errors[False][0], errors


def test_displacement_follows_the_trajectories():
    """A contraction ``u = a (x - c)`` (exact on the grid): the point at x is at ``c + (x - c) e^(a dt)``
    after dt; the straight line ``dt u(x)`` overshoots it."""
    grid = FlowGrid(*SENSOR, 4, 4)
    c = np.array([(SENSOR[0] - 1) / 2.0, (SENSOR[1] - 1) / 2.0])
    a, dt = -4.0, 0.1
    nx, ny = grid.node_positions()
    nodes = np.stack([a * (nx - c[0]), a * (ny - c[1])], axis=-1)
    yy, xx = np.mgrid[0 : SENSOR[1], 0 : SENSOR[0]].astype(np.float64)
    exact = np.stack([xx - c[0], yy - c[1]]) * (np.exp(a * dt) - 1.0)
    res = FlowResult(grid, nodes, 0.0, dt, 10, 0.0, None)
    np.testing.assert_allclose(res.displacement(), exact, atol=1e-4)
    np.testing.assert_allclose(res.displacement(trajectories=False), grid.dense(nodes) * dt)
    assert np.abs(res.displacement(trajectories=False) - exact).max() > 3.0
    constant = np.broadcast_to([30.0, -10.0], grid.shape)
    np.testing.assert_allclose(grid.trajectories(constant, dt), grid.dense(constant) * dt, atol=1e-12)


def test_deterministic_to_the_last_bit(f64, scene):
    """The same window gives the same node values, bit for bit (the kernels add their per-thread partial
    sums in a fixed order; L-BFGS-B is deterministic)."""
    est = DenseFlowEstimator((4, 4), levels=2, regularizers=REGS)
    a = est.estimate(scene.events)
    b = est.estimate(scene.events)
    c = DenseFlowEstimator((4, 4), levels=2, regularizers=REGS).estimate(scene.events)
    assert np.array_equal(a.nodes, b.nodes) and np.array_equal(a.nodes, c.nodes)
    assert a.value == b.value == c.value


def test_warm_start_and_sequence(f64, scene):
    est = DenseFlowEstimator((4, 4), levels=2, regularizers=REGS)
    first = est.estimate(scene.events)
    warm = est.estimate(scene.events, warm=first)
    assert warm.init == "warm" and warm.n_evaluations < first.n_evaluations
    assert warm.value >= first.value - 1e-3
    windows = list(iter_flow(scene.events, est, n_events=4000, max_windows=2))
    assert [w.index for w in windows] == [0, 1]
    assert windows[0].result.init == "search" and windows[1].result.init == "warm"
    assert windows[0].metrics is None  # Events carry no ground truth
    assert windows[1].displacement.shape == (2, SENSOR[1], SENSOR[0])


def test_levels_scales_and_options_are_checked(f64, scene):
    assert auto_scales(4) == (4, 4, 2, 1) and auto_scales(1) == (1,)
    with pytest.raises(ValueError, match="multiples of 4"):
        DenseFlowEstimator((6, 6), levels=3).estimate(scene.events)
    with pytest.raises(ValueError, match="scales must be 2"):
        DenseFlowEstimator((4, 4), levels=2, scales=(1,))
    with pytest.raises(ValueError, match="max_iter"):
        DenseFlowEstimator((4, 4), levels=2, max_iter=(5, 0))
    with pytest.raises(ValueError, match="init must be"):
        DenseFlowEstimator((4, 4), levels=2).estimate(scene.events, init="best")
    with pytest.raises(ValueError, match="takes 18"):
        DenseFlowEstimator((4, 4), levels=2).estimate(scene.events, init=np.zeros(5))
    with pytest.raises(ValueError, match="unknown reference"):
        DenseFlowEstimator(references="start")


def _write_recording(tmp_path, scene):
    ev = scene.events
    path = tmp_path / "events.txt"
    (tmp_path / "calib.txt").write_text(f"100 100 59.5 44.5\n{SENSOR[0]} {SENSOR[1]}\n")  # no distortion
    with path.open("w") as f:
        for t, x, y, p in zip(ev.t, ev.x, ev.y, ev.p, strict=True):
            f.write(f"{t:.9f} {int(x)} {int(y)} {int(p > 0)}\n")
    return path


def test_flow_command_end_to_end(tmp_path, f64, scene):
    """``cmax-taichi flow`` on a recording written to disk: flow files readable back, the timestamps,
    the table (with what the optimizer did on each level) and the figure."""

    from cmax_taichi.cli import main
    from cmax_taichi.io.writers import read_flow_npz

    path = _write_recording(tmp_path, scene)
    out = tmp_path / "out"
    rc = main(
        [
            "flow", str(path), "--out", str(out), "--window", "4000", "--grid", "4", "4", "--levels", "2",
            "--reg", "deformation=1", "--reg", "curvature=0.1", "--quiet", "--max-windows", "2",
        ]
    )  # fmt: skip
    assert rc == 0
    files = sorted((out / "flow").glob("flow_*.npz"))
    assert len(files) == 2
    flow, meta = read_flow_npz(files[0])
    assert flow.shape == (2, SENSOR[1], SENSOR[0]) and meta["unit"] == "px"
    assert (out / "flow_timestamps.txt").read_text().count("\n") == 2
    assert (out / "figures" / "window_0000.png").is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["windows"] == 2 and summary["stalled_windows"] == 0
    assert summary["options"]["regularizers"] == {"deformation": 1.0, "curvature": 0.1}
    # every event accounted for as estimate does: the windows after --max-windows are counted
    assert summary["events"]["total"] == len(scene.events) and (
        summary["events"]["after_max_windows"] == len(scene.events) - 8000
    )
    assert summary["recording"]["fingerprint"] and meta["fingerprint"] == summary["recording"]["fingerprint"]
    with (out / "results.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["status"] for r in rows] == ["estimated", "estimated"]
    assert [r["optimizer"] for r in rows] == ["ok", "ok"]
    assert rows[0]["levels"].startswith("2x2 ") and rows[0]["levels"].count(" it ") == 2
    assert not (out / ".cmax-taichi.lock").exists()
    assert main(["flow", str(path), "--reg", "smooth=1"]) == 2  # one clear error, no traceback
    assert main(["flow", "--out", str(out)]) == 2
    # --keep-tail: the partial tail estimated as a shorter window, a row either way
    rc = main(
        [
            "flow", str(path), "--out", str(out), "--window", "5000", "--grid", "2", "2", "--levels", "1",
            "--quiet", "--keep-tail", "--figures", "0",
        ]
    )  # fmt: skip
    assert rc == 0
    with (out / "results.csv").open() as f:
        assert [r["status"] for r in csv.DictReader(f)] == ["estimated", "short_tail"]
    assert len(list((out / "flow").glob("flow_*.npz"))) == 2  # the previous run's files replaced


def test_flow_command_reports_a_stalled_level(tmp_path, f64, scene, monkeypatch, capsys):
    """The exact penalties' kinks stall L-BFGS-B at the global search's constant flow (t_ref first,
    divergence 10 + deformation 10): the command says so, and so do results.csv and summary.json."""

    from cmax_taichi.cli import main

    monkeypatch.setitem(DenseFlowEstimator.__init__.__kwdefaults__, "kink_width", 0.0)
    path = _write_recording(tmp_path, scene)
    out = tmp_path / "out"
    rc = main(
        [
            "flow", str(path), "--out", str(out), "--window", "8000", "--grid", "4", "4", "--levels", "2",
            "--references", "first", "--reg", "divergence=10", "--reg", "deformation=10", "--figures", "0",
            "--quiet",
        ]
    )  # fmt: skip
    assert rc == 0
    assert "have a level whose optimizer did not move the flow" in capsys.readouterr().out
    with (out / "results.csv").open() as f:
        row = next(csv.DictReader(f))
    assert row["optimizer"] == "stalled" and "stalled 0 it 0 px" in row["levels"]
    assert json.loads((out / "summary.json").read_text())["stalled_windows"] == 1


def test_bad_windows_are_refused(f64):
    with pytest.raises(TypeError, match="Events"):
        DenseFlowEstimator().estimate(np.zeros(3))
    ev = cm.Events([1.0, 2.0], [1.0, 2.0], [0.0, 0.0], [1, 1], (20, 20))
    with pytest.raises(ValueError, match="zero time"):
        DenseFlowEstimator((2, 2), levels=1).estimate(ev)


def test_flow_example_prints_its_error_against_the_truth(tmp_path, f64, capsys):
    """``cmax-taichi flow --example boxroom``: one window, scored against the exact flow and printed."""
    from cmax_taichi.cli import main

    out = tmp_path / "ex"
    rc = main(
        ["flow", "--example", "boxroom", "--grid", "4", "4", "--levels", "2", "--out", str(out), "--quiet"]
    )
    assert rc == 0
    text = capsys.readouterr().out
    aee = float(text.split("AEE ")[1].split(" px")[0])
    zero = float(text.split("zero flow: AEE ")[1].split(" px")[0])
    assert 0.0 < aee < 0.5 * zero  # a coarse grid, far better than no motion
    summary = json.loads((out / "summary.json").read_text())
    assert summary["metrics"]["AEE"] == pytest.approx(aee, abs=1e-3)
    assert main(["flow", "--example", "nowhere", "--out", str(tmp_path / "x")]) == 2


def test_flow_files_are_scored_by_evaluate_as_by_flow(tmp_path, f64):
    """``cmax-taichi flow`` on a simulated recording in MVSEC's files (``*_data.hdf5`` with its
    ``*_gt_flow_dist.npz``), dt = 1 frame, then ``cmax-taichi evaluate`` on its flow files: the same AEE
    per window as the one ``flow`` computed from the recording's ground truth."""

    from cmax_taichi import sim as sm
    from cmax_taichi.cli import main

    rec = sm.simulate_depth("planes", duration=0.11, scale=0.25)
    h5, _ = rec.write(tmp_path / "sim", "planes", frame_rate=40.0)
    W, H = rec.sensor_size
    size = ["--sensor-size", str(W), str(H)]
    out = tmp_path / "flow"
    args = ["flow", str(h5), *size, "--duration", "0.05", "--dt", "0.025", "--grid", "4", "4"]
    args += ["--levels", "2", "--max-windows", "2"]
    assert main([*args, "--out", str(out), "--quiet", "--figures", "0"]) == 0
    with (out / "results.csv").open() as f:
        own = [float(r["AEE"]) for r in csv.DictReader(f)]
    assert len(own) == 2 and all(0.0 < a < 3.0 for a in own)
    assert main(["evaluate", str(out / "flow"), "--data", str(h5), *size, "--out", str(tmp_path / "ev")]) == 0
    rows = json.loads((tmp_path / "ev" / "metrics.json").read_text())["windows"]
    assert [r["AEE"] for r in rows] == pytest.approx(own, abs=1e-3)


def test_iter_flow_accounts_for_every_event_and_window(f64, scene):
    """Windows too small or of zero duration are rows with their status, the events of each reason are
    counted (they sum to the source's), one warning gives them; a flow over a dt that carries points
    beyond the sensor is refused up front (no integration whose cost grows with dt)."""
    from cmax_taichi.core.checks import EventsDroppedWarning
    from cmax_taichi.flow.sequence import BEYOND_SENSOR

    ev = scene.events
    t = np.concatenate([ev.t, [0.2], np.full(5, 0.3)])
    x = np.concatenate([ev.x, [10.0], np.full(5, 20.0)])
    y = np.concatenate([ev.y, [10.0], np.full(5, 20.0)])
    events = cm.Events(x, y, t, np.concatenate([ev.p, np.ones(6)]), SENSOR)
    est = DenseFlowEstimator((2, 2), levels=1, regularizers=REGS)
    skipped = []
    with pytest.warns(EventsDroppedWarning, match="6 of 8006 event"):
        flows = iter_flow(events, est, duration=0.05, dt=1e4, on_skipped=skipped.append)
        windows = list(flows)
    assert [w.status for w in windows] == [BEYOND_SENSOR]  # 1e4 s of a 5 px flow: far off the sensor
    assert windows[0].displacement is None and "beyond the 120x90 sensor" in windows[0].note
    assert [(w.status, w.n_events) for w in skipped] == [("too_few_events", 1), ("zero_duration", 5)]
    assert flows.skipped == skipped
    counts = flows.events
    assert counts["estimated"] == len(ev) and counts["too_few_events"] == 1 and counts["zero_duration"] == 5
    assert counts["total"] == sum(v for k, v in counts.items() if k not in ("total", "windows"))
    # count windows: the partial tail is a row, or a short window with keep_tail
    with pytest.warns(EventsDroppedWarning, match="partial last window"):
        rows = list(iter_flow(ev, est, n_events=5000, dt=None))
    assert len(rows) == 1
    tail = list(iter_flow(ev, est, n_events=5000, keep_tail=True))
    assert [w.status for w in tail] == ["estimated", "short_tail"] and tail[1].n_events == len(ev) - 5000


def test_trajectories_and_the_padded_image_are_bounded_up_front():
    from cmax_taichi.core.limits import get_limits
    from cmax_taichi.flow.grid import FlowBeyondSensorError, auto_padding, check_padded_sensor

    grid = FlowGrid(120, 90, 2, 2)
    burst = np.full(grid.shape, 1e7)  # a window of a microsecond: px/s in the millions
    with pytest.raises(FlowBeyondSensorError, match="beyond the 120x90 sensor"):
        grid.trajectories(burst, 0.05)
    # the README's largest sensor runs with the automatic padding, which shrinks to fit the limit
    side = int(np.sqrt(get_limits().max_sensor_pixels))
    assert auto_padding((side, side), 0.03) == 0 and auto_padding((346, 260), 0.03) == 10
    check_padded_sensor((side, side), 0)
    with pytest.raises(ValueError, match=rf"the {side}x{side} sensor with a margin of 10 px .*at most 0 px"):
        check_padded_sensor((side, side), 10, "--padding")
    with pytest.raises(ValueError, match=rf"the {side + 1}x{side} sensor"):
        check_padded_sensor((side + 1, side), 0)


def test_levels_beyond_the_grid_are_refused_at_once(f64):
    # a huge levels used to build 2^levels integers (minutes, then an unreadable number)
    ev = cm.Events([1.0, 30.0, 12.0], [1.0, 20.0, 9.0], [0.0, 0.01, 0.02], [1, 1, 1], (40, 30))
    for levels, multiple in ((10**6, r"2\^999999"), (6, "32")):
        start = time.perf_counter()
        with pytest.raises(ValueError, match=f"16x16 cells allow at most 5 level.*multiples of {multiple}$"):
            DenseFlowEstimator(levels=levels).estimate(ev)
        assert time.perf_counter() - start < 5.0
