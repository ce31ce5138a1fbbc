"""Live input: replayed recordings, the online estimator on dv-processing TCP streams served on the loopback
address (late packets, bursts, an estimator that falls behind, a producer that stops, a malformed packet:
counted or one clear error, every event accounted for), and ``estimate --live`` (rows appended as they
come, Ctrl-C / SIGTERM keep them)."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import shared_data_dir

import cmax_taichi as cm
from cmax_taichi.core.windows import CATEGORIES, STREAM_CATEGORIES
from cmax_taichi.io.streams import ReplayStream, StreamError, free_port, open_stream
from cmax_taichi.solve import sequence
from cmax_taichi.solve.adaptive import AdaptiveWindows
from cmax_taichi.solve.online import run_live

SENSOR = (120, 90)
V = (150.0, 60.0)  # px/s


def moving_dots(n=12000, duration=0.12, seed=0, t0=1.0):
    """Integer-pixel events of dots translating at V (times from ``t0`` s)."""
    rng = np.random.default_rng(seed)
    W, H = SENSOR
    k = rng.integers(0, 60, n)
    x0, y0 = rng.uniform(10, W - 40, 60), rng.uniform(10, H - 30, 60)
    t = np.sort(rng.uniform(0, duration, n))
    x = np.clip(np.rint(x0[k] + V[0] * t + rng.normal(0, 0.7, n)), 0, W - 1)
    y = np.clip(np.rint(y0[k] + V[1] * t + rng.normal(0, 0.7, n)), 0, H - 1)
    return cm.Events(x, y, t0 + t, rng.choice([-1, 1], n), SENSOR)


def _accounted(events: dict, received: int) -> None:
    counted = sum(events[c] for c in (*CATEGORIES, "after_max_windows", *STREAM_CATEGORIES))
    assert counted == events["total"] == received, events


def test_replay_stream_packets_and_pace():
    events = moving_dots(n=3000, duration=0.05)
    stream = ReplayStream(events, loops=2, packet_seconds=0.002)
    t0 = time.perf_counter()
    packets = []
    while not stream.ended:
        packet = stream.read(0.5)
        if packet is not None:
            packets.append(packet)
    assert time.perf_counter() - t0 >= 0.09  # two loops of 50 ms at the recorded speed
    t = np.concatenate([p.t for p in packets])
    assert len(t) == 6000 and np.all(np.diff(t) >= 0)  # the second loop follows the first
    np.testing.assert_array_equal(t[:3000], events.t)
    np.testing.assert_array_equal(np.concatenate([p.x for p in packets])[3000:], events.x)
    assert all(np.ptp(p.t) < 0.002 for p in packets)


def test_open_stream_refuses_bad_sources(tmp_path):
    with pytest.raises(ValueError, match="tcp://HOST:PORT"):
        open_stream("tcp://127.0.0.1")
    with pytest.raises(FileNotFoundError, match="nor tcp://HOST:PORT, camera"):
        open_stream(tmp_path / "nothing")


def test_live_replay_matches_the_recorded_pass():
    """A replay estimated live gives the windows and estimates of sequence.process with the same
    adaptive rule (the last window aside: a recording's last window takes a short tail, a stream's
    cannot know it is the last)."""
    events = moving_dots()
    rule = AdaptiveWindows(target_px=4.0, min_events=300, first_events=2000)
    rows = []
    result = run_live(
        ReplayStream(events), "translation2", windows=rule,
        on_window=lambda row, prob, res, latency: rows.append(row),
    )  # fmt: skip
    offline = sequence.process(events, "translation2", adaptive=rule, progress=False, compute_fwl=False)
    assert result.windows == len(rows) >= 4 and result.stop_reason == "ended"
    for live_row, row in zip(rows[:-1], offline.windows[:-1], strict=False):
        assert (live_row.t_start, live_row.t_end, live_row.n_events) == (row.t_start, row.t_end, row.n_events)
        np.testing.assert_allclose(live_row.theta, row.theta, rtol=1e-6, atol=1e-6)
    _accounted(result.events, len(events))
    assert result.real_time_factor() > 0 and np.all(result.latencies >= 0)
    assert result.warm_up_seconds > 0 and len(result.recent) == len(rows) + result.skipped


dv = pytest.importorskip("dv_processing", reason="live TCP streams need 'dv-processing' (cmax-taichi[live])")
import live_producers  # noqa: E402


def _serve(target, *args):
    ctx = multiprocessing.get_context("spawn")
    ready, port = ctx.Event(), free_port()
    process = ctx.Process(target=target, args=(port, ready, *args), daemon=True)
    process.start()
    assert ready.wait(60), "the producer did not start"
    return process, f"tcp://127.0.0.1:{port}"


def _packets(events: cm.Events, size: int):
    for a in range(0, len(events), size):
        sl = slice(a, a + size)
        yield (np.rint(events.t[sl] * 1e6).astype(np.int64), events.x[sl].astype(int),
               events.y[sl].astype(int), (events.p[sl] > 0).astype(int))  # fmt: skip


def test_loopback_nothing_listening_is_one_clear_error():
    address = f"tcp://127.0.0.1:{free_port()}"
    with pytest.raises(StreamError, match=r"cannot open \(RuntimeError: connect: Connection refused\)$"):
        open_stream(address)


def test_loopback_late_packets_burst_behind_and_a_producer_that_stops():
    """Packets at the recorded pace, a late packet (times earlier than what came before), a burst while
    the estimator is slow (the buffer skips whole windows: ``behind``), then the producer stops sending
    (the connection stays): the idle timeout ends the run; every event is estimated or counted."""
    events = moving_dots(n=16000, duration=0.16)
    packets = list(_packets(events, 500))
    late = packets[2]
    script = []
    for k, packet in enumerate(packets):
        script.append(("events", *packet))
        script.append(("sleep", 0.0 if 12 <= k < 28 else 0.005))  # packets 12-27: a burst
        if k == 6:
            script.append(("events", *late))  # 500 events older than what the client already has
    script.append(("sleep", 60.0))  # the producer stops, the connection stays open
    process, address = _serve(live_producers.scripted_server, script, SENSOR)
    slow = []

    def on_window(row, prob, res, latency):
        slow.append(latency)
        if len(slow) == 2:
            time.sleep(0.6)  # an estimator that falls behind: the burst arrives meanwhile

    try:
        with open_stream(address) as stream:
            assert stream.sensor_size == SENSOR
            result = run_live(stream, "translation2", windows=1500, backlog_events=3000, idle_timeout=1.5,
                              on_window=on_window)  # fmt: skip
    finally:
        process.terminate()
    assert result.stop_reason == "idle"
    ev = result.events
    assert ev["late"] == 500
    assert ev["behind"] > 0 and ev["windows"]["behind"] >= 1 and ev["behind"] % 1500 == 0  # whole windows
    assert result.windows >= 2  # before the slow window and after the burst (how many: the machine's load)
    assert ev["estimated"] + ev["behind"] + ev["late"] + ev["partial_tail"] + ev["after_stop"] == ev["total"]
    _accounted(ev, len(events) + 500)


def test_loopback_malformed_packet_is_one_clear_error():
    process, address = _serve(live_producers.malformed_server, SENSOR, 3000)
    rows = []
    try:
        with open_stream(address) as stream, pytest.raises(StreamError, match="reader process ended") as info:
            run_live(stream, "translation2", windows=1000, on_window=lambda *a: rows.append(a[0]))
    finally:
        process.terminate()
    result = info.value.live_result
    assert result.stop_reason == "error" and "reader process ended" in result.error
    assert result.windows == len(rows) == 3  # the good packet's three windows, estimated before the error
    _accounted(result.events, 3000)


def test_loopback_replay_server_delivers_every_event():
    from cmax_taichi.io.streams import start_replay_server

    folder = shared_data_dir("ecd_slider_depth")
    server = start_replay_server(folder, speed=4.0, linger=0.5)
    try:
        with open_stream(server.address) as stream:
            result = run_live(stream, "translation2", windows=AdaptiveWindows(target_px=4.0))
    finally:
        server.stop()
    assert result.stop_reason == "ended" and result.windows >= 3
    _accounted(result.events, 50000)
    assert server.started.value > 0


# --- the command line -------------------------------------------------------------------------------
def _cli(args, tmp_path, command="estimate", **kwargs):
    """``cmax-taichi COMMAND ARGS`` in a subprocess, without a display server."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["CMAX_TAICHI_CACHE"] = str(tmp_path / "cache")
    return subprocess.Popen(
        [sys.executable, "-m", "cmax_taichi.cli", command, *args], stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, env=env, **kwargs,
    )  # fmt: skip


