"""Warp models as Taichi functions (docs/FORMULAS.md, "Warp models").

Every model provides four ``@ti.func`` with one signature, so that kernels are generic over the model:

* ``warp(p, dt, th, ctx) -> vec2``  the event at pixel ``p`` (px) and time offset ``dt`` (s) moved to t_ref;
* ``det(p, dt, th, ctx) -> scalar`` ``det dx'/dx`` (signed) at the event;
* ``div(p, th, ctx) -> scalar``     divergence of the flow at ``p`` (1/s);
* ``flow(p, th, ctx) -> vec2``      instantaneous flow ``v(p)`` (px/s), ``v = -dW/d(dt)`` at ``dt = 0``.

``th`` is the parameter vector (physical units). ``ctx`` is the 5-vector ``(cx, cy, fx, fy, T)``: the
centre of the coordinates (principal point or image centre, px), the focal lengths (px, used by
``rotation3`` only) and the window duration ``T`` (s, used by ``mitrokhin4`` only).

The functions use no ``floor`` and no dynamic loops, so they work in reverse and forward mode autodiff.
"""

import taichi as ti

# Below these magnitudes the closed forms divide ~0 by ~0: switch to Taylor series.
SERIES_EPS = 1e-4
# A rotated ray with z below this is behind the camera: the event is sent far outside the image.
MIN_RAY_Z = 1e-6
OUTSIDE = -1.0e7


@ti.func
def _rel(p, ctx):
    return ti.Vector([p[0] - ctx[0], p[1] - ctx[1]])


@ti.func
def _cmul(a, b):
    return ti.Vector([a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0]])


@ti.func
def _cexp(z):
    r = ti.exp(z[0])
    return ti.Vector([r * ti.cos(z[1]), r * ti.sin(z[1])])


@ti.func
def _cexpm1_over_z(z):
    """(e^z - 1) / z for a complex z, with its series near 0."""
    out = ti.Vector([1.0, 0.0])
    nrm2 = z[0] * z[0] + z[1] * z[1]
    if nrm2 < SERIES_EPS * SERIES_EPS:
        z2 = _cmul(z, z)
        z3 = _cmul(z2, z)
        out = ti.Vector([1.0, 0.0]) + z / 2.0 + z2 / 6.0 + z3 / 24.0
    else:
        num = _cexp(z) - ti.Vector([1.0, 0.0])
        # num / z = num * conj(z) / |z|^2
        out = _cmul(num, ti.Vector([z[0], -z[1]])) / nrm2
    return out


# --- zoom1: theta = (h_z [1/s]) ------------------------------------------------------------------
@ti.func
def zoom1_warp(p, dt, th, ctx):
    q = _rel(p, ctx)
    s = 1.0 - dt * th[0]
    return ti.Vector([ctx[0] + s * q[0], ctx[1] + s * q[1]])


@ti.func
def zoom1_det(p, dt, th, ctx):
    s = 1.0 - dt * th[0]
    return s * s


@ti.func
def zoom1_div(p, th, ctx):
    return 2.0 * th[0]


@ti.func
def zoom1_flow(p, th, ctx):
    return th[0] * _rel(p, ctx)


# --- translation2: theta = (v_x, v_y [px/s]) ---------------------------------------------------
@ti.func
def translation2_warp(p, dt, th, ctx):
    return ti.Vector([p[0] - dt * th[0], p[1] - dt * th[1]])


@ti.func
def translation2_det(p, dt, th, ctx):
    return 1.0 + 0.0 * th[0]


@ti.func
def translation2_div(p, th, ctx):
    return 0.0 * th[0]


@ti.func
def translation2_flow(p, th, ctx):
    return ti.Vector([th[0], th[1]])


# --- rotation3: theta = (w_x, w_y, w_z [rad/s]), camera rotation ------------------------------------
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
def rotation3_warp(p, dt, th, ctx):
    Xr = _rotation(dt, th) @ _ray(p, ctx)
    out = ti.Vector([OUTSIDE, OUTSIDE])
    if Xr[2] > MIN_RAY_Z:
        out = ti.Vector([ctx[0] + ctx[2] * Xr[0] / Xr[2], ctx[1] + ctx[3] * Xr[1] / Xr[2]])
    return out


@ti.func
def rotation3_det(p, dt, th, ctx):
    R = _rotation(dt, th)
    X = _ray(p, ctx)
    z = ti.max(R[2, 0] * X[0] + R[2, 1] * X[1] + R[2, 2] * X[2], MIN_RAY_Z)
    return 1.0 / (z * z * z)


@ti.func
def rotation3_div(p, th, ctx):
    X = _ray(p, ctx)
    return -3.0 * (th[1] * X[0] - th[0] * X[1])


@ti.func
def rotation3_flow(p, th, ctx):
    X = _ray(p, ctx)
    dx = th[1] * (1.0 + X[0] * X[0]) - th[0] * X[0] * X[1] - th[2] * X[1]
    dy = -th[0] * (1.0 + X[1] * X[1]) + th[1] * X[0] * X[1] + th[2] * X[0]
    return ti.Vector([-ctx[2] * dx, -ctx[3] * dy])


# --- se2 / sim2: exact group exponential, complex notation ------------------------------------------
@ti.func
def _sim2_apply(p, dt, vx, vy, w, s, ctx):
    z = ti.Vector([-dt * s, -dt * w])
    u = ti.Vector([-dt * vx, -dt * vy])
    q = _cmul(_cexp(z), _rel(p, ctx)) + _cmul(_cexpm1_over_z(z), u)
    return ti.Vector([ctx[0] + q[0], ctx[1] + q[1]])


