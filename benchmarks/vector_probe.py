"""Does Taichi's CPU code generator vectorize the event loops of rotation3's stored terms?

``python benchmarks/vector_probe.py [--events N]``

Compiles small kernels shaped like the fused kernel's stage-2 terms loop (``kernels/fused.py``: per thread
slice, a serial loop over its events that evaluates ``warp_terms`` and stores the results), with
Taichi's optimized LLVM IR written to a temporary folder, and prints per kernel the wall time per event
(median of 30 calls, 2 thread slices) and how many vector instructions (``<2 x double>``, ``<4 x
double>``, ``<8 x double>``) and vectorized loops (``vector.body``) the optimized IR holds:

* ``copy``: one multiply-add per event from a host array into another (nothing to stop a vectorizer but
  the loop's own stores);
* ``warp``: rotation3's warped position (``warp_terms``' first output) into two rows;
* ``warp+jacobian``: the position and its 2x3 parameter Jacobian into eight rows (the stored terms of a
  ``value_and_grad`` without regularizers);
* ``lanes``: the position of four events per iteration written out lane by lane (the short tier of
  Rodrigues' coefficients without branches), to give LLVM's SLP vectorizer isomorphic chains to pack.

On 2026-12-05 (Taichi 1.7.4, LLVM 15, this 2-core AMD EPYC) none of the four had a vectorized loop or a
4-wide vector instruction (benchmarks/NOTES.md): every ndarray store is followed by a reload of the
array's base pointer from the kernel's argument buffer (the IR carries no alias information), so neither
the loop vectorizer nor the SLP vectorizer can prove the next iteration's addresses. A loop that only
loads and sums does vectorize once it has no branch: the fused kernel's gather (``kernels/fused.py``'s
``grad_at``: clamped reads, selects, bitwise conditions) runs four events a step since ``1293e58``.
"""

