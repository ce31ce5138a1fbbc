"""User objectives registered through the public API (docs/RECIPE_OBJECTIVE.md).

* An objective that reuses a built-in reduce (the variance's slots) with its own finalize is computed
  with its own finalize, on the generic chain: value against the float64 reference and gradient against
  central differences, on two warps.
* An objective with a full fused declaration takes the fused path, and equals the chain and the
  reference (value and gradient), on two warps.
* A fused declaration whose finalize is not the objective's is refused.
"""

import dataclasses

import numpy as np
import pytest
import taichi as ti
from cmax_taichi.kernels import blocks
from conftest import CAMERA, SENSOR, THETAS, edge_events

import cmax_taichi as cm
from cmax_taichi.pipeline.fused import FusedPipeline
from cmax_taichi.testing import reference

pytestmark = pytest.mark.usefixtures("f64")

WARPS = ["translation2", "mitrokhin4"]
REGS = {"translation2": {}, "mitrokhin4": {"deformation": 1.3}}


# --- a finalize on the variance's slots (sum I, sum I^2): mean(I^2) + mean(I)^2 ----------------------
@ti.func
def _second_moment_plus_mean_finalize(a, c: ti.template(), n_pixels):
    mean = a[2 * c] / n_pixels
    return a[2 * c + 1] / n_pixels + mean * mean


def _variance(img: np.ndarray) -> float:
    return float(np.sum(np.var(img, axis=(1, 2))))


def _second_moment_plus_mean(img: np.ndarray) -> float:
    return float(np.sum(np.mean(img**2, axis=(1, 2)) + np.mean(img, axis=(1, 2)) ** 2))


# --- a new objective with a full fused declaration: mean(I^2) - 0.5 mean(I)^2 --------------------------
@ti.func
def _half_variance_finalize(a, c: ti.template(), n_pixels):
    mean = a[2 * c] / n_pixels
    return a[2 * c + 1] / n_pixels - 0.5 * mean * mean


@ti.func
def _half_variance_adjoint(a, c: ti.template(), n_pixels):
    """dG/dI = 2 I / N - mean / N: scale 2 / N, offset -mean / N."""
    return 2.0 / n_pixels, -a[2 * c] / (n_pixels * n_pixels)


def _half_variance(img: np.ndarray) -> float:
    return float(np.sum(np.mean(img**2, axis=(1, 2)) - 0.5 * np.mean(img, axis=(1, 2)) ** 2))


def _register():
    variance = cm.OBJECTIVES.get("variance")
    reused = cm.register_objective(
        cm.Objective(
            "test_second_moment_plus_mean",
            variance.slots_per_channel,
            variance.make_reduce,  # the built-in reduce, another finalize, no fused declaration
            _second_moment_plus_mean_finalize,
            "mean(I^2) + mean(I)^2 (test)",
        ),
        replace=True,
    )
    declared = cm.register_objective(
        cm.Objective(
            "test_half_variance",
            2,
            None,  # the chain's reduce kernel is built from the declared pixel terms
            _half_variance_finalize,
            "mean(I^2) - mean(I)^2 / 2 (test)",
            fused=cm.FusedObjective(
                pixel=blocks.variance_pixel,
                finalize=_half_variance_finalize,
                adjoint=_half_variance_adjoint,
            ),
        ),
        replace=True,
    )
    return reused, declared


def _problem(warp, objective, *, chain=False):
    x, y, t, p = edge_events(n=400, seed=2)
    saved = FusedPipeline.enabled
    FusedPipeline.enabled = not chain
    try:
        prob = cm.ContrastMaximization(
            cm.Events(x, y, t, p, SENSOR),
            warp=warp,
            objective=objective,
            regularizers=REGS[warp],
            camera=CAMERA,
        )
    finally:
        FusedPipeline.enabled = saved
    return prob, (x, y, t, p)


def _reference_j(raw, warp, theta, objective_fn) -> float:
    """J = G(theta) / G(0) - lambda_def R_def with G = objective_fn of the reference's blurred IWE."""
    kwargs = dict(
        warp=warp,
        sensor_size=SENSOR,
        center=(CAMERA.cx, CAMERA.cy),
        focal=(CAMERA.fx, CAMERA.fy),
        lambda_def=REGS[warp].get("deformation", 0.0),
    )
    ref = reference.evaluate(*raw, theta, **kwargs)
    ref0 = reference.evaluate(*raw, np.zeros_like(theta), **kwargs)
    return objective_fn(ref["iwe"]) / objective_fn(ref0["iwe"]) - kwargs["lambda_def"] * ref["R_def"]


def _reference_grad(raw, warp, theta, objective_fn, rel_step=1e-6) -> np.ndarray:
    return reference.central_differences(
        lambda th: _reference_j(raw, warp, th, objective_fn), theta, rel_step=rel_step
    )


def _check_against_reference(prob, raw, warp, objective_fn):
    theta = np.asarray(THETAS[warp], dtype=np.float64)
    value, grad = prob.value_and_grad(theta)
    assert value == pytest.approx(_reference_j(raw, warp, theta, objective_fn), rel=1e-10, abs=1e-10)
    fd = _reference_grad(raw, warp, theta, objective_fn)
    err = np.max(np.abs(grad - fd)) / max(np.max(np.abs(fd)), 1e-12)
    assert err < 2e-6, f"gradient {grad} vs finite differences {fd} (rel err {err:.2e})"
    return theta, value, grad


@pytest.mark.parametrize("warp", WARPS)
def test_reused_reduce_with_own_finalize_takes_the_chain(warp):
    reused, _ = _register()
    prob, raw = _problem(warp, reused.name)
    assert prob._fused is None  # no fused declaration: never computed as the built-in variance
    theta, value, _ = _check_against_reference(prob, raw, warp, _second_moment_plus_mean)
    # its own finalize, not the variance's: the two differ by far more than the tolerance above
    variance, _ = _problem(warp, "variance")
    assert abs(variance.value(theta) - value) > 1e-5
    assert abs(_reference_j(raw, warp, theta, _variance) - value) > 1e-5


@pytest.mark.parametrize("warp", WARPS)
def test_declared_objective_takes_the_fused_path(warp):
    _, declared = _register()
    fused, raw = _problem(warp, declared.name)
    assert fused._fused is not None
    theta, value, grad = _check_against_reference(fused, raw, warp, _half_variance)
    chain, _ = _problem(warp, declared.name, chain=True)
    assert chain._fused is None
    v2, g2 = chain.value_and_grad(theta)
    assert value == pytest.approx(v2, rel=1e-11, abs=1e-12)
    np.testing.assert_allclose(grad, g2, rtol=1e-8, atol=1e-10 * max(1.0, np.max(np.abs(g2))))


def test_fused_declaration_must_use_the_objectives_finalize():
    variance = cm.OBJECTIVES.get("variance")
    with pytest.raises(ValueError, match="finalize"):
        dataclasses.replace(variance, name="test_bad", finalize=_second_moment_plus_mean_finalize)
    with pytest.raises(ValueError, match="needs a pixel term"):
        cm.Objective("test_bad", 2, None, _second_moment_plus_mean_finalize)
    with pytest.raises(ValueError, match="needs finalize"):
        cm.Objective("test_bad", 2, pixel=blocks.variance_pixel)
    with pytest.raises(ValueError, match="pixel is not the fused declaration's"):
        cm.Objective(
            "test_bad", 2, pixel=blocks.mean_square_pixel, finalize=variance.finalize, fused=variance.fused
        )
    with pytest.raises(TypeError, match="FusedObjective"):
        cm.Objective("test_bad", 2, variance.make_reduce, variance.finalize, fused="variance")
