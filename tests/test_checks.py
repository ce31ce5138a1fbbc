"""The library's checker (``cm.check_model``, ``cm.check_objective``, ``cm.check_regularizer``) on every
registered entry, on a model registered at run time, and on deliberately wrong declarations.

Every built-in is checked by being registered: the parametrisations below read the registries, so a new
model, objective or regularizer is held to the same checks without an edit here. The model of
``examples/user_extensions.py`` (a 6-DOF affine warp, registered at run time) goes through exactly the
checks of the built-ins (:func:`model_checks`).
"""

from __future__ import annotations

import dataclasses

import pytest
import taichi as ti
from conftest import EXAMPLES_DIR

import cmax_taichi as cm
from cmax_taichi.core.registry import load_plugin
from cmax_taichi.testing import reference
from cmax_taichi.testing.checks import CheckError

#: the registries as the suite starts (the built-ins)
BUILTIN_WARPS = cm.warp_names()
BUILTIN_OBJECTIVES = cm.objective_names()
BUILTIN_REGULARIZERS = cm.regularizer_names()


def model_checks(name: str) -> cm.CheckReport:
    """What the suite checks of every warp model, per event and in both precisions (the problem-level
    checks of every model are the combinations of test_pipeline_gradients.py and test_fused.py)."""
    return cm.check_model(name, problem=False).raise_if_failed()


@pytest.fixture(scope="module")
def user():
    """examples/user_extensions.py, imported as a plugin (registered at run time); removed afterwards."""
    module = load_plugin(str(EXAMPLES_DIR / "user_extensions.py"))
    module.register()
    yield module
    module.unregister()


@pytest.mark.parametrize("name", BUILTIN_WARPS)
def test_every_registered_warp_passes_the_checker(name):
    report = model_checks(name)
    assert "param_jac: column 0" in " ".join(report.passed) or cm.get_warp(name).param_jac is None
    assert not report.notes or cm.get_warp(name).param_jac is None or "twin" not in report.notes[0]


def test_a_model_registered_at_run_time_passes_the_same_checks(user):
    assert user.WARP in cm.warp_names() and user.WARP in reference.REFERENCE_WARPS
    report = model_checks(user.WARP)
    assert any(p.startswith("param_jac: column 5 (b_y)") for p in report.passed)
    assert "det against the float64 reference" in report.passed


@ti.func
def _wrong_det(p, dt, th, ctx):
    """The affine det without its dt^2 a12 a21 term."""
    return (1.0 - dt * th[0]) * (1.0 - dt * th[3])


def test_the_checker_names_a_wrong_param_jac_column(user):
    right = user.affine_param_jac

    @ti.func
    def wrong(p, dt, th, ctx):  # column 4 (b_x) of dx'/dtheta: -2 dt instead of -dt
        jx, ddet, ddiv = right(p, dt, th, ctx)
        jx[0, 4] = -2.0 * dt
        return jx, ddet, ddiv

    report = cm.check_model(user.affine_model("test_wrong_jac", param_jac=wrong), precisions=("f64",))
    assert not report.ok
    failed = "\n".join(report.failures)
    assert "param_jac: column 4 (b_x) of dx'/dtheta (row x')" in failed
    # only that column: the other columns, rows and closed forms hold; the gradient it feeds does not
    assert all("column 4 (b_x) of dx'/dtheta (row x')" in f or "dJ/dtheta" in f for f in report.failures)
    assert "dJ/dtheta (fused path)" in failed
    with pytest.raises(CheckError, match=r"column 4 \(b_x\)"):
        report.raise_if_failed()


def test_the_checker_names_a_wrong_det(user):
    model = user.affine_model("test_wrong_det", det=_wrong_det, param_jac=None)
    reference.register_reference_warp(user.affine_twin("test_wrong_det"))
    try:
        report = cm.check_model(model, precisions=("f64",), problem=False)
    finally:
        reference.unregister_reference_warp("test_wrong_det")
    failed = "\n".join(report.failures)
    assert "det is det dx'/dx" in failed
    assert "det against the float64 reference" in failed
    assert "x' against the float64 reference" in report.passed  # the warp itself is right


