"""Benchmark this library's Taichi kernels against a PyTorch autograd twin and the NumPy reference.

Checks first that every implementation returns the same value and gradient on identical inputs, then
times them (medians over interleaved repeats), and writes results.csv, results.md and results.png.
PyTorch is optional (``pip install "cmax-taichi[bench]"``); without it the torch rows say so.
"""

from __future__ import annotations

import argparse
import os

NAME = "bench"
HELP = "time value-and-gradient against PyTorch and NumPy (checked for agreement first)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="a sub-two-minute subset (CI)")
    parser.add_argument("--out", default="bench-results", help="output folder (default: bench-results)")
    parser.add_argument(
        "--precision",
        default=None,
        choices=["f64", "f32"],
        help="Taichi and PyTorch precision (default: f64 on the CPU, f32 on a GPU arch)",
    )
    parser.add_argument(
        "--arch",
        default=None,
        choices=["cpu", "gpu", "cuda", "vulkan", "metal"],
        help="Taichi backend (default: CMAX_TAICHI_ARCH, else cpu); a GPU arch that is not available is an "
        "error here, not a fallback to the CPU",
    )
    parser.add_argument(
        "--gpu-sweep",
        action="store_true",
        help="the GPU throughput sweep (N = 1e3 .. 1e7, two sensors, three warps) instead of the CPU plan",
    )
    parser.add_argument(
        "--max-events",
        type=int,
        default=10_000_000,
        help="largest N of --gpu-sweep (default 1e7; smaller for a software-Vulkan check)",
    )
    parser.add_argument("--no-solve", action="store_true", help="skip the window-solve timing")
    parser.add_argument(
        "--no-segment", action="store_true", help="skip the motion-segmentation timing (full run only)"
    )


def _start_backend(arch: str | None, precision: str) -> str:
    """Start the requested arch; a GPU arch that Taichi cannot start (it falls back to the CPU) is an
    error, so that no CPU timing is reported as a GPU one."""
    import warnings

    from cmax_taichi.cli import CliError
    from cmax_taichi.core import backend

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the fallback warning: said below instead
        info = backend.init(arch=arch, precision=precision)
    if info.requested_arch != "cpu" and info.arch == "cpu":
        raise CliError(
            f"arch {info.requested_arch!r} is not available on this machine (Taichi fell back to the CPU); "
            "no benchmark was run"
        )
    return info.requested_arch


def run(args: argparse.Namespace) -> int:
    from cmax_taichi.cli import CliError
    from cmax_taichi.core.backend import ARCH_ENV
    from cmax_taichi.lab import bench

    if args.max_events < 1:
        raise CliError(f"--max-events must be at least 1, got {args.max_events}")
    requested = (args.arch or os.environ.get(ARCH_ENV) or "cpu").strip().lower()
    precision = args.precision or ("f64" if requested == "cpu" else "f32")
    if requested in ("vulkan", "metal") and precision == "f64":
        raise CliError(f"arch {requested!r} has no f64 support; use --precision f32")
    arch = _start_backend(requested, precision)
    if args.gpu_sweep:
        plan = bench.gpu_plan(precision, max_events=args.max_events)
        if not plan.configs:
            raise CliError(f"--max-events {args.max_events} leaves no configuration (the smallest N is 1000)")
    elif args.quick:
        plan = bench.quick_plan(precision)
    else:
        plan = bench.full_plan(precision)
    if args.no_solve:
        plan.solve = False
    if args.no_segment:
        plan.segment = False
    result = bench.run_benchmark(plan, args.out, arch=arch)
    print()
    print(result["markdown"])
    bad = [r for r in result["rows"] if r.status.startswith("DISAGREES")]
    return 1 if bad else 0
