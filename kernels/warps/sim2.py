"""``sim2``: 4-DOF similarity (exact Sim(2) exponential), theta = (v_x, v_y [px/s], w [rad/s], s [1/s])
(docs/FORMULAS.md)."""

import taichi as ti

from .common import _rel, _sim2_apply, _sim2_param_jac

#: the model's declarations, read by ``cmax_taichi/models/warps.py`` (``WarpModel.from_module``)
MODEL = {
    "name": "sim2",
    "params": ("v_x", "v_y", "w", "s"),
    "units": ("px/s", "px/s", "rad/s", "1/s"),
    "constant_quantities": ("div",),  # div v = 2 s for every event
    "positive_det": True,  # det = exp(-2 dt s)
    "collapse_enabled": True,
    "description": "4-DOF similarity (Sim(2) exponential)",
}


@ti.func
def warp(p, dt, th, ctx):
    return _sim2_apply(p, dt, th[0], th[1], th[2], th[3], ctx)


@ti.func
def det(p, dt, th, ctx):
    return ti.exp(-2.0 * dt * th[3])


@ti.func
def div(p, th, ctx):
    return 2.0 * th[3]


@ti.func
def flow(p, th, ctx):
    q = _rel(p, ctx)
    return ti.Vector([th[0] + th[3] * q[0] - th[2] * q[1], th[1] + th[2] * q[0] + th[3] * q[1]])


@ti.func
def param_jac(p, dt, th, ctx):
    c_vx, c_vy, c_w, c_s = _sim2_param_jac(p, dt, th[0], th[1], th[2], th[3], ctx)
    jx = ti.Matrix([[c_vx[0], c_vy[0], c_w[0], c_s[0]], [c_vx[1], c_vy[1], c_w[1], c_s[1]]])
    det = ti.exp(-2.0 * dt * th[3])
    zero = 0.0 * dt
    return jx, ti.Vector([zero, zero, zero, -2.0 * dt * det]), ti.Vector([zero, zero, zero, 2.0 + zero])
