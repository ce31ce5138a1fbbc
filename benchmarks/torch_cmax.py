"""The PyTorch twin of the CMax pipeline (benchmark only): see :mod:`cmax_taichi.testing.torch_cmax`.

It lives in the package so that ``cmax-taichi bench`` finds it in an installed wheel; this module
re-exports it for ``from benchmarks.torch_cmax import TorchCMax``.
"""

from cmax_taichi.testing.torch_cmax import KAPPA, TWIN_WARPS, TorchCMax

__all__ = ["TorchCMax", "TWIN_WARPS", "KAPPA"]
