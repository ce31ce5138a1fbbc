"""``mitrokhin4``: 4-DOF in-plane camera motion of Mitrokhin et al. (IROS 2018) with window-normalised
time, theta = (h_x, h_y [px/s], h_z [1/s], theta [rad/s]) (docs/FORMULAS.md).

Uses the window duration ``T = ctx[4]`` (s).
"""

import taichi as ti

from .common import _rel

#: the model's declarations, read by ``cmax_taichi/models/warps.py`` (``WarpModel.from_module``)
MODEL = {
    "name": "mitrokhin4",
    "params": ("h_x", "h_y", "h_z", "theta"),
    "units": ("px/s", "px/s", "1/s", "rad/s"),
    "constant_quantities": ("div",),  # div v = 2 (a11 - 1) / T for every event
    "positive_det": True,  # det = a^2 + b^2
    "collapse_enabled": True,
    "description": "4-DOF in-plane camera motion of Mitrokhin et al. (IROS 2018)",
}


@ti.func
def _mitrokhin_a(th, ctx):
    T = ctx[4]
    k = th[2] * T + 1.0
    ang = th[3] * T
    return k * ti.cos(ang), k * ti.sin(ang)


@ti.func
def warp(p, dt, th, ctx):
    ac, as_ = _mitrokhin_a(th, ctx)
    sig = dt / ctx[4]
    q = _rel(p, ctx)
    # (A - I) q with A = [[ac, -as], [as, ac]]
    mx = (ac - 1.0) * q[0] - as_ * q[1]
    my = as_ * q[0] + (ac - 1.0) * q[1]
    return ti.Vector([p[0] - dt * th[0] - sig * mx, p[1] - dt * th[1] - sig * my])


@ti.func
def det(p, dt, th, ctx):
    ac, as_ = _mitrokhin_a(th, ctx)
    sig = dt / ctx[4]
    a = 1.0 + sig - sig * ac
    b = sig * as_
    return a * a + b * b


@ti.func
def div(p, th, ctx):
    ac, as_ = _mitrokhin_a(th, ctx)
    return 2.0 * (ac - 1.0) / ctx[4]


@ti.func
def flow(p, th, ctx):
    ac, as_ = _mitrokhin_a(th, ctx)
    q = _rel(p, ctx)
    T = ctx[4]
    return ti.Vector(
        [th[0] + ((ac - 1.0) * q[0] - as_ * q[1]) / T, th[1] + (as_ * q[0] + (ac - 1.0) * q[1]) / T]
    )


@ti.func
def param_jac(p, dt, th, ctx):
    T = ctx[4]
    k = th[2] * T + 1.0
    cs = ti.cos(th[3] * T)
    sn = ti.sin(th[3] * T)
    a11 = k * cs
    a21 = k * sn
    sig = dt / T
    q = _rel(p, ctx)
    # x' = x - dt h - sig (A - I) q with A = [[a11, -a21], [a21, a11]]
    dx_a11 = -sig * q
    dx_a21 = -sig * ti.Vector([-q[1], q[0]])
    da11 = ti.Vector([T * cs, -k * T * sn])  # d a11 / d (h_z, theta)
    da21 = ti.Vector([T * sn, k * T * cs])  # d a21 / d (h_z, theta)
    zero = 0.0 * dt
    jx = ti.Matrix(
        [
            [-dt, zero, dx_a11[0] * da11[0] + dx_a21[0] * da21[0], dx_a11[0] * da11[1] + dx_a21[0] * da21[1]],
            [zero, -dt, dx_a11[1] * da11[0] + dx_a21[1] * da21[0], dx_a11[1] * da11[1] + dx_a21[1] * da21[1]],
        ]
    )
    # det = (1 + sig - sig a11)^2 + (sig a21)^2; div = 2 (a11 - 1) / T
    g11 = -2.0 * sig * (1.0 + sig - sig * a11)
    g21 = 2.0 * sig * sig * a21
    ddet = ti.Vector([zero, zero, g11 * da11[0] + g21 * da21[0], g11 * da11[1] + g21 * da21[1]])
    ddiv = ti.Vector([zero, zero, 2.0 / T * da11[0], 2.0 / T * da11[1]])
    return jx, ddet, ddiv
