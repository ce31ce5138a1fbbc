"""Benchmarks of cmax-taichi: ``python -m benchmarks.run [--quick] [--out DIR]``.

The harness lives in the package (``cmax_taichi.lab.bench``, also ``cmax-taichi bench``) so that it runs
from an installed wheel; this folder holds the entry points (``run``, ``profile_stages``).
"""