def test_cli_live_replay_writes_rows_as_they_come(tmp_path):
    folder = shared_data_dir("ecd_slider_depth")
    out = tmp_path / "out"
    proc = _cli(["--live", str(folder), "--out", str(out), "--speed", "2"], tmp_path)
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr
    lines = (out / "results.csv").read_text().splitlines()
    assert lines[0].startswith("index,t_start [s],t_end [s],n_events,v_x [px/s],v_y [px/s]")
    assert lines[0].endswith("latency [s]") and len(lines) >= 3
    summary = json.loads((out / "results.json").read_text())
    assert summary["live"]["stop_reason"] == "ended" and summary["events"]["total"] == 50000
    assert len(summary["windows"]) == len(lines) - 1
    assert "window(s) estimated" in stdout and "latency median" in stdout


def test_cli_live_sigterm_keeps_what_was_written(tmp_path):
    folder = shared_data_dir("ecd_slider_depth")
    out = tmp_path / "out"
    proc = _cli(["--live", str(folder), "--out", str(out), "--loops", "500", "--no-display"], tmp_path)
    csv = out / "results.csv"
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and (not csv.exists() or len(csv.read_text().splitlines()) < 4):
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 143, stderr
    lines = csv.read_text().splitlines()
    assert len(lines) >= 4 and all(len(line.split(",")) == len(lines[0].split(",")) for line in lines)
    summary = json.loads((out / "results.json").read_text())
    assert summary["live"]["stop_reason"] == "stopped" and len(summary["windows"]) == len(lines) - 1


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--live", "tcp://127.0.0.1", "--no-display"], "tcp://HOST:PORT"),
        (["PATH", "--live", "x"], "--live SOURCE replaces PATH"),
        (["--live", "x", "--display"], "--display: no display here"),
        (["--live", "x", "--window-mode", "count", "--target-px", "3"], "--target-px: options of"),
        (["--live", "nowhere", "--no-display"], "no such file or folder"),
    ],
)
def test_cli_live_bad_input(tmp_path, args, fragment):
    proc = _cli([*args, "--out", str(tmp_path / "o")], tmp_path, cwd=tmp_path)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 2
    lines = [line for line in stderr.splitlines() if line.strip() and not line.startswith("[Taichi]")]
    assert len(lines) == 1 and fragment in lines[0], stderr
    assert not (tmp_path / "o").exists()  # a run that failed before its first row leaves no folder


