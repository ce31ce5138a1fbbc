"""Regularizer maps: vote-weighted averages of per-event quantities and their support-weighted means.

The splat kernel (``iwe.py``) votes ``C(x) = sum |w| beta`` into ``count`` and
``N_r(x) = sum |w| beta q_r`` into ``numer[r]``. Here, per pixel with ``C > 0``, the map value is
``N_r / C``, its penalty ``P_r`` is given by the regularizer's pixel function, and
``m = C / (C + kappa)`` (``blocks.support_weight``) weights it: ``macc[0] += m``, ``macc[1 + r] += m P_r``.
Only touched pixels have ``C > 0``: the kernels run over the touched segments (``tiles.py``, list 0), the
reduction through per-segment partial sums added in list order (a fixed order).
Formulas: docs/FORMULAS.md, "Regularizer maps and penalties".
"""

import taichi as ti

from . import blocks as _b
from . import tiles as _t

DEF_FLOOR = 1e-3  # deformation guard: alpha stays finite at collapse (det -> 0)


@ti.func
def divergence_penalty(avg):
    """Pixel penalty of the divergence map: the map itself (scaled by s_t T in the loss)."""
    return avg


@ti.func
def deformation_penalty(avg):
    """alpha = max(D, 1/D) - 1 with D = max(DEF, DEF_FLOOR)."""
    d = ti.max(avg, DEF_FLOOR)
    return ti.max(d, 1.0 / d) - 1.0


@ti.func
def divergence_penalty_grad(avg):
    """d(divergence_penalty)/d(map value)."""
    return 1.0 + 0.0 * avg


@ti.func
def deformation_penalty_grad(avg):
    """d(deformation_penalty)/d(map value): 0 up to the floor, -1/D^2 up to 1, 1 above. At the kinks
    it takes the side Taichi's autodiff of ``ti.max`` takes (the second argument on a tie)."""
    out = 0.0 * avg
    if avg > DEF_FLOOR:
        out = 1.0 if avg > 1.0 else -1.0 / (avg * avg)
    return out


#: derivatives of the built-in pixel penalties, for the fused pipeline's hand-written map adjoints
PENALTY_GRADS = {
    divergence_penalty: divergence_penalty_grad,
    deformation_penalty: deformation_penalty_grad,
}


@ti.func
def _count_hw(count: ti.template(), j: ti.template(), y, x):
    """Pixel of the one-warp count image ``(H, W)``."""
    return count[y, x]


def make_maps_reduce(penalty_fns: tuple, width: int, height: int, n_clusters: int = 0):
    """Kernel ``reduce(count, numer, macc, tiles, part)``: ``macc[0] += sum m``,
    ``macc[1 + r] += sum m P_r(N_r / C)`` over the touched pixels (list 0 of ``tiles``) with ``C > 0``,
    through the per-segment partial sums ``part[k, .]`` (zero before), added in list order.

    ``n_clusters = K > 0``: the same per cluster j (``clusters.py``), with the count ``count[j]`` of a
    ``(K, H, W)`` image, the numerators ``numer[j n_r + r]`` and the slots ``j (1 + n_r) + .`` of
    ``macc`` and ``part``; 0: one warp, count ``(H, W)``."""
    n_r = len(penalty_fns)
    K = max(n_clusters, 1)
    S = 1 + n_r
    count_at = _b.read_chw if n_clusters else _count_hw
    entry = _t.entry

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
                        cnt = count_at(count, j, y, x)
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


def make_maps_image_kernel(penalty_fns: tuple, width: int, height: int):
    """Forward-only: write the maps ``N_r / C`` and penalties into ``out[2 r]`` and ``out[2 r + 1]`` at
    the touched pixels (list 0 of ``tiles``; ``out`` is read where ``C > 0`` only)."""
    n_r = len(penalty_fns)
    entry = _t.entry

    @ti.kernel
    def images(count: ti.template(), numer: ti.template(), out: ti.template(), tiles: ti.template()):
        for i in range(tiles.count[0] * _t.SEG):
            y, x0 = entry(tiles, 0, i // _t.SEG)
            x = x0 + i % _t.SEG
            if x < width:
                cnt = count[y, x]
                for r in ti.static(range(n_r)):
                    v = 0.0
                    pen = 0.0
                    if cnt > 0.0:
                        v = numer[r, y, x] / cnt
                        pen = penalty_fns[r](v)
                    out[2 * r, y, x] = v
                    out[2 * r + 1, y, x] = pen

    return images
