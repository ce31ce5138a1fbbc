"""Benchmark this library's Taichi kernels against a PyTorch autograd twin and the NumPy reference.

Checks first that every implementation returns the same value and gradient on identical inputs, then
times them (medians over interleaved repeats), and writes results.csv, results.md and results.png.
PyTorch is optional (``pip install "cmax-taichi[bench]"``); without it the torch rows say so.
"""

from __future__ import annotations

import argparse

NAME = "bench"
HELP = "time value-and-gradient against PyTorch and NumPy (checked for agreement first)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="a sub-two-minute subset (CI)")
    parser.add_argument("--out", default="bench-results", help="output folder (default: bench-results)")
    parser.add_argument(
        "--precision", default="f64", choices=["f64", "f32"], help="Taichi and PyTorch precision"
    )
    parser.add_argument("--no-solve", action="store_true", help="skip the window-solve timing")
    parser.add_argument(
        "--no-segment", action="store_true", help="skip the motion-segmentation timing (full run only)"
    )


def run(args: argparse.Namespace) -> int:
    from cmax_taichi.lab import bench

    plan = bench.quick_plan(args.precision) if args.quick else bench.full_plan(args.precision)
    if args.no_solve:
        plan.solve = False
    if args.no_segment:
        plan.segment = False
    result = bench.run_benchmark(plan, args.out)
    print()
    print(result["markdown"])
    bad = [r for r in result["rows"] if r.status.startswith("DISAGREES")]
    return 1 if bad else 0
