"""Median ``value_and_grad`` of a few benchmark windows, small and large, through the library's
benchmark implementation: ``python benchmarks/ab_rows.py`` (run it with each version's environment,
alternating, to compare two versions on one machine; docs/performance.md, issue 16)."""

import time

import numpy as np

from cmax_taichi.core import backend
from cmax_taichi.lab import bench_impls

backend.init(precision="f64")
CONFS = [
    (1000, "346x260", "translation2", "none"),
    (1000, "1280x720", "translation2", "none"),
    (1000, "346x260", "mitrokhin4", "div+def"),
    (1000, "1280x720", "mitrokhin4", "div+def"),
    (30000, "346x260", "mitrokhin4", "div+def"),
    (1000000, "346x260", "mitrokhin4", "div+def"),
]
for n, sensor, warp, regs in CONFS:
    cfg = bench_impls.BenchConfig(n, sensor, warp, regs)
    win = bench_impls.make_window(cfg.n, cfg.sensor, seed=cfg.n % 9973)
    impl = bench_impls.build_taichi(win, cfg)
    th = np.asarray(bench_impls.THETAS[warp], dtype=np.float64)
    for _ in range(3):
        impl.vg(th)
    ts = []
    reps = 15 if n >= 1000000 else 100
    for _ in range(reps):
        t = time.perf_counter()
        impl.vg(th)
        ts.append(time.perf_counter() - t)
    print(f"{n:8d} {sensor:9s} {warp:13s} {regs:8s} {np.median(ts) * 1e3:8.3f} ms", flush=True)
