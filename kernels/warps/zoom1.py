"""``zoom1``: 1-DOF zoom about the centre, theta = (h_z [1/s]) (docs/FORMULAS.md, "Warp models")."""

import taichi as ti

from .common import _rel

#: the model's declarations, read by ``cmax_taichi/models/warps.py`` (``WarpModel.from_module``)
MODEL = {
    "name": "zoom1",
    "params": ("h_z",),
    "units": ("1/s",),
    "constant_quantities": ("div",),  # div v = 2 h_z for every event
    "positive_det": True,  # det = (1 - dt h_z)^2
    "collapse_enabled": True,
    "description": "1-DOF zoom in/out about the centre (forward/backward camera motion)",
}


@ti.func
def warp(p, dt, th, ctx):
    q = _rel(p, ctx)
    s = 1.0 - dt * th[0]
    return ti.Vector([ctx[0] + s * q[0], ctx[1] + s * q[1]])


@ti.func
def det(p, dt, th, ctx):
    s = 1.0 - dt * th[0]
    return s * s


@ti.func
def div(p, th, ctx):
    return 2.0 * th[0]


@ti.func
def flow(p, th, ctx):
    return th[0] * _rel(p, ctx)


@ti.func
def param_jac(p, dt, th, ctx):
    s = 1.0 - dt * th[0]
    jx = ti.Matrix([[-dt * (p[0] - ctx[0])], [-dt * (p[1] - ctx[1])]])
    return jx, ti.Vector([-2.0 * dt * s]), ti.Vector([2.0 + 0.0 * dt])
