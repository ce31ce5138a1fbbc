"""The dense flow of a live stream (``run_live_flow``, ``flow --live``): the same windows and flows as a
recorded pass, motion-adaptive windows, a dv-processing TCP stream on the loopback address whose
producer stops (the idle timeout), Ctrl-C with the outputs intact, a malformed packet: one clear error;
every event estimated or counted."""

from __future__ import annotations

import json
import math
import signal
import time

import numpy as np
import pytest
from conftest import shared_data_dir
from test_live import SENSOR, V, _accounted, moving_dots

import cmax_taichi as cm
from cmax_taichi.flow import DenseFlowEstimator, iter_flow
from cmax_taichi.flow.live import flow_speed, run_live_flow
from cmax_taichi.io.streams import ReplayStream
from cmax_taichi.io.writers import read_flow_npz
from cmax_taichi.solve.adaptive import AdaptiveWindows

GRID = ["--grid", "4", "4", "--levels", "2"]  # small: the tests check the loop, not the flow's detail


def _estimator() -> DenseFlowEstimator:
    return DenseFlowEstimator((4, 4), levels=2)


def test_live_flow_matches_the_recorded_pass():
    """A replay's live dense flow: the windows and node flows of iter_flow on the same events, every
    event estimated; the rows kept in the result hold no events nor flow images."""
    events = moving_dots()
    rows, nodes = [], []

    def on_window(row, estimator, result, latency):
        assert row.displacement.shape == (2, SENSOR[1], SENSOR[0]) and len(row.events) == row.n_events
        rows.append(row)
        nodes.append(result.nodes.copy())

    result = run_live_flow(ReplayStream(events), _estimator(), windows=3000, on_window=on_window)
    recorded = list(iter_flow(events, _estimator(), n_events=3000, keep_tail=True, score=False))
    assert result.stop_reason == "ended" and result.windows == len(rows) == len(recorded) == 4
    for row, flow, window in zip(rows, nodes, recorded, strict=True):
        assert (row.index, row.n_events, row.t_start, row.t_end) == (
            window.index, window.n_events, window.t_start, window.t_end)  # fmt: skip
        np.testing.assert_allclose(flow, window.result.nodes, atol=1e-9)
        assert row.dt == pytest.approx(window.dt)
        np.testing.assert_allclose(np.median(flow.reshape(-1, 2), axis=0), V, rtol=0.15)
    _accounted(result.events, len(events))
    assert result.events["estimated"] == len(events) and result.warp == "dense_flow"
    assert all(row.events is None and row.displacement is None for row in result.recent)
    closed_by_end = not math.isnan(result.end_latency)  # the last window, when the stream's end closed it
    assert result.warm_up_seconds > 0 and len(result.latencies) + closed_by_end == 4


def test_live_flow_behind_skips_whole_windows_counted():
    """An estimator slower than the stream, with a small buffer: whole windows are skipped from the
    buffer's front, each a row with status ``behind``, their events counted."""
    events = moving_dots()
    skipped, estimated = [], []

    def on_window(row, estimator, result, latency):
        estimated.append(row)
        time.sleep(0.3)  # slower than the stream: 12,000 events arrive in 0.12 s

    result = run_live_flow(ReplayStream(events), _estimator(), windows=1500, backlog_events=3000,
                           on_window=on_window, on_skipped=skipped.append)  # fmt: skip
    ev = result.events
    assert ev["behind"] > 0 and ev["behind"] == 1500 * len(skipped) == 1500 * ev["windows"]["behind"]
    assert all(row.status == "behind" and row.n_events == 1500 and row.result is None for row in skipped)
    assert ev["estimated"] == 1500 * len(estimated) and len(estimated) >= 2
    _accounted(ev, len(events))


def test_live_flow_adaptive_windows_hold_the_target_motion():
    """Motion-adaptive windows: each window lasts the time in which the previous window's flow moves the
    fast pixels by the target."""
    events = moving_dots()
    rule = AdaptiveWindows(target_px=4.0, min_events=300, first_events=2000)
    seen = []

    def on_window(row, estimator, result, latency):
        seen.append((row.t_end - row.t_start, flow_speed(result, row.events)))

    result = run_live_flow(ReplayStream(events), _estimator(), windows=rule, on_window=on_window)
    assert result.windows == len(seen) >= 4
    assert seen[0][0] * seen[0][1] >= rule.accept * rule.target_px  # the first window was not grown
    for (_, speed), (duration, _) in zip(seen[:-2], seen[1:-1], strict=True):
        assert 0.8 * rule.target_px <= speed * duration <= 1.25 * rule.target_px
    _accounted(result.events, len(events))
    assert result.events["estimated"] == len(events)


dv = pytest.importorskip("dv_processing", reason="live TCP streams need 'dv-processing' (cmax-taichi[live])")
import live_producers  # noqa: E402
from test_live import _cli, _packets, _serve  # noqa: E402


def _flow_cli(args, tmp_path, **kwargs):
    return _cli(args, tmp_path, "flow", **kwargs)


