"""Real-time factor of whole recordings: ``cmax-taichi bench --realtime``.

Runs :func:`cmax_taichi.solve.sequence.process` (warm start, FWL on) over the shared real recordings
(``../shared/data`` or ``--data``; a recording that is absent is reported as skipped) and over long
simulated streams, and reports per run: windows, data per window, the median evaluations and wall time
of a warm-started window, the first window's seconds and evaluations (the problem's set-up and the
global search), and the real-time factor (seconds of data per wall second) with the first window
included and without it. Each run is preceded by its first window alone, which loads the kernels of
that sensor and model into the process (or compiles them, with a cold offline cache): that fixed cost
of a process is reported in its own column, and ``cmax-taichi estimate``'s whole process time in
benchmarks/NOTES.md.

Cases (:data:`CASES`): ECD slider_depth with translation2, the four ECD rotation cuts with rotation3,
MVSEC indoor_flying1 with mitrokhin4 and both regularizers, all at 5,000-event windows; the simulated
stream (a textured plane translating at (80, -50) px/s, 240x180, ``--sim-seconds`` long) with
translation2 and with mitrokhin4 and both regularizers, in windows of :data:`SIM_WINDOW_EVENTS` events;
and a simulated 1280x720 stream of about one million events per second (the plane at (50, -30) px/s,
:data:`HD_SECONDS` long) with translation2, in windows of :data:`HD_WINDOW_EVENTS` events.

Each row also says how good the estimates were, so that a fast run of a degenerate solve shows: the
windows whose estimate is the identity warp exactly (the spike of events at their integer pixel
coordinates, the sharpest image when a window holds about a pixel of motion or less), and on the
simulated streams the median error of the estimated translation (the first two parameters) against
the simulated motion, relative to its speed.
"""

from __future__ import annotations

import csv
import statistics
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cmax_taichi.core import limits

__all__ = ["CASES", "RealtimeCase", "run_realtime"]

BOTH_REGULARIZERS = {"divergence": 10.0, "deformation": 10.0}
SIMULATED_MOTION = (80.0, -50.0)  # px/s
#: the HD stream: a 1280x720 sensor and the motion that makes the simulator's textured plane give about
#: 1 million events per second
HD_SENSOR = (1280, 720)
HD_MOTION = (50.0, -30.0)  # px/s
#: seconds of the HD stream (about 500,000 events; simulating them takes a minute or two)
HD_SECONDS = 0.5
#: the shared recordings beside the checkout, read when --data is not given
DEFAULT_DATA = "../shared/data"
#: events per window of the HD stream: the textured plane gives about 19,000 events per px of motion
#: there, so a 5,000-event window holds 0.3 px of it and every estimate was the identity (docs/
#: performance.md, 2026-12-04); 50,000 events (about 45 ms, 2.5 px) is a window that can be estimated
HD_WINDOW_EVENTS = 50_000
#: events per window of the 240x180 simulated stream: about 4,500 events per px of motion there, so a
#: 5,000-event window holds 1.1 px and every estimate was the identity, as on the HD stream; 20,000
#: events (about 47 ms, 4.5 px) can be estimated
SIM_WINDOW_EVENTS = 20_000


@dataclass(frozen=True)
class RealtimeCase:
    """One run: a recording (a folder under the data directory, or ``"simulated"``) and its settings."""

    name: str
    source: str
    warp: str
    regularizers: dict = field(default_factory=dict)
    n_events: int = 5000
    #: the simulated translation (px/s) of a simulated stream, against which the estimates are scored
    truth: tuple[float, float] | None = None


CASES = (
    RealtimeCase("ECD slider_depth", "ecd_slider_depth", "translation2"),
    *(
        RealtimeCase(f"ECD {cut}", f"ecd_rotation/{cut}", "rotation3")
        for cut in ("shapes_rotation", "boxes_rotation", "dynamic_rotation", "poster_rotation")
    ),
    RealtimeCase("MVSEC indoor_flying1", "mvsec_indoor_flying1", "mitrokhin4", BOTH_REGULARIZERS),
    RealtimeCase(
        "simulated stream", "simulated", "translation2", n_events=SIM_WINDOW_EVENTS, truth=SIMULATED_MOTION
    ),
    RealtimeCase(
        "simulated stream",
        "simulated",
        "mitrokhin4",
        BOTH_REGULARIZERS,
        n_events=SIM_WINDOW_EVENTS,
        truth=SIMULATED_MOTION,
    ),
    RealtimeCase(
        "simulated 1280x720 stream",
        "simulated-hd",
        "translation2",
        n_events=HD_WINDOW_EVENTS,
        truth=HD_MOTION,
    ),
)


