"""A new warp model defined entirely in this file through the public API (docs/RECIPE_WARP.md).

The model is the 6-DOF affine flow ``v(x) = A q + b`` (``q = x - c``, ``A`` in 1/s, ``b`` in px/s)
with the first-order warp ``x' = x - dt (A q + b)`` (not the exact exponential ``e^{-dt A}``: the
first-order form keeps every closed form a polynomial, and it is the same model the first-order
``zoom1`` and ``translation2`` follow). Closed forms:

* ``det dx'/dx = det(I - dt A) = (1 - dt a11)(1 - dt a22) - dt^2 a12 a21`` (negative where ``dt A`` is
  large: the model declares ``positive_det=False``);
* ``div v = a11 + a22``, the same for every event: ``constant_quantities=("div",)``;
* ``d x'/d theta``, ``d det/d theta``, ``d div/d theta`` below (``param_jac``).

Its Taichi functions, its :class:`cmax_taichi.WarpModel` with capabilities, its registration and its
float64 NumPy twin in the reference all live here. The checks are those of the built-ins
(test_pipeline_gradients.py): value against the reference, gradient against central differences of the
reference, with and without both regularizers and for both objectives; plus the fast path, the chain
path of the same model without ``param_jac``, and the closed forms against autodiff.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import taichi as ti
from conftest import CAMERA, SENSOR, edge_events, use_precision
from test_pipeline_gradients import OBJECTIVES, REGS, check_against_reference

import cmax_taichi as cm
from cmax_taichi.pipeline import problem as problem_module
from cmax_taichi.testing import reference

NAME = "test_affine6"
NAME_NO_JAC = "test_affine6_nojac"
PARAMS = ("a11", "a12", "a21", "a22", "b_x", "b_y")
UNITS = ("1/s", "1/s", "1/s", "1/s", "px/s", "px/s")
THETA = np.array([4.0, -2.5, 3.0, -3.5, 30.0, -20.0])  # a few px over the 50 ms windows of conftest


# --- the Taichi functions (signatures of kernels/warps/__init__.py) ---------------------------------
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


def affine_model(name: str, with_param_jac: bool) -> cm.WarpModel:
    return cm.WarpModel(
        name,
        PARAMS,
        UNITS,
        affine_warp,
        affine_flow,
        det=affine_det,
        div=affine_div,
        param_jac=affine_param_jac if with_param_jac else None,
        constant_quantities=("div",),
        positive_det=False,
        collapse_enabled=True,
        description="6-DOF affine flow, first-order warp (test model)",
    )


# --- the float64 NumPy twin, written from the formulas of the module docstring ------------------------
def affine_reference_warp(theta, x, y, dt, *, center, focal, duration):
    a11, a12, a21, a22, bx, by = theta
    qx, qy = x - center[0], y - center[1]
    xw = x - dt * (a11 * qx + a12 * qy + bx)
    yw = y - dt * (a21 * qx + a22 * qy + by)
    jac = np.stack([[1.0 - dt * a11, -dt * a12], [-dt * a21, 1.0 - dt * a22]])  # (2, 2, N)
    det = jac[0, 0] * jac[1, 1] - jac[0, 1] * jac[1, 0]
    return xw, yw, det, np.full_like(x, a11 + a22)


def affine_reference_flow(theta, xt, yt, *, focal, duration):
    a11, a12, a21, a22, bx, by = theta
    return a11 * xt + a12 * yt + bx, a21 * xt + a22 * yt + by


@pytest.fixture(scope="module", autouse=True)
def registered():
    """Register both variants of the model and their NumPy twins; remove them afterwards."""
    for name, with_jac in ((NAME, True), (NAME_NO_JAC, False)):
        cm.register_warp(affine_model(name, with_jac))
        twin = reference.ReferenceWarp(name, len(PARAMS), affine_reference_warp, affine_reference_flow)
        reference.register_reference_warp(twin)
    yield
    for name in (NAME, NAME_NO_JAC):
        cm.unregister_warp(name)
        reference.unregister_reference_warp(name)


def _problem(name, **options):
    x, y, t, p = edge_events(n=400, seed=0)
    return cm.ContrastMaximization(cm.Events(x, y, t, p, SENSOR), warp=name, camera=CAMERA, **options)


def test_registration_and_declarations():
    model = cm.get_warp(NAME)
    assert NAME in cm.warp_names() and NAME in reference.REFERENCE_WARPS
    assert model.parameter_kinds == ("rate",) * 4 + ("velocity",) * 2  # from the units
    with pytest.raises(ValueError, match="already registered"):
        cm.register_warp(affine_model(NAME, True))
    with pytest.raises(ValueError, match="constant_quantities"):
        cm.WarpModel("bad", PARAMS, UNITS, affine_warp, affine_flow, constant_quantities=("det",))
    with pytest.raises(ValueError, match="param_jac"):
        cm.WarpModel("bad", PARAMS, UNITS, affine_warp, affine_flow, param_jac=affine_param_jac)


def test_takes_the_fused_path_without_warning():
    use_precision("f64")
    with warnings.catch_warnings():
        warnings.simplefilter("error", cm.ChainPathWarning)
        prob = _problem(NAME, regularizers=REGS["both"])
    assert prob.path == "fused" and prob.path_reason == ""
    assert prob._fused is not None


@pytest.mark.parametrize("objective", OBJECTIVES)
@pytest.mark.parametrize("regs", list(REGS))
def test_value_and_gradient_against_reference_f64(objective, regs):
    """The checks of the built-ins: J against the float64 reference (1e-10 relative), dJ/dtheta against
    its central differences, R and G_raw as reported."""
    check_against_reference(
        "f64",
        dict(warp=NAME, objective=objective, regularizers=REGS[regs], camera=CAMERA, theta=THETA),
    )


def test_closed_forms_against_autodiff():
    use_precision("f64")
    prob = _problem(NAME)
    for scale in (0.0, 1.0, 3.0):
        closed = cm.event_jacobians(prob, THETA * scale, method="closed")
        auto = cm.event_jacobians(prob, THETA * scale, method="autodiff")
        np.testing.assert_allclose(closed["det"], auto["det"], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(closed["div"], auto["div"], rtol=1e-12, atol=1e-12)


def test_without_param_jac_runs_on_the_chain_with_the_same_values(monkeypatch):
    """The same model registered without param_jac: the generic chain serves it, one ChainPathWarning
    says so (once for the reason, however many problems), and value and gradient are the same."""
    use_precision("f64")
    monkeypatch.setattr(problem_module, "_WARNED_REASONS", set())  # whatever ran before in this process
    configs = [
        dict(objective="variance", regularizers=REGS["both"]),
        dict(objective="gradient_magnitude", regularizers=REGS["def"]),
    ]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        chains = [_problem(NAME_NO_JAC, **options) for options in configs]
    chain_warnings = [w for w in caught if issubclass(w.category, cm.ChainPathWarning)]
    assert len(chain_warnings) == 1
    assert NAME_NO_JAC in str(chain_warnings[0].message) and "param_jac" in str(chain_warnings[0].message)
    for options, chain in zip(configs, chains, strict=True):
        assert chain.path == "chain" and "param_jac" in chain.path_reason
        fused = _problem(NAME, **options)
        assert fused.path == "fused"
        for scale in (0.5, 1.0, 2.0):
            v1, g1 = fused.value_and_grad(THETA * scale)
            v2, g2 = chain.value_and_grad(THETA * scale)
            assert v1 == pytest.approx(v2, rel=1e-11)
            np.testing.assert_allclose(g1, g2, rtol=1e-8, atol=1e-10 * np.max(np.abs(g2)))


def test_negative_determinant_on_both_paths():
    """Where ``det(I - dt A)`` changes sign within the window, the fused backward (which multiplies
    d det/d theta by the sign of det, the model declaring positive_det=False) equals the chain's
    autodiff of |det|, and the reference's central differences."""
    use_precision("f64")
    theta = np.array([30.0, -2.5, 3.0, -3.5, 30.0, -20.0])  # 1 - dt a11 < 0 for dt > 33 ms
    reg = {"deformation": 1.3}
    fused = _problem(NAME, regularizers=reg)
    ev = cm.event_jacobians(fused, theta)
    assert np.any(ev["det"] < 0) and np.any(ev["det"] > 0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cm.ChainPathWarning)
        chain = _problem(NAME_NO_JAC, regularizers=reg)
    v1, g1 = fused.value_and_grad(theta)
    v2, g2 = chain.value_and_grad(theta)
    assert v1 == pytest.approx(v2, rel=1e-11)
    np.testing.assert_allclose(g1, g2, rtol=1e-8, atol=1e-10 * np.max(np.abs(g2)))
    check_against_reference("f64", dict(warp=NAME, regularizers=reg, camera=CAMERA, theta=theta))
