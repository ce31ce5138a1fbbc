"""The dense flow kernels on a GPU arch (atomic splat and node scatter) in float32, against the float64
NumPy reference; and a short coarse-to-fine solve.

Runs only when ``CMAX_TAICHI_ARCH`` names a GPU arch (see tests/test_gpu_path.py, whose start-up and skip
rules it shares); CI runs it on Mesa's software Vulkan driver (lavapipe):

    CMAX_TAICHI_ARCH=vulkan CMAX_TAICHI_PRECISION=f32 python -m pytest -q -m gpu tests/test_dense_flow_gpu.py
"""

from __future__ import annotations

import numpy as np
import pytest
from test_dense_flow import CASES, check_dense_against_reference
from test_gpu_path import gpu_backend, on_gpu, pytestmark  # noqa: F401 - GPU fixtures, marks

from cmax_taichi.flow import DenseFlowEstimator, FlowGrid


@pytest.mark.parametrize("case", list(CASES))
def test_dense_value_and_gradient_against_f64_reference(case):
    prob = check_dense_against_reference("f32", case)
    assert prob._atomic, "a GPU arch must take the atomic scatter"


def test_dense_crowded_window_against_f64_reference():
    """10,000 events on 64 x 48 pixels: many atomic adds into every pixel and node, in float32."""
    check_dense_against_reference("f32", "gradmag-multi-all", seed=3, n=10_000)


def test_dense_solve_recovers_a_field():
    """A short coarse-to-fine solve on the GPU recovers a spatially varying flow."""
    from cmax_taichi.testing.flow_scenes import depth_scene

    scene = depth_scene((120, 90), duration=0.05, displacement=(4.0, 1.5), n_events=8000, seed=2)
    est = DenseFlowEstimator((4, 4), levels=2, regularizers={"deformation": 1.0, "total_variation": 0.3})
    res = est.estimate(scene.events)
    assert res.grid == FlowGrid(120, 90, 4, 4)
    err = np.hypot(*(res.displacement() - scene.displacement()))
    assert np.all(np.isfinite(err)) and float(np.median(err)) < 1.0, float(np.median(err))
