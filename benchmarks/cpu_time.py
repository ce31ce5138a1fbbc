"""CPU time (all threads, ``getrusage``) and wall time per ``value_and_grad`` at 1M events on the
benchmark's 346x260 windows: ``python benchmarks/cpu_time.py [f64|f32] [WARP:REGS ...]``.

On a machine shared with other processes the wall time of a call mostly measures the others (time
slicing); the process's CPU time per call measures the work itself. Runs on any version of the library
that has ``cmax_taichi.lab.bench_impls``: run this file with each version's environment, alternating,
and compare the medians. Default rows: mitrokhin4 with both regularizers, mitrokhin4 and translation2
without. Prints, per row, the median and minimum over 7 blocks of 5 calls.
"""

from __future__ import annotations

import resource
import sys
import time

import numpy as np

from cmax_taichi.core import backend
from cmax_taichi.lab import bench_impls

DEFAULT_ROWS = ("mitrokhin4:div+def", "mitrokhin4:none", "translation2:none")


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    precision = argv[0] if argv else "f64"
    rows = argv[1:] or DEFAULT_ROWS
    backend.init(precision=precision)
    for row in rows:
        warp, regs = row.split(":")
        cfg = bench_impls.BenchConfig(1_000_000, "346x260", warp, regs)
        win = bench_impls.make_window(cfg.n, cfg.sensor, seed=cfg.n % 9973)
        impl = bench_impls.build_taichi(win, cfg)
        theta = np.asarray(bench_impls.THETAS[warp], dtype=np.float64)
        for _ in range(3):  # compile and warm up
            impl.vg(theta)
        cpus, walls = [], []
        for _ in range(7):
            c0, w0 = _cpu_seconds(), time.perf_counter()
            for _ in range(5):
                impl.vg(theta)
            cpus.append((_cpu_seconds() - c0) / 5 * 1e3)
            walls.append((time.perf_counter() - w0) / 5 * 1e3)
        print(
            f"{warp:13s} {regs:8s} cpu ms/call med {np.median(cpus):6.2f} min {min(cpus):6.2f}  "
            f"wall med {np.median(walls):6.2f} min {min(walls):6.2f}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
