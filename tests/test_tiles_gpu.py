"""The passes over the touched segments (kernels/tiles.py) on a GPU arch in float32: sparse windows of
``test_tiles`` (a corner, the far corner with the rows' partial last segments, a band) on the fused
pipeline (atomic scatter) and the generic chain, against the float64 reference and its central
differences, and again after evaluations that touched other regions (what the passes clear).

Runs only with ``CMAX_TAICHI_ARCH`` set to a GPU arch, as ``tests/test_gpu_path.py`` (whose fixtures
start it):

    CMAX_TAICHI_ARCH=vulkan CMAX_TAICHI_PRECISION=f32 CMAX_TAICHI_REQUIRE_GPU=1 \
        python -m pytest -q -n 0 -m gpu tests/test_tiles_gpu.py
"""

from __future__ import annotations

import numpy as np
import pytest
from test_gpu_path import gpu_backend, on_gpu, pytestmark  # noqa: F401 - the GPU fixtures and marks
from test_pipeline_gradients import TOL
from test_tiles import BOTH, THETAS, _problem, _ref_kwargs, window

from cmax_taichi.testing import reference

CASES = [
    ("corner", "translation2", dict(regularizers=BOTH)),
    ("far_corner", "mitrokhin4", dict(objective="gradient_magnitude", regularizers={"deformation": 1.0})),
    ("band", "rotation3", dict(blur_sigma=2.0, polarity="split")),
]


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "chain"])
@pytest.mark.parametrize("case", range(len(CASES)), ids=[f"{k}-{w}" for k, w, _ in CASES])
def test_sparse_windows_on_the_gpu_against_reference(case, fused):
    kind, warp, options = CASES[case]
    raw = window(kind)
    prob = _problem(raw, warp, options, fused=fused)
    kwargs = _ref_kwargs(warp, options)
    tol = TOL["f32"]
    theta = np.asarray(THETAS[warp], dtype=np.float64)
    first = None
    for other in (None, theta * 2.5, theta * -1.0):
        if other is not None:  # a call over other regions first: its leftovers must be cleared
            prob.value_and_grad(other)
        value, grad = prob.value_and_grad(theta)
        if first is None:
            first = value
            ref = reference.evaluate(*raw, theta, **kwargs)
            fd = reference.central_difference_grad(*raw, theta, rel_step=1e-6, **kwargs)
            assert value == pytest.approx(ref["J"], rel=tol["value"], abs=tol["value"])
            err = np.max(np.abs(grad - fd)) / max(np.max(np.abs(fd)), 1e-12)
            assert err < tol["grad"], f"gradient {grad} vs finite differences {fd} (rel err {err:.2e})"
        else:  # atomics may add in another order on a GPU: equal to the f32 tolerance
            assert value == pytest.approx(first, rel=tol["value"], abs=tol["value"])
