"""The side-by-side harness of the dense-flow reference (benchmarks/reference_flow.py): it skips with a
message without the reference checkout, and its own measures (FWL of a dense flow, the scoring of a
window) are right on events whose flow is known."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

import cmax_taichi as cm

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def harness():
    spec = importlib.util.spec_from_file_location("reference_flow", ROOT / "benchmarks" / "reference_flow.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["reference_flow"] = module
    spec.loader.exec_module(module)
    return module


def test_skips_without_the_reference(harness, tmp_path, capsys):
    assert harness.main(["--reference", str(tmp_path / "absent"), "--out", str(tmp_path / "out")]) == 0
    assert "skip: no event_based_optical_flow checkout" in capsys.readouterr().out
    assert not (tmp_path / "out").exists()


def _translating_events(v=(200.0, -120.0), n=20000, seed=0):
    """Scene points translating at ``v`` px/s over 0.1 s, on a 64x48 sensor."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(4, 36, n)
    y0 = rng.uniform(16, 44, n)
    t = np.sort(rng.uniform(0.0, 0.1, n))
    # 60 scene points, each firing many events along its track
    k = rng.integers(0, 60, n)
    x0, y0 = x0[k], y0[k]
    return cm.Events(x0 + v[0] * t, y0 + v[1] * t, t, rng.choice([-1, 1], n), (64, 48))


def test_fwl_of_the_true_flow_beats_zero_and_a_wrong_flow(harness):
    events = _translating_events()
    true = np.zeros((2, 48, 64))
    true[0], true[1] = 200.0, -120.0
    assert harness.fwl_of_flow(events, np.zeros_like(true)) == pytest.approx(1.0)
    good = harness.fwl_of_flow(events, true)
    assert good > 2.0
    assert good > harness.fwl_of_flow(events, 0.7 * true)


def test_score_of_a_window_with_ground_truth(harness):
    events = _translating_events()
    gt = np.zeros((2, 48, 64))
    gt[0], gt[1] = 20.0, -12.0  # px over the 0.1 s window
    window = {"events": events, "score_events": events, "gt": gt, "dt": 0.1}
    pred = np.zeros_like(gt)
    pred[0], pred[1] = 200.0, -120.0  # px/s
    out = harness.score(window, pred)
    assert out["AEE"] == pytest.approx(0.0, abs=1e-12) and out["3PE"] == 0.0
    assert out["AEE_zero_flow"] == pytest.approx(np.hypot(20.0, 12.0))
    pred[0] += 30.0  # 3 px too fast over the window: not above 3 px
    assert harness.score(window, pred)["AEE"] == pytest.approx(3.0)


def test_global_baseline_recovers_a_translation(harness):
    events = _translating_events()
    flow, report = harness.run_global("translation2", events, None, 0.1)
    assert flow.shape == (2, 48, 64)
    np.testing.assert_allclose(flow[0], 200.0, rtol=0.05)  # 60 points, 20k events: a few px/s
    np.testing.assert_allclose(flow[1], -120.0, rtol=0.05)
    assert report["params_total"] == 2 and report["cpu_s"] > 0