def test_cli_flow_live_loopback_stream_until_the_producer_stops(tmp_path):
    """flow --live on a TCP stream whose producer stops sending (the connection stays): the idle timeout
    ends the run; each window's flow file, timestamps line and row are written; the flows are those of
    the recorded pass over the same events; every event is accounted for."""
    events = moving_dots(n=12000, duration=0.12)
    packets = list(_packets(events, 500))
    script = [step for packet in packets for step in (("events", *packet), ("sleep", 0.005))]
    script.append(("sleep", 60.0))  # the producer stops, the connection stays open
    process, address = _serve(live_producers.scripted_server, script, SENSOR)
    out = tmp_path / "out"
    try:
        proc = _flow_cli(["--live", address, "--window", "3000", *GRID, "--idle-timeout", "2", "--no-display",
                          "--out", str(out)], tmp_path)  # fmt: skip
        stdout, stderr = proc.communicate(timeout=240)
    finally:
        process.terminate()
    assert proc.returncode == 0, stderr
    lines = (out / "results.csv").read_text().splitlines()
    assert lines[0].startswith("window,status,t_start,t_end,n_events") and lines[0].endswith(",latency [s]")
    assert len(lines) == 5 and all(line.split(",")[1] == "estimated" for line in lines[1:])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["live"]["stop_reason"] == "idle" and summary["live"]["windows_estimated"] == 4
    assert summary["events"]["total"] == summary["events"]["estimated"] == len(events)
    assert summary["live"]["latency_p99_s"] > 0 and summary["options"]["grid"] == [4, 4]
    stamps = (out / "flow_timestamps.txt").read_text().splitlines()
    # the stream's times are whole microseconds: the recorded pass over the same events
    received = cm.Events(events.x, events.y, np.rint(events.t * 1e6) / 1e6, events.p, SENSOR)
    recorded = list(iter_flow(received, _estimator(), n_events=3000, keep_tail=True, score=False))
    for k, window in enumerate(recorded):
        flow, meta = read_flow_npz(out / "flow" / f"flow_{k:04d}.npz")
        np.testing.assert_allclose(flow, window.displacement, atol=1e-4)
        assert float(meta["t_start"]) == pytest.approx(window.t_start)
        assert stamps[k].split() == [f"{window.t_start:.9f}", f"{window.t_start + window.dt:.9f}"]
    assert "4 window(s) estimated, 0 not (idle)" in stdout


def test_cli_flow_live_ctrl_c_keeps_what_was_written(tmp_path):
    """Ctrl-C ends a long replay after the window in flight (exit 130): the rows written as the windows
    came, one flow file and timestamps line per estimated row, the summary, no partial file."""
    folder = shared_data_dir("ecd_slider_depth")
    out = tmp_path / "out"
    proc = _flow_cli(["--live", str(folder), "--loops", "500", "--window", "5000", *GRID, "--no-display",
                      "--out", str(out)], tmp_path)  # fmt: skip
    csv = out / "results.csv"
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and (not csv.exists() or len(csv.read_text().splitlines()) < 4):
        assert proc.poll() is None, proc.communicate()[1]
        time.sleep(0.2)
    assert len(csv.read_text().splitlines()) >= 4  # rows appear while the run goes on
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    lines = csv.read_text().splitlines()
    assert len(lines) >= 4 and all(len(line.split(",")) == len(lines[0].split(",")) for line in lines)
    estimated = [line.split(",")[0] for line in lines[1:] if line.split(",")[1] == "estimated"]
    assert sorted(p.name for p in (out / "flow").iterdir()) == [f"flow_{int(k):04d}.npz" for k in estimated]
    assert len((out / "flow_timestamps.txt").read_text().splitlines()) == len(estimated)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["live"]["stop_reason"] == "stopped"
    assert summary["live"]["windows_estimated"] + summary["live"]["windows_not_estimated"] == len(lines) - 1
    _accounted(summary["events"], summary["events"]["total"])
    assert summary["events"]["estimated"] + summary["events"]["undistortion"] == 5000 * len(estimated)
    manifest = json.loads((out / ".cmax-taichi-manifest.json").read_text())
    assert "summary.json" in str(manifest) and "flow/flow_0000.npz" in str(manifest)


def test_cli_flow_live_malformed_packet_is_one_clear_error(tmp_path):
    process, address = _serve(live_producers.malformed_server, SENSOR, 3000)
    out = tmp_path / "out"
    try:
        proc = _flow_cli(["--live", address, "--window", "1000", *GRID, "--no-display", "--out", str(out)],
                         tmp_path)  # fmt: skip
        _, stderr = proc.communicate(timeout=240)
    finally:
        process.terminate()
    assert proc.returncode == 2, stderr
    assert "Traceback" not in stderr
    last = stderr.strip().splitlines()[-1]
    assert "reader process ended" in last and "the 3 row(s) before it are in" in last
    assert len((out / "results.csv").read_text().splitlines()) == 4  # the good packet's 3 windows
    assert len(list((out / "flow").glob("flow_*.npz"))) == 3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["live"]["stop_reason"] == "error" and summary["events"]["total"] == 3000


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--live", "tcp://127.0.0.1", "--no-display"], "tcp://HOST:PORT"),
        (["PATH", "--live", "x"], "--live SOURCE replaces PATH"),
        (["--live", "x", "--figures", "2"], "--figures: not with --live"),
        (["--live", "x", "--window-mode", "count", "--target-px", "3"], "--target-px: options of"),
        (["--live", "x", "--stride", "100"], "has no --stride"),
        (["--live", "nowhere", "--no-display"], "no such file or folder"),
        (["REC", "--window-mode", "adaptive"], "--window-mode adaptive: with --live"),
    ],
)
def test_cli_flow_live_bad_input(tmp_path, args, fragment):
    (tmp_path / "REC").mkdir()
    proc = _flow_cli([*args, "--out", str(tmp_path / "o")], tmp_path, cwd=tmp_path)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 2
    lines = [line for line in stderr.splitlines() if line.strip() and not line.startswith("[Taichi]")]
    assert len(lines) == 1 and fragment in lines[0], stderr
    assert not (tmp_path / "o").exists()
