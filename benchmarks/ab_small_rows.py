"""Median ``value_and_grad`` (60 calls) of the eight small benchmark rows that a single pair of full
runs showed slower after issue 16 (docs/performance.md): ``python benchmarks/ab_small_rows.py``, run
with each version's environment, alternating."""

import time

import numpy as np

from cmax_taichi.core import backend
from cmax_taichi.lab import bench_impls

backend.init(precision="f64")
CONFS = [
    (1000, "1280x720", "rotation3", "div+def"),
    (1000, "1280x720", "translation2", "none"),
    (1000, "240x180", "translation2", "div+def"),
    (1000, "346x260", "rotation3", "div+def"),
    (1000, "640x480", "rotation3", "none"),
    (10000, "240x180", "mitrokhin4", "none"),
    (10000, "240x180", "translation2", "none"),
    (10000, "346x260", "rotation3", "none"),
]
out = []
for n, sensor, warp, regs in CONFS:
    cfg = bench_impls.BenchConfig(n, sensor, warp, regs)
    win = bench_impls.make_window(cfg.n, cfg.sensor, seed=cfg.n % 9973)
    impl = bench_impls.build_taichi(win, cfg)
    th = np.asarray(bench_impls.THETAS[warp], dtype=np.float64)
    for _ in range(3):
        impl.vg(th)
    ts = []
    for _ in range(60):
        t = time.perf_counter()
        impl.vg(th)
        ts.append(time.perf_counter() - t)
    out.append(f"{np.median(ts) * 1e3:.2f}")
print(" ".join(out))
