"""The default global search of ``maximize()`` (coarse to fine, ``solve/pyramid.py``) against a thorough
2,000-point grid search followed by the same local refinement, on the first window of the shared
recordings, the simulator and the collapse-enabled 4-DOF cases.

Usage::

    python -m benchmarks.search_quality [--data ../shared/data] [--out search-results] [--cases NAME ...]

Per case: the evaluations of ``maximize(prob)`` (every evaluation of every coarse view counted) and of
``maximize(prob, init="grid", n_init=2000)``, J at both results and their ratio, the mean area scale of
the warp at both (``cmax_taichi.metrics.area_scale``: below 0.5 is a collapse) and the wall time of
both calls (kernels compiled beforehand). Writes ``search_quality.csv`` and ``search_quality.md``.
Shared recordings that are absent are skipped.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
import warnings
from pathlib import Path

import numpy as np

BOTH = {"divergence": 10.0, "deformation": 10.0}

#: name -> (kind, arguments): "recording" (folder under --data, window events, warp, regularizers) or
#: "simulated" (warp, theta, seconds, sensor, regularizers; a textured plane under that motion)
CASES = {
    "slider_depth, first 5,000 events": ("recording", ("ecd_slider_depth", 5000, "translation2", None)),
    "slider_depth, first 30,000 events": ("recording", ("ecd_slider_depth", 30000, "translation2", None)),
    **{
        f"{cut}, first 5,000 events": ("recording", (f"ecd_rotation/{cut}", 5000, "rotation3", None))
        for cut in ("shapes_rotation", "boxes_rotation", "dynamic_rotation", "poster_rotation")
    },
    **{
        f"{cut}, whole cut": ("recording", (f"ecd_rotation/{cut}", None, "rotation3", None))
        for cut in ("shapes_rotation", "boxes_rotation", "dynamic_rotation", "poster_rotation")
    },
    "MVSEC indoor_flying1, first 5,000 events": (
        "recording",
        ("mvsec_indoor_flying1", 5000, "mitrokhin4", BOTH),
    ),
    "MVSEC indoor_flying1, whole cut": ("recording", ("mvsec_indoor_flying1", None, "mitrokhin4", BOTH)),
    "simulated translation (2000, -1000) px/s": (
        "simulated",
        ("translation2", (2000.0, -1000.0), 0.02, (240, 180), None),
    ),
    "simulated rotation (3, -4, 8) rad/s": (
        "simulated",
        ("rotation3", (3.0, -4.0, 8.0), 0.02, (240, 180), None),
    ),
    "simulated 1280x720 translation (-3000, 1500) px/s": (
        "simulated",
        ("translation2", (-3000.0, 1500.0), 0.005, (1280, 720), None),
    ),
    "4-DOF example 'collapse' (mitrokhin4, both)": ("example", ("collapse", "mitrokhin4", BOTH)),
    "simulated mitrokhin4 (1500, -800, 0, 0), both": (
        "simulated",
        ("mitrokhin4", (1500.0, -800.0, 0.0, 0.0), 0.02, (240, 180), BOTH),
    ),
    "simulated mitrokhin4 (-400, 250, -5, 2), no regularizer": (
        "simulated",
        ("mitrokhin4", (-400.0, 250.0, -5.0, 2.0), 0.02, (240, 180), None),
    ),
    "simulated sim2 (600, -300, 2, -4), both": (
        "simulated",
        ("sim2", (600.0, -300.0, 2.0, -4.0), 0.02, (240, 180), BOTH),
    ),
    "simulated zoom1 -3 1/s, both": ("simulated", ("zoom1", (-3.0,), 0.02, (240, 180), BOTH)),
    "simulated zoom1 8 1/s, no regularizer": ("simulated", ("zoom1", (8.0,), 0.02, (240, 180), None)),
}


def build(kind: str, args: tuple, data: Path):
    """The problem of a case, or None when its recording is absent."""
    import cmax_taichi as cm
    from cmax_taichi import io

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if kind == "recording":
            folder, n, warp, regs = args
            if not (data / folder).exists():
                return None
            with io.open_recording(data / folder) as rec:
                events = rec.read() if n is None else next(iter(rec.windows(n_events=n)))
                camera = rec.camera
        elif kind == "example":
            from cmax_taichi.sim.examples import make_example

            name, warp, regs = args
            example = make_example(name)
            events = next(iter(example.events.windows_by_duration(example.example.window)))
            camera = example.camera
        else:
            from cmax_taichi.sim import default_camera, simulate, warp_scene
            from cmax_taichi.sim.examples import _SIM

            warp, theta, seconds, sensor, regs = args
            camera = default_camera(sensor)
            segment = seconds if warp == "mitrokhin4" else None
            scene = warp_scene(warp, theta, sensor, texture="minduka", camera=camera, segment=segment)
            events = simulate(scene, seconds, seed=0, **_SIM).events()
        return cm.ContrastMaximization(events, warp=warp, camera=camera, regularizers=regs)


def run_case(prob) -> dict:
    import cmax_taichi as cm
    from cmax_taichi.metrics import area_scale

    prob.value_and_grad(np.zeros(prob.model.n_params))  # kernels loaded before the timing
    t0 = time.perf_counter()
    ours = cm.maximize(prob)
    t1 = time.perf_counter()
    ref = cm.maximize(prob, init="grid", n_init=2000)
    t2 = time.perf_counter()
    return {
        "events": prob.n_events,
        "sensor": f"{prob.width}x{prob.height}",
        "warp": prob.model.name,
        "regularizers": "+".join(f"{k}={v:g}" for k, v in prob.regularizer_weights.items()) or "none",
        "evaluations": ours.n_evaluations,
        "grid_evaluations": ref.n_evaluations,
        "J": ours.value,
        "grid_J": ref.value,
        "J_ratio": ours.value / ref.value,
        "area_scale": area_scale(prob, ours.theta),
        "grid_area_scale": area_scale(prob, ref.theta),
        "seconds": t1 - t0,
        "grid_seconds": t2 - t1,
        "converged": ours.converged,
        "theta": np.round(ours.theta, 4).tolist(),
        "grid_theta": np.round(ref.theta, 4).tolist(),
    }


def markdown(rows: list[dict]) -> str:
    lines = [
        "| case | events, sensor | warp, regularizers | evaluations (grid) | J (grid) | J ratio | "
        "area scale (grid) | s (grid s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "status" in r:
            lines.append(f"| {r['case']} | | | | | | | {r['status']} |")
            continue
        lines.append(
            f"| {r['case']} | {r['events']:,}, {r['sensor']} | {r['warp']}, {r['regularizers']} | "
            f"{r['evaluations']} ({r['grid_evaluations']}) | {r['J']:.4f} ({r['grid_J']:.4f}) | "
            f"{r['J_ratio']:.4f} | {r['area_scale']:.3f} ({r['grid_area_scale']:.3f}) | "
            f"{r['seconds']:.2f} ({r['grid_seconds']:.2f}) |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default="../shared/data", help="the shared recordings")
    parser.add_argument("--out", default="search-results", help="output folder")
    parser.add_argument("--cases", nargs="*", default=None, help=f"a subset of: {'; '.join(CASES)}")
    args = parser.parse_args(argv)
    names = args.cases or list(CASES)
    unknown = [n for n in names if n not in CASES]
    if unknown:
        parser.error(f"unknown case(s) {unknown}")
    rows = []
    for name in names:
        kind, case_args = CASES[name]
        prob = build(kind, case_args, Path(args.data))
        if prob is None:
            rows.append({"case": name, "status": "skipped: recording absent"})
            print(f"{name}: skipped (recording absent)", flush=True)
            continue
        row = {"case": name, **run_case(prob)}
        rows.append(row)
        print(
            f"{name}: {row['evaluations']} evaluations (grid {row['grid_evaluations']}), "
            f"J ratio {row['J_ratio']:.4f}, area scale {row['area_scale']:.3f}",
            flush=True,
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with (out / "search_quality.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
        writer.writeheader()
        writer.writerows(rows)
    text = markdown(rows)
    (out / "search_quality.md").write_text(text)
    print(text)
    measured = [r for r in rows if "status" not in r]
    if measured:
        print(
            f"at most {max(r['evaluations'] for r in measured)} evaluations; "
            f"worst J ratio {min(r['J_ratio'] for r in measured):.4f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
