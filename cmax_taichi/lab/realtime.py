"""Real-time factor of whole recordings: ``cmax-taichi bench --realtime``.

Runs :func:`cmax_taichi.solve.sequence.process` (warm start, FWL on) over the shared real recordings
(``../shared/data`` or ``--data``; a recording that is absent is reported as skipped) and over a long
simulated stream, and reports per run: windows, data per window, the median evaluations and wall time
of a warm-started window, the real-time factor (seconds of data per wall second, without the first
window, whose time includes compiling and the global search) and the first window's seconds.

Cases (:data:`CASES`): ECD slider_depth with translation2, the four ECD rotation cuts with rotation3,
MVSEC indoor_flying1 with mitrokhin4 and both regularizers, all at 5,000-event windows; the simulated
stream (a textured plane translating at (80, -50) px/s, 240x180, ``--sim-seconds`` long) with
translation2 and with mitrokhin4 and both regularizers.
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

__all__ = ["CASES", "RealtimeCase", "run_realtime"]

BOTH_REGULARIZERS = {"divergence": 10.0, "deformation": 10.0}
SIMULATED_MOTION = (80.0, -50.0)  # px/s


@dataclass(frozen=True)
class RealtimeCase:
    """One run: a recording (a folder under the data directory, or ``"simulated"``) and its settings."""

    name: str
    source: str
    warp: str
    regularizers: dict = field(default_factory=dict)
    n_events: int = 5000


CASES = (
    RealtimeCase("ECD slider_depth", "ecd_slider_depth", "translation2"),
    *(
        RealtimeCase(f"ECD {cut}", f"ecd_rotation/{cut}", "rotation3")
        for cut in ("shapes_rotation", "boxes_rotation", "dynamic_rotation", "poster_rotation")
    ),
    RealtimeCase("MVSEC indoor_flying1", "mvsec_indoor_flying1", "mitrokhin4", BOTH_REGULARIZERS),
    RealtimeCase("simulated stream", "simulated", "translation2"),
    RealtimeCase("simulated stream", "simulated", "mitrokhin4", BOTH_REGULARIZERS),
)


def simulated_stream(seconds: float, seed: int = 0):
    """``(events, camera)``: ``seconds`` of a textured plane translating at :data:`SIMULATED_MOTION`
    seen by a 240x180 camera (the simulator of :mod:`cmax_taichi.sim`, about 420,000 events/s)."""
    from cmax_taichi.sim.examples import _SIM, default_camera
    from cmax_taichi.sim.scenes import warp_scene
    from cmax_taichi.sim.simulator import simulate

    sensor = (240, 180)
    camera = default_camera(sensor)
    scene = warp_scene("translation2", SIMULATED_MOTION, sensor, texture="minduka", camera=camera)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        recording = simulate(scene, seconds, seed=seed, **_SIM)
    return recording.events(), camera


def _row(case: RealtimeCase, result, wall: float) -> dict:
    warm = result.windows[1:]
    durations = [w.t_end - w.t_start for w in result.windows]
    return {
        "recording": case.name,
        "warp": case.warp,
        "regularizers": "+".join(f"{k}={v:g}" for k, v in case.regularizers.items()) or "none",
        "window_events": case.n_events,
        "windows": len(result.windows),
        "data_per_window_ms": 1e3 * statistics.median(durations) if durations else float("nan"),
        "warm_evaluations_median": statistics.median(w.evaluations for w in warm) if warm else float("nan"),
        "warm_window_ms_median": 1e3 * statistics.median(w.seconds for w in warm) if warm else float("nan"),
        "global_searches_after_first": sum(1 for w in warm if w.search != "warm"),
        "real_time_factor": result.real_time_factor(),
        "first_window_s": result.windows[0].seconds if result.windows else float("nan"),
        "wall_s": wall,
        "status": "ok",
    }


def run_realtime(
    data_dir: str | Path,
    out_dir: str | Path,
    *,
    sim_seconds: float = 2.0,
    cases: tuple[RealtimeCase, ...] = CASES,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """Run ``cases`` and write ``realtime.csv`` and ``realtime.md`` into ``out_dir``; returns the rows.

    Parameters
    ----------
    data_dir : path
        Folder of the shared recordings (cases whose folder is absent are reported as skipped).
    out_dir : path
        Output folder (created).
    sim_seconds : float
        Length of the simulated stream, s (about 420,000 events per second).
    """
    from cmax_taichi.solve.sequence import process

    if not (np.isfinite(sim_seconds) and sim_seconds > 0):
        raise ValueError(f"--sim-seconds must be a positive number of seconds, got {sim_seconds}")
    data_dir, out = Path(data_dir), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stream = None
    rows = []
    for case in cases:
        if case.source == "simulated":
            if stream is None:
                log(f"simulating {sim_seconds:g} s of a plane translating at {SIMULATED_MOTION} px/s ...")
                stream = simulated_stream(sim_seconds)
            source, camera = stream
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
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # undistortion drops: counted by the reader
            result = process(
                source,
                case.warp,
                regularizers=case.regularizers or None,
                camera=camera,
                n_events=case.n_events,
                progress=False,
            )
        row = _row(case, result, time.perf_counter() - t0)
        log(
            f"  {row['windows']} windows, real-time factor {row['real_time_factor']:.2f}, warm window "
            f"{row['warm_window_ms_median']:.1f} ms / {row['warm_evaluations_median']:g} evaluations (median)"
        )
        rows.append(row)
    columns = list(next((r for r in rows if r["status"] == "ok"), rows[0]).keys()) if rows else []
    with (out / "realtime.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(rows)
    (out / "realtime.md").write_text(markdown(rows))
    log(f"wrote {out / 'realtime.csv'} and {out / 'realtime.md'}")
    return rows


def markdown(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    lines = [
        "| recording | warp | regularizers | windows | data per window (ms) | evaluations per warm window "
        "(median) | warm window (ms, median) | global searches after the first | real-time factor |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r["status"] != "ok":
            lines.append(f"| {r['recording']} | {r['warp']} | | | | | | | {r['status']} |")
            continue
        lines.append(
            f"| {r['recording']} | {r['warp']} | {r['regularizers']} | {r['windows']} | "
            f"{r['data_per_window_ms']:.1f} | {r['warm_evaluations_median']:g} | "
            f"{r['warm_window_ms_median']:.1f} | {r['global_searches_after_first']} | "
            f"{r['real_time_factor']:.2f} |"
        )
    return "\n".join(lines) + "\n"
