"""The augmented objective J = G / G0 - sum_r lambda_r R_r as one serial kernel into a 0-D loss field.

``G`` is the objective summed over channels (``finalize`` of ``objectives.py``), ``G0`` the identity
warp's value (1 for the raw objective), ``R_r = s_r macc[1 + r] / macc[0]`` the regularizer penalties
(``max(0, .)`` for one-sided ones), with ``lam[None][r] = lambda_r`` and ``lam[None][n + r] = s_r`` the
regularizer's scale. ``diag`` receives ``(G_raw, R_0, ...)`` for reporting.
Formulas: docs/FORMULAS.md, "Augmented objective".
"""

import taichi as ti

from . import blocks as _b


def make_objective_term(finalize_fn, n_channels: int, n_pixels: int, one_sided: tuple):
    """``term(a, sums, lam, g0, t, diag)``: the augmented objective ``G_t / g0 - sum_r lambda_r R_tr`` of
    term ``t`` (static), ``G_t`` the sum of ``finalize(a, c, n_pixels)`` over its channels
    ``c = t n_channels + .`` and ``R_tr`` from the slots ``t (1 + n_r) + .`` of ``sums``; writes
    ``(G_t, R_t0, ...)`` at ``diag[None][t (1 + n_r)]``. One term for one warp, one per cluster for K
    clusters (``clusters.py``)."""
    n_regs = len(one_sided)
    S = 1 + n_regs
    augmented = _b.make_augmented(one_sided)

    @ti.func
    def term(a, sums, lam, g0, t: ti.template(), diag: ti.template()):
        g = 0.0
        for c in ti.static(range(n_channels)):
            g += finalize_fn(a, t * n_channels + c, n_pixels)
        j, rvals = augmented(g, g0, sums, t * S, lam)
        diag[None][t * S] = g
        for r in ti.static(range(n_regs)):
            diag[None][t * S + 1 + r] = rvals[r]
        return j

    return term


def make_loss_kernel(finalize_fn, n_channels: int, n_pixels: int, one_sided: tuple):
    """Kernel ``loss_kernel(acc, macc, lam, g0, loss, diag)``: ``J = G / g0 - sum_r lambda_r R_r`` of one
    warp into ``loss[None]``, ``G`` summed over the ``n_channels`` channels (``g0`` a Python float)."""
    term = make_objective_term(finalize_fn, n_channels, n_pixels, one_sided)

    @ti.kernel
    def loss_kernel(
        acc: ti.template(),
        macc: ti.template(),
        lam: ti.template(),
        g0: float,
        loss: ti.template(),
        diag: ti.template(),
    ):
        loss[None] = term(acc[None], macc[None], lam[None], g0, 0, diag)

    return loss_kernel


def make_cluster_loss_kernel(finalize_fn, n_clusters: int, n_pixels: int, one_sided: tuple):
    """Kernel ``loss_kernel(acc, macc, lam, g0, cw, loss, diag)``: ``J = sum_j cw_j (G_j / G0_j -
    sum_r lambda_r R_jr)`` of K clusters into ``loss[None]``, ``G_j`` channel j of the objective reduce,
    ``R_jr`` from the cluster's block of ``macc`` (``maps.make_maps_reduce`` with ``n_clusters``), ``G0_j``
    and ``cw_j`` (0 or 1) in the 0-D vectors ``g0``, ``cw``; ``diag`` receives ``(G_raw_j, R_j0, ...)``
    per cluster."""
    term = make_objective_term(finalize_fn, 1, n_pixels, one_sided)

    @ti.kernel
    def loss_kernel(
        acc: ti.template(),
        macc: ti.template(),
        lam: ti.template(),
        g0: ti.template(),
        cw: ti.template(),
        loss: ti.template(),
        diag: ti.template(),
    ):
        total = 0.0
        for j in ti.static(range(n_clusters)):
            total += cw[None][j] * term(acc[None], macc[None], lam[None], g0[None][j], j, diag)
        loss[None] = total

    return loss_kernel
