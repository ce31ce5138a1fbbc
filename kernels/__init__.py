"""Taichi kernels of cmax-taichi (installed as ``cmax_taichi.kernels``).

One concern per module: ``blocks`` (every shared formula as a ``ti.func``), ``warps`` (warp models),
``events`` (the per-event kernels' inputs), ``jacobian_ad`` (autodiff Jacobians), ``iwe`` (voting and
blur), ``objectives``, ``maps`` (regularizer maps), ``whitening``, ``loss``, ``fused`` (one-launch value
and gradient), ``clusters`` (segmentation). Kernels import nothing from the drivers.
"""
