"""Whitening baseline (Nunes & Demiris): whiten the warped positions before building the IWE.

``x'' = mu0 + S0^(1/2) (S + eps I)^(-1/2) (x' - mu)`` (docs/FORMULAS.md, "Whitening baseline").
The moments of the warped positions are reduced into one 0-D vector field ``wmom``:
slots 0-4 hold ``sum x, sum y, sum x^2, sum x y, sum y^2`` of the positions relative to the centre
``(cx, cy)`` of ``ctx`` (less cancellation in f32), slot 5 the number of events in the moments, slots
6-7 ``mu0`` and 8-10 the entries ``(a, b, d)`` of the symmetric ``S0^(1/2)``; slots 5-10 are written by
the driver (slot 5: the event count). An event that the warp sends nowhere (``(OUTSIDE, OUTSIDE)``: a
``rotation3`` ray rotated behind the camera) is dropped as in the IWE: left out of the moments (the
moments kernel takes it off slot 5) and not whitened, so that it is voted nowhere. Counting it at the
sentinel position would make ``mu`` and ``S`` depend on an arbitrary constant (-1e7 px).
"""

import taichi as ti

from . import events as _ev
from .warps.common import OUTSIDE

N_SLOTS = 11
EPS = 1e-6  # px^2, keeps the covariance invertible at total collapse


@ti.func
def _nowhere(q):
    """The warp sent the event nowhere (``warps.common.OUTSIDE`` in both coordinates)."""
    return q[0] == OUTSIDE and q[1] == OUTSIDE


@ti.func
def _inv_sqrt_2x2(a, b, d):
    """Inverse of the symmetric square root of the SPD matrix [[a, b], [b, d]]."""
    det = ti.max(a * d - b * b, EPS * EPS)
    s = ti.sqrt(det)
    t = ti.sqrt(a + d + 2.0 * s)
    # sqrt(S) = (S + s I) / t; its inverse is adj(S + s I) / (det(S + s I) / t)
    ra, rb, rd = (a + s) / t, b / t, (d + s) / t
    rdet = ra * rd - rb * rb
    return rd / rdet, -rb / rdet, ra / rdet


@ti.func
def apply(q, m, c):
    """Whitened position of the warped position ``q`` given the moments ``m`` and the context ``c``
    (``q`` itself when the warp sent the event nowhere)."""
    n = ti.max(m[5], 1.0)  # every event dropped: no moments (and nothing to whiten)
    mx = m[0] / n
    my = m[1] / n
    sxx = ti.max(m[2] / n - mx * mx, 0.0) + EPS
    sxy = m[3] / n - mx * my
    syy = ti.max(m[4] / n - my * my, 0.0) + EPS
    ia, ib, id_ = _inv_sqrt_2x2(sxx, sxy, syy)
    # the moments are relative to the centre (c[0], c[1])
    ux = q[0] - c[0] - mx
    uy = q[1] - c[1] - my
    wx = ia * ux + ib * uy
    wy = ib * ux + id_ * uy
    out = ti.Vector([m[6] + m[8] * wx + m[9] * wy, m[7] + m[9] * wx + m[10] * wy])
    if _nowhere(q):
        out = q
    return out


def make_moments_kernel(warp_fn):
    """Reduce the first and second moments of the warped positions into ``wmom`` (slots 0-4); an
    event sent nowhere is taken off the count in slot 5 instead. Signature ``moments(n, ev, wmom)``,
    ``ev`` the ``events.WarpInputs``."""

    @ti.kernel
    def moments(n: ti.i32, ev: ti.template(), wmom: ti.template()):
        for i in range(n):
            q = _ev.warped_point(warp_fn, ev, i)
            if _nowhere(q):
                wmom[None][5] -= 1.0
            else:
                ux = q[0] - ev.ctx[None][0]
                uy = q[1] - ev.ctx[None][1]
                wmom[None][0] += ux
                wmom[None][1] += uy
                wmom[None][2] += ux * ux
                wmom[None][3] += ux * uy
                wmom[None][4] += uy * uy

    return moments
