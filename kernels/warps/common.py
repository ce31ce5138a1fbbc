"""Helpers shared by the warp models of this package: constants, complex arithmetic (``se2``, ``sim2``),
the finite-difference stand-ins for user warps without closed forms, and the dense-flow kernel factory.

Signatures of a model's functions (see ``__init__.py``): ``warp(p, dt, th, ctx) -> vec2``,
``det(p, dt, th, ctx)``, ``div(p, th, ctx)``, ``flow(p, th, ctx) -> vec2``,
``param_jac(p, dt, th, ctx) -> (jx, ddet, ddiv)``.
"""

import math

import taichi as ti

# Below these magnitudes the closed forms divide ~0 by ~0: switch to Taylor series.
SERIES_EPS = 1e-4
# A rotated ray with z below this is behind the camera: the event is sent far outside the image.
MIN_RAY_Z = 1e-6
OUTSIDE = -1.0e7


# --- truncated Taylor series in place of per-event trigonometry ------------------------------------
def float_epsilon() -> float:
    """Machine epsilon of the float type the kernels compile with now (Taichi's ``default_fp``: f32 or
    f64); read inside ``ti.static`` when a kernel compiles, so one source serves both precisions."""
    return 2.0**-52 if ti.lang.impl.current_cfg().default_fp == ti.f64 else 2.0**-23


def taylor_terms(coefficient, u_max: float, floor: float) -> tuple[float, ...]:
    """The coefficients ``c_0 .. c_{K-1}`` of an alternating series ``sum_k c_k u^k`` (``coefficient(k)``
    gives ``c_k``, with ``|c_k| u^k`` decreasing for ``0 <= u <= u_max``), truncated at the smallest ``K``
    whose first omitted term ``|c_K| u_max^K`` is at most ``float_epsilon() / 8`` times ``floor`` (a lower
    bound of the series' value on ``[0, u_max]``): the truncation error of an alternating series is at
    most its first omitted term, so the polynomial is exact to an eighth of the precision in use."""
    tol = float_epsilon() / 8.0 * floor
    k = 1
    while abs(coefficient(k)) * u_max**k > tol:
        k += 1
    return tuple(float(coefficient(j)) for j in range(k))


def taylor_error(coefficient, n_terms: int, u_max: float) -> float:
    """The bound ``|c_K| u_max^K`` on the truncation error of ``n_terms`` terms (see :func:`taylor_terms`)."""
    return abs(coefficient(n_terms)) * u_max**n_terms


@ti.func
def _pair(c: ti.template(), m: ti.template(), v):
    return ti.static(c[2 * m]) + ti.static(c[2 * m + 1]) * v


