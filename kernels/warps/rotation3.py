"""``rotation3``: 3-DOF camera rotation, theta = (w_x, w_y, w_z [rad/s]) (docs/FORMULAS.md).

Uses the focal lengths ``ctx[2], ctx[3]`` (px).
"""

import taichi as ti

from .common import MIN_RAY_Z, OUTSIDE, SERIES_EPS

#: the model's declarations, read by ``cmax_taichi/models/warps.py`` (``WarpModel.from_module``)
MODEL = {
    "name": "rotation3",
    "params": ("w_x", "w_y", "w_z"),
    "units": ("rad/s", "rad/s", "rad/s"),
    "scale_kinds": ("focal", "focal", "rate"),  # w_x, w_y tilt the rays: f px per rad
    "constant_quantities": (),
    "positive_det": True,  # det = 1 / z^3 with z clamped to MIN_RAY_Z > 0
    "needs_camera": True,
    "description": "3-DOF camera rotation (SO(3), needs intrinsics)",
}


@ti.func
def _ray(p, ctx):
    return ti.Vector([(p[0] - ctx[0]) / ctx[2], (p[1] - ctx[1]) / ctx[3], 1.0])


@ti.func
def _rotation(dt, th):
    """exp(dt [w]_x) by Rodrigues, with its series for small angles (no sqrt at 0)."""
    a = dt * ti.Vector([th[0], th[1], th[2]])
    A = ti.Matrix([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    phi2 = a.dot(a)
    s1 = 1.0 - phi2 / 6.0
    s2 = 0.5 - phi2 / 24.0
    if phi2 >= SERIES_EPS * SERIES_EPS:
        phi = ti.sqrt(phi2)
        s1 = ti.sin(phi) / phi
        s2 = (1.0 - ti.cos(phi)) / phi2
    return ti.Matrix.identity(float, 3) + s1 * A + s2 * (A @ A)


@ti.func
def warp(p, dt, th, ctx):
    Xr = _rotation(dt, th) @ _ray(p, ctx)
    out = ti.Vector([OUTSIDE, OUTSIDE])
    if Xr[2] > MIN_RAY_Z:
        out = ti.Vector([ctx[0] + ctx[2] * Xr[0] / Xr[2], ctx[1] + ctx[3] * Xr[1] / Xr[2]])
    return out


@ti.func
def det(p, dt, th, ctx):
    R = _rotation(dt, th)
    X = _ray(p, ctx)
    z = ti.max(R[2, 0] * X[0] + R[2, 1] * X[1] + R[2, 2] * X[2], MIN_RAY_Z)
    return 1.0 / (z * z * z)


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


@ti.func
def _cross_basis(j: ti.template(), v):
    """``e_j x v`` for the unit vector ``e_j``."""
    out = ti.Vector([0.0 * v[0], 0.0 * v[0], 0.0 * v[0]])
    if ti.static(j == 0):
        out = ti.Vector([0.0 * v[0], -v[2], v[1]])
    elif ti.static(j == 1):
        out = ti.Vector([v[2], 0.0 * v[0], -v[0]])
    else:
        out = ti.Vector([-v[1], v[0], 0.0 * v[0]])
    return out


@ti.func
def param_jac(p, dt, th, ctx):
    X = ti.Vector([(p[0] - ctx[0]) / ctx[2], (p[1] - ctx[1]) / ctx[3], 1.0])
    a = dt * ti.Vector([th[0], th[1], th[2]])
    u = a.dot(a)
    # s1 = sin(phi) / phi, s2 = (1 - cos(phi)) / phi^2 as _rotation, and their derivatives in u = phi^2
    s1 = 1.0 - u / 6.0
    s2 = 0.5 - u / 24.0
    d1 = -1.0 / 6.0 + 0.0 * u
    d2 = -1.0 / 24.0 + 0.0 * u
    if u >= SERIES_EPS * SERIES_EPS:
        phi = ti.sqrt(u)
        s1 = ti.sin(phi) / phi
        s2 = (1.0 - ti.cos(phi)) / u
        if u < 1e-4:  # the closed forms of the derivatives cancel badly for small phi: series
            d1 = -1.0 / 6.0 + u / 60.0 - u * u / 1680.0
            d2 = -1.0 / 24.0 + u / 360.0 - u * u / 13440.0
        else:
            d1 = (phi * ti.cos(phi) - ti.sin(phi)) / (2.0 * u * phi)
            d2 = (phi * ti.sin(phi) - 2.0 * (1.0 - ti.cos(phi))) / (2.0 * u * u)
    aX = a.cross(X)
    aaX = a.cross(aX)
    Xr = X + s1 * aX + s2 * aaX
    # dXr/da_j = s1 e_j x X + s2 (e_j x (a x X) + a x (e_j x X)) + 2 a_j (d1 a x X + d2 a x (a x X))
    D = ti.Matrix.zero(float, 3, 3)
    for j in ti.static(range(3)):
        col = (
            s1 * _cross_basis(j, X)
            + s2 * (_cross_basis(j, aX) + a.cross(_cross_basis(j, X)))
            + 2.0 * a[j] * (d1 * aX + d2 * aaX)
        )
        for i in ti.static(range(3)):
            D[i, j] = dt * col[i]
    z = Xr[2]
    jx = ti.Matrix.zero(float, 2, 3)
    ddet = ti.Vector([0.0, 0.0, 0.0])
    if z > MIN_RAY_Z:
        for j in ti.static(range(3)):
            jx[0, j] = ctx[2] * (D[0, j] / z - Xr[0] * D[2, j] / (z * z))
            jx[1, j] = ctx[3] * (D[1, j] / z - Xr[1] * D[2, j] / (z * z))
            ddet[j] = -3.0 * D[2, j] / (z * z * z * z)
    ddiv = ti.Vector([3.0 * X[1], -3.0 * X[0], 0.0])
    return jx, ddet, ddiv
