"""Multi-cluster kernels for motion segmentation (Stoffregen et al. ICCV 2019 style, with the
event-collapse regularizers of Shiba et al. 2022).

K clusters each have a warp model and parameters; every event votes into every cluster's image with
its membership weight ``P[i, j]`` at its position warped by cluster j's parameters. Layouts:

* ``pw``    (capacity, K) memberships, no gradient;
* ``th``    0-D vector of all parameters, cluster j at ``th[off_j : off_j + n_j]`` (needs grad);
* ``vote``, ``tmp``, ``img``  (K, H, W): one IWE channel per cluster (blur: ``iwe.make_blur_kernel``
  with ``n_channels = K``; objective reduce: the factories of ``objectives.py`` with ``n_channels = K``);
* ``numer`` (K * n_r, H, W): the regularizer map numerators of each cluster (``numer[j * n_r + r]``),
  built with ``|P[i, j]| = P[i, j]`` as the event's weight (as ``iwe.py`` uses ``|w|``); the map count
  ``C_j`` is the unblurred ``vote[j]`` (memberships are >= 0);
* ``macc``  0-D vector of K * (1 + n_r) slots: per cluster the support sum and the support-weighted
  penalties (``maps.py`` convention, one block per cluster);
* ``g0``, ``cw`` 0-D vectors of K: per-cluster normaliser G0_j and on/off weight of the cluster in J.

The per-cluster warp functions, quantities and parameter offsets are static: one compiled kernel per
combination of warp models (different clusters may use different models). The K clusters, the four
bilinear taps and the blur taps are unrolled with ``ti.static``; image writes are atomic adds; no
field is written after it is read. A forward-only pass marks the segments any cluster's votes touch
(``tiles.py``); the blurs and reductions run over them. Formulas: docs/SEGMENTATION.md.
"""

import taichi as ti

from . import blocks as _b
from . import tiles as _t


def make_cluster_splat_kernel(
    warp_fns: tuple,
    quantity_fns: tuple,
    offsets: tuple,
    n_params: tuple,
    *,
    width: int,
    height: int,
):
    """Build the fused per-event kernel of K clusters: warp, membership-weighted IWE and map votes.

    Parameters
    ----------
    warp_fns : tuple of ti.func, length K
        ``warp(p, dt, th, ctx) -> vec2`` of each cluster's model.
    quantity_fns : tuple of tuples of ti.func, K x n_r
        Per-event regularizer quantities of each cluster's model (same regularizers for all).
    offsets, n_params : tuple of int, length K
        Where cluster j's parameters start in ``th`` and how many it has.
    width, height : int
        Image size (px).

    Memberships are >= 0, so the maps' count image ``C_j = sum_i |P_ij| beta`` equals the unblurred
    ``vote[j]``: pass ``vote`` as ``count`` to the maps reduce. Signature:
    ``splat(n, ex, ey, edt, pw, th, ctx, vote, numer)``; :func:`make_cluster_mark_kernel` marks the
    segments its votes touch.
    """
    K = len(warp_fns)
    n_r = len(quantity_fns[0]) if K else 0
    W, H = width, height
    vote_at, vote_maps, _ = _b.make_bilinear(W, H)

    @ti.kernel
    def splat(
        n: ti.i32,
        ex: ti.template(),
        ey: ti.template(),
        edt: ti.template(),
        pw: ti.template(),
        th: ti.template(),
        ctx: ti.template(),
        vote: ti.template(),
        numer: ti.template(),
    ):
        for i in range(n):
            p = ti.Vector([ex[i], ey[i]])
            dt = edt[i]
            c = ctx[None]
            thv = th[None]
            for j in ti.static(range(K)):
                b = pw[i, j]
                # a zero membership adds nothing: skip its atomics (hard assignments are 1/K dense)
                if b != 0.0:
                    theta = ti.Vector([thv[offsets[j] + a] for a in ti.static(range(n_params[j]))])
                    q = warp_fns[j](p, dt, theta, c)
                    vote_at(vote, j, q, b)
                    if ti.static(n_r > 0):
                        vals = ti.Vector([quantity_fns[j][r](p, dt, theta, c) for r in ti.static(range(n_r))])
                        vote_maps(vote, numer, j * n_r, q, b, vals, False)

    return splat


def make_cluster_mark_kernel(warp_fns: tuple, offsets: tuple, n_params: tuple, *, width: int, height: int):
    """Forward only: mark in ``tiles`` the footprints that :func:`make_cluster_splat_kernel` votes (every
    cluster with a non-zero membership). Signature ``mark(n, ex, ey, edt, pw, th, ctx, tiles)``."""
    K = len(warp_fns)
    mark = _t.make_mark_position(width, height)

    @ti.kernel
    def mark_events(
        n: ti.i32,
        ex: ti.template(),
        ey: ti.template(),
        edt: ti.template(),
        pw: ti.template(),
        th: ti.template(),
        ctx: ti.template(),
        tiles: ti.template(),
    ):
        for i in range(n):
            p = ti.Vector([ex[i], ey[i]])
            c = ctx[None]
            thv = th[None]
            for j in ti.static(range(K)):
                if pw[i, j] != 0.0:
                    theta = ti.Vector([thv[offsets[j] + a] for a in ti.static(range(n_params[j]))])
                    mark(tiles, warp_fns[j](p, edt[i], theta, c))

    return mark_events


