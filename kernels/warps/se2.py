"""``se2``: 3-DOF planar Euclidean motion (exact SE(2) exponential), theta = (v_x, v_y [px/s], w [rad/s])
(docs/FORMULAS.md).

In complex notation ``x'~ = e^z x~ + E(z) u`` with ``z = i theta``, ``theta = -dt w``, ``u = -dt (v_x + i
v_y)`` and ``E(z) = (e^z - 1) / z``. On the imaginary axis ``e^{i theta} = (1 - theta^2 s2) + i theta s1``
and ``E(i theta) = s1 + i theta s2`` with rotation3's Rodrigues coefficients ``s1 = sin(theta) /
theta``, ``s2 = (1 - cos theta) / theta^2`` at ``theta^2`` (``common.rodrigues``: truncated series exact
to the precision in use, no maths-library call per event), and
``E'(i theta) = (s2 + 2 theta^2 ds2/du) - i 2 theta ds1/du`` (``E' = -i dE/dtheta``; beyond the
series' range the equal ``(e^z - E) / z``, which does not overflow). ``sim2`` keeps the
general complex exponential of ``common.py`` (its real part ``e^{-dt s}`` is an ``exp`` per event).
"""

import taichi as ti

from .common import HALF_ANGLE_MAX, _cmul, _rel, _unit_det, _zero_div, _zero_vec, rodrigues

#: the model's declarations, read by ``cmax_taichi/models/warps.py`` (``WarpModel.from_module``)
MODEL = {
    "name": "se2",
    "params": ("v_x", "v_y", "w"),
    "units": ("px/s", "px/s", "rad/s"),
    "constant_quantities": ("div", "absdet"),  # div v = 0, det = 1 for every event
    "positive_det": True,
    "description": "3-DOF planar Euclidean motion (SE(2) exponential)",
}


@ti.func
def warp_terms(p, dt, th, ctx):
    """``(warp, det, jx, ddet, ddiv)`` of one event from one evaluation of the exponential."""
    theta = -dt * th[2]
    u = theta * theta
    s1, s2, d1, d2 = rodrigues(u, ti.Vector([theta]))
    ez = ti.Vector([1.0 - theta * (theta * s2), theta * s1])  # e^{i theta} (no theta^2: it overflows)
    E = ti.Vector([s1, theta * s2])  # (e^{i theta} - 1) / (i theta)
    Ep = ti.Vector([s2 + 2.0 * u * d2, -2.0 * theta * d1])  # E'(i theta) from the series' slopes
    if ti.abs(theta) > 2.0 * HALF_ANGLE_MAX:
        # the reduced side: E' = (e^z - E) / z (no cancellation here; u = theta^2 overflows f32 from
        # |theta| ~ 1.8e19, and u ds2/du with it)
        D = (ez - E) / theta
        Ep = ti.Vector([D[1], -D[0]])
    vel = ti.Vector([-dt * th[0], -dt * th[1]])
    rot = _cmul(ez, _rel(p, ctx))
    q = rot + _cmul(E, vel)
    # d x'~ / d z = e^z x~ + E'(z) u, and dz / dw = -i dt
    dF = rot + _cmul(Ep, vel)
    c_vx = -dt * E
    c_vy = -dt * ti.Vector([-E[1], E[0]])
    c_w = -dt * ti.Vector([-dF[1], dF[0]])
    jx = ti.Matrix([[c_vx[0], c_vy[0], c_w[0]], [c_vx[1], c_vy[1], c_w[1]]])
    zero = _zero_vec(3, dt)
    return ti.Vector([ctx[0] + q[0], ctx[1] + q[1]]), 1.0 + 0.0 * dt, jx, zero, zero


@ti.func
def warp(p, dt, th, ctx):
    terms = warp_terms(p, dt, th, ctx)
    return terms[0]


# a rigid motion preserves areas and its flow is divergence-free
det = _unit_det
div = _zero_div


@ti.func
def flow(p, th, ctx):
    q = _rel(p, ctx)
    return ti.Vector([th[0] - th[2] * q[1], th[1] + th[2] * q[0]])


@ti.func
def param_jac(p, dt, th, ctx):
    terms = warp_terms(p, dt, th, ctx)
    return terms[2], terms[3], terms[4]
