"""Dense optical flow, side by side: tub-rip/event_based_optical_flow (the authors' reference) on
the same windows as ours, its time and its accuracy.

    python benchmarks/reference_flow.py --reference /work/peers/event_based_optical_flow \\
        [--threads 1 2] [--repeats 1] [--windows mvsec planes] [--ours MODULE:FUNCTION] \\
        [--global mitrokhin4:divergence=10,deformation=10] [--out DIR]

The reference is a separate checkout with its own environment (``REF/.venv/bin/python`` with torch
2.13 CPU and its requirements, or ``--python``); nothing of it is imported here: each run starts
``benchmarks/reference_flow_driver.py`` with that Python, on its released
``configs/mvsec_indoor_no_timeaware.yaml`` (4 pyramid levels of 2x2 .. 16x16 patches, multi-reference
normalized gradient magnitude + 0.01 total variation, Newton-CG). Without the checkout the script
prints why and exits with 0.

Windows (the same events for every method):

* ``mvsec``: the first 30,000 events of ``../shared/data/mvsec_indoor_flying1`` (rectified
  coordinates, its ``calib.txt`` camera). No flow ground truth: time, parameters, and the FWL of each
  flow (``Var(IWE(flow)) / Var(IWE(0))``, bilinear votes, blur 1 px, t_ref = the first event).
* ``planes`` (and any other depth preset, ``sm.DEPTH_PRESETS``): the simulator's scene over
  ``[0.02, 0.02 + window]`` s, scored as MVSEC is: each method sees the last 30,000 events before the
  window's end; its flow (px/s) times the window length against the exact displacement, on the pixels
  with at least one event of the window (AEE, 3PE, %Out).

``--global WARP[:REG=W,...]`` adds our best global warp (maximized on the same events) as a baseline.
``--ours MODULE:FUNCTION`` adds our dense solver: ``FUNCTION(events, camera) -> (2, H, W)`` flow in px/s
(x, y) at the first event's time, called on the same events, timed the same way (wall and CPU time
of the call). Writes ``OUT/reference_flow.json`` (every run), ``OUT/reference_flow.md`` (the table) and
each flow as ``OUT/flow_<window>_<method>_<threads>t.npz``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_REFERENCE = Path(os.environ.get("CMAX_REFERENCE_FLOW", "/work/peers/event_based_optical_flow"))
CONFIG = "configs/mvsec_indoor_no_timeaware.yaml"
MVSEC_CUT = ROOT.parent / "shared" / "data" / "mvsec_indoor_flying1"
N_EVENTS = 30_000


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def mvsec_window(n: int = N_EVENTS) -> dict:
    """The first ``n`` events on the sensor of the shared MVSEC indoor_flying1 cut (no ground truth;
    its rectified coordinates put 0.4% of the events outside the 346x260 image: those are skipped)."""
    import warnings

    from cmax_taichi.io import open_recording

    if not MVSEC_CUT.is_dir():
        raise FileNotFoundError(f"{MVSEC_CUT}: the shared MVSEC cut is not there")
    with open_recording(MVSEC_CUT) as rec, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the events outside the sensor, counted below
        events = rec.read(0, min(rec.n_events, n + n // 50))
        camera = rec.camera
    if len(events) < n:
        raise ValueError(f"{MVSEC_CUT}: only {len(events)} events on the sensor in the first {n + n // 50}")
    events = _slice(events, 0, n)
    return {"name": "mvsec", "events": events, "camera": camera, "score_events": events, "gt": None}


def depth_window(name: str, n: int = N_EVENTS) -> dict:
    """A depth preset's window (``sm.depth_example``): the last ``n`` events before its end, its exact
    displacement."""
    from cmax_taichi import sim as sm

    example = sm.depth_example(name)
    window = example.events
    return {
        "name": name,
        "events": _slice(window, max(len(window) - n, 0)),
        "camera": example.camera,
        "score_events": window,
        "gt": example.flow,
        "dt": example.t1 - example.t0,
    }


def _slice(events, lo: int, hi: int | None = None):
    import cmax_taichi as cm

    sl = slice(lo, hi)
    return cm.Events(events.x[sl], events.y[sl], events.t[sl], events.p[sl], events.sensor_size)


def run_reference(
    reference: Path, python: Path, events, threads: int, seed: int, profiler: bool = True
) -> tuple[np.ndarray, dict]:
    """One run of the reference's solver on ``events`` in a subprocess (its own environment)."""
    W, H = events.sensor_size
    with tempfile.TemporaryDirectory(prefix="reference_flow_") as tmp:
        src = Path(tmp) / "window.npz"
        out = Path(tmp) / "out.npz"
        p = np.where(np.asarray(events.p) > 0, 1.0, -1.0)
        np.savez(src, x=events.x, y=events.y, t=events.t, p=p, height=H, width=W)
        cmd = [
            str(python),
            str(ROOT / "benchmarks" / "reference_flow_driver.py"),
            "--reference",
            str(reference),
            "--config",
            str(reference / CONFIG),
            "--events",
            str(src),
            "--threads",
            str(threads),
            "--seed",
            str(seed),
            "--out",
            str(out),
        ] + ([] if profiler else ["--no-profiler"])
        env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
        if proc.returncode != 0 or not out.is_file():
            raise RuntimeError(f"the reference failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
        with np.load(out) as data:
            return np.array(data["flow"]), json.loads(str(data["report"]))


def run_ours(spec: str, events, camera) -> tuple[np.ndarray, dict]:
    """Our dense solver, ``MODULE:FUNCTION(events, camera) -> (2, H, W) px/s``."""
    module, _, name = spec.partition(":")
    if str(ROOT) not in sys.path:  # MODULE may be one of the repository's own (benchmarks.dense_flow)
        sys.path.insert(0, str(ROOT))
    func = getattr(importlib.import_module(module), name)
    cpu0, wall0 = _cpu_seconds(), time.perf_counter()
    flow = np.asarray(func(events, camera), dtype=np.float64)
    return flow, {"wall_s": time.perf_counter() - wall0, "cpu_s": _cpu_seconds() - cpu0}


def run_global(spec: str, events, camera, dt: float) -> tuple[np.ndarray, dict]:
    """Our best global warp as a flow baseline: ``WARP[:NAME=WEIGHT,...]`` (e.g.
    ``mitrokhin4:divergence=10,deformation=10``), maximized on ``events``; the flow is its displacement
    over ``dt`` divided by ``dt`` (px/s), so that it is scored like the others."""
    import cmax_taichi as cm

    warp, _, regs = spec.partition(":")
    weights = {k: float(v) for k, v in (item.split("=") for item in regs.split(",") if item)} or None
    cpu0, wall0 = _cpu_seconds(), time.perf_counter()
    prob = cm.ContrastMaximization(events, warp=warp, camera=camera, regularizers=weights)
    result = cm.maximize(prob)
    flow = prob.dense_flow(result.theta, dt=dt) / dt
    report = {"wall_s": time.perf_counter() - wall0, "cpu_s": _cpu_seconds() - cpu0}
    report["theta"] = [float(v) for v in result.theta]
    report["params_finest"] = report["params_total"] = prob.model.n_params
    return flow, report


def fwl_of_flow(events, flow: np.ndarray) -> float:
    """``Var(IWE) / Var(IWE(0))`` of the events warped by a dense flow (px/s) to the first event's time:
    ``x' = x - (t - t_0) u(round(x))``, bilinear votes, Gaussian blur 1 px (the NumPy reference IWE)."""
    from cmax_taichi.testing import reference as ref

    W, H = events.sensor_size
    xi = np.clip(np.rint(events.x).astype(int), 0, W - 1)
    yi = np.clip(np.rint(events.y).astype(int), 0, H - 1)
    dt = events.t - events.t[0]
    xw = events.x - dt * flow[0, yi, xi]
    yw = events.y - dt * flow[1, yi, xi]

    def variance(x, y):
        return float(ref.gaussian_blur(ref.bilinear_votes(x, y, np.ones(len(x)), W, H), 1.0).var())

    return variance(xw, yw) / variance(events.x, events.y)


def score(window: dict, flow: np.ndarray) -> dict:
    from cmax_taichi import metrics

    out = {"FWL": fwl_of_flow(window["events"], flow)}
    if window["gt"] is not None:
        pred = flow * window["dt"]
        err = metrics.flow_error(pred, window["gt"], metrics.event_mask(window["score_events"]), (3.0,))
        out.update({k: err[k] for k in ("AEE", "3PE", "outlier", "n_pixels")})
        zero = metrics.flow_error(
            np.zeros_like(pred), window["gt"], metrics.event_mask(window["score_events"])
        )
        out["AEE_zero_flow"] = zero["AEE"]
    return out


def _table(runs: list[dict]) -> str:
    lines = [
        "| window | method | threads | events | wall s | CPU s | params (finest / all) | loss evals | "
        "CPU ms per loss | FWL | AEE px | 3PE % | %Out |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        rep = r["report"]
        n_loss = rep.get("counts", {}).get("objective")
        cpu = rep.get("cpu_seconds", rep.get("seconds", {}))
        ms = 1e3 * cpu["objective"] / n_loss if n_loss else None
        params = f"{rep['params_finest']} / {rep['params_total']}" if "params_finest" in rep else ""
        s = r["score"]

        def f(v, fmt):
            return format(v, fmt) if isinstance(v, (int, float)) and v == v else ""

        accuracy = " | ".join(
            f(s.get(k), fmt)
            for k, fmt in (("FWL", ".3f"), ("AEE", ".2f"), ("3PE", ".1f"), ("outlier", ".1f"))
        )
        lines.append(
            f"| {r['window']} | {r['method']} | {r['threads']} | {rep.get('n_events', r['n_events'])} | "
            f"{rep['wall_s']:.1f} | {rep['cpu_s']:.1f} | {params} | {n_loss or ''} | {f(ms, '.1f')} | "
            f"{accuracy} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE, help="the reference checkout")
    parser.add_argument("--python", type=Path, default=None, help="its Python (default REF/.venv/bin/python)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="torch threads per run")
    parser.add_argument("--repeats", type=int, default=1, help="runs per window and thread count")
    parser.add_argument(
        "--windows", nargs="+", default=["mvsec", "planes"], help="mvsec and/or depth presets"
    )
    parser.add_argument(
        "--ours", default=None, metavar="MODULE:FUNCTION", help="our dense solver, to run beside"
    )
    parser.add_argument(
        "--global",
        dest="global_warps",
        action="append",
        default=[],
        metavar="WARP[:REG=W,...]",
        help="also our best global warp, e.g. mitrokhin4:divergence=10,deformation=10 (repeatable)",
    )
    parser.add_argument("--no-reference", action="store_true", help="run only --ours / --global")
    parser.add_argument(
        "--no-profiler", action="store_true", help="the reference without the cProfile wrapper of its release"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "reference_flow")
    args = parser.parse_args(argv)

    reference = args.reference.resolve()
    python = args.python or reference / ".venv" / "bin" / "python"
    if not args.no_reference and not (reference / "src" / "solver" / "patch_contrast_pyramid.py").is_file():
        print(f"skip: no event_based_optical_flow checkout at {reference} (pass --reference PATH)")
        return 0
    if not args.no_reference and not python.is_file():
        print(f"skip: no Python for the reference at {python} (pass --python)")
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {os.cpu_count()} CPUs")
    runs = []
    for name in args.windows:
        window = mvsec_window() if name == "mvsec" else depth_window(name)
        events = window["events"]
        methods = ([] if args.no_reference else ["reference"]) + (["ours"] if args.ours else [])
        methods += [f"global {spec}" for spec in args.global_warps]
        dt = window.get("dt", float(events.t[-1] - events.t[0]))
        for method in methods:
            for threads in args.threads if method == "reference" else [None]:
                for k in range(args.repeats):
                    if method == "reference":
                        flow, report = run_reference(
                            reference, python, events, threads, seed=k, profiler=not args.no_profiler
                        )
                    elif method == "ours":
                        flow, report = run_ours(args.ours, events, window["camera"])
                    else:
                        flow, report = run_global(method.split(" ", 1)[1], events, window["camera"], dt)
                    run = {
                        "window": name,
                        "method": method,
                        "threads": threads if threads is not None else "",
                        "repeat": k,
                        "n_events": len(events),
                        "report": report,
                        "score": score(window, flow),
                        "load": os.getloadavg(),
                    }
                    runs.append(run)
                    tag = f"{threads}t" if threads is not None else "own"
                    label = method.split(":")[0].replace(" ", "_")
                    np.savez(args.out / f"flow_{name}_{label}_{tag}_{k}.npz", flow=flow, unit="px/s")
                    print(_table([run]).splitlines()[-1], flush=True)
    (args.out / "reference_flow.json").write_text(json.dumps(runs, indent=1, default=float))
    table = _table(runs)
    (args.out / "reference_flow.md").write_text(table + "\n")
    print(table)
    print(f"wrote {args.out / 'reference_flow.json'}, {args.out / 'reference_flow.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
