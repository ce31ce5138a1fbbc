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

Each cluster is the one-warp chain's case: its votes are ``iwe.make_warp_vote``'s, its map sums
``maps.make_maps_reduce``'s and its term of J ``loss.make_objective_term``'s, with the cluster's
channel, slots and parameter slice (``events.make_cluster_theta``). The per-cluster warp functions,
quantities and parameter offsets are static: one compiled kernel per combination of warp models
(different clusters may use different models). The K clusters, the four bilinear taps and the blur
taps are unrolled with ``ti.static``; image writes are atomic adds; no field is written after it is
read. A forward-only pass marks the segments any cluster's votes touch
(``tiles.py``); the blurs and reductions run over them. Formulas: docs/SEGMENTATION.md.
"""

import taichi as ti

from . import blocks as _b
from . import events as _ev
from . import iwe as _iwe
from . import loss as _loss
from . import maps as _maps
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

    Each cluster votes as the single-warp splat does (``iwe.make_warp_vote``) into channel j.
    Memberships are >= 0, so the maps' count image ``C_j = sum_i |P_ij| beta`` equals the unblurred
    ``vote[j]``: pass ``vote`` as ``count`` to the maps reduce. Signature:
    ``splat(n, ev, pw, vote, numer)`` with ``ev`` the ``events.WarpInputs``;
    :func:`make_cluster_mark_kernel` marks the segments its votes touch.
    """
    K = len(warp_fns)
    n_r = len(quantity_fns[0]) if K else 0
    theta_of = _ev.make_cluster_theta(offsets, n_params)
    votes = tuple(
        _iwe.make_warp_vote(
            warp_fns[j],
            quantity_fns[j],
            width=width,
            height=height,
            do_iwe=True,
            whiten=False,
            with_count=False,
        )
        for j in range(K)
    )

    @ti.kernel
    def splat(n: ti.i32, ev: ti.template(), pw: ti.template(), vote: ti.template(), numer: ti.template()):
        for i in range(n):
            p, dt = _ev.event_point(ev, i)
            c = ev.ctx[None]
            thv = ev.th[None]
            for j in ti.static(range(K)):
                b = pw[i, j]
                # a zero membership adds nothing: skip its atomics (hard assignments are 1/K dense)
                if b != 0.0:
                    votes[j](p, dt, theta_of(thv, j), c, b, j, j * n_r, None, vote, vote, numer)

    return splat


def make_cluster_mark_kernel(warp_fns: tuple, offsets: tuple, n_params: tuple, *, width: int, height: int):
    """Forward only: mark in ``tiles`` the footprints that :func:`make_cluster_splat_kernel` votes (every
    cluster with a non-zero membership). Signature ``mark(n, ev, pw, tiles)``."""
    K = len(warp_fns)
    mark = _t.mark_position
    warp_of = _ev.make_cluster_warp(warp_fns, offsets, n_params)

    @ti.kernel
    def mark_events(n: ti.i32, ev: ti.template(), pw: ti.template(), tiles: ti.template()):
        for i in range(n):
            for j in ti.static(range(K)):
                if pw[i, j] != 0.0:
                    mark(tiles, warp_of(ev, i, j))

    return mark_events


def make_cluster_maps_reduce(penalty_fns: tuple, n_clusters: int, width: int, height: int):
    """Per cluster j: ``macc[j (1 + n_r)] += m``, ``macc[j (1 + n_r) + 1 + r] += m P_r(N_jr / C_j)`` with
    the soft support ``m = C_j / (C_j + kappa)``: ``maps.make_maps_reduce`` with ``n_clusters``.
    Signature: ``reduce(count, numer, macc, tiles, part)``."""
    return _maps.make_maps_reduce(penalty_fns, width, height, n_clusters=n_clusters)


def make_cluster_loss_kernel(finalize_fn, n_clusters: int, n_pixels: int, one_sided: tuple):
    """``J = sum_j cw_j (G_j / G0_j - sum_r lambda_r R_jr)`` into ``loss[None]``:
    ``loss.make_cluster_loss_kernel``. Signature ``loss_kernel(acc, macc, lam, g0, cw, loss, diag)``."""
    return _loss.make_cluster_loss_kernel(finalize_fn, n_clusters, n_pixels, one_sided)


def make_cluster_lookup_kernel(warp_fns: tuple, offsets: tuple, n_params: tuple, *, width: int, height: int):
    """Forward only: ``out[i, j]`` = cluster j's image ``img[j]`` bilinearly interpolated at event i's
    position warped by cluster j's parameters; ``pos[i, j]`` = that position (px).

    Taps outside the image read 0; an event warped outside ``(-1, W) x (-1, H)`` (or not finite) reads 0.
    Signature: ``lookup(n, ev, img, out, pos)``.
    """
    K = len(warp_fns)
    _, _, sample = _b.make_bilinear(_b.Size(width, height))
    warp_of = _ev.make_cluster_warp(warp_fns, offsets, n_params)

    @ti.kernel
    def lookup(n: ti.i32, ev: ti.template(), img: ti.template(), out: ti.template(), pos: ti.template()):
        for i in range(n):
            for j in ti.static(range(K)):
                q = warp_of(ev, i, j)
                pos[i, j, 0] = q[0]
                pos[i, j, 1] = q[1]
                out[i, j] = sample(img, j, q)

    return lookup
