"""Regularizer maps: vote-weighted averages of per-event quantities and their support-weighted means.

The splat kernel (``iwe.py``) votes ``C(x) = sum |w| beta`` into ``count`` and
``N_r(x) = sum |w| beta q_r`` into ``numer[r]``. Here, per pixel with ``C > 0``, the map value is
``N_r / C``, its penalty ``P_r`` is given by the regularizer's pixel function, and
``m = C / (C + kappa)`` (``blocks.support_weight``) weights it: ``macc[0] += m``, ``macc[1 + r] += m P_r``.
Formulas: docs/FORMULAS.md, "Regularizer maps and penalties".
"""

import taichi as ti

from . import blocks as _b

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


def make_maps_reduce(penalty_fns: tuple, width: int, height: int):
    """Kernel ``reduce(count, numer, macc)``: ``macc[0] += sum m``, ``macc[1 + r] += sum m P_r(N_r / C)``
    over the pixels with ``C > 0``."""
    n_r = len(penalty_fns)

    @ti.kernel
    def reduce(count: ti.template(), numer: ti.template(), macc: ti.template()):
        for y, x in ti.ndrange(height, width):
            cnt = count[y, x]
            if cnt > 0.0:
                m = _b.support_weight(cnt)
                macc[None][0] += m
                for r in ti.static(range(n_r)):
                    macc[None][1 + r] += m * penalty_fns[r](numer[r, y, x] / cnt)

    return reduce


def make_maps_image_kernel(penalty_fns: tuple, width: int, height: int):
    """Forward-only: write the maps ``N_r / C`` and penalties into ``out[2 r]`` and ``out[2 r + 1]``."""
    n_r = len(penalty_fns)

    @ti.kernel
    def images(count: ti.template(), numer: ti.template(), out: ti.template()):
        for y, x in ti.ndrange(height, width):
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
