"""What one ``value`` / ``value_and_grad`` call costs besides the events: the Python work around the kernel,
Taichi's launch, and the kernel itself.

``python benchmarks/call_overhead.py [--repeats N] [--json OUT]``

Rows: translation2 without regularizers, 2 events on a 16x12 sensor (image passes of 192 pixels: the
fixed cost of a call) and 1,000 events on 240x180 (the row of the 0.2 ms per-call target). For each, wall
medians (over blocks of 50 calls) of: the public ``value_and_grad`` and ``value``; the fused kernel
called the ordinary way (``Kernel.__call__``: Taichi's Python argument handling, then the launch); the
same compiled kernel launched from its C++ launch context (no Python around it: the kernel and the
dispatch of its parallel tasks; where the pipeline has its own direct launch, that launch, which sets
the arguments from Python: a few us), the fastest block of each, and the median CPU time per call (all
threads). ``python work`` is the public call minus the C++ launch. Runs on any version that has the
fused pipeline (the kernel's signature before and after the window's constants went into one params
array) (``prob._fused``'s kernel of the window's loop schedule): the launch context is built here, with
the Taichi 1.7.4 internals that ``pipeline/fused.py`` uses.
"""

import argparse
import json
import resource
import statistics
import sys
import time

import numpy as np
from taichi.lang import impl

import cmax_taichi as cm
from cmax_taichi.core import backend

ROWS = [(2, (16, 12)), (1000, (240, 180))]


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)  # all threads of the process
    return usage.ru_utime + usage.ru_stime


def _median_us(fn, repeats: int) -> tuple[float, float, float]:
    """Microseconds per call over blocks of 50 calls (after 20 warm-up calls): the median block's wall
    time, the fastest block's (on a loaded machine the fastest block is the closest to the cost on an
    idle one) and the median block's CPU time (all threads: what the call costs the machine, which time
    slicing by other processes leaves nearly unchanged)."""
    for _ in range(20):
        fn()
    blocks, cpus = [], []
    for _ in range(max(1, repeats // 50)):
        c0, t0 = _cpu_seconds(), time.perf_counter()
        for _ in range(50):
            fn()
        blocks.append((time.perf_counter() - t0) / 50)
        cpus.append((_cpu_seconds() - c0) / 50)
    return statistics.median(blocks) * 1e6, min(blocks) * 1e6, statistics.median(cpus) * 1e6


def _window(n: int, sensor):
    rng = np.random.default_rng(1)
    W, H = sensor
    t = np.sort(rng.uniform(0.0, 0.01, n))
    t[0], t[-1] = 0.0, 0.01
    return cm.Events(rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n), t, rng.integers(0, 2, n), sensor)


def _c_launch(kernel, args, c_args=None):
    """A callable launching the compiled ``kernel`` with ``args`` from its C++ launch context: ints,
    floats, Taichi ndarrays, NumPy arrays; ``c_args`` (default ``args``) what the context gets in their
    place (a host array's address and shape: ``pipeline/fused.py``'s ``_HostArray``)."""
    primal = kernel._primal
    t_kernel = primal.compiled_kernels[primal.ensure_compiled(*args)]
    prog = impl.get_runtime().prog
    data = prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)
    ctx = t_kernel.make_launch_context()
    for j, arg in enumerate(args if c_args is None else c_args):
        if isinstance(arg, bool | int):
            ctx.set_arg_int((j,), int(arg))
        elif isinstance(arg, float):
            ctx.set_arg_float((j,), arg)
        elif hasattr(arg, "address"):  # a host array (the events of the params version)
            ctx.set_arg_external_array_with_shape((j,), arg.address, arg.nbytes, arg.shape, 0)
        elif isinstance(arg, np.ndarray):
            ctx.set_arg_external_array_with_shape((j,), int(arg.ctypes.data), arg.nbytes, arg.shape, 0)
        else:
            ctx.set_arg_ndarray((j,), arg.arr)
    return lambda: prog.launch_kernel(data, ctx)


def _kernel(fused):
    """The compiled kernel that ``fused`` launches for its window (its schedule's, where the version
    has CPU loop schedules; ``_run_k`` before)."""
    if not hasattr(fused, "_schedules"):
        return fused._run_k
    if hasattr(fused, "kernel_call"):  # a kernel per tier, the optimized one per sensor
        return fused._schedules.kernel(fused.serial, fused.tier, fused._sensor)
    return fused._schedules.kernel(fused.serial)


def _kernel_call(fused, theta):
    """``(args, c_args)`` of one gradient launch of ``fused``'s kernel: ``(n, events, terms, params, grad,
    out)`` since the kernel takes the stored event terms, ``(n, events, params, grad, out)`` since the
    window's constants went into one params array, ``(n, events, theta_0..theta_7, grad, out)`` before
    (all are timed by this script)."""

    def host(array):  # a _HostArray's NumPy array, or a Taichi ndarray
        return array.array if hasattr(array, "address") else array

    if hasattr(fused, "_params"):
        fused._params.array[: theta.size] = theta
        events = fused.events
        out = np.zeros_like(fused._out.array)
        if hasattr(fused, "_terms"):
            terms = fused._terms
            args = (fused.n_events, host(events), host(terms), fused._params.array, 1, out)
            return args, (fused.n_events, events, terms, fused._params.array, 1, out)
        args = (fused.n_events, host(events), fused._params.array, 1, out)
        return args, (fused.n_events, events, fused._params.array, 1, out)
    args = (fused.n_events, fused.events, *[float(v) for v in theta], *[0.0] * 6, 1, np.zeros(4))
    return args, None


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
        row = {
            "value_and_grad": _median_us(lambda prob=prob: prob.value_and_grad(theta), args.repeats),
            "value": _median_us(lambda prob=prob: prob.value(theta), args.repeats),
        }
        # the kernel as the library compiles and launches it (the scheduling that per_thread_loops sets)
        with backend.per_thread_loops():
            if hasattr(fused, "kernel_call"):  # the version's own arguments and direct launch
                fused._params.array[: theta.size] = theta
                call = fused.kernel_call(1)
                with backend.hand_written_gradient_kernels(fused.tier):  # the tier's compile settings
                    row["kernel, ordinary call (Kernel.__call__)"] = _median_us(
                        lambda fused=fused, call=call: _kernel(fused)(*call), args.repeats
                    )
                row["kernel, C++ launch (no Python)"] = _median_us(
                    lambda fused=fused: fused._launch(1), args.repeats
                )
            else:
                call, c_call = _kernel_call(fused, theta)
                row["kernel, ordinary call (Kernel.__call__)"] = _median_us(
                    lambda fused=fused, call=call: _kernel(fused)(*call), args.repeats
                )
                row["kernel, C++ launch (no Python)"] = _median_us(
                    _c_launch(_kernel(fused), call, c_call), args.repeats
                )
        row["python work (value_and_grad - C++ launch)"] = tuple(
            a - b for a, b in zip(row["value_and_grad"], row["kernel, C++ launch (no Python)"], strict=True)
        )
        key = f"{n} events {sensor[0]}x{sensor[1]}"
        results[key] = row
        print(key)
        for name, (med, best, cpu) in row.items():
            print(
                f"  {name:44s} median {med:8.1f} us   fastest block {best:8.1f} us   CPU {cpu:8.1f} us",
                flush=True,
            )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
