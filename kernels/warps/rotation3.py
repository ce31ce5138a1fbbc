"""``rotation3``: 3-DOF camera rotation, theta = (w_x, w_y, w_z [rad/s]) (docs/FORMULAS.md).

Uses the focal lengths ``ctx[2], ctx[3]`` (px).

The rotation of an event's ray is Rodrigues' ``X' = X + dt s1(u) (w x X) + dt^2 s2(u) w x (w x X)``
with ``u = phi^2 = dt^2 |w|^2``, ``s1 = sin(phi) / phi`` and ``s2 = (1 - cos(phi)) / phi^2``, written
with the half angle ``h = phi / 2``: ``s1 = (sin(h) / h) cos(h)``, ``s2 = (sin(h) / h)^2 / 2``. Up to
``phi = pi / 2`` (90 degrees between an event and the reference time) ``(h - sin h) / h^3`` and
``(1 - cos h) / h^2`` are their Taylor polynomials in ``v = h^2 = u / 4``, truncated where the first
omitted term is below an eighth of the machine epsilon of the precision in use
(``common.taylor_terms``: 8 and 8 terms in f64, 5 and 5 in f32; for ``phi <= 0.09`` rad, where a
window of a few ms keeps all its events, the same rule on that range gives 4 and 4 in f64, 2 and 2 in
f32), so they are exact to the rounding of that precision; ``s1``, ``s2`` and their slopes ``ds1/du``,
``ds2/du`` all come from these two (``common.rodrigues``). Beyond, the half angle is reduced modulo
``pi / 2`` into ``[-pi/4, pi/4]`` first (in a branch: a square root, a ``floor``, a division; the same
polynomials), with an error of about the rounding of ``phi`` itself. No event calls the maths
library: with libm calls in its event loops rotation3 cost 8x translation2 per event
(benchmarks/NOTES.md).
``warp_terms`` computes the warp, ``det`` and ``param_jac`` of an event from one evaluation (the fused
kernels call it, so they rotate each ray once); ``warp``, ``det`` and ``param_jac`` are its parts. The
parameter Jacobian is ``dX'/dw = -c1 [X]x + c2 w X^T + c2 (w . X) I + (g - 2 c2 X) w^T`` projected row
by row (docs/FORMULAS.md): about a third fewer operations than its three columns one by one, in the
event loops whose arithmetic sets rotation3's cost. The error bound: docs/FORMULAS.md ("rotation3");
``tests/test_rotation_series.py`` holds it in f32 and f64.
"""

import taichi as ti

from .common import MIN_RAY_Z, OUTSIDE, rodrigues

#: the model's declarations, read by ``cmax_taichi/models/warps.py`` (``WarpModel.from_module``)
MODEL = {
    "name": "rotation3",
    "params": ("w_x", "w_y", "w_z"),
    "units": ("rad/s", "rad/s", "rad/s"),
    "scale_kinds": ("focal", "focal", "rate"),  # w_x, w_y tilt the rays: f px per rad
    "constant_quantities": (),
    "positive_det": True,  # det = 1 / z^3 with z clamped to MIN_RAY_Z > 0
    "needs_camera": True,
    # its warp_terms is the costliest per event of the built-in models: evaluated once per event and
    # call, stored for the gather (benchmarks/NOTES.md, "stored event terms")
    "store_event_terms": True,
    "description": "3-DOF camera rotation (SO(3), needs intrinsics)",
}

@ti.func
def _reciprocal(f):
    """``1 / f`` for a focal length ``f > 0``, through a select: LLVM (with Taichi's ``reassoc`` flags)
    rewrites ``x * (1 / f)`` as ``x / f``, a division in every event; the select keeps one division per
    window, outside the event loop."""
    return ti.select(f != 0.0, 1.0 / f, 0.0)


@ti.func
def _ray(p, ctx):
    """The calibrated ray ``((x - c_x) / f_x, (y - c_y) / f_y, 1)``."""
    return ti.Vector([(p[0] - ctx[0]) * _reciprocal(ctx[2]), (p[1] - ctx[1]) * _reciprocal(ctx[3]), 1.0])


@ti.func
def _omega(th):
    return ti.Vector([th[0], th[1], th[2]])