@ti.func
def polynomial(coefficients: ti.template(), v):
    """``sum_k c_k v^k`` for a tuple of at least two Python floats (unrolled): Horner's rule in ``v^2``
    over the pairs ``c_2m + c_2m+1 v``, which halves the chain of dependent multiply-adds (the event
    loops that call it are bound by that latency, not by the arithmetic)."""
    c = ti.static(coefficients)
    n_pairs = ti.static(len(c) // 2)
    v2 = v * v
    out = _pair(c, n_pairs - 1, v)
    if ti.static(len(c) % 2 == 1):
        out = out + v2 * ti.static(c[len(c) - 1])
    for m in ti.static(range(n_pairs - 2, -1, -1)):
        out = _pair(c, m, v) + v2 * out
    return out


def _factorial_series(offset: int):
    """``c_k = (-1)^k / (2k + offset)!``: ``offset = 2`` gives ``(1 - cos(r)) / r^2``, ``offset = 3``
    ``(r - sin(r)) / r^3`` as series in ``v = r^2``."""
    return lambda k: (-1.0) ** k / math.factorial(2 * k + offset)


ONE_MINUS_COS_OVER_R2 = _factorial_series(2)
SIN_TAIL_OVER_R3 = _factorial_series(3)

#: the half angle ``h = phi / 2`` enters the series up to ``HALF_ANGLE_MAX`` (``phi <= pi / 2``); beyond
#: it is reduced modulo ``pi / 2`` into ``[-pi/4, pi/4]``
HALF_ANGLE_MAX = math.pi / 4
#: lower bounds of ``(1 - cos r) / r^2`` and ``(r - sin r) / r^3`` on ``|r| <= pi / 4`` (both decrease
#: in ``|r|``): the truncation error of their series is bounded relative to them
_VERSINE_FLOOR = (1.0 - math.cos(HALF_ANGLE_MAX)) / HALF_ANGLE_MAX**2
_TAIL_FLOOR = (HALF_ANGLE_MAX - math.sin(HALF_ANGLE_MAX)) / HALF_ANGLE_MAX**3


#: the short tier: half angles up to ``SHORT_HALF_ANGLE`` (``phi <= 0.09`` rad, 5.2 degrees: every event
#: of a window of a few ms at a hand-held camera's rates, and of the benchmark's 50 ms rotation3 window)
#: take polynomials truncated for that range, half as long in f64 (4 and 4 terms instead of 8 and 8);
#: the same ``eps / 8`` truncation rule, so both tiers are exact to the rounding of the precision in use
SHORT_HALF_ANGLE = 0.045


def versine_terms(half_angle_max: float = HALF_ANGLE_MAX) -> tuple[float, ...]:
    """Taylor coefficients (in ``v = r^2``) of ``(1 - cos r) / r^2`` for the precision in use, on
    ``|r| <= half_angle_max`` (at most :data:`HALF_ANGLE_MAX`)."""
    return taylor_terms(ONE_MINUS_COS_OVER_R2, half_angle_max**2, _VERSINE_FLOOR)


def tail_terms(half_angle_max: float = HALF_ANGLE_MAX) -> tuple[float, ...]:
    """Taylor coefficients (in ``v = r^2``) of ``(r - sin r) / r^3`` for the precision in use, on
    ``|r| <= half_angle_max`` (at most :data:`HALF_ANGLE_MAX`)."""
    return taylor_terms(SIN_TAIL_OVER_R3, half_angle_max**2, _TAIL_FLOOR)


@ti.func
def _norm(vec):
    """``|vec|`` scaled by its largest component, so that the squares neither overflow nor underflow
    (``vec != 0``)."""
    m = ti.abs(vec[0])
    for i in ti.static(range(1, vec.n)):
        m = ti.max(m, ti.abs(vec[i]))
    scaled = vec / m
    return m * ti.sqrt(scaled.dot(scaled))


@ti.func
def rodrigues(u, rot):
    """``(s1, s2, ds1/du, ds2/du)`` with ``s1 = sin(phi) / phi``, ``s2 = (1 - cos(phi)) / phi^2`` at
    ``u = phi^2 = |rot|^2`` (``rot``: the rotation vector, ``dt w``; ``u`` computed by the caller as a
    smooth function of theta, since reverse mode differentiates it), from the half angle ``h = phi / 2``.

    ``h <= pi / 4``: two Taylor polynomials in ``v = h^2 = u / 4``, ``T`` of ``(h - sin h) / h^3`` and
    ``C`` of ``(1 - cos h) / h^2`` (no square root, no division; for ``h <= SHORT_HALF_ANGLE`` shorter
    ones, truncated for that range by the same rule), give ``S = sin(h) / h = 1 - v T`` and
    ``cos(h) = 1 - v C``; then ``s1 = S cos(h)``, ``s2 = S^2 / 2``, and the slopes in closed form from
    the same two polynomials, ``ds1/du = (s3 - s2) / 2`` with ``s3 = (phi - sin phi) / phi^3 = (T + S C)
    / 4`` and ``ds2/du = S (cos h - S) / (8 h^2) = S (T - C) / 8`` (no difference of nearly equal
    terms: both are about -1/6 and -1/24 at 0). Beyond (a branch: a square root, a ``floor``, a
    division): ``h = k pi / 2 + r`` with ``|r| <= pi / 4``, ``sin(r) = r S(r^2)``, ``cos(r) = 1 - r^2
    C(r^2)``, ``sin(h) cos(h) = (-1)^k sin(r) cos(r)``, ``sin(h)^2 = sin(r)^2`` (k even) or
    ``cos(r)^2`` (k odd); there ``s3 = (1 - s1) / u`` (``u >= (pi / 2)^2``: no cancellation). The
    branch takes ``h`` as the scaled norm of ``rot`` (``u`` overflows f32 from ``phi ~ 1.8e19``) and
    clamps ``r`` into ``[-pi/4, pi/4]`` (beyond ``phi ~ 1e7`` in f32, ``1e15`` in f64, the rounding of
    ``phi`` exceeds pi and the reduction keeps no digit: the values stay finite, as bounded as sin and
    cos). Two polynomials rather than one per coefficient and slope (four): the event loops that call
    this are bound by its arithmetic. No call into the maths library (an opaque call per event), so
    that LLVM can if-convert the branch and vectorize where it can. Shared by ``rotation3`` (the
    rotation of a ray by ``phi = |w| dt``) and ``se2`` (the planar rotation ``e^{i theta}`` and
    ``(e^{i theta} - 1) / (i theta)`` of its exponential).
    """
    v = 0.25 * u
    big = v > HALF_ANGLE_MAX * HALF_ANGLE_MAX
    r = 0.0 * u
    k = 0.0 * u
    ih = 0.0 * u
    T = 0.0 * u
    C = 0.0 * u
    if v <= SHORT_HALF_ANGLE * SHORT_HALF_ANGLE:
        # the short tier (a branch that flips at most twice per time-sorted window: dt grows away from
        # t_ref); the polynomials are the arithmetic that bounds rotation3's event loops
        T = polynomial(ti.static(tail_terms(SHORT_HALF_ANGLE)), v)
        C = polynomial(ti.static(versine_terms(SHORT_HALF_ANGLE)), v)
    else:
        if big:
            h = 0.5 * _norm(rot)
            k = ti.floor(h * (2.0 / math.pi) + 0.5)
            r = ti.min(ti.max(h - k * (0.5 * math.pi), -HALF_ANGLE_MAX), HALF_ANGLE_MAX)
            ih = 1.0 / h
            v = r * r
        T = polynomial(ti.static(tail_terms()), v)
        C = polynomial(ti.static(versine_terms()), v)
    S = 1.0 - v * T  # sin(r) / r
    cr = 1.0 - v * C  # cos(r)
    s1 = S * cr
    s2 = 0.5 * S * S
    d1 = 0.125 * (T + S * C) - 0.5 * s2
    d2 = 0.125 * S * (T - C)
    if big:
        # a = +-sin(h) / h and b = +-cos(h) (one sign)
        sr = r * S
        odd = k - 2.0 * ti.floor(0.5 * k) > 0.5  # sin(h) = +-cos(r), cos(h) = -+sin(r)
        a = ti.select(odd, cr, sr) * ih
        b = ti.select(odd, -sr, cr)
        ih2 = ih * ih
        s1 = a * b
        s2 = 0.5 * a * a
        d1 = 0.5 * ((1.0 - s1) * (0.25 * ih2) - s2)
        d2 = 0.125 * a * (b - a) * ih2
    return s1, s2, d1, d2


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


def make_dense_flow_kernel(flow_fn, warp_fn, width: int, height: int, n_params: int):
    """Kernel ``dense(params, out)`` writing the flow on the pixel grid into ``out``, an array of shape
    ``(3, H, W)``, from ``params = (theta_0 .. theta_{P-1}, c_x, c_y, f_x, f_y, T, dt)``.

    ``dt == 0``: the instantaneous flow ``v(x)`` (px/s); ``dt != 0``: the displacement
    ``-(W(x, dt) - x)`` (px) of each pixel over ``dt`` seconds. ``out[2]`` is 1 where the warp sends
    the pixel nowhere (it returns ``(OUTSIDE, OUTSIDE)``: a ray rotated behind the camera), else 0.
    Both are external arrays (NumPy on the host): no field, so the first call in a process does not
    build a new field tree and its accessors (0.3-0.7 s of a one-window command's figure).
    """
    P = int(n_params)

    @ti.kernel
    def dense(params: ti.types.ndarray(ndim=1), out: ti.types.ndarray(ndim=3)):
        for y, x in ti.ndrange(height, width):
            th = ti.Vector([params[j] for j in ti.static(range(P))])
            ctx = ti.Vector([params[P + j] for j in ti.static(range(5))])
            dt = params[P + 5]
            p = ti.Vector([ti.cast(x, float), ti.cast(y, float)])
            v = ti.Vector([0.0, 0.0])
            nowhere = 0.0
            if dt == 0.0:
                v = flow_fn(p, th, ctx)
            else:
                moved = warp_fn(p, dt, th, ctx)
                if moved[0] == OUTSIDE and moved[1] == OUTSIDE:
                    nowhere = 1.0
                v = p - moved
            out[0, y, x] = v[0]
            out[1, y, x] = v[1]
            out[2, y, x] = nowhere

    return dense
