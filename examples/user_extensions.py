"""User extensions in one file: a 6-DOF affine warp, an objective with only a pixel term and a log-area
penalty, registered when the file is imported (docs/RECIPE_WARP.md, docs/RECIPE_OBJECTIVE.md).

From the command line (the file is imported before the registries are read)::

    cmax-taichi info --plugin examples/user_extensions.py
    cmax-taichi estimate --plugin examples/user_extensions.py --example collapse --warp user_affine6 \\
        --reg log_area=10 --out out/affine

From Python::

    import cmax_taichi as cm
    from cmax_taichi.core.registry import load_plugin

    load_plugin("examples/user_extensions.py")
    print(cm.check_model("user_affine6"))

* ``user_affine6``: the flow ``v(x) = A q + b`` (``q = x - c``; ``A`` in 1/s, ``b`` in px/s) with the
  first-order warp ``x' = x - dt (A q + b)``: ``det dx'/dx = (1 - dt a11)(1 - dt a22) - dt^2 a12 a21``
  (negative where ``dt A`` is large: ``positive_det=False``), ``div v = a11 + a22`` for every event
  (``constant_quantities=("div",)``), and the closed-form ``param_jac``: the fused path. Its float64
  NumPy twin is registered in the reference, so the checker and the simulator can use it.
* ``xlogx_contrast``: ``G = mean((1 + |I|) log(1 + |I|) - |I|)``, a contrast that grows like ``I^2 / 2``
  for small votes and like ``I log I`` for large ones (a pile of collapsed events gains less than under
  the variance); a pixel term and a finalize only: the generic chain's reduce kernel is derived from
  the pixel term, and Taichi's autodiff differentiates it (no fused declaration).
* ``log_area``: the per-pixel penalty ``P(D) = log(max(D, LOG_FLOOR))^2`` of the deformation map ``D``
  (``quantity="absdet"``), with its derivative ``penalty_grad``: it takes the fused path with any warp
  and objective that do.

No ``from __future__ import annotations`` in this file: it turns the ``ti.template()`` annotations of
the Taichi functions into strings, and Taichi then fails with "TaichiSyntaxError: Invalid type
annotation".
"""

import numpy as np
import taichi as ti

import cmax_taichi as cm
from cmax_taichi.testing import reference

WARP = "user_affine6"
OBJECTIVE = "xlogx_contrast"
REGULARIZER = "log_area"
PARAMS = ("a11", "a12", "a21", "a22", "b_x", "b_y")
UNITS = ("1/s", "1/s", "1/s", "1/s", "px/s", "px/s")
#: log_area's guard against a collapsed map (D = 0)
LOG_FLOOR = 1e-3


# --- the warp: Taichi functions with the signatures of kernels/warps/__init__.py -----------------------
@ti.func
def affine_warp(p, dt, th, ctx):
    qx = p[0] - ctx[0]
    qy = p[1] - ctx[1]
    return ti.Vector(
        [p[0] - dt * (th[0] * qx + th[1] * qy + th[4]), p[1] - dt * (th[2] * qx + th[3] * qy + th[5])]
    )


@ti.func
def affine_det(p, dt, th, ctx):
    return (1.0 - dt * th[0]) * (1.0 - dt * th[3]) - dt * dt * th[1] * th[2]


@ti.func
def affine_div(p, th, ctx):
    return th[0] + th[3]


@ti.func
def affine_flow(p, th, ctx):
    qx = p[0] - ctx[0]
    qy = p[1] - ctx[1]
    return ti.Vector([th[0] * qx + th[1] * qy + th[4], th[2] * qx + th[3] * qy + th[5]])


@ti.func
def affine_param_jac(p, dt, th, ctx):
    qx = p[0] - ctx[0]
    qy = p[1] - ctx[1]
    zero = 0.0 * dt
    jx = ti.Matrix(
        [
            [-dt * qx, -dt * qy, zero, zero, -dt, zero],
            [zero, zero, -dt * qx, -dt * qy, zero, -dt],
        ]
    )
    ddet = ti.Vector(
        [-dt * (1.0 - dt * th[3]), -dt * dt * th[2], -dt * dt * th[1], -dt * (1.0 - dt * th[0]), zero, zero]
    )
    ddiv = ti.Vector([1.0 + zero, zero, zero, 1.0 + zero, zero, zero])
    return jx, ddet, ddiv


