"""The GPU code path (atomic scatter in the fused pipeline, the generic kernel chain, segmentation, a
short solve) in float32 on a GPU arch, against the float64 NumPy reference.

Runs only when ``CMAX_TAICHI_ARCH`` names a GPU arch (vulkan, cuda, metal or gpu); on the ordinary CPU
run every test here skips. CI runs it on Mesa's software Vulkan driver (lavapipe):

    CMAX_TAICHI_ARCH=vulkan python -m pytest -q -m gpu tests/test_gpu_path.py

A GPU arch that Taichi cannot start falls back to the CPU (cmax_taichi.core.backend); these tests then
skip saying so, or fail when ``CMAX_TAICHI_REQUIRE_GPU=1`` (benchmarks/gpu_check.sh sets it). Vulkan and
Metal have no float64, so everything runs in float32 with the f32 tolerances of
test_pipeline_gradients.py. See docs/GPU.md.
"""

from __future__ import annotations

import itertools
import os
import warnings

import numpy as np
import pytest
from conftest import CAMERA, THETAS
from test_optimize import V_TRUE, moving_edges
from test_pipeline_gradients import FULL_COMPILE_CASES, OBJECTIVES, REGS, check_against_reference

import cmax_taichi as cm
from cmax_taichi.core import backend
from cmax_taichi.lab import segment_eval as se

#: the archs that select this module (``gpu`` lets Taichi pick CUDA, Vulkan or Metal)
GPU_ARCHS = ("vulkan", "cuda", "metal", "gpu")
#: set to 1 to fail (instead of skip) when the requested GPU arch is not available
REQUIRE_ENV = "CMAX_TAICHI_REQUIRE_GPU"

REQUESTED = os.environ.get(backend.ARCH_ENV, "").strip().lower()

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(
        REQUESTED not in GPU_ARCHS,
        reason=f"GPU-path tests run only with {backend.ARCH_ENV} set to one of {', '.join(GPU_ARCHS)} "
        f"(it is {REQUESTED or 'unset'}); see docs/GPU.md",
    ),
]


