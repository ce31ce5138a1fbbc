"""Live input measured: recordings replayed through a loopback TCP stream, a simulated HD stream, memory
over a long looped replay, and a multi-GB ROS bag read with bounded memory.

``python -m benchmarks.live [--data ../shared/data] [--out DIR] [--rounds 3] [--parts tcp,hd,flow,soak,bag]``

* **tcp**: each ECD rotation cut (rotation3) and slider_depth (translation2; at 1x and 2x) is served by
  :func:`cmax_taichi.io.streams.start_replay_server` on 127.0.0.1 at its recorded speed (times
  ``speed``) and estimated by :func:`cmax_taichi.solve.online.run_live` with motion-adaptive windows,
  the optimized kernels compiled (``compile_mode="full"``) by the warm-up before the replay starts. Per
  run: the real-time factor (data seconds of the windows / wall seconds spent on them, the first window
  included), the latency from a window's last event's arrival to its estimate (median, 99th percentile;
  the last window, which the stream's end closes, apart), the windows, and the accuracy: rotation3
  against the gyro of ``motion.txt`` (relative error of the angular velocity, median over the windows,
  and of the duration-weighted mean over the windows), beside ``sequence.process`` with 30,000-event
  windows (the whole cut of 20,000 for shapes_rotation); slider_depth against (-110, 0) px/s.
  ``--rounds`` rounds, the cases alternating; medians over the rounds.
* **hd**: a simulated 1280x720 stream of about 1 million events per second (a textured plane translating
  at (50, -30) px/s, ``--hd-seconds`` long, simulated once into ``OUT/hd_stream.npz``) replayed in the
  process at its recorded speed (:class:`~cmax_taichi.io.streams.ReplayStream`), translation2.
* **soak**: slider_depth looped for ``--soak-minutes`` through TCP; the resident set size of this process
  (and of the stream's reader process) every 2 s into ``soak_live.csv``; growth from the first minute on.
* **flow**: slider_depth served through TCP at its recorded speed, its dense flow estimated live by
  :func:`cmax_taichi.flow.live.run_live_flow` (``flow --live``): the command's defaults (16x16 cells, 4
  levels, 30,000-event windows), a coarser flow (8x8 cells, 3 levels) and the default flow on
  motion-adaptive windows; the real-time factor, the latency and the median node flow (px/s; the
  dominant depth's flow is about (-110, 0)), ``--rounds`` rounds, medians; ``live_flow.csv`` /
  ``live_flow.md``.
* **bag**: a ROS1 bag of ``--bag-gb`` GB of ``dvs_msgs/EventArray`` (slider_depth tiled in time) written
  into OUT, then opened (decoded into the event cache) in a child process whose peak RSS is reported;
  the bag and its cache are deleted afterwards.

Writes ``live.csv`` and ``live.md`` (one row per run) and prints the figures with ``uptime``'s load.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import statistics
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from benchmarks.soak import rss_mb

ROTATION_CUTS = ("shapes_rotation", "boxes_rotation", "dynamic_rotation", "poster_rotation")
SLIDER_TRUTH = (-110.0, 0.0)  # px/s, the dominant depth's flow (../shared/data/README.md)


def load() -> str:
    return os.getloadavg().__repr__()


def rss_of(pid: int) -> float:
    with open(f"/proc/{pid}/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


# --- accuracy --------------------------------------------------------------------------------------------
def rotation_errors(rows, gyro) -> tuple[float, float]:
    """(median over the windows, duration-weighted mean's) relative error of the angular velocity."""
    from cmax_taichi import metrics

    theta = np.array([r.theta for r in rows])
    per = metrics.angular_velocity_error(theta, np.broadcast_to(gyro, theta.shape))["relative"]
    weights = np.array([r.t_end - r.t_start for r in rows])
    mean = np.average(theta, axis=0, weights=weights)
    return float(np.median(per)), float(metrics.angular_velocity_error(mean, gyro)["relative"][0])


def translation_error(rows, truth) -> float:
    truth = np.asarray(truth)
    errors = [np.linalg.norm(np.asarray(r.theta[:2]) - truth) / np.linalg.norm(truth) for r in rows]
    return float(np.median(errors))


def baseline(folder: Path, warp: str, n_events: int = 30000):
    """``sequence.process`` rows of ``n_events``-event windows (the partial tail kept)."""
    from cmax_taichi import io
    from cmax_taichi.solve.sequence import process

    with warnings.catch_warnings(), io.open_recording(folder) as rec:
        warnings.simplefilter("ignore")
        result = process(rec, warp, n_events=min(n_events, rec.n_events), keep_tail=True, progress=False)
    return result.windows


# --- runs ------------------------------------------------------------------------------------------------
def live_run(stream_factory, warp: str, camera, rule, on_ready=None) -> tuple:
    from cmax_taichi.solve.online import run_live

    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        stream = stream_factory()
        result = run_live(
            stream, warp, camera=camera, windows=rule, on_ready=on_ready,
            on_window=lambda row, prob, res, latency: rows.append(row),
        )  # fmt: skip
    return result, rows


def tcp_case(data: Path, name: str, warp: str, speed: float, rule) -> dict:
    from cmax_taichi import io
    from cmax_taichi.io.streams import open_stream, start_replay_server

    folder = data / name
    with io.open_recording(folder) as rec:
        camera, n_total = rec.camera, rec.n_events
        gyro = rec.angular_velocity(0.5 * (rec.t_start + rec.t_end)) if warp == "rotation3" else None
        span = rec.t_end - rec.t_start
    server = start_replay_server(folder, speed=speed, linger=0.3, wait_for_go=True, wait_for_client=900)
    load_before = load()
    try:
        result, rows = live_run(lambda: open_stream(server.address, camera=camera), warp, camera, rule,
                                on_ready=server.go.set)  # fmt: skip
    finally:
        server.stop()
    row = summary_row(f"{name} (TCP, {speed:g}x)", warp, result, rows, n_total, span / speed, load_before)
    if gyro is not None:
        row["error_median"], row["error_mean"] = rotation_errors(rows, gyro)
    else:
        row["error_median"] = translation_error(rows, SLIDER_TRUTH)
    return row


def summary_row(case: str, warp: str, result, rows, n_total: int, replay_seconds: float, load_before) -> dict:
    ev = result.events
    return {
        "case": case,
        "warp": warp,
        "events": ev["total"],
        "events_sent": n_total,
        "estimated": ev["estimated"],
        "behind": ev.get("behind", 0),
        "windows": result.windows,
        "events_per_window_median": statistics.median(r.n_events for r in rows) if rows else 0,
        "ms_per_window_median": 1e3 * statistics.median(r.t_end - r.t_start for r in rows) if rows else 0,
        "first_window_s": result.first_window_seconds,
        "first_window_search": getattr(rows[0], "search", "") if rows else "",
        "warm_up_s": result.warm_up_seconds,
        "busy_s": result.busy_seconds,
        "data_s": result.data_seconds,
        "replay_s": replay_seconds,
        "real_time_factor": result.real_time_factor(),
        "latency_median_ms": 1e3 * result.latency(50),
        "latency_p99_ms": 1e3 * result.latency(99),
        "latency_max_ms": 1e3 * float(np.max(result.latencies)) if len(result.latencies) else math.nan,
        "end_latency_ms": 1e3 * result.end_latency,
        "load": f"{load_before} -> {load()}",
    }


def run_tcp(data: Path, rounds: int, rule, log) -> list[dict]:
    cases = [(f"ecd_rotation/{cut}", "rotation3", 1.0) for cut in ROTATION_CUTS]
    cases += [("ecd_slider_depth", "translation2", 1.0), ("ecd_slider_depth", "translation2", 2.0)]
    cases = [c for c in cases if (data / c[0]).exists()]
    base = {}
    for name, warp, _ in cases:
        rows = baseline(data / name, warp)
        if warp == "rotation3":
            from cmax_taichi import io

            with io.open_recording(data / name) as rec:
                gyro = rec.angular_velocity(0.5 * (rec.t_start + rec.t_end))
            base[name] = rotation_errors(rows, gyro)
        else:
            base[name] = (translation_error(rows, SLIDER_TRUTH), math.nan)
    out = []
    for k in range(rounds):
        for name, warp, speed in cases:
            row = tcp_case(data, name, warp, speed, rule)
            row["round"] = k
            row["baseline_30k_error"] = base[name][0]
            out.append(row)
            log(format_row(row))
    return out


def run_hd(out_dir: Path, seconds: float, rounds: int, rule, log) -> list[dict]:
    from cmax_taichi import Events
    from cmax_taichi.io.streams import ReplayStream
    from cmax_taichi.lab import realtime

    path = out_dir / "hd_stream.npz"
    if path.exists():
        z = np.load(path)
        events = Events(z["x"], z["y"], z["t"], z["p"], tuple(int(v) for v in z["sensor"]))
    else:
        log(f"simulating {seconds:g} s of the 1280x720 stream (once) ...")
        events, _ = realtime.simulated_stream(seconds, sensor=realtime.HD_SENSOR, motion=realtime.HD_MOTION)
        np.savez(path, x=events.x, y=events.y, t=events.t, p=events.p, sensor=np.array(events.sensor_size))
    camera = None  # translation2 needs none; the simulated events are already on the pinhole grid
    rows_out = []
    for k in range(rounds):
        load_before = load()
        result, rows = live_run(lambda: ReplayStream(events), "translation2", camera, rule)
        row = summary_row("1280x720 simulated, 1x (in-process replay)", "translation2", result, rows,
                          len(events), events.duration, load_before)  # fmt: skip
        row["error_median"] = translation_error(rows, realtime.HD_MOTION)
        row["events_per_second"] = len(events) / events.duration
        row["round"] = k
        rows_out.append(row)
        log(format_row(row))
    return rows_out


#: the dense flows of the flow part: (label, DenseFlowEstimator options, windows: events or "adaptive")
FLOW_CASES = (
    ("16x16 cells, 4 levels, 30,000-event windows", {}, 30000),
    ("8x8 cells, 3 levels, 30,000-event windows", {"grid": (8, 8), "levels": 3}, 30000),
    ("16x16 cells, 4 levels, adaptive windows", {}, "adaptive"),
)


def flow_case(data: Path, label: str, options: dict, windows, speed: float = 1.0) -> dict:
    """slider_depth through TCP, its dense flow estimated live (see the module docstring)."""
    from cmax_taichi import io
    from cmax_taichi.flow import DenseFlowEstimator
    from cmax_taichi.flow.live import run_live_flow
    from cmax_taichi.io.streams import open_stream, start_replay_server
    from cmax_taichi.solve.adaptive import AdaptiveWindows

    folder = data / "ecd_slider_depth"
    with io.open_recording(folder) as rec:
        camera, n_total, span = rec.camera, rec.n_events, rec.t_end - rec.t_start
    server = start_replay_server(folder, speed=speed, linger=0.3, wait_for_go=True, wait_for_client=900)
    rows, flows = [], []

    def on_window(row, estimator, result, latency):
        rows.append(row)
        flows.append(np.median(result.nodes.reshape(-1, 2), axis=0))

    load_before = load()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = run_live_flow(
                open_stream(server.address, camera=camera), DenseFlowEstimator(**options),
                windows=AdaptiveWindows() if windows == "adaptive" else windows, on_ready=server.go.set,
                on_window=on_window,
            )  # fmt: skip
    finally:
        server.stop()
    row = summary_row(f"slider_depth, {label} (TCP, {speed:g}x)", "dense_flow", result, rows, n_total,
                      span / speed, load_before)  # fmt: skip
    u, v = np.median(np.array(flows), axis=0) if flows else (math.nan, math.nan)
    row["flow_median_u"], row["flow_median_v"] = float(u), float(v)
    return row


def run_flow(data: Path, rounds: int, log) -> list[dict]:
    out = []
    for k in range(rounds):
        for label, options, windows in FLOW_CASES:
            row = flow_case(data, label, options, windows)
            row["round"] = k
            out.append(row)
            log(
                format_row(row)
                + f"; median flow ({row['flow_median_u']:.1f}, {row['flow_median_v']:.1f}) px/s"
            )
    return out


def flow_markdown(rows: list[dict]) -> str:
    lines = [
        "| case | events | windows (median events, ms of data) | behind | first window (ms) | "
        "real-time factor, first window included | latency median / p99 (ms) | last window (ms) | "
        "median node flow (px/s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['events']:.0f} | {r['windows']:.0f} ({r['events_per_window_median']:.0f}, "
            f"{r['ms_per_window_median']:.1f}) | {r['behind']:.0f} | {1e3 * r['first_window_s']:.0f} | "
            f"{r['real_time_factor']:.3f} | {r['latency_median_ms']:.0f} / {r['latency_p99_ms']:.0f} | "
            f"{r['end_latency_ms']:.0f} | ({r['flow_median_u']:.1f}, {r['flow_median_v']:.1f}) |"
        )
    return "\n".join(lines) + "\n"


def write_table(rows: list[dict], path: Path) -> None:
    """Every run's row as CSV."""
    with path.open("w", newline="") as fh:
        columns = sorted(
            {k for r in rows for k in r}, key=lambda k: list(rows[0]).index(k) if k in rows[0] else 99
        )
        w = csv.DictWriter(fh, fieldnames=columns, restval="")
        w.writeheader()
        w.writerows(rows)


def run_soak(data: Path, out_dir: Path, minutes: float, rule, log) -> dict:
    from cmax_taichi import io
    from cmax_taichi.io.streams import open_stream, start_replay_server

    folder = data / "ecd_slider_depth"
    with io.open_recording(folder) as rec:
        camera, span = rec.camera, rec.t_end - rec.t_start
    loops = int(math.ceil(minutes * 60 / span)) + 1
    server = start_replay_server(folder, loops=loops, linger=0.3, wait_for_go=True, wait_for_client=900)
    samples = []
    stop = threading.Event()
    stream_box = {}

    def sample() -> None:
        t0 = time.perf_counter()
        while not stop.wait(2.0):
            child = stream_box.get("pid")
            samples.append((time.perf_counter() - t0, rss_mb(), rss_of(child) if child else math.nan))

    def factory():
        stream = open_stream(server.address, camera=camera)
        stream_box["pid"] = stream._process.pid
        return stream

    sampler = threading.Thread(target=sample, daemon=True)
    load_before = load()
    stopper = threading.Event()

    def on_ready():  # the replay, the samples and the clock of the run start together
        server.go.set()
        sampler.start()
        threading.Timer(minutes * 60, stopper.set).start()

    from cmax_taichi.solve.online import run_live

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_live(
            factory(), "translation2", camera=camera, windows=rule, on_ready=on_ready, stop=stopper
        )
    stop.set()
    server.stop()
    with (out_dir / "soak_live.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["seconds", "rss_mb", "reader_rss_mb"])
        w.writerows(samples)
    after_minute = [s for s in samples if s[0] >= 60.0]
    rss = [s[1] for s in after_minute] or [math.nan]
    child = [s[2] for s in after_minute] or [math.nan]
    row = {
        "case": f"slider_depth looped {minutes:g} min (TCP)",
        "windows": result.windows,
        "behind": result.events.get("behind", 0),
        "events": result.events["total"],
        "real_time_factor": result.real_time_factor(),
        "latency_median_ms": 1e3 * result.latency(50),
        "latency_p99_ms": 1e3 * result.latency(99),
        "rss_first_minute_end_mb": rss[0],
        "rss_last_mb": rss[-1],
        "rss_growth_after_first_minute_mb": rss[-1] - rss[0],
        "rss_range_after_first_minute_mb": max(rss) - min(rss),
        "reader_rss_range_after_first_minute_mb": max(child) - min(child),
        "load": f"{load_before} -> {load()}",
    }
    log(json.dumps(row))
    return row


def write_bag(path: Path, folder: Path, gigabytes: float, log) -> int:
    """A ROS1 bag of slider_depth's events tiled in time, ``gigabytes`` GB, 50,000 events a message."""
    from rosbags.rosbag1 import Writer

    from cmax_taichi import io
    from cmax_taichi.io.rosbag import typestore
    from cmax_taichi.testing.bags import event_times_ns, ros1_event_array_bytes

    with io.open_recording(folder) as rec:
        ev = rec.read()
    W, H = ev.sensor_size
    ns = event_times_ns(ev.t)
    period = int(ns[-1] - ns[0]) + 1000
    per = 50_000
    target = int(gigabytes * 1e9)
    written = events = k = 0
    with Writer(path) as writer:
        connection = writer.add_connection(
            "/dvs/events", "dvs_msgs/msg/EventArray", typestore=typestore(False)
        )
        while written < target:
            shift = 10**9 + k * period
            for a in range(0, len(ev), per):
                sl = slice(a, a + per)
                data = ros1_event_array_bytes(ev.x[sl], ev.y[sl], ns[sl] + shift, ev.p[sl] > 0, W, H, seq=k)
                writer.write(connection, int(ns[sl][-1] + shift), data)
                written += len(data)
                events += len(ev.x[sl])
            k += 1
    log(f"wrote {path}: {path.stat().st_size / 1e9:.2f} GB, {events} events")
    return events


_READ_BAG = """
import json, resource, sys, time
t0 = time.perf_counter()
from cmax_taichi.io import open_recording
with open_recording(sys.argv[1], cache_dir=sys.argv[2]) as rec:
    n = rec.n_events
    tail = rec.read(n - 5, n)
print(json.dumps({"events": n, "seconds": time.perf_counter() - t0,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
                  "last_t": float(tail.t[-1])}))
"""


def run_bag(data: Path, out_dir: Path, gigabytes: float, keep: bool, log) -> dict:
    path, cache = out_dir / "big.bag", out_dir / "bag_cache"
    load_before = load()
    events = write_bag(path, data / "ecd_slider_depth", gigabytes, log)
    try:
        proc = subprocess.run([sys.executable, "-c", _READ_BAG, str(path), str(cache)],
                              capture_output=True, text=True, check=True)  # fmt: skip
        read = json.loads(proc.stdout.strip().splitlines()[-1])
    finally:
        if not keep:
            path.unlink(missing_ok=True)
            for f in cache.glob("*"):
                f.unlink()
    row = {
        "case": f"ROS1 bag, {gigabytes:g} GB",
        "bag_events": events,
        **read,
        "load": f"{load_before} -> {load()}",
    }
    log(json.dumps(row))
    return row


def format_row(row: dict) -> str:
    parts = [row["case"], f"RTF {row['real_time_factor']:.2f}", f"windows {row['windows']}",
             f"behind {row['behind']}", f"latency median {row['latency_median_ms']:.1f} ms",
             f"p99 {row['latency_p99_ms']:.1f} ms", f"first window {row['first_window_s'] * 1e3:.1f} ms "
             f"({row['first_window_search']})", f"error {row.get('error_median', math.nan):.3f}"]  # fmt: skip
    if "error_mean" in row:
        parts.append(f"(mean's {row['error_mean']:.3f}; 30k windows {row['baseline_30k_error']:.3f})")
    return ", ".join(parts) + f"; load {row['load']}"


def medians(rows: list[dict]) -> list[dict]:
    """One row per case: the median of each number over the rounds."""
    by_case: dict[str, list[dict]] = {}
    for row in rows:
        by_case.setdefault(row["case"], []).append(row)
    out = []
    for case, group in by_case.items():
        merged = {"case": case, "rounds": len(group)}
        for key, value in group[0].items():
            if isinstance(value, (int, float)) and key not in ("round",):
                merged[key] = statistics.median(g[key] for g in group)
            elif key not in merged:
                merged[key] = value
        merged["load"] = "; ".join(g["load"] for g in group)
        out.append(merged)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", default="../shared/data")
    parser.add_argument("--out", default="bench_live")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--parts", default="tcp,hd,flow,soak,bag")
    parser.add_argument("--hd-seconds", type=float, default=0.5)
    parser.add_argument("--soak-minutes", type=float, default=10.0)
    parser.add_argument("--bag-gb", type=float, default=2.0)
    parser.add_argument("--keep-bag", action="store_true")
    parser.add_argument("--target-px", type=float, default=None)
    args = parser.parse_args(argv)
    from cmax_taichi.core import backend
    from cmax_taichi.solve.adaptive import AdaptiveWindows

    # the optimized kernels (compiled, or loaded from the cache, by each run's warm-up before its replay):
    # with the default "auto" a sensor whose optimized kernels are not cached yet would run its few
    # seconds of replay on the quick ones, while they compile in the background
    backend.init_if_needed(None, None, "full")
    data, out = Path(args.data), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rule = AdaptiveWindows() if args.target_px is None else AdaptiveWindows(target_px=args.target_px)
    parts = set(args.parts.split(","))
    log = print
    log(f"rule {rule.as_dict()}; load {load()}")
    rows = []
    if "tcp" in parts:
        rows += run_tcp(data, args.rounds, rule, log)
    if "hd" in parts:
        rows += run_hd(out, args.hd_seconds, args.rounds, rule, log)
    table = medians(rows)
    if table:
        write_table(rows, out / "live.csv")
        (out / "live.md").write_text(markdown(table))
        log(markdown(table))
    if "flow" in parts:
        flow_rows = run_flow(data, args.rounds, log)
        write_table(flow_rows, out / "live_flow.csv")
        (out / "live_flow.md").write_text(flow_markdown(medians(flow_rows)))
        log(flow_markdown(medians(flow_rows)))
    if "soak" in parts:
        (out / "soak.json").write_text(
            json.dumps(run_soak(data, out, args.soak_minutes, rule, log), indent=1)
        )
    if "bag" in parts:
        (out / "bag.json").write_text(
            json.dumps(run_bag(data, out, args.bag_gb, args.keep_bag, log), indent=1)
        )
    return 0


def markdown(rows: list[dict]) -> str:
    lines = [
        "| case | warp | events | windows (median events, ms) | behind | first window (ms, search) | "
        "real-time factor | latency median / p99 (ms) | error (median; mean's) | 30k windows' error |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        mean = f"; {r['error_mean']:.3f}" if "error_mean" in r else ""
        base = f"{r['baseline_30k_error']:.3f}" if "baseline_30k_error" in r else ""
        lines.append(
            f"| {r['case']} | {r['warp']} | {r['events']:.0f} | {r['windows']:.0f} "
            f"({r['events_per_window_median']:.0f}, {r['ms_per_window_median']:.1f}) | {r['behind']:.0f} | "
            f"{1e3 * r['first_window_s']:.1f} "
            f"({r['first_window_search']}) | {r['real_time_factor']:.2f} | {r['latency_median_ms']:.1f} / "
            f"{r['latency_p99_ms']:.1f} | {r['error_median']:.3f}{mean} | {base} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
