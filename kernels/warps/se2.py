"""``se2``: 3-DOF planar Euclidean motion (exact SE(2) exponential), theta = (v_x, v_y [px/s], w [rad/s])
(docs/FORMULAS.md)."""

import taichi as ti

from .common import _rel, _sim2_apply, _sim2_param_jac, _unit_det, _zero_div, _zero_vec

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
