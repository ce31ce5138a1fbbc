"""The dense flow's accuracy target on the 3-D simulator: on the ``corridor`` depth preset (346x260, 5-14 px
over the window, the flow varying by a factor 2.5) the dense flow with its defaults is within 0.5 px of the
exact displacement and at most half as far off as the best global warp (benchmarks/NOTES.md, "Accuracy on
simulated depth scenes")."""

from __future__ import annotations

import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi.flow import DenseFlowEstimator
from cmax_taichi.metrics import event_mask, flow_error
from cmax_taichi.sim import depth_example


@pytest.mark.slow
def test_dense_flow_meets_the_target_on_the_corridor(f64):
    example = depth_example("corridor")
    events, truth = example.events, example.flow
    T = example.t1 - example.t0
    mag = np.hypot(*truth)
    assert mag.min() >= 5.0 and mag.max() <= 15.0 and mag.max() >= 1.3 * mag.min()
    mask = event_mask(events)
    dense = DenseFlowEstimator((16, 16), levels=4).estimate(events)
    aee = flow_error(dense.flow(T), truth, mask)["AEE"]
    prob = cm.ContrastMaximization(
        events, warp="mitrokhin4", regularizers={"divergence": 10.0, "deformation": 10.0}
    )
    glob = flow_error(prob.dense_flow(cm.maximize(prob).theta, dt=T), truth, mask)["AEE"]
    assert aee <= 0.5 and aee <= 0.5 * glob, (aee, glob)