def affine_model(name: str = WARP, *, param_jac=affine_param_jac, det=affine_det) -> cm.WarpModel:
    """The model (``param_jac=None``: the same model on the generic chain; another ``param_jac`` or
    ``det``: a deliberately wrong one, for the checker's tests)."""
    return cm.WarpModel(
        name,
        PARAMS,
        UNITS,
        affine_warp,
        affine_flow,
        det=det,
        div=affine_div,
        param_jac=param_jac,
        constant_quantities=("div",),
        positive_det=False,
        collapse_enabled=True,
        description="6-DOF affine flow, first-order warp (examples/user_extensions.py)",
    )


# --- its float64 NumPy twin, written from the formulas above ------------------------------------------
def affine_reference_warp(theta, x, y, dt, *, center, focal, duration):
    a11, a12, a21, a22, bx, by = theta
    qx, qy = x - center[0], y - center[1]
    xw = x - dt * (a11 * qx + a12 * qy + bx)
    yw = y - dt * (a21 * qx + a22 * qy + by)
    det = (1.0 - dt * a11) * (1.0 - dt * a22) - dt * dt * a12 * a21
    return xw, yw, det, np.full_like(x, a11 + a22)


def affine_reference_flow(theta, xt, yt, *, focal, duration):
    a11, a12, a21, a22, bx, by = theta
    return a11 * xt + a12 * yt + bx, a21 * xt + a22 * yt + by


def affine_twin(name: str = WARP) -> reference.ReferenceWarp:
    return reference.ReferenceWarp(name, len(PARAMS), affine_reference_warp, affine_reference_flow)


# --- the objective: a pixel term and a finalize --------------------------------------------------------
@ti.func
def xlogx_pixel(v, gx, gy):
    a = ti.abs(v)
    return ti.Vector([(1.0 + a) * ti.log(1.0 + a) - a])


@ti.func
def mean_finalize(a, c: ti.template(), n_pixels):
    return a[c] / n_pixels


def xlogx_contrast_numpy(images: np.ndarray) -> float:
    """The objective in NumPy, of the blurred IWE (C, H, W) (for the checker)."""
    a = np.abs(np.asarray(images, dtype=np.float64))
    return float(np.sum(np.mean((1.0 + a) * np.log1p(a) - a, axis=(-2, -1))))


# --- the regularizer: a per-pixel penalty of the deformation map ----------------------------------------
@ti.func
def log_area_penalty(avg):
    d = ti.log(ti.max(avg, LOG_FLOOR))
    return d * d


@ti.func
def log_area_penalty_grad(avg):
    out = 0.0 * avg
    if avg > LOG_FLOOR:
        out = 2.0 * ti.log(avg) / avg
    return out


def log_area_numpy(values: np.ndarray) -> np.ndarray:
    """The penalty in NumPy (for the checker)."""
    return np.log(np.maximum(values, LOG_FLOOR)) ** 2


def register() -> None:
    """Register the three entries and the warp's NumPy twin (again, if they were removed)."""
    cm.register_warp(affine_model(), replace=True)
    reference.register_reference_warp(affine_twin(), replace=True)
    cm.register_objective(
        cm.Objective(
            OBJECTIVE,
            1,
            pixel=xlogx_pixel,
            finalize=mean_finalize,
            description="mean((1 + |I|) log(1 + |I|) - |I|) (examples/user_extensions.py)",
        ),
        replace=True,
    )
    cm.register_regularizer(
        cm.Regularizer(
            REGULARIZER,
            "absdet",
            log_area_penalty,
            scale=lambda duration, orientation: 1.0,
            map_unit="",
            neutral=1.0,
            description="mean of log(DEF)^2 of the area deformation map (examples/user_extensions.py)",
            penalty_grad=log_area_penalty_grad,
        ),
        replace=True,
    )


def unregister() -> None:
    """Remove what :func:`register` added (those still registered)."""
    for names, remove in (
        (cm.warp_names(), cm.unregister_warp),
        (cm.objective_names(), cm.unregister_objective),
        (cm.regularizer_names(), cm.unregister_regularizer),
        (list(reference.REFERENCE_WARPS), reference.unregister_reference_warp),
    ):
        for name in (WARP, OBJECTIVE, REGULARIZER):
            if name in names:
                remove(name)


register()