def simulated_stream(seconds: float, seed: int = 0, sensor=(240, 180), motion=SIMULATED_MOTION):
    """``(events, camera)``: ``seconds`` of a textured plane translating at ``motion`` (px/s) seen by a
    ``sensor`` camera (the simulator of :mod:`cmax_taichi.sim`; 240x180 at :data:`SIMULATED_MOTION`:
    about 420,000 events/s; :data:`HD_SENSOR` at :data:`HD_MOTION`: about 1 million)."""
    from cmax_taichi.sim import default_camera
    from cmax_taichi.sim.examples import _SIM
    from cmax_taichi.sim.scenes import warp_scene
    from cmax_taichi.sim.simulator import simulate

    camera = default_camera(sensor)
    scene = warp_scene("translation2", motion, sensor, texture="minduka", camera=camera)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        recording = simulate(scene, seconds, seed=seed, **_SIM)
    return recording.events(), camera


def _row(case: RealtimeCase, result, wall: float, event_rate: float) -> dict:
    warm = result.windows[1:]
    first = result.windows[0] if result.windows else None
    durations = [w.t_end - w.t_start for w in result.windows]
    return {
        "recording": case.name,
        "warp": case.warp,
        "regularizers": "+".join(f"{k}={v:g}" for k, v in case.regularizers.items()) or "none",
        "window_events": case.n_events,
        "events_per_second": event_rate,
        "windows": len(result.windows),
        "data_per_window_ms": 1e3 * statistics.median(durations) if durations else float("nan"),
        "warm_evaluations_median": statistics.median(w.evaluations for w in warm) if warm else float("nan"),
        "warm_window_ms_median": 1e3 * statistics.median(w.seconds for w in warm) if warm else float("nan"),
        "global_searches_after_first": sum(1 for w in warm if w.search != "warm"),
        "first_window_s": first.seconds if first else float("nan"),
        "first_window_evaluations": first.evaluations if first else 0,
        "real_time_factor": result.real_time_factor(),
        "real_time_factor_with_first": result.real_time_factor(skip_first=False),
        "identity_windows": result.identity_windows(),
        "translation_error_median": _translation_error(result.windows, case.truth),
        "wall_s": wall,
        "status": "ok",
    }


def _translation_error(windows, truth) -> float:
    """Median over ``windows`` of ``|theta[:2] - truth| / |truth|`` (NaN without a truth)."""
    if truth is None or not windows:
        return float("nan")
    truth = np.asarray(truth, dtype=np.float64)
    errors = [float(np.linalg.norm(np.asarray(w.theta[:2]) - truth)) for w in windows]
    return statistics.median(errors) / float(np.linalg.norm(truth))


