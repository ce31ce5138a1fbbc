"""The Taichi pipeline against the float64 NumPy reference: values, and gradients against central
finite differences of the reference, for every warp x objective x regularizer combination, in f64
and (looser) f32."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from conftest import CAMERA, SENSOR, THETAS, edge_events, use_precision

import cmax_taichi as cm
from cmax_taichi.pipeline.fused import FusedPipeline
from cmax_taichi.testing import reference

WARPS = list(THETAS)
OBJECTIVES = ["variance", "gradient_magnitude"]
REGS = {
    "none": {},
    "div": {"divergence": 0.7},
    "def": {"deformation": 1.3},
    "both": {"divergence": 0.7, "deformation": 1.3},
}
TOL = {"f64": dict(value=1e-10, grad=2e-6), "f32": dict(value=2e-4, grad=2e-2)}


def _events(seed=0, n=400):
    x, y, t, p = edge_events(n=n, seed=seed)
    return cm.Events(x, y, t, p, SENSOR), (x, y, t, p)


def _ref_kwargs(options):
    regs = options.get("regularizers", {})
    camera = options.get("camera")
    return dict(
        warp=options["warp"],
        sensor_size=SENSOR,
        center=None if camera is None else (camera.cx, camera.cy),
        focal=None if camera is None else (camera.fx, camera.fy),
        t_ref=options.get("t_ref", "first"),
        objective=options.get("objective", "variance"),
        normalize=options.get("normalize", True),
        blur_sigma=options.get("blur_sigma", 1.0),
        polarity=options.get("polarity", "ignore"),
        weights=options.get("weights"),
        lambda_div=regs.get("divergence", 0.0),
        lambda_def=regs.get("deformation", 0.0),
        whitening=options.get("whitening", False),
    )


def _ref_fd_grad(raw, theta, kwargs, rel_step=1e-6):
    return reference.central_difference_grad(*raw, theta, rel_step=rel_step, **kwargs)


def check_against_reference(
    precision: str, options: dict, seed: int = 0, *, fused: bool = True, n: int = 400
) -> cm.ContrastMaximization:
    """Value, gradient, penalties and G_raw of one problem against the float64 reference; ``fused=False``
    builds it on the generic kernel chain (tests/test_gpu_path.py runs both paths on a GPU)."""
    use_precision(precision)
    events, raw = _events(seed, n)
    kwargs = _ref_kwargs(options)
    saved = FusedPipeline.enabled
    FusedPipeline.enabled = fused
    try:
        prob = cm.ContrastMaximization(
            events,
            warp=options["warp"],
            objective=kwargs["objective"],
            regularizers=options.get("regularizers"),
            camera=options.get("camera"),
            t_ref=kwargs["t_ref"],
            blur_sigma=kwargs["blur_sigma"],
            polarity=kwargs["polarity"],
            weights=options.get("weights"),
            normalize=kwargs["normalize"],
            whitening=kwargs["whitening"],
        )
    finally:
        FusedPipeline.enabled = saved
    if not fused:
        assert prob._fused is None, "the generic chain was asked for but the fused pipeline was built"
    theta = np.asarray(options["theta"] if "theta" in options else THETAS[options["warp"]], dtype=np.float64)
    value, grad = prob.value_and_grad(theta)
    ref = reference.evaluate(*raw, theta, **kwargs)
    fd = _ref_fd_grad(raw, theta, kwargs)
    tol = TOL[precision]
    assert np.isfinite(value) and np.all(np.isfinite(grad))
    assert value == pytest.approx(ref["J"], rel=tol["value"], abs=tol["value"])
    scale = max(np.max(np.abs(fd)), 1e-12)
    err = np.max(np.abs(grad - fd)) / scale
    assert err < tol["grad"], f"gradient {grad} vs finite differences {fd} (rel err {err:.2e})"
    # the regularizer penalties as reported, against the reference
    ev = prob.evaluate(theta)
    assert ev.R["divergence"] == pytest.approx(ref["R_div"], rel=tol["value"] * 10, abs=1e-9)
    assert ev.R["deformation"] == pytest.approx(ref["R_def"], rel=tol["value"] * 10, abs=1e-9)
    assert ev.G_raw == pytest.approx(ref["G_raw"], rel=tol["value"] * 10)
    return prob


COMBOS = list(itertools.product(WARPS, OBJECTIVES, REGS))


@pytest.mark.parametrize("warp,objective,regs", COMBOS)
def test_value_and_gradient_f64(warp, objective, regs):
    check_against_reference(
        "f64", dict(warp=warp, objective=objective, regularizers=REGS[regs], camera=CAMERA)
    )


VARIANTS = {
    "raw_objective": dict(normalize=False),
    "no_camera_centre": dict(camera=None),
    "mean_square": dict(objective="mean_square"),
    "no_blur": dict(blur_sigma=0.0),
    "wide_blur": dict(blur_sigma=2.0),
    "signed_polarity": dict(polarity="signed"),
    "split_polarity": dict(polarity="split"),
    "t_ref_middle": dict(t_ref="middle"),
    "t_ref_last": dict(t_ref="last"),
    "t_ref_float": dict(t_ref=0.0123),
    "whitening": dict(whitening=True),
    "whitening_regs": dict(whitening=True, regularizers=REGS["both"]),
    "weights": dict(weights=np.linspace(0.2, 1.5, 400)),
}


OPTION_CASES = [(variant, warp) for variant in VARIANTS for warp in ("mitrokhin4", "rotation3")]
# the orientation of R_Div depends on t_ref: check it where the divergence is largest (zoom)
OPTION_CASES += [(variant, "zoom1") for variant in ("t_ref_middle", "t_ref_last", "whitening")]


@pytest.mark.parametrize("variant,warp", OPTION_CASES)
def test_options_f64(variant, warp):
    options = dict(warp=warp, objective="variance", regularizers=REGS["both"], camera=CAMERA)
    options.update(VARIANTS[variant])
    if options["camera"] is None and warp == "rotation3":
        pytest.skip("rotation3 needs a camera")
    check_against_reference("f64", options)


@pytest.mark.parametrize("warp,objective,regs", COMBOS)
def test_value_and_gradient_f32(warp, objective, regs):
    check_against_reference(
        "f32", dict(warp=warp, objective=objective, regularizers=REGS[regs], camera=CAMERA)
    )


# The optimized compile users get by default (the suite compiles fast, tests/conftest.py): a covering
# set on which Taichi's advanced IR optimizations must not change a value or a gradient. Every model,
# every objective with every regularizer setting, the fused kernels and the generic chain.
PAIRS = list(itertools.product(OBJECTIVES, REGS))
# derived from the registry, so that a new built-in model is in it without an edit here
FULL_COMPILE_CASES = [
    (WARPS[k % len(WARPS)], *PAIRS[k % len(PAIRS)], True) for k in range(max(len(WARPS), len(PAIRS)))
] + [(WARPS[-1], "variance", "both", False)]


@pytest.mark.full_compile
@pytest.mark.parametrize("warp,objective,regs,fused", FULL_COMPILE_CASES)
def test_value_and_gradient_optimized_compile(warp, objective, regs, fused):
    assert cm.backend_info().compile_mode == "full"
    check_against_reference(
        "f64",
        dict(warp=warp, objective=objective, regularizers=REGS[regs], camera=CAMERA),
        fused=fused,
    )


def test_full_compile_cases_cover_every_pair():
    """Every model, and every objective with every regularizer setting, is in the covering set."""
    assert {w for w, *_ in FULL_COMPILE_CASES} == set(WARPS)
    assert {(o, r) for _, o, r, _ in FULL_COMPILE_CASES} == set(itertools.product(OBJECTIVES, REGS))
    assert {f for *_, f in FULL_COMPILE_CASES} == {True, False}