def test_the_checker_names_a_warp_terms_that_is_not_the_separate_functions(user):
    """warp_terms (what the fused kernels call instead of warp, det and param_jac) is held to them."""
    warp, det, param_jac = user.affine_warp, user.affine_det, user.affine_param_jac

    @ti.func
    def terms(p, dt, th, ctx):  # the det without its dt^2 a12 a21 term
        jx, ddet, ddiv = param_jac(p, dt, th, ctx)
        return warp(p, dt, th, ctx), det(p, dt, th, ctx) + dt * dt * th[1] * th[2], jx, ddet, ddiv

    model = dataclasses.replace(user.affine_model("test_wrong_terms"), warp_terms=terms)
    report = cm.check_model(model, precisions=("f64",))
    failed = "\n".join(report.failures)
    assert "warp_terms: its det is the model's" in failed
    assert "warp_terms: its x' is the model's" in report.passed
    assert "warp_terms: its d det/dtheta is param_jac's" in report.passed


def test_a_twin_under_another_name_is_named_in_the_note(user):
    """The twin is found by the model's name; one registered under another (a recipe's built-in name
    beside a user model) is named, so the skipped reference checks are not missed."""
    model = user.affine_model("test_misnamed_twin")
    reference.register_reference_warp(user.affine_twin("test_misnamed"))
    try:
        report = cm.check_model(model, precisions=("f64",), problem=False)
    finally:
        reference.unregister_reference_warp("test_misnamed")
    assert report.ok
    note = "\n".join(report.notes)
    assert "no float64 NumPy twin named 'test_misnamed_twin'" in note and "test_misnamed" in note
    assert not any("float64 reference" in p for p in report.passed)


@pytest.mark.parametrize("name", BUILTIN_OBJECTIVES)
def test_every_registered_objective_passes_the_checker(name):
    report = cm.check_objective(name, warps=("translation2",)).raise_if_failed()
    assert "J against the float64 reference" in report.passed


@pytest.mark.parametrize("name", BUILTIN_REGULARIZERS)
def test_every_registered_regularizer_passes_the_checker(name):
    report = cm.check_regularizer(name, warps=("zoom1",)).raise_if_failed()
    assert "penalty_grad is d penalty / d map value" in report.passed
    assert "J against the float64 reference" in report.passed


def test_a_pixel_term_objective_and_a_penalty_regularizer_registered_at_run_time(user):
    objective = cm.check_objective(
        user.OBJECTIVE, reference=user.xlogx_contrast_numpy, warps=("translation2",)
    )
    objective.raise_if_failed()
    assert any("(generic chain" in p for p in objective.passed)
    reg = cm.check_regularizer(user.REGULARIZER, reference_penalty=user.log_area_numpy, warps=("zoom1",))
    reg.raise_if_failed()
    assert "J against the float64 reference" in reg.passed


@ti.func
def _wrong_penalty_grad(avg):
    return 2.0 * ti.log(ti.max(avg, 1e-3))  # forgot the 1 / avg


def test_the_checker_names_a_wrong_penalty_grad(user):
    wrong = cm.Regularizer(
        "test_wrong_grad",
        "absdet",
        user.log_area_penalty,
        scale=lambda d, o: 1.0,
        penalty_grad=_wrong_penalty_grad,
    )
    report = cm.check_regularizer(
        wrong, reference_penalty=user.log_area_numpy, warps=("zoom1",), precisions=("f64",)
    )
    assert "test_wrong_grad" not in cm.regularizer_names()  # registered for the check only
    failed = "\n".join(report.failures)
    assert "penalty_grad is d penalty / d map value [f64]: at map value" in failed
    assert "dJ/dtheta (fused path)" in failed


def test_the_checker_refuses_bad_arguments():
    with pytest.raises(ValueError, match="precisions"):
        cm.check_model("zoom1", precisions=("f16",))
    with pytest.raises(ValueError, match="takes 1 parameter"):
        cm.check_model("zoom1", thetas=[[1.0, 2.0]])
    with pytest.raises(ValueError, match="unknown warp"):
        cm.check_model("nope")
