"""``translation2``: 2-DOF constant feature flow, theta = (v_x, v_y [px/s]) (docs/FORMULAS.md)."""

import taichi as ti

from .common import _zero_vec

#: per-event quantities that do not depend on the event (see ``__init__.py``)
CONSTANT_QUANTITIES = ("div", "absdet")


@ti.func
def warp(p, dt, th, ctx):
    return ti.Vector([p[0] - dt * th[0], p[1] - dt * th[1]])


@ti.func
def det(p, dt, th, ctx):
    return 1.0 + 0.0 * th[0]


@ti.func
def div(p, th, ctx):
    return 0.0 * th[0]


@ti.func
def flow(p, th, ctx):
    return ti.Vector([th[0], th[1]])


@ti.func
def param_jac(p, dt, th, ctx):
    jx = ti.Matrix([[-dt, 0.0 * dt], [0.0 * dt, -dt]])
    zero = _zero_vec(2, dt)
    return jx, zero, zero