import argparse
import glob
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--events", type=int, default=300_000)
    args = parser.parse_args(argv)
    n_events, slices, lanes = args.events, 2, 4

    import numpy as np
    import taichi as ti

    folder = tempfile.mkdtemp(prefix="cmax_vector_probe_")
    os.chdir(folder)  # Taichi writes the IR files into the working directory
    ti.init(
        arch=ti.cpu,
        default_fp=ti.f64,
        offline_cache=False,
        print_kernel_llvm_ir_optimized=True,
        log_level=ti.ERROR,
    )
    from cmax_taichi.kernels.warps.common import SHORT_HALF_ANGLE, polynomial, tail_terms, versine_terms
    from cmax_taichi.kernels.warps.rotation3 import warp_terms

    rng = np.random.default_rng(0)
    ev = np.stack(
        [
            rng.uniform(0, 240, n_events),
            rng.uniform(0, 180, n_events),
            np.linspace(-0.025, 0.025, n_events),  # dt (s): a 50 ms window about t_ref
            np.ones(n_events),
        ]
    )
    out = np.zeros((8, n_events))
    theta = ti.Vector.field(3, ti.f64, shape=())
    theta[None] = [0.3, -0.2, 0.5]  # rad/s
    ctx = ti.Vector.field(5, ti.f64, shape=())
    ctx[None] = [120.0, 90.0, 200.0, 200.0, 0.05]  # cx, cy, fx, fy (px), T (s)
    arr = ti.types.ndarray(dtype=ti.f64, ndim=2)

    @ti.kernel
    def copy(n: ti.i32, e: arr, t: arr):
        ti.loop_config(block_dim=1)
        for s in range(slices):
            for i in range(s * n // slices, (s + 1) * n // slices):
                t[0, i] = e[0, i] * 2.0 + e[1, i]

    def terms_kernel(with_jacobian: bool):
        """The terms loop: rotation3's position (and its 2x3 Jacobian) of each event into rows of ``t``."""

        @ti.kernel
        def terms(n: ti.i32, e: arr, t: arr):
            ti.loop_config(block_dim=1)
            for s in range(slices):
                th, c = theta[None], ctx[None]
                for i in range(s * n // slices, (s + 1) * n // slices):
                    out = warp_terms(ti.Vector([e[0, i], e[1, i]]), e[2, i], th, c)
                    t[0, i] = out[0][0]
                    t[1, i] = out[0][1]
                    if ti.static(with_jacobian):
                        for k in ti.static(range(2)):
                            for j in ti.static(range(3)):
                                t[2 + 3 * k + j, i] = out[2][k, j]

        return terms

    @ti.func
    def lane_positions(x0, x1, dt, w, c):
        """rotation3's short tier for ``lanes`` rays at once (the lanes as vector components)."""
        v = 0.25 * dt * dt * w.dot(w)
        tail = polynomial(ti.static(tail_terms(SHORT_HALF_ANGLE)), v)
        versine = polynomial(ti.static(versine_terms(SHORT_HALF_ANGLE)), v)
        sinc = 1.0 - v * tail
        c1 = dt * sinc * (1.0 - v * versine)
        c2 = dt * dt * 0.5 * sinc * sinc
        wx = ti.Vector([w[1] - w[2] * x1[k] for k in ti.static(range(lanes))])
        wy = w[2] * x0 - w[0]
        wz = w[0] * x1 - w[1] * x0
        xr = x0 + c1 * wx + c2 * (w[1] * wz - w[2] * wy)
        yr = x1 + c1 * wy + c2 * (w[2] * wx - w[0] * wz)
        zr = 1.0 + c1 * wz + c2 * (w[0] * wy - w[1] * wx)
        iz = 1.0 / ti.max(zr, 1e-6)
        return c[0] + c[2] * xr * iz, c[1] + c[3] * yr * iz

    @ti.kernel
    def lanes_kernel(n: ti.i32, e: arr, t: arr):
        ti.loop_config(block_dim=1)
        for s in range(slices):
            th, c = theta[None], ctx[None]
            lo, hi = s * n // slices, (s + 1) * n // slices
            for b in range((hi - lo) // lanes):
                i = lo + b * lanes
                x0 = ti.Vector([(e[0, i + k] - c[0]) / c[2] for k in ti.static(range(lanes))])
                x1 = ti.Vector([(e[1, i + k] - c[1]) / c[3] for k in ti.static(range(lanes))])
                dt = ti.Vector([e[2, i + k] for k in ti.static(range(lanes))])
                qx, qy = lane_positions(x0, x1, dt, th, c)
                for k in ti.static(range(lanes)):
                    t[0, i + k] = qx[k]
                    t[1, i + k] = qy[k]

    kernels = {
        "copy": copy,
        "warp": terms_kernel(False),
        "warp+jacobian": terms_kernel(True),
        "lanes": lanes_kernel,
    }
    print(
        f"{'kernel':14s} {'ns/event':>9s} {'<2 x double>':>13s} {'<4 x double>':>13s} {'<8 x double>':>13s} "
        f"{'vector.body':>12s}"
    )
    for name, kernel in kernels.items():
        before = set(glob.glob("*.ll"))
        for _ in range(3):
            kernel(n_events, ev, out)
        times = []
        for _ in range(30):
            t0 = time.perf_counter()
            kernel(n_events, ev, out)
            ti.sync()
            times.append(time.perf_counter() - t0)
        ir = "".join(Path(f).read_text() for f in sorted(set(glob.glob("*.ll")) - before))
        counts = [ir.count(f"<{w} x double>") for w in (2, 4, 8)]
        ns = 1e9 * statistics.median(times) / n_events
        print(
            f"{name:14s} {ns:9.1f} {counts[0]:13d} {counts[1]:13d} {counts[2]:13d} "
            f"{ir.count('vector.body:'):12d}"
        )
    print(f"(the optimized IR: {folder})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
