"""Benchmark this library's Taichi kernels against a PyTorch autograd twin and the NumPy reference.

Checks first that every implementation returns the same value and gradient on identical inputs, then
times them (medians over interleaved repeats), and writes results.csv, results.md and results.png.
PyTorch is optional (``pip install "cmax-taichi[bench]"``); without it the torch rows say so.
The harness and its options are :mod:`cmax_taichi.lab.bench`.
"""

from __future__ import annotations

from cmax_taichi.lab.bench import add_arguments
from cmax_taichi.lab.bench import run_from_args as run

NAME = "bench"
HELP = "time value-and-gradient against PyTorch and NumPy (checked for agreement first)"

__all__ = ["NAME", "HELP", "add_arguments", "run"]