def run_realtime(
    data_dir: str | Path | None,
    out_dir: str | Path,
    *,
    sim_seconds: float = 2.0,
    hd_seconds: float = HD_SECONDS,
    cases: tuple[RealtimeCase, ...] = CASES,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """Run ``cases`` and write ``realtime.csv`` and ``realtime.md`` into ``out_dir``; returns the rows.

    Parameters
    ----------
    data_dir : path
        Folder of the shared recordings (cases whose folder is absent are reported as skipped); None:
        :data:`DEFAULT_DATA`, where it is. A folder that does not exist is a ValueError.
    out_dir : path
        Output folder (created; guarded as every command's: :class:`cmax_taichi.io.outputs.OutputFolder`).
    sim_seconds : float
        Length of the simulated 240x180 stream, s (about 420,000 events per second).
    hd_seconds : float
        Length of the simulated 1280x720 stream, s (about 1 million events per second).
    """
    from cmax_taichi.solve.sequence import process

    if not (np.isfinite(sim_seconds) and sim_seconds > 0):
        raise ValueError(f"--sim-seconds must be a positive number of seconds, got {sim_seconds}")
    if not (np.isfinite(hd_seconds) and hd_seconds > 0):
        raise ValueError(f"hd_seconds must be a positive number of seconds, got {hd_seconds}")
    streams = ((sim_seconds, 420_000, "--sim-seconds"), (hd_seconds, 1_000_000, "hd_seconds"))
    for seconds, rate, what in streams:
        # the stream is held whole (x, y, t, p: 8 bytes each): refused before hours of simulation
        what = f"the simulated stream of {what} {seconds:g}"
        limits.check_bytes(int(seconds * rate * 32), what, f"about {rate:,} events/s")
    if data_dir is None:  # the shared recordings beside the checkout, where there are
        data_dir = Path(DEFAULT_DATA)
    elif not Path(data_dir).is_dir():
        raise ValueError(f"{data_dir}: no such folder of recordings (--data)")
    data_dir = Path(data_dir)
    from cmax_taichi.io.outputs import OutputFolder

    folder = OutputFolder(
        out_dir, inputs=[data_dir], patterns=["realtime.csv", "realtime.md"], command="bench"
    )
    folder.check()  # an out_dir that holds the data, or files this run may not replace: before any work
    streams: dict = {}
    rows = []
    for case in cases:
        if case.source in ("simulated", "simulated-hd"):
            if case.source not in streams:
                hd = case.source == "simulated-hd"
                seconds, sensor, motion = (
                    (hd_seconds, HD_SENSOR, HD_MOTION) if hd else (sim_seconds, (240, 180), SIMULATED_MOTION)
                )
                log(
                    f"simulating {seconds:g} s of a plane translating at {motion} px/s, "
                    f"{sensor[0]}x{sensor[1]} ..."
                )
                streams[case.source] = simulated_stream(seconds, sensor=sensor, motion=motion)
            source, camera = streams[case.source]
        else:
            source, camera = data_dir / case.source, None
            if not source.exists():
                log(f"{case.name}: {source} not found, skipped")
                rows.append({"recording": case.name, "warp": case.warp, "status": f"skipped: no {source}"})
                continue
        log(
            f"{case.name}: {case.warp}, regularizers {case.regularizers or 'none'}, "
            f"{case.n_events}-event windows"
        )
        options = dict(
            regularizers=case.regularizers or None, camera=camera, n_events=case.n_events, progress=False
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # undistortion drops: counted by the reader
            # the first window once before the timed run: it loads (or compiles) the kernels of this
            # sensor and model into the process, the command's fixed cost, reported in its own column
            t0 = time.perf_counter()
            process(source, case.warp, max_windows=1, **options)
            load = time.perf_counter() - t0
            t0 = time.perf_counter()
            result = process(source, case.warp, **options)
        rate = float("nan")
        if result.windows:
            span = result.windows[-1].t_end - result.windows[0].t_start
            rate = sum(w.n_events for w in result.windows) / span if span > 0 else float("nan")
        row = _row(case, result, time.perf_counter() - t0, rate)
        row["kernels_and_first_window_s"] = load
        log(
            f"  {row['windows']} windows, real-time factor {row['real_time_factor_with_first']:.2f} with the "
            f"first window ({row['first_window_s']:.2f} s, {row['first_window_evaluations']} evaluations), "
            f"{row['real_time_factor']:.2f} without it; warm window {row['warm_window_ms_median']:.1f} ms / "
            f"{row['warm_evaluations_median']:g} evaluations (median); {row['identity_windows']} window(s) "
            f"at the identity"
            + (
                f", translation error {100 * row['translation_error_median']:.1f}% (median)"
                if case.truth is not None
                else ""
            )
        )
        rows.append(row)
    columns = list(next((r for r in rows if r["status"] == "ok"), rows[0]).keys()) if rows else []
    with folder:
        with folder.path("realtime.csv").open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=columns, restval="")
            writer.writeheader()
            writer.writerows(rows)
        folder.path("realtime.md").write_text(markdown(rows))
        written = folder.commit()
    log(f"wrote {' and '.join(str(p) for p in written)}")
    return rows


def markdown(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    lines = [
        "| recording | warp | regularizers | events/s (M) | windows | data per window (ms) | kernels "
        "loaded + first window (s) | first window (s / evaluations) | warm window (ms / evaluations, median) "
        "| global searches after the first | real-time factor, first window included | without the first "
        "window | windows at the identity | translation error (median, % of the speed) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r["status"] != "ok":
            lines.append(f"| {r['recording']} | {r['warp']} | | | | | | | | | | | | {r['status']} |")
            continue
        lines.append(
            f"| {r['recording']} | {r['warp']} | {r['regularizers']} | {r['events_per_second'] / 1e6:.2f} | "
            f"{r['windows']} | {r['data_per_window_ms']:.1f} | {r['kernels_and_first_window_s']:.2f} | "
            f"{r['first_window_s']:.3f} / "
            f"{r['first_window_evaluations']} | {r['warm_window_ms_median']:.1f} / "
            f"{r['warm_evaluations_median']:g} | {r['global_searches_after_first']} | "
            f"{r['real_time_factor_with_first']:.2f} | {r['real_time_factor']:.2f} | "
            f"{r['identity_windows']} | {_percent(r['translation_error_median'])} |"
        )
    return "\n".join(lines) + "\n"


def _percent(fraction: float) -> str:
    return "" if not np.isfinite(fraction) else f"{100 * fraction:.1f}"
