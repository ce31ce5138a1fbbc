"""Metrics against hand-computed values: AEE / NPE masks, event mask, angular-velocity RMS, FWL, the
flow of a parametric warp over an interval, and the covered share."""

from __future__ import annotations

import math

import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi import metrics

pytestmark = pytest.mark.usefixtures("f64")


def test_flow_error_by_hand():
    gt = np.zeros((2, 2, 3))
    pred = np.zeros((2, 2, 3))
    # pixel (row 0, col 0): gt (1, 1), pred (4, 5): error 5
    gt[:, 0, 0] = (1.0, 1.0)
    pred[:, 0, 0] = (4.0, 5.0)
    # pixel (0, 1): gt (2, -2), pred (2, -2): error 0
    gt[:, 0, 1] = (2.0, -2.0)
    pred[:, 0, 1] = (2.0, -2.0)
    # pixel (0, 2): gt (-3, 1), pred (9, -4): error 13
    gt[:, 0, 2] = (-3.0, 1.0)
    pred[:, 0, 2] = (9.0, -4.0)
    # pixel (1, 0): gt has a zero component -> invalid; (1, 1): NaN -> invalid
    gt[:, 1, 0] = (5.0, 0.0)
    pred[:, 1, 0] = (100.0, 100.0)
    gt[:, 1, 1] = (np.nan, 1.0)
    # pixel (1, 2): valid, error 1, but no event there
    gt[:, 1, 2] = (1.0, 1.0)
    pred[:, 1, 2] = (1.0, 2.0)
    mask = np.array([[True, True, True], [True, True, False]])
    out = metrics.flow_error(pred, gt, mask, thresholds=(3, 10, 20, 0.5))
    assert out["n_pixels"] == 3
    assert out["AEE"] == pytest.approx((5 + 0 + 13) / 3)
    assert out["3PE"] == pytest.approx(100 * 2 / 3)
    assert out["10PE"] == pytest.approx(100 / 3)
    assert out["20PE"] == 0.0
    assert out["0.5PE"] == pytest.approx(100 * 2 / 3)
    # without the event mask the eventless pixel counts too
    assert metrics.flow_error(pred, gt)["AEE"] == pytest.approx((5 + 0 + 13 + 1) / 4)
    empty = metrics.flow_error(pred, gt, np.zeros((2, 3), bool))
    assert empty["n_pixels"] == 0 and math.isnan(empty["AEE"])
    with pytest.raises(ValueError, match="shapes differ"):
        metrics.flow_error(pred[:, :1], gt)


def test_event_mask_rounds_to_the_nearest_pixel():
    ev = cm.Events([0.4, 2.6, 2.0], [0.0, 1.4, 1.6], [0.0, 0.1, 0.2], [1, 0, 1], (4, 3))
    mask = metrics.event_mask(ev)
    expected = np.zeros((3, 4), bool)
    expected[0, 0] = expected[1, 3] = expected[2, 2] = True
    np.testing.assert_array_equal(mask, expected)


def test_angular_velocity_error_by_hand():
    est = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    gt = np.array([[0.0, 0.0, 0.0], [0.0, 3.0, 4.0]])
    out = metrics.angular_velocity_error(est, gt)
    d = 180 / math.pi
    np.testing.assert_allclose(out["error_deg_s"], [d, 5 * d])
    assert out["rms_deg_s"] == pytest.approx(d * math.sqrt((1 + 25) / 2))
    np.testing.assert_allclose(out["rms_axes_deg_s"], d * np.sqrt([0.5, 4.5, 8.0]))
    assert math.isnan(out["relative"][0]) and out["relative"][1] == pytest.approx(1.0)
    single = metrics.angular_velocity_error([1.0, 1.0, 1.0], [1.0, 1.0, 2.0])
    assert single["relative"][0] == pytest.approx(1 / math.sqrt(6))


def _edges(v=(100.0, 0.0), n=800, sensor=(40, 30), duration=0.05):
    rng = np.random.default_rng(0)
    t = np.sort(rng.uniform(0, duration, n))
    x = rng.choice([8.0, 18.0, 27.0], n) + v[0] * t + rng.normal(0, 0.2, n)
    y = rng.uniform(2, sensor[1] - 3, n)
    return cm.Events(np.clip(x, 0, sensor[0] - 1), y, t, np.ones(n), sensor)


def test_fwl_is_one_at_identity_and_above_one_at_the_true_motion():
    ev = _edges()
    assert metrics.fwl(ev, "translation2", [0.0, 0.0]) == pytest.approx(1.0)
    at_truth = metrics.fwl(ev, "translation2", [100.0, 0.0])
    assert at_truth > 1.5
    # the FWL is the normalised variance: the same number as a variance problem's value
    prob = cm.ContrastMaximization(ev, warp="translation2", objective="variance")
    assert at_truth == pytest.approx(prob.value([100.0, 0.0]))
    assert metrics.fwl(ev, "translation2", [-100.0, 0.0]) < at_truth


def test_flow_from_warp_scales_to_the_interval():
    flow = metrics.flow_from_warp("translation2", [30.0, -20.0], (6, 5), dt=0.1)
    assert flow.shape == (2, 5, 6)
    np.testing.assert_allclose(flow[0], 3.0)
    np.testing.assert_allclose(flow[1], -2.0)
    # zoom: displacement -(W(x, dt) - x) = dt h_z (x - c), c the image centre
    z = metrics.flow_from_warp("zoom1", [2.0], (5, 3), dt=0.05)
    xs = np.arange(5) - 2.0
    np.testing.assert_allclose(z[0, 1], 0.1 * xs)
    np.testing.assert_allclose(z[1, :, 0], 0.1 * (np.arange(3) - 1.0))
    with pytest.raises(ValueError, match="dt must be"):
        metrics.flow_from_warp("translation2", [1.0, 1.0], (6, 5), dt=0.0)


def test_covered_share_drops_when_events_collapse():
    ev = _edges()
    prob = cm.ContrastMaximization(ev, warp="zoom1")
    assert metrics.covered_share(prob, [0.0]) == pytest.approx(1.0)
    collapsed = metrics.covered_share(prob, [0.99 / ev.duration])
    assert collapsed < 0.5
    assert metrics.covered_area_ratio(prob, [0.0]) == pytest.approx(1.0)
    assert metrics.covered_area_ratio(prob, [0.99 / ev.duration]) < 0.8  # gathered into less area
    assert metrics.covered_area_ratio(prob, [-2.0 / ev.duration]) > 1.0  # spread out