def _start_gpu() -> backend.BackendInfo:
    """Initialise the requested GPU arch in f32; skip (or fail under REQUIRE_ENV) on a CPU fallback."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        info = cm.init(arch=REQUESTED, precision="f32")
    if info.arch == "cpu":
        said = "; ".join(str(w.message) for w in caught if issubclass(w.category, RuntimeWarning))
        message = (
            f"{backend.ARCH_ENV}={REQUESTED} was requested but Taichi fell back to the CPU "
            f"({said or 'no warning'}); the GPU path was NOT tested"
        )
        if os.environ.get(REQUIRE_ENV, "") not in ("", "0"):
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    return info


@pytest.fixture(scope="module")
def gpu_backend() -> backend.BackendInfo:
    return _start_gpu()


@pytest.fixture(autouse=True)
def on_gpu(gpu_backend) -> backend.BackendInfo:
    """Every test runs on the GPU arch in f32 (re-initialised if anything switched it)."""
    info = cm.backend_info()
    if info.arch != gpu_backend.arch or info.precision != "f32":
        info = _start_gpu()
    return info


def test_backend_is_the_requested_gpu(on_gpu):
    assert on_gpu.arch != "cpu" and on_gpu.precision == "f32"
    if REQUESTED != "gpu":
        assert on_gpu.arch == REQUESTED


# every warp x objective x regularizer set, on the fused pipeline (atomic scatter on a GPU) and on the
# generic kernel chain; 400 events on 64 x 48 pixels (compiling dominates: each case is its own kernel)
# This module found the f64 alignment bug of Taichi's SPIR-V field layout (docs/GPU.md); the fused kernels
# now read no field (their f64 sums and f32 images are arrays of their own, or kernel-level values).
COMBOS = list(itertools.product(("fused", "chain"), THETAS, OBJECTIVES, REGS))


@pytest.mark.parametrize("path,warp,objective,regs", COMBOS)
def test_value_and_gradient_against_f64_reference(path, warp, objective, regs):
    prob = check_against_reference(
        "f32",
        dict(warp=warp, objective=objective, regularizers=REGS[regs], camera=CAMERA),
        fused=path == "fused",
    )
    assert (prob._fused is not None) == (path == "fused")


# The suite compiles the fused kernels fast (tests/conftest.py); the optimized SPIR-V that users get by
# default, on the covering set of tests/test_pipeline_gradients.py (the chain's autodiff kernels are
# optimized in both modes, so its cases above already run optimized code)
@pytest.mark.full_compile
@pytest.mark.parametrize("warp,objective,regs", [(w, o, r) for w, o, r, fused in FULL_COMPILE_CASES if fused])
def test_fused_value_and_gradient_optimized_compile(warp, objective, regs):
    assert cm.backend_info().compile_mode == "full" and cm.backend_info().arch != "cpu"
    prob = check_against_reference(
        "f32", dict(warp=warp, objective=objective, regularizers=REGS[regs], camera=CAMERA)
    )
    assert prob._fused is not None


@pytest.mark.parametrize("warp", list(THETAS))
def test_every_registered_warp_passes_the_checker_on_the_gpu(warp):
    """The closed forms of every registered model, compiled for the GPU, in f32 (cm.check_model)."""
    report = cm.check_model(warp, problem=False)
    assert cm.backend_info().arch != "cpu" and cm.backend_info().precision == "f32"
    report.raise_if_failed()


@pytest.mark.parametrize("path", ["fused", "chain"])
def test_crowded_window_against_f64_reference(path):
    """20,000 events on 64 x 48 pixels: many atomic adds into every pixel, in float32."""
    check_against_reference(
        "f32",
        dict(warp="mitrokhin4", objective="variance", regularizers=REGS["both"], camera=CAMERA),
        seed=3,
        fused=path == "fused",
        n=20_000,
    )


@pytest.mark.parametrize("name", ["pitch", "oblique"])
def test_whitening_with_events_behind_the_camera_against_f64_reference(name):
    """rotation3 rays rotated behind the camera stay out of the whitening moments on the GPU too."""
    from test_whitening_collapse import BEHIND

    options = dict(warp="rotation3", regularizers=REGS["both"], camera=CAMERA, whitening=True)
    check_against_reference("f32", {**options, "theta": BEHIND[name]}, fused=False)


def test_fused_and_chain_agree_along_a_path():
    """The two GPU code paths give the same J and gradient at several parameter vectors (f32)."""
    from cmax_taichi.pipeline.fused import FusedPipeline

    events = moving_edges(n=3000, seed=4)
    options = dict(warp="sim2", regularizers=REGS["both"], camera=CAMERA)
    fused = cm.ContrastMaximization(events, **options)
    FusedPipeline.enabled = False
    try:
        chain = cm.ContrastMaximization(events, **options)
    finally:
        FusedPipeline.enabled = True
    assert fused._fused is not None and chain._fused is None
    for scale in (0.0, 0.5, 1.0, 2.0):
        theta = np.asarray(THETAS["sim2"]) * scale
        v1, g1 = fused.value_and_grad(theta)
        v2, g2 = chain.value_and_grad(theta)
        assert v1 == pytest.approx(v2, rel=2e-4, abs=1e-5)
        np.testing.assert_allclose(g1, g2, rtol=0, atol=1e-2 * max(1e-6, np.max(np.abs(g2))))


def test_maximize_recovers_translation():
    prob = cm.ContrastMaximization(moving_edges(), warp="translation2", regularizers=REGS["both"])
    res = cm.maximize(prob, method="adam")
    assert np.all(np.isfinite(res.theta))
    assert np.all(np.abs(res.theta - V_TRUE) < 0.05 * np.linalg.norm(V_TRUE)), res
    assert res.value > prob.value([0.0, 0.0]) and res.value >= res.value_init


def test_segment_two_objects():
    scene = se.synthetic_scene(2, 8000, sensor_size=(120, 90), duration=0.04, speed=(150.0, 300.0), seed=0)
    res = cm.segment(scene.events, 2, warp="mitrokhin4", regularizers={"divergence": 1.0, "deformation": 1.0})
    n = len(scene.events)
    assert res.labels.shape == (n,) and res.probabilities.shape == (n, 2)
    np.testing.assert_allclose(res.probabilities.sum(axis=1), 1.0, atol=1e-5)
    assert not res.empty.any()
    assert se.label_accuracy(res.labels, scene.labels, 2) > 0.9
    errors = se.motion_errors(res, scene)
    assert max(errors) < 1.5, errors  # px at the reference time
