"""What one ``value`` / ``value_and_grad`` call costs besides the events: the Python work around the kernel,
Taichi's launch, and the kernel itself.

``python benchmarks/call_overhead.py [--repeats N] [--json OUT]``

Rows: translation2 without regularizers, 2 events on a 16x12 sensor (image passes of 192 pixels: the
fixed cost of a call) and 1,000 events on 240x180 (the row of issue 20's 0.2 ms target). For each, wall
medians (over blocks of 50 calls) of: the public ``value_and_grad`` and ``value``; the fused kernel
called the ordinary way (``Kernel.__call__``: Taichi's Python argument handling, then the launch); the
same compiled kernel launched from its C++ launch context (no Python around it: the kernel and the
dispatch of its parallel tasks), and the fastest block of each. ``python work`` is the public call
minus the C++ launch. Runs on any
version that has the fused pipeline (``prob._fused._run_k``): the launch context is built here, with
the Taichi 1.7.4 internals that ``pipeline/fused.py`` uses.
"""

import argparse
import json
import statistics
import sys
import time

import numpy as np
from taichi.lang import impl

import cmax_taichi as cm

ROWS = [(2, (16, 12)), (1000, (240, 180))]


def _median_us(fn, repeats: int) -> tuple[float, float]:
    """Wall microseconds per call over blocks of 50 calls (after 20 warm-up calls): the median block and
    the fastest (on a loaded machine the fastest block is the closest to the cost on an idle one)."""
    for _ in range(20):
        fn()
    blocks = []
    for _ in range(max(1, repeats // 50)):
        t0 = time.perf_counter()
        for _ in range(50):
            fn()
        blocks.append((time.perf_counter() - t0) / 50)
    return statistics.median(blocks) * 1e6, min(blocks) * 1e6


def _window(n: int, sensor):
    rng = np.random.default_rng(1)
    W, H = sensor
    t = np.sort(rng.uniform(0.0, 0.01, n))
    t[0], t[-1] = 0.0, 0.01
    return cm.Events(rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n), t, rng.integers(0, 2, n), sensor)


def _c_launch(kernel, args):
    """A callable launching the compiled ``kernel`` with ``args`` from its C++ launch context."""
    primal = kernel._primal
    t_kernel = primal.compiled_kernels[primal.ensure_compiled(*args)]
    prog = impl.get_runtime().prog
    data = prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)
    ctx = t_kernel.make_launch_context()
    n, events, *floats, grad, out = args
    ctx.set_arg_int((0,), n)
    ctx.set_arg_ndarray((1,), events.arr)
    for j, v in enumerate(floats):
        ctx.set_arg_float((2 + j,), v)
    ctx.set_arg_int((10,), grad)
    ctx.set_arg_external_array_with_shape((11,), int(out.ctypes.data), out.nbytes, out.shape, 0)
    return lambda: prog.launch_kernel(data, ctx)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=2000)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    cm.init(precision="f64")
    theta = np.array([120.0, -80.0])
    results = {}
    for n, sensor in ROWS:
        prob = cm.ContrastMaximization(_window(n, sensor), warp="translation2", blur_sigma=1.0)
        prob.value_and_grad(theta)
        fused = prob._fused
        call = (fused.n_events, fused.events, *[float(v) for v in theta], *[0.0] * 6, 1, np.zeros(4))
        row = {
            "value_and_grad": _median_us(lambda prob=prob: prob.value_and_grad(theta), args.repeats),
            "value": _median_us(lambda prob=prob: prob.value(theta), args.repeats),
            "kernel, ordinary call (Kernel.__call__)": _median_us(
                lambda fused=fused, call=call: fused._run_k(*call), args.repeats
            ),
            "kernel, C++ launch (no Python)": _median_us(_c_launch(fused._run_k, call), args.repeats),
        }
        row["python work (value_and_grad - C++ launch)"] = tuple(
            a - b for a, b in zip(row["value_and_grad"], row["kernel, C++ launch (no Python)"], strict=True)
        )
        key = f"{n} events {sensor[0]}x{sensor[1]}"
        results[key] = row
        print(key)
        for name, (med, best) in row.items():
            print(f"  {name:44s} median {med:8.1f} us   fastest block {best:8.1f} us", flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