def test_display_frames_draw_and_update():
    """The live display's drawing (run in its own process by estimate --live): a first frame builds the
    panels, the next updates them in place."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from cmax_taichi.cli._live import draw_frame

    fig = Figure(figsize=(9, 3))
    FigureCanvasAgg(fig)
    artists: dict = {}
    for k in range(2):
        frame = {
            "identity": np.random.default_rng(k).random((18, 24)), "estimate": np.ones((18, 24)),
            "t": [0.01, 0.02, 0.03][: k + 2], "theta": [[1.0, 2.0, 3.0][: k + 2], [0.0, 1.0, 0.0][: k + 2]],
            "names": ("v_x", "v_y"), "units": ("px/s", "px/s"), "title": f"window {k}",
        }  # fmt: skip
        draw_frame(fig, frame, artists)
        fig.canvas.draw()
    assert len(fig.axes) >= 3 and fig._suptitle.get_text() == "window 1"
    np.testing.assert_array_equal(artists["lines"][0].get_xdata(), [0.01, 0.02, 0.03])


def test_cli_live_calib_file_is_checked(tmp_path):
    folder = shared_data_dir("ecd_slider_depth")
    proc = _cli(["--live", str(folder), "--calib", str(tmp_path / "none.txt"), "--out", str(tmp_path / "o")],
                tmp_path)  # fmt: skip
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 2 and "--calib" in stderr and "no such file" in stderr
    assert not (tmp_path / "o").exists()  # a run that failed before its first row leaves no folder
