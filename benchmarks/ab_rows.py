"""Median ``value_and_grad`` of a few benchmark windows through the library's benchmark implementation:
``python benchmarks/ab_rows.py [--small]``. Run it with each version's environment, alternating, to
compare two versions on one machine (docs/performance.md, issue 16). By default six windows, small and
large (100 calls each, 15 at 1M events); ``--small``: the eight small rows that one pair of full runs
showed slower after issue 16 (60 calls each)."""

import sys
import time

import numpy as np

from cmax_taichi.core import backend
from cmax_taichi.lab import bench_impls

DEFAULT_ROWS = [
    (1000, "346x260", "translation2", "none"),
    (1000, "1280x720", "translation2", "none"),
    (1000, "346x260", "mitrokhin4", "div+def"),
    (1000, "1280x720", "mitrokhin4", "div+def"),
    (30000, "346x260", "mitrokhin4", "div+def"),
    (1000000, "346x260", "mitrokhin4", "div+def"),
]
SMALL_ROWS = [
    (1000, "1280x720", "rotation3", "div+def"),
    (1000, "1280x720", "translation2", "none"),
    (1000, "240x180", "translation2", "div+def"),
    (1000, "346x260", "rotation3", "div+def"),
    (1000, "640x480", "rotation3", "none"),
    (10000, "240x180", "mitrokhin4", "none"),
    (10000, "240x180", "translation2", "none"),
    (10000, "346x260", "rotation3", "none"),
]


def median_ms(n: int, sensor: str, warp: str, regs: str, repeats: int) -> float:
    """Median wall time of one ``value_and_grad`` (ms) after three warm-up calls."""
    cfg = bench_impls.BenchConfig(n, sensor, warp, regs)
    win = bench_impls.make_window(cfg.n, cfg.sensor, seed=cfg.n % 9973)
    impl = bench_impls.build_taichi(win, cfg)
    theta = np.asarray(bench_impls.THETAS[warp], dtype=np.float64)
    for _ in range(3):
        impl.vg(theta)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        impl.vg(theta)
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e3


def main(argv: list[str]) -> int:
    small = "--small" in argv
    backend.init(precision="f64")
    for n, sensor, warp, regs in SMALL_ROWS if small else DEFAULT_ROWS:
        repeats = 60 if small else (15 if n >= 1_000_000 else 100)
        ms = median_ms(n, sensor, warp, regs, repeats)
        print(f"{n:8d} {sensor:9s} {warp:13s} {regs:8s} {ms:8.3f} ms", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