def make_cluster_maps_reduce(penalty_fns: tuple, n_clusters: int, width: int, height: int):
    """Per cluster j: ``macc[j (1 + n_r)] += m``, ``macc[j (1 + n_r) + 1 + r] += m P_r(N_jr / C_j)`` with
    the soft support ``m = C_j / (C_j + kappa)`` (``maps.py`` per cluster), over the touched pixels (list
    0 of ``tiles``) through the per-segment partial sums ``part[k, .]`` (zero before), added in list
    order. Signature: ``reduce(count, numer, macc, tiles, part)``."""
    n_r = len(penalty_fns)
    K = n_clusters
    S = 1 + n_r
    entry = _t.make_entry(width)

    @ti.kernel
    def reduce(
        count: ti.template(),
        numer: ti.template(),
        macc: ti.template(),
        tiles: ti.template(),
        part: ti.template(),
    ):
        for k in range(tiles.count[0]):
            y, x0 = entry(tiles, 0, k)
            for p in ti.static(range(_t.SEG)):
                x = x0 + p
                if x < width:
                    for j in ti.static(range(K)):
                        cnt = count[j, y, x]
                        if cnt > 0.0:
                            m = _b.support_weight(cnt)
                            part[k, j * S] += m
                            for r in ti.static(range(n_r)):
                                part[k, j * S + 1 + r] += m * penalty_fns[r](numer[j * n_r + r, y, x] / cnt)
        ti.loop_config(serialize=True)  # the partial sums in list order
        for k in range(tiles.count[0]):
            for i in ti.static(range(K * S)):
                macc[None][i] += part[k, i]

    return reduce


def make_cluster_loss_kernel(finalize_fn, n_clusters: int, n_pixels: int, one_sided: tuple):
    """``J = sum_j cw_j (G_j / G0_j - sum_r lambda_r R_jr)`` into ``loss[None]``.

    ``G_j = finalize(acc, j, n_pixels)`` (channel j of the objective reduce) and
    ``R_jr = s_r macc[j S + 1 + r] / macc[j S]`` (0 when cluster j has no support; ``max(0, .)`` for the
    regularizers flagged in ``one_sided``), ``S = 1 + n_regs``, ``lam[None][r] = lambda_r`` and
    ``lam[None][n_regs + r] = s_r`` the regularizer's scale. ``diag`` receives per cluster
    ``(G_raw_j, R_j0, ...)`` at ``j S``.
    """
    K = n_clusters
    n_regs = len(one_sided)
    S = 1 + n_regs
    augmented = _b.make_augmented(one_sided)

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
        a = acc[None]
        sums = macc[None]
        total = 0.0
        for j in ti.static(range(K)):
            g = finalize_fn(a, j, n_pixels)
            term, rvals = augmented(g, g0[None][j], sums, j * S, lam[None])
            diag[None][j * S] = g
            for r in ti.static(range(n_regs)):
                diag[None][j * S + 1 + r] = rvals[r]
            total += cw[None][j] * term
        loss[None] = total

    return loss_kernel


def make_cluster_lookup_kernel(warp_fns: tuple, offsets: tuple, n_params: tuple, *, width: int, height: int):
    """Forward only: ``out[i, j]`` = cluster j's image ``img[j]`` bilinearly interpolated at event i's
    position warped by cluster j's parameters; ``pos[i, j]`` = that position (px).

    Taps outside the image read 0; an event warped outside ``(-1, W) x (-1, H)`` (or not finite) reads 0.
    Signature: ``lookup(n, ex, ey, edt, th, ctx, img, out, pos)``.
    """
    K = len(warp_fns)
    W, H = width, height
    _, _, sample = _b.make_bilinear(W, H)

    @ti.kernel
    def lookup(
        n: ti.i32,
        ex: ti.template(),
        ey: ti.template(),
        edt: ti.template(),
        th: ti.template(),
        ctx: ti.template(),
        img: ti.template(),
        out: ti.template(),
        pos: ti.template(),
    ):
        for i in range(n):
            p = ti.Vector([ex[i], ey[i]])
            dt = edt[i]
            c = ctx[None]
            thv = th[None]
            for j in ti.static(range(K)):
                theta = ti.Vector([thv[offsets[j] + a] for a in ti.static(range(n_params[j]))])
                q = warp_fns[j](p, dt, theta, c)
                pos[i, j, 0] = q[0]
                pos[i, j, 1] = q[1]
                out[i, j] = sample(img, j, q)

    return lookup
