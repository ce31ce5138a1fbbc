"""``se2``: 3-DOF planar Euclidean motion (exact SE(2) exponential), theta = (v_x, v_y [px/s], w [rad/s])
(docs/FORMULAS.md)."""

import taichi as ti

from .common import _rel, _sim2_apply, _sim2_param_jac, _unit_det, _zero_div, _zero_vec

#: per-event quantities that do not depend on the event (see ``__init__.py``)
CONSTANT_QUANTITIES = ("div", "absdet")


@ti.func
def warp(p, dt, th, ctx):
    return _sim2_apply(p, dt, th[0], th[1], th[2], 0.0, ctx)


# a rigid motion preserves areas and its flow is divergence-free
det = _unit_det
div = _zero_div


@ti.func
def flow(p, th, ctx):
    q = _rel(p, ctx)
    return ti.Vector([th[0] - th[2] * q[1], th[1] + th[2] * q[0]])


@ti.func
def param_jac(p, dt, th, ctx):
    c_vx, c_vy, c_w, _ = _sim2_param_jac(p, dt, th[0], th[1], th[2], 0.0, ctx)
    jx = ti.Matrix([[c_vx[0], c_vy[0], c_w[0]], [c_vx[1], c_vy[1], c_w[1]]])
    zero = _zero_vec(3, dt)
    return jx, zero, zero
