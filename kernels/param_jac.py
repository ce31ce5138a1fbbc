"""Closed-form parameter Jacobians of the built-in warps, for the fused pipeline's hand-written backward.

For the event at pixel ``p`` (px) and time offset ``dt`` (s), ``<model>_param_jac(p, dt, th, ctx)``
returns ``(jx, ddet, ddiv)``:

* ``jx``   (2 x P matrix): ``d x' / d theta`` of the model's ``warp`` (px per parameter unit);
* ``ddet`` (P-vector):     ``d det(dx'/dx) / d theta`` of the model's ``det``;
* ``ddiv`` (P-vector):     ``d div v / d theta`` of the model's ``div``.

They differentiate exactly the expressions of ``warps.py`` (same series branches), and the tests hold
them against Taichi autodiff and finite differences. The per-event cost is a few multiply-adds: the
trigonometric factors depend on theta only, so the compiler hoists them out of the serial event loop.
Models without an entry here (user warps) are differentiated by Taichi autodiff instead.
"""

import taichi as ti

from . import warps as kw


@ti.func
def _zero_vec(n: ti.template(), like):
    return ti.Vector([0.0 * like for _ in ti.static(range(n))])


@ti.func
def zoom1_param_jac(p, dt, th, ctx):
    s = 1.0 - dt * th[0]
    jx = ti.Matrix([[-dt * (p[0] - ctx[0])], [-dt * (p[1] - ctx[1])]])
    return jx, ti.Vector([-2.0 * dt * s]), ti.Vector([2.0 + 0.0 * dt])


@ti.func
def translation2_param_jac(p, dt, th, ctx):
    jx = ti.Matrix([[-dt, 0.0 * dt], [0.0 * dt, -dt]])
    zero = _zero_vec(2, dt)
    return jx, zero, zero


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
def rotation3_param_jac(p, dt, th, ctx):
    X = ti.Vector([(p[0] - ctx[0]) / ctx[2], (p[1] - ctx[1]) / ctx[3], 1.0])
    a = dt * ti.Vector([th[0], th[1], th[2]])
    u = a.dot(a)
    # s1 = sin(phi) / phi, s2 = (1 - cos(phi)) / phi^2 as kw._rotation, and their derivatives in u = phi^2
    s1 = 1.0 - u / 6.0
    s2 = 0.5 - u / 24.0
    d1 = -1.0 / 6.0 + 0.0 * u
    d2 = -1.0 / 24.0 + 0.0 * u
    if u >= kw.SERIES_EPS * kw.SERIES_EPS:
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
    if z > kw.MIN_RAY_Z:
        for j in ti.static(range(3)):
            jx[0, j] = ctx[2] * (D[0, j] / z - Xr[0] * D[2, j] / (z * z))
            jx[1, j] = ctx[3] * (D[1, j] / z - Xr[1] * D[2, j] / (z * z))
            ddet[j] = -3.0 * D[2, j] / (z * z * z * z)
    ddiv = ti.Vector([3.0 * X[1], -3.0 * X[0], 0.0])
    return jx, ddet, ddiv


@ti.func
def _cmul(a, b):
    return ti.Vector([a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0]])


_EXPM1_PRIME_SERIES = (1 / 2, 1 / 3, 1 / 8, 1 / 30, 1 / 144, 1 / 840, 1 / 5760)  # k / (k+1)!, k = 1..7


@ti.func
def _cexpm1_over_z_prime(z):
    """d/dz of (e^z - 1) / z; its series (error < 1e-10) where |z| < 0.1 (the closed form cancels)."""
    out = ti.Vector([0.0 * z[0], 0.0 * z[0]])
    nrm2 = z[0] * z[0] + z[1] * z[1]
    if nrm2 < 1e-2:
        for k in ti.static(range(len(_EXPM1_PRIME_SERIES) - 1, -1, -1)):  # Horner
            out = _cmul(out, z) + ti.Vector([ti.static(_EXPM1_PRIME_SERIES[k]), 0.0])
    else:
        ez = kw._cexp(z)
        num = _cmul(z, ez) - ez + ti.Vector([1.0, 0.0])
        z2 = _cmul(z, z)
        out = _cmul(num, ti.Vector([z2[0], -z2[1]])) / (z2[0] * z2[0] + z2[1] * z2[1])
    return out


@ti.func
def _sim2_param_jac(p, dt, vx, vy, w, s, ctx):
    """Columns d x' / d (vx, vy, w, s) of the exact Sim(2) exponential (complex notation)."""
    z = ti.Vector([-dt * s, -dt * w])
    u = ti.Vector([-dt * vx, -dt * vy])
    E = kw._cexpm1_over_z(z)
    dF = _cmul(kw._cexp(z), kw._rel(p, ctx)) + _cmul(_cexpm1_over_z_prime(z), u)
    c_vx = -dt * E
    c_vy = -dt * ti.Vector([-E[1], E[0]])
    c_w = -dt * ti.Vector([-dF[1], dF[0]])
    c_s = -dt * dF
    return c_vx, c_vy, c_w, c_s


