"""The augmented objective J = G / G0 - sum_r lambda_r R_r as one serial kernel into a 0-D loss field.

``G`` is the objective summed over channels (``finalize`` of ``objectives.py``), ``G0`` the identity
warp's value (1 for the raw objective), ``R_r = s_r macc[1 + r] / macc[0]`` the regularizer penalties
(``max(0, .)`` for one-sided ones), with ``lam[None][r] = lambda_r`` and ``lam[None][n + r] = s_r`` the
regularizer's scale. ``diag`` receives ``(G_raw, R_0, ...)`` for reporting.
Formulas: docs/FORMULAS.md, "Augmented objective".
"""

import taichi as ti

from . import blocks as _b


def make_loss_kernel(finalize_fn, n_channels: int, n_pixels: int, one_sided: tuple):
    n_regs = len(one_sided)
    augmented = _b.make_augmented(one_sided)

    @ti.kernel
    def loss_kernel(
        acc: ti.template(),
        macc: ti.template(),
        lam: ti.template(),
        g0: float,
        loss: ti.template(),
        diag: ti.template(),
    ):
        a = acc[None]
        g = 0.0
        for c in ti.static(range(n_channels)):
            g += finalize_fn(a, c, n_pixels)
        j, rvals = augmented(g, g0, macc[None], 0, lam[None])
        diag[None][0] = g
        for r in ti.static(range(n_regs)):
            diag[None][1 + r] = rvals[r]
        loss[None] = j

    return loss_kernel