@ti.func
def warp_terms(p, dt, th, ctx):
    """``(warp, det, jx, ddet, ddiv)`` of one event from one evaluation of the rotation (the fused
    kernels call this; the parts a kernel does not use are dead code there)."""
    X = _ray(p, ctx)
    w = _omega(th)
    dt2 = dt * dt
    s1, s2, d1, d2 = rodrigues(dt2 * w.dot(w), dt * w)
    wX = w.cross(X)
    wwX = w.cross(wX)
    c1 = dt * s1
    c2 = dt2 * s2
    Xr = X + c1 * wX + c2 * wwX
    out = ti.Vector([OUTSIDE, OUTSIDE])
    iz = 1.0 / ti.max(Xr[2], MIN_RAY_Z)
    det_value = iz * iz * iz
    jx = ti.Matrix.zero(float, 2, 3)
    ddet = ti.Vector([0.0, 0.0, 0.0])
    if Xr[2] > MIN_RAY_Z:
        px = Xr[0] * iz
        py = Xr[1] * iz
        out = ti.Vector([ctx[0] + ctx[2] * px, ctx[1] + ctx[3] * py])
        # X' = X + c1 w x X + c2 w x (w x X), c1 = dt s1(u), c2 = dt^2 s2(u), u = dt^2 |w|^2:
        # dX'/dw = -c1 [X]x + c2 w X^T + c2 (w . X) I + h w^T, h = g - 2 c2 X,
        # g = 2 dt^2 (dt d1 w x X + dt^2 d2 w x (w x X)); x' = c + f X'_{x,y} / z: each row of dx'/dw is
        # f / z times a row of N dX'/dw, N = [[1, 0, -px], [0, 1, -py]] (a^T [X]x = (a x X)^T, X_z = 1)
        g = 2.0 * dt2 * ((dt * d1) * wX + (dt2 * d2) * wwX)
        h = g - 2.0 * c2 * X
        k = c2 * w.dot(X)
        row_f = ti.Vector([ctx[2] * iz, ctx[3] * iz])
        row_p = ti.Vector([px, py])
        cross_rows = ti.Matrix([[px * X[1], -px * X[0] - 1.0, X[1]], [1.0 + py * X[1], -py * X[0], -X[0]]])
        for i in ti.static(range(2)):
            m = c2 * (w[i] - row_p[i] * w[2])  # c2 (N w)_i
            n = h[i] - row_p[i] * h[2]  # (N h)_i
            for j in ti.static(range(3)):
                d = m * X[j] + n * w[j] - c1 * cross_rows[i, j]
                if ti.static(j == i):
                    d += k
                elif ti.static(j == 2):
                    d -= k * row_p[i]
                jx[i, j] = row_f[i] * d
        # det = 1 / z^3: d det / dw_j = -3 z^-4 (dX'/dw)_{z, j}, whose row is (e_z x X)^T = (-X_y, X_x, 0)
        iz4 = -3.0 * det_value * iz
        ez_cross = ti.Vector([-X[1], X[0], 0.0])
        for j in ti.static(range(3)):
            d = c2 * w[2] * X[j] + h[2] * w[j] - c1 * ez_cross[j]
            if ti.static(j == 2):
                d += k
            ddet[j] = iz4 * d
    ddiv = ti.Vector([3.0 * X[1], -3.0 * X[0], 0.0])
    return out, det_value, jx, ddet, ddiv


@ti.func
def warp(p, dt, th, ctx):
    terms = warp_terms(p, dt, th, ctx)
    return terms[0]


@ti.func
def det(p, dt, th, ctx):
    terms = warp_terms(p, dt, th, ctx)
    return terms[1]


@ti.func
def param_jac(p, dt, th, ctx):
    terms = warp_terms(p, dt, th, ctx)
    return terms[2], terms[3], terms[4]


@ti.func
def div(p, th, ctx):
    X = _ray(p, ctx)
    return -3.0 * (th[1] * X[0] - th[0] * X[1])


@ti.func
def flow(p, th, ctx):
    X = _ray(p, ctx)
    dx = th[1] * (1.0 + X[0] * X[0]) - th[0] * X[0] * X[1] - th[2] * X[1]
    dy = -th[0] * (1.0 + X[1] * X[1]) + th[1] * X[0] * X[1] + th[2] * X[0]
    return ti.Vector([-ctx[2] * dx, -ctx[3] * dy])
