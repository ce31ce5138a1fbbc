"""Cold compile cost against blur sigma and cluster count: the measurements behind the default limits.

``python -m benchmarks.compile_cost [--blur 1 3 5 8] [--clusters 2 4 8] [--compile full fast]``
``[--timeout 300]``

Each case runs in a fresh process with an empty Taichi offline cache (``TI_OFFLINE_CACHE_FILE_PATH`` in
a temporary folder), so what is timed is the compile of every kernel plus the first evaluation:

* ``blur``: a 64 x 48 ``mitrokhin4`` problem with both regularizers (the fused pipeline), one
  ``value_and_grad``, at each ``blur_sigma`` (px);
* ``clusters``: a 64 x 48 :class:`~cmax_taichi.pipeline.clusters.MultiClusterCMax` of K ``mitrokhin4``
  clusters without regularizers, ``set_memberships`` + ``value_and_grad`` + ``lookup``.

``--compile`` runs every case in each compile mode (``cm.init(compile_mode=...)``: ``full`` is the
default, ``fast`` skips Taichi's advanced IR optimizations), alternating, and adds what the mode costs
when the kernels run: the median of 20 warm ``value_and_grad`` calls of the same problem on 200,000
events (same 64 x 48 sensor, so the same compiled kernels).

Prints one line per case: seconds and the peak resident memory of the process (MB), and the load
average before the case (the machine is shared: compare cases of one run only). The limits above the
measured values are set with ``cm.set_limits`` inside the child process.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

CHILD = r"""
import resource, sys, time
import numpy as np
import cmax_taichi as cm
from cmax_taichi.pipeline.clusters import MultiClusterCMax
kind, value = sys.argv[1], float(sys.argv[2])
cm.set_limits(max_blur_sigma=max(value, 1.0), max_clusters=max(int(value), 1))
rng = np.random.default_rng(0)
n = 3000
ev = cm.Events(rng.uniform(0, 63, n), rng.uniform(0, 47, n), np.sort(rng.uniform(0, 0.01, n)),
               rng.choice([-1, 1], n), (64, 48))
cm.init()
t0 = time.perf_counter()
warm = ""
if kind == "blur":
    regs = {"divergence": 1.0, "deformation": 1.0}
    cm.ContrastMaximization(ev, "mitrokhin4", regularizers=regs, blur_sigma=value).value_and_grad(np.zeros(4))
    seconds = time.perf_counter() - t0
    m = 200_000
    big = cm.Events(rng.uniform(0, 63, m), rng.uniform(0, 47, m), np.sort(rng.uniform(0, 0.01, m)),
                    rng.choice([-1, 1], m), (64, 48))
    prob = cm.ContrastMaximization(big, "mitrokhin4", regularizers=regs, blur_sigma=value)
    theta = np.array([10.0, -5.0, 0.5, 0.2])
    prob.value_and_grad(theta)
    times = []
    for _ in range(20):
        a = time.perf_counter()
        prob.value_and_grad(theta)
        times.append(time.perf_counter() - a)
    warm = f" {1e3 * float(np.median(times)):.2f}"
else:
    K = int(value)
    prob = MultiClusterCMax(ev, K, "mitrokhin4")
    prob.set_memberships(rng.uniform(0, 1, (n, K)))
    thetas = rng.normal(0, 1, (K, 4))
    prob.value_and_grad(thetas)
    prob.lookup(thetas)
    seconds = time.perf_counter() - t0
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(f"{seconds:.1f} {rss:.0f}{warm}")
"""


def run_case(kind: str, value: float, timeout: float, compile_mode: str = "full") -> str:
    """``seconds peak_MB`` of one cold case (and the warm call's ms), or why it has none."""
    with tempfile.TemporaryDirectory(prefix="cmax_compile_cost_") as cache:
        env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=cache, CMAX_TAICHI_COMPILE=compile_mode)
        try:
            done = subprocess.run(
                [sys.executable, "-c", CHILD, kind, str(value)],
                capture_output=True,
                text=True,
                timeout=timeout,
                env=env,
            )
        except subprocess.TimeoutExpired:
            return f"over {timeout:.0f} s"
    if done.returncode != 0:
        return "failed: " + (done.stderr.strip().splitlines() or ["?"])[-1]
    seconds, peak, *warm = done.stdout.strip().splitlines()[-1].split()
    text = f"{seconds} s, peak {peak} MB"
    return text + (f", warm value_and_grad at 200k events {warm[0]} ms" if warm else "")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--blur", type=float, nargs="*", default=[1, 3, 5, 8], help="blur sigmas, px")
    parser.add_argument("--clusters", type=int, nargs="*", default=[2, 4, 8], help="cluster counts K")
    parser.add_argument(
        "--compile", nargs="+", default=["full"], choices=["full", "fast"], help="compile modes to run"
    )
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds per case")
    args = parser.parse_args(argv)
    cases = [("blur", s) for s in args.blur] + [("clusters", k) for k in args.clusters]
    for kind, value in cases:
        for mode in args.compile:
            load = os.getloadavg()[0]
            result = run_case(kind, value, args.timeout, mode)
            print(f"{kind} {value:g} [{mode}]: {result} (load {load:.1f})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
