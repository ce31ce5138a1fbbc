"""``translation2``: 2-DOF constant feature flow, theta = (v_x, v_y [px/s]) (docs/FORMULAS.md)."""

import taichi as ti

from .common import _unit_det, _zero_div, _zero_vec

#: the model's declarations, read by ``cmax_taichi/models/warps.py`` (``WarpModel.from_module``)
MODEL = {
    "name": "translation2",
    "params": ("v_x", "v_y"),
    "units": ("px/s", "px/s"),
    "constant_quantities": ("div", "absdet"),  # div v = 0, det = 1 for every event
    "positive_det": True,
    "description": "2-DOF constant feature flow",
}


@ti.func
def warp(p, dt, th, ctx):
    return ti.Vector([p[0] - dt * th[0], p[1] - dt * th[1]])


# a translation preserves areas and its flow is divergence-free
det = _unit_det
div = _zero_div


@ti.func
def flow(p, th, ctx):
    return ti.Vector([th[0], th[1]])


@ti.func
def param_jac(p, dt, th, ctx):
    jx = ti.Matrix([[-dt, 0.0 * dt], [0.0 * dt, -dt]])
    zero = _zero_vec(2, dt)
    return jx, zero, zero