@ti.func
def se2_warp(p, dt, th, ctx):
    return _sim2_apply(p, dt, th[0], th[1], th[2], 0.0, ctx)


@ti.func
def se2_det(p, dt, th, ctx):
    return 1.0 + 0.0 * th[0]


@ti.func
def se2_div(p, th, ctx):
    return 0.0 * th[0]


@ti.func
def se2_flow(p, th, ctx):
    q = _rel(p, ctx)
    return ti.Vector([th[0] - th[2] * q[1], th[1] + th[2] * q[0]])


@ti.func
def sim2_warp(p, dt, th, ctx):
    return _sim2_apply(p, dt, th[0], th[1], th[2], th[3], ctx)


@ti.func
def sim2_det(p, dt, th, ctx):
    return ti.exp(-2.0 * dt * th[3])


@ti.func
def sim2_div(p, th, ctx):
    return 2.0 * th[3]


@ti.func
def sim2_flow(p, th, ctx):
    q = _rel(p, ctx)
    return ti.Vector([th[0] + th[3] * q[0] - th[2] * q[1], th[1] + th[2] * q[0] + th[3] * q[1]])


# --- mitrokhin4: theta = (h_x, h_y [px/s], h_z [1/s], theta [rad/s]), window-normalised time ---------
@ti.func
def _mitrokhin_a(th, ctx):
    T = ctx[4]
    k = th[2] * T + 1.0
    ang = th[3] * T
    return k * ti.cos(ang), k * ti.sin(ang)


@ti.func
def mitrokhin4_warp(p, dt, th, ctx):
    ac, as_ = _mitrokhin_a(th, ctx)
    sig = dt / ctx[4]
    q = _rel(p, ctx)
    # (A - I) q with A = [[ac, -as], [as, ac]]
    mx = (ac - 1.0) * q[0] - as_ * q[1]
    my = as_ * q[0] + (ac - 1.0) * q[1]
    return ti.Vector([p[0] - dt * th[0] - sig * mx, p[1] - dt * th[1] - sig * my])


@ti.func
def mitrokhin4_det(p, dt, th, ctx):
    ac, as_ = _mitrokhin_a(th, ctx)
    sig = dt / ctx[4]
    a = 1.0 + sig - sig * ac
    b = sig * as_
    return a * a + b * b


@ti.func
def mitrokhin4_div(p, th, ctx):
    ac, as_ = _mitrokhin_a(th, ctx)
    return 2.0 * (ac - 1.0) / ctx[4]


@ti.func
def mitrokhin4_flow(p, th, ctx):
    ac, as_ = _mitrokhin_a(th, ctx)
    q = _rel(p, ctx)
    T = ctx[4]
    return ti.Vector(
        [th[0] + ((ac - 1.0) * q[0] - as_ * q[1]) / T, th[1] + (as_ * q[0] + (ac - 1.0) * q[1]) / T]
    )


# --- generic fallbacks for user warps without closed forms ---------------------------------------
FD_STEP = 1e-2  # px; central differences of smooth warps are exact to O(step^2)


def make_fd_det(warp_fn):
    """``det dx'/dx`` by central differences of ``warp_fn`` (reverse-mode differentiable in theta)."""

    @ti.func
    def det(p, dt, th, ctx):
        ex = ti.Vector([FD_STEP, 0.0])
        ey = ti.Vector([0.0, FD_STEP])
        jx = (warp_fn(p + ex, dt, th, ctx) - warp_fn(p - ex, dt, th, ctx)) / (2.0 * FD_STEP)
        jy = (warp_fn(p + ey, dt, th, ctx) - warp_fn(p - ey, dt, th, ctx)) / (2.0 * FD_STEP)
        return jx[0] * jy[1] - jx[1] * jy[0]

    return det


def make_fd_div(flow_fn):
    """``div v`` by central differences of ``flow_fn``."""

    @ti.func
    def div(p, th, ctx):
        ex = ti.Vector([FD_STEP, 0.0])
        ey = ti.Vector([0.0, FD_STEP])
        dvx = (flow_fn(p + ex, th, ctx)[0] - flow_fn(p - ex, th, ctx)[0]) / (2.0 * FD_STEP)
        dvy = (flow_fn(p + ey, th, ctx)[1] - flow_fn(p - ey, th, ctx)[1]) / (2.0 * FD_STEP)
        return dvx + dvy

    return div


def make_dense_flow_kernel(flow_fn, warp_fn, width: int, height: int):
    """Kernel writing the flow on the pixel grid into ``out`` (shape (2, H, W)).

    ``dt == 0``: the instantaneous flow ``v(x)`` (px/s); ``dt != 0``: the displacement
    ``-(W(x, dt) - x)`` (px) of each pixel over ``dt`` seconds.
    """

    @ti.kernel
    def dense(th: ti.template(), ctx: ti.template(), dt: float, out: ti.template()):
        for y, x in ti.ndrange(height, width):
            p = ti.Vector([ti.cast(x, float), ti.cast(y, float)])
            v = ti.Vector([0.0, 0.0])
            if dt == 0.0:
                v = flow_fn(p, th[None], ctx[None])
            else:
                v = p - warp_fn(p, dt, th[None], ctx[None])
            out[0, y, x] = v[0]
            out[1, y, x] = v[1]

    return dense
