"""How much the dense flow depends on the number of CPU threads: the same windows estimated at 1 and at
2 threads (``TI_CPU_MAX_NUM_THREADS``), each in its own process, and the differences of their flows.

    python -m benchmarks.flow_threads [--threads 1 2] [--out DIR]

The kernels accumulate into one slice per CPU thread and add the slices in slice order, so a run is
reproducible to the last bit at a given thread count; another thread count partitions the sums
differently, the last bits of J and its gradient change, and L-BFGS-B's path follows them. This measures
the result: per window and configuration, the largest and the mean difference of the displacement over
the window (px, on every pixel), the difference of J, and of the AEE where the window has truth.
Windows: the MVSEC cut's first 30,000 events and its first 12,350, the ECD boxes_rotation cut, the
simulator's ``corridor``; configurations: the defaults, no regularizer (a collapsing flow), and
divergence + deformation 10 with the reference time at the first event. Writes ``OUT/flow_threads.md``
and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("CMAX_TAICHI_COMPILE", "fast")

CONFIGS = {
    "defaults": {},
    "none": {"regularizers": {}},
    "div+def 10, t_ref first": {
        "references": "first",
        "regularizers": {"divergence": 10.0, "deformation": 10.0},
    },
}


def _windows() -> list:
    from benchmarks.flow_ablation import ecd_windows, mvsec_windows, sim_windows

    return (
        mvsec_windows(["first 30000", "third 1"], None)
        + ecd_windows(["boxes_rotation"], None)
        + sim_windows(["corridor"], None)
    )


def worker(path: Path) -> None:
    """Estimate every (window, configuration) and save the displacements and J to ``path`` (.npz)."""
    from cmax_taichi.flow import DenseFlowEstimator
    from cmax_taichi.pipeline.footprint import n_slices

    out = {}
    for w in _windows():
        for label, options in CONFIGS.items():
            est = DenseFlowEstimator(**options)
            est.camera = w.camera
            res = est.estimate(w.events)
            key = f"{w.dataset}|{w.name}|{label}"
            out[key + "|disp"] = res.displacement()
            out[key + "|J"] = np.array(res.value)
    out["slices"] = np.array(n_slices())
    np.savez(path, **out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, nargs=2, default=[1, 2])
    parser.add_argument("--out", type=Path, default=Path("bench-flow-threads"))
    parser.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker is not None:
        worker(args.worker)
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {os.cpu_count()} CPUs", flush=True)
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.threads:
            path = Path(tmp) / f"threads_{n}.npz"
            env = dict(os.environ, TI_CPU_MAX_NUM_THREADS=str(n))
            t0 = time.perf_counter()
            subprocess.run(
                [sys.executable, "-m", "benchmarks.flow_threads", "--worker", str(path)], env=env, check=True
            )
            print(f"{n} thread(s): {time.perf_counter() - t0:.0f} s", flush=True)
            with np.load(path) as f:
                runs[n] = {k: f[k] for k in f.files}
    a, b = (runs[n] for n in args.threads)
    assert int(a["slices"]) == args.threads[0] and int(b["slices"]) == args.threads[1]
    truth = {(w.dataset, w.name): w for w in _windows() if w.truth is not None}
    rows = []
    for key in sorted(k[: -len("|disp")] for k in a if k.endswith("|disp")):
        dataset, name, label = key.split("|")
        da, db = a[key + "|disp"], b[key + "|disp"]
        diff = np.hypot(*(da - db))
        row = {
            "window": f"{dataset} {name}",
            "config": label,
            "max_px": float(diff.max()),
            "mean_px": float(diff.mean()),
            "dJ": float(abs(a[key + "|J"] - b[key + "|J"])),
            "identical": bool(np.array_equal(da, db)),
        }
        w = truth.get((dataset, name))
        if w is not None:
            from cmax_taichi.metrics import event_mask, flow_error

            mask = event_mask(w.undistorted)
            row["AEE"] = [flow_error(d, w.truth, mask)["AEE"] for d in (da, db)]
        rows.append(row)
    lines = [
        f"threads {args.threads[0]} vs {args.threads[1]}; load average at the start {load[0]:.2f}",
        "",
        "| window | configuration | max diff px | mean diff px | J diff | AEE px (each) |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        aee = " / ".join(f"{v:.3f}" for v in r["AEE"]) if "AEE" in r else ""
        lines.append(
            f"| {r['window']} | {r['config']} | {r['max_px']:.3g} | {r['mean_px']:.3g} | {r['dJ']:.2g} "
            f"| {aee} |"
        )
    text = "\n".join(lines)
    (args.out / "flow_threads.md").write_text(text + "\n")
    (args.out / "flow_threads.json").write_text(json.dumps(rows, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
