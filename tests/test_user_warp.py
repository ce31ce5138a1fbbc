"""A new warp model registered at run time through the public API (docs/RECIPE_WARP.md): the 6-DOF
affine flow of ``examples/user_extensions.py`` (a user plugin file: its Taichi functions, its
:class:`cmax_taichi.WarpModel` with capabilities, its registration and its float64 NumPy twin).

The checks are those of the built-ins (test_pipeline_gradients.py): value against the reference,
gradient against central differences of the reference, with and without both regularizers and for both
objectives; plus the fast path, the chain path of the same model without ``param_jac``, and a
determinant that changes sign. Its closed forms are held by the checker (tests/test_checks.py).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import taichi as ti
from conftest import CAMERA, EXAMPLES_DIR, SENSOR, edge_events, use_precision
from test_pipeline_gradients import OBJECTIVES, REGS, check_against_reference

import cmax_taichi as cm
from cmax_taichi.core.registry import load_plugin
from cmax_taichi.pipeline import problem as problem_module
from cmax_taichi.testing import reference

NAME = "user_affine6"  # examples/user_extensions.py's WARP
NAME_NO_JAC = "test_affine6_nojac"
THETA = np.array([4.0, -2.5, 3.0, -3.5, 30.0, -20.0])  # a few px over the 50 ms windows of conftest


@pytest.fixture(scope="module", autouse=True)
def user():
    """The plugin's entries, and the same model without param_jac with its twin; removed afterwards."""
    module = load_plugin(str(EXAMPLES_DIR / "user_extensions.py"))
    module.register()
    assert module.WARP == NAME
    cm.register_warp(module.affine_model(NAME_NO_JAC, param_jac=None))
    reference.register_reference_warp(module.affine_twin(NAME_NO_JAC))
    yield module
    module.unregister()
    cm.unregister_warp(NAME_NO_JAC)
    reference.unregister_reference_warp(NAME_NO_JAC)


def _problem(name, **options):
    x, y, t, p = edge_events(n=400, seed=0)
    return cm.ContrastMaximization(cm.Events(x, y, t, p, SENSOR), warp=name, camera=CAMERA, **options)


def test_registration_and_declarations(user):
    model = cm.get_warp(NAME)
    assert NAME in cm.warp_names() and NAME in reference.REFERENCE_WARPS
    assert model.parameter_kinds == ("rate",) * 4 + ("velocity",) * 2  # from the units
    with pytest.raises(ValueError, match="already registered"):
        cm.register_warp(user.affine_model(NAME))
    args = ("bad", user.PARAMS, user.UNITS, user.affine_warp, user.affine_flow)
    with pytest.raises(ValueError, match="constant_quantities"):
        cm.WarpModel(*args, constant_quantities=("det",))
    with pytest.raises(ValueError, match="param_jac"):
        cm.WarpModel(*args, param_jac=user.affine_param_jac)


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


@ti.func
def _nan_warp(p, dt, th, ctx):
    bad = ti.sqrt(-1.0 - 0.0 * th[0])  # NaN for every event, whatever theta
    return ti.Vector([p[0] - dt * th[0] + bad, p[1] - dt * th[1] + bad])


@ti.func
def _nan_flow(p, th, ctx):
    return ti.Vector([th[0], th[1]])


def test_a_warp_that_loses_the_events_at_the_identity_is_named():
    """A user's warp that returns NaN put every event off the image: the error named a "flat image"
    (the events'), not the warp."""
    model = cm.WarpModel("test_nan_warp", ("v_x", "v_y"), ("px/s", "px/s"), _nan_warp, _nan_flow)
    cm.register_warp(model)
    try:
        with pytest.raises(ValueError, match=r"warp 'test_nan_warp' at the identity .* puts 0 of 400 event"):
            _problem("test_nan_warp")
    finally:
        cm.unregister_warp("test_nan_warp")
