"""Wall and CPU time of the dense flow estimator (cmax_taichi.flow) on the MVSEC and VGA windows.

    python benchmarks/dense_flow.py [--rows mvsec vga] [--configs ours reference] [--repeats 3] [--out DIR]

Rows:

* ``mvsec``: the first 30,000 events on the sensor of ``../shared/data/mvsec_indoor_flying1`` (346x260),
  finest grid 16 x 16 cells (17 x 17 nodes, 578 parameters), 4 levels (2 x 2 .. 16 x 16 cells): the final
  grid of the reference's released MVSEC configuration (16 x 16 patches, 512 parameters);
* ``vga``: 1,000,000 events of a simulated 640x480 depth scene (``cmax_taichi.testing.flow_scenes``), the
  same grid and levels.

Configurations: ``ours`` (:data:`cmax_taichi.flow.DEFAULT_OPTIONS`) and ``reference`` (the objective of
tub-rip/event_based_optical_flow's released configuration: multi-reference normalised gradient magnitude
with the middle counted twice, and total variation, no collapse regularizer).

Each row runs once to compile (its time is reported as ``first``), then ``--repeats`` times; medians of
wall and CPU time (getrusage over all threads) are reported with the load average. Writes
``OUT/dense_flow.json`` and ``OUT/dense_flow.md``. ``ours(events, camera)`` is the interface of the
side-by-side script of the reference (``benchmarks/reference_flow.py --ours benchmarks.dense_flow:ours``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MVSEC_CUT = ROOT.parent / "shared" / "data" / "mvsec_indoor_flying1"


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def mvsec_events(n: int = 30_000):
    """The first ``n`` events on the sensor of the shared MVSEC cut and its camera."""
    from cmax_taichi.io import open_recording

    with open_recording(MVSEC_CUT) as rec, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 0.4% of the rectified events fall outside the image
        events = rec.read(0, n + n // 50)
        camera = rec.camera
    return events[:n], camera


def vga_events(n: int = 1_000_000):
    from cmax_taichi.testing.flow_scenes import depth_scene

    scene = depth_scene(
        (640, 480), duration=0.05, displacement=(6.0, 2.0), n_events=n, threshold=0.08, seed=1
    )
    return scene.events, None


def configs() -> dict:
    from cmax_taichi.flow import DEFAULT_OPTIONS

    return {
        "ours": dict(DEFAULT_OPTIONS),
        "reference": dict(
            DEFAULT_OPTIONS,
            references="multi",
            regularizers={"total_variation": 0.1},
        ),
    }


_ESTIMATORS: dict = {}


def ours(events, camera) -> np.ndarray:
    """Our dense flow of one window with the default options: ``(2, H, W)`` px/s at the first event's time
    (the interface of ``benchmarks/reference_flow.py --ours``). The estimator is kept between calls (its
    kernels compile once per process, as a sequence of windows uses them): run it with ``--repeats 2`` or
    more, the first call includes the compilation."""
    from cmax_taichi.flow import DenseFlowEstimator

    key = (events.sensor_size, repr(camera))
    if key not in _ESTIMATORS:
        _ESTIMATORS[key] = DenseFlowEstimator((16, 16), levels=4, camera=camera)
    return _ESTIMATORS[key].estimate(events).flow()


def run_row(name: str, config: str, repeats: int) -> dict:
    from cmax_taichi.flow import DenseFlowEstimator, DenseFlowProblem

    events, camera = mvsec_events() if name == "mvsec" else vga_events()
    options = configs()[config]
    est = DenseFlowEstimator((16, 16), levels=4, camera=camera, **options)
    t0, c0 = time.perf_counter(), _cpu()
    first = est.estimate(events)
    first_wall, first_cpu = time.perf_counter() - t0, _cpu() - c0
    walls, cpus, results = [], [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), _cpu()
        res = est.estimate(events)
        walls.append(time.perf_counter() - t0)
        cpus.append(_cpu() - c0)
        results.append(res)
    same = all(np.array_equal(r.nodes, first.nodes) for r in results)
    res = results[-1]
    # the FWL of the flow: IWE variance (t_ref first, blur 1 px) of the warped over the unwarped events
    prob = DenseFlowProblem(events, res.grid, objective="variance", camera=camera, references="first")
    fwl_value = prob.value(res.nodes)
    return {
        "row": name,
        "config": config,
        "n_events": res.n_events,
        "sensor": list(res.sensor_size),
        "grid": [res.grid.nx, res.grid.ny],
        "parameters": res.grid.n_params,
        "first_wall_s": first_wall,
        "first_cpu_s": first_cpu,
        "wall_s": float(np.median(walls)),
        "cpu_s": float(np.median(cpus)),
        "walls": walls,
        "evaluations": res.n_evaluations,
        "J": res.value,
        "FWL": fwl_value,
        "identical_repeats": bool(same),
        "levels": [lv.evaluations for lv in res.levels],
    }


def _table(runs: list[dict]) -> str:
    lines = [
        "| row | config | events | grid (params) | first run s | wall s (median) | CPU s | evaluations "
        "| J | FWL |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        lines.append(
            f"| {r['row']} | {r['config']} | {r['n_events']:,} | "
            f"{r['grid'][0]}x{r['grid'][1]} ({r['parameters']}) | "
            f"{r['first_wall_s']:.2f} | {r['wall_s']:.3f} | {r['cpu_s']:.3f} | {r['evaluations']} | "
            f"{r['J']:.4f} | {r['FWL']:.4f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", nargs="+", default=["mvsec", "vga"], choices=["mvsec", "vga"])
    parser.add_argument("--configs", nargs="+", default=["ours", "reference"], choices=["ours", "reference"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="bench-dense-flow")
    args = parser.parse_args(argv)
    if "mvsec" in args.rows and not MVSEC_CUT.is_dir():
        print(f"{MVSEC_CUT} is absent: the mvsec row is skipped")
        args.rows = [r for r in args.rows if r != "mvsec"]
    import cmax_taichi as cm

    info = cm.init()
    load = os.getloadavg()
    runs = []
    for row in args.rows:
        for config in args.configs:
            r = run_row(row, config, args.repeats)
            r["load_average"] = list(load)
            runs.append(r)
            print(json.dumps({k: v for k, v in r.items() if k != "walls"}), flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {"arch": info.arch, "precision": info.precision, "cpus": os.cpu_count(), "load_start": list(load)}
    (out / "dense_flow.json").write_text(json.dumps({"meta": meta, "runs": runs}, indent=2) + "\n")
    table = _table(runs)
    (out / "dense_flow.md").write_text(
        f"{info.arch} {info.precision}, {os.cpu_count()} CPUs, load average at the start {load[0]:.2f}\n\n"
        + table
    )
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
