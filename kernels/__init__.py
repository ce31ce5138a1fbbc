"""Taichi kernels of cmax-taichi (installed as ``cmax_taichi.kernels``).

One concern per module: ``warps`` (warp models), ``jacobian_ad`` (autodiff Jacobians), ``iwe``
(voting and blur), ``objectives``, ``maps`` (regularizer maps), ``whitening``, ``loss``.
Kernels import nothing from the drivers.
"""
