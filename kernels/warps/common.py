"""Helpers shared by the warp models of this package: constants, complex arithmetic (``se2``, ``sim2``),
the finite-difference stand-ins for user warps without closed forms, and the dense-flow kernel factory.

Signatures of a model's functions (see ``__init__.py``): ``warp(p, dt, th, ctx) -> vec2``,
``det(p, dt, th, ctx)``, ``div(p, th, ctx)``, ``flow(p, th, ctx) -> vec2``,
``param_jac(p, dt, th, ctx) -> (jx, ddet, ddiv)``.
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
def _zero_vec(n: ti.template(), like):
    return ti.Vector([0.0 * like for _ in ti.static(range(n))])


@ti.func
def _unit_det(p, dt, th, ctx):
    """``det dx'/dx = 1`` of an area-preserving warp (written through ``th`` so its type follows theta's)."""
    return 1.0 + 0.0 * th[0]


@ti.func
def _zero_div(p, th, ctx):
    """``div v = 0`` (1/s) of a divergence-free flow."""
    return 0.0 * th[0]


# --- complex arithmetic on 2-vectors (re, im) ---------------------------------------------------------
@ti.func
def _cmul(a, b):
    return ti.Vector([a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0]])


@ti.func
def _cdiv(a, b):
    """a / b for complex a, b != 0, scaled by max(|Re b|, |Im b|) so that |b|^2 neither overflows nor
    underflows (f32 overflows at |b| ~ 1.8e19, its gradient at |b| ~ 4e9)."""
    m = ti.max(ti.abs(b[0]), ti.abs(b[1]))
    bs = b / m
    return _cmul(a, ti.Vector([bs[0], -bs[1]])) / ((bs[0] * bs[0] + bs[1] * bs[1]) * m)


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
        out = _cdiv(_cexp(z) - ti.Vector([1.0, 0.0]), z)
    return out


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
        ez = _cexp(z)
        num = _cmul(z, ez) - ez + ti.Vector([1.0, 0.0])
        # num / z^2 as two scaled divisions: z^2 itself overflows f32 from |z| ~ 1.8e19 and |z^2|^2
        # from |z| ~ 4e9 (a NaN gradient of se2 / sim2 at rotation rates >= 1e15 rad/s)
        out = _cdiv(_cdiv(num, z), z)
    return out


# --- the exact Sim(2) exponential, shared by se2 (s = 0) and sim2 --------------------------------------
@ti.func
def _sim2_apply(p, dt, vx, vy, w, s, ctx):
    z = ti.Vector([-dt * s, -dt * w])
    u = ti.Vector([-dt * vx, -dt * vy])
    q = _cmul(_cexp(z), _rel(p, ctx)) + _cmul(_cexpm1_over_z(z), u)
    return ti.Vector([ctx[0] + q[0], ctx[1] + q[1]])


@ti.func
def _sim2_param_jac(p, dt, vx, vy, w, s, ctx):
    """Columns d x' / d (vx, vy, w, s) of the exact Sim(2) exponential (complex notation)."""
    z = ti.Vector([-dt * s, -dt * w])
    u = ti.Vector([-dt * vx, -dt * vy])
    E = _cexpm1_over_z(z)
    dF = _cmul(_cexp(z), _rel(p, ctx)) + _cmul(_cexpm1_over_z_prime(z), u)
    c_vx = -dt * E
    c_vy = -dt * ti.Vector([-E[1], E[0]])
    c_w = -dt * ti.Vector([-dF[1], dF[0]])
    c_s = -dt * dF
    return c_vx, c_vy, c_w, c_s


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
    """Kernel writing the flow on the pixel grid into ``out`` (shape (3, H, W)).

    ``dt == 0``: the instantaneous flow ``v(x)`` (px/s); ``dt != 0``: the displacement
    ``-(W(x, dt) - x)`` (px) of each pixel over ``dt`` seconds. ``out[2]`` is 1 where the warp sends
    the pixel nowhere (it returns ``(OUTSIDE, OUTSIDE)``: a ray rotated behind the camera), else 0.
    """

    @ti.kernel
    def dense(th: ti.template(), ctx: ti.template(), dt: float, out: ti.template()):
        for y, x in ti.ndrange(height, width):
            p = ti.Vector([ti.cast(x, float), ti.cast(y, float)])
            v = ti.Vector([0.0, 0.0])
            nowhere = 0.0
            if dt == 0.0:
                v = flow_fn(p, th[None], ctx[None])
            else:
                moved = warp_fn(p, dt, th[None], ctx[None])
                if moved[0] == OUTSIDE and moved[1] == OUTSIDE:
                    nowhere = 1.0
                v = p - moved
            out[0, y, x] = v[0]
            out[1, y, x] = v[1]
            out[2, y, x] = nowhere

    return dense