@ti.func
def se2_param_jac(p, dt, th, ctx):
    c_vx, c_vy, c_w, _ = _sim2_param_jac(p, dt, th[0], th[1], th[2], 0.0, ctx)
    jx = ti.Matrix([[c_vx[0], c_vy[0], c_w[0]], [c_vx[1], c_vy[1], c_w[1]]])
    zero = _zero_vec(3, dt)
    return jx, zero, zero


@ti.func
def sim2_param_jac(p, dt, th, ctx):
    c_vx, c_vy, c_w, c_s = _sim2_param_jac(p, dt, th[0], th[1], th[2], th[3], ctx)
    jx = ti.Matrix([[c_vx[0], c_vy[0], c_w[0], c_s[0]], [c_vx[1], c_vy[1], c_w[1], c_s[1]]])
    det = ti.exp(-2.0 * dt * th[3])
    zero = 0.0 * dt
    return jx, ti.Vector([zero, zero, zero, -2.0 * dt * det]), ti.Vector([zero, zero, zero, 2.0 + zero])


@ti.func
def mitrokhin4_param_jac(p, dt, th, ctx):
    T = ctx[4]
    k = th[2] * T + 1.0
    cs = ti.cos(th[3] * T)
    sn = ti.sin(th[3] * T)
    a11 = k * cs
    a21 = k * sn
    sig = dt / T
    q = kw._rel(p, ctx)
    # x' = x - dt h - sig (A - I) q with A = [[a11, -a21], [a21, a11]]
    dx_a11 = -sig * q
    dx_a21 = -sig * ti.Vector([-q[1], q[0]])
    da11 = ti.Vector([T * cs, -k * T * sn])  # d a11 / d (h_z, theta)
    da21 = ti.Vector([T * sn, k * T * cs])  # d a21 / d (h_z, theta)
    zero = 0.0 * dt
    jx = ti.Matrix(
        [
            [-dt, zero, dx_a11[0] * da11[0] + dx_a21[0] * da21[0], dx_a11[0] * da11[1] + dx_a21[0] * da21[1]],
            [zero, -dt, dx_a11[1] * da11[0] + dx_a21[1] * da21[0], dx_a11[1] * da11[1] + dx_a21[1] * da21[1]],
        ]
    )
    # det = (1 + sig - sig a11)^2 + (sig a21)^2; div = 2 (a11 - 1) / T
    g11 = -2.0 * sig * (1.0 + sig - sig * a11)
    g21 = 2.0 * sig * sig * a21
    ddet = ti.Vector([zero, zero, g11 * da11[0] + g21 * da21[0], g11 * da11[1] + g21 * da21[1]])
    ddiv = ti.Vector([zero, zero, 2.0 / T * da11[0], 2.0 / T * da11[1]])
    return jx, ddet, ddiv


#: (warp, det, div) functions of warps.py -> their parameter Jacobian. Every built-in determinant is
#: >= 0, so the deformation quantity |det| differentiates as det.
PARAM_JACOBIANS = {
    (kw.zoom1_warp, kw.zoom1_det, kw.zoom1_div): zoom1_param_jac,
    (kw.translation2_warp, kw.translation2_det, kw.translation2_div): translation2_param_jac,
    (kw.rotation3_warp, kw.rotation3_det, kw.rotation3_div): rotation3_param_jac,
    (kw.se2_warp, kw.se2_det, kw.se2_div): se2_param_jac,
    (kw.sim2_warp, kw.sim2_det, kw.sim2_div): sim2_param_jac,
    (kw.mitrokhin4_warp, kw.mitrokhin4_det, kw.mitrokhin4_div): mitrokhin4_param_jac,
}

#: per-event quantities that do not depend on the event for a built-in model: their map is the same
#: value on every pixel that received a vote, so the fused pipeline does not vote them
CONSTANT_QUANTITIES = {
    (kw.zoom1_warp, kw.zoom1_det, kw.zoom1_div): ("div",),
    (kw.translation2_warp, kw.translation2_det, kw.translation2_div): ("div", "absdet"),
    (kw.rotation3_warp, kw.rotation3_det, kw.rotation3_div): (),
    (kw.se2_warp, kw.se2_det, kw.se2_div): ("div", "absdet"),
    (kw.sim2_warp, kw.sim2_det, kw.sim2_div): ("div",),
    (kw.mitrokhin4_warp, kw.mitrokhin4_det, kw.mitrokhin4_div): ("div",),
}
