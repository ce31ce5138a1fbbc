"""ContrastMaximization.set_events: a problem that takes the next window in place gives exactly what a
new problem on that window gives (value, gradient, G0, maps), on the fused and the chain paths, across
event-capacity buckets and with weights; a rejected window leaves the previous one in place. Also the
per-pixel undistortion table gives the same events as the direct undistortion."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi.core import events as cm_events
from cmax_taichi.core.checks import EventsDroppedWarning

pytestmark = pytest.mark.usefixtures("f64")

SENSOR = (64, 48)


def window(n: int, seed: int, v=(90.0, -40.0), sensor=SENSOR, whole_pixels: bool = False) -> cm.Events:
    rng = np.random.default_rng(seed)
    W, H = sensor
    t = np.sort(rng.uniform(0.0, 0.03, n))
    x0 = rng.uniform(5, W - 6, n // 20 + 1)[rng.integers(0, n // 20 + 1, n)]
    y0 = rng.uniform(5, H - 6, n // 20 + 1)[rng.integers(0, n // 20 + 1, n)]
    x = np.clip(x0 + v[0] * t + rng.normal(0, 0.3, n), 0, W - 1)
    y = np.clip(y0 + v[1] * t + rng.normal(0, 0.3, n), 0, H - 1)
    if whole_pixels:
        x, y = np.round(x), np.round(y)
    return cm.Events(x, y, t, rng.integers(0, 2, n), sensor)


CASES = [
    pytest.param(dict(warp="translation2"), id="fused-translation2"),
    pytest.param(
        dict(warp="mitrokhin4", regularizers={"divergence": 2.0, "deformation": 1.0}), id="fused-regs"
    ),
    pytest.param(
        dict(warp="translation2", polarity="split", objective="gradient_magnitude"), id="fused-split"
    ),
    pytest.param(dict(warp="zoom1", whitening=True), id="chain-whitening"),
]


@pytest.mark.parametrize("options", CASES)
def test_set_events_matches_a_new_problem(options):
    # 3000 -> 1500 (same capacity bucket) -> 700 (another bucket) -> 3000 (back)
    windows = [window(3000, 0), window(1500, 1), window(700, 2), window(3000, 3)]
    theta = np.array([60.0, -20.0, 3.0, 0.1])[: cm.get_warp(options["warp"]).n_params]
    reused = cm.ContrastMaximization(windows[0], **options)
    for w in windows[1:]:
        reused.set_events(w)
        fresh = cm.ContrastMaximization(w, **options)
        assert reused.n_events == fresh.n_events == len(w)
        assert reused.path == fresh.path and reused.duration == fresh.duration
        assert pytest.approx(fresh.G0, rel=1e-12) == reused.G0
        v1, g1 = reused.value_and_grad(theta)
        v2, g2 = fresh.value_and_grad(theta)
        assert v1 == pytest.approx(v2, rel=1e-12, abs=1e-12)
        np.testing.assert_allclose(g1, g2, rtol=1e-9, atol=1e-12)
        # the fresh problem used the shared fields in between: the reused one uploads its window again
        assert reused.value(theta) == pytest.approx(v2, rel=1e-12, abs=1e-12)
        assert pytest.approx(fresh.evaluate(theta).R, rel=1e-9, abs=1e-12) == reused.evaluate(theta).R


def test_set_events_with_weights_and_rejected_windows():
    w0, w1 = window(2000, 4), window(2500, 5)
    weights1 = np.linspace(0.5, 1.5, len(w1))
    prob = cm.ContrastMaximization(w0, "translation2", weights=np.ones(len(w0)))
    prob.set_events(w1, weights=weights1)
    fresh = cm.ContrastMaximization(w1, "translation2", weights=weights1)
    assert prob.value([50.0, 10.0]) == pytest.approx(fresh.value([50.0, 10.0]), rel=1e-12)
    before = prob.value([50.0, 10.0])
    with pytest.raises(ValueError, match="weights has 3 values for 2500 events"):
        prob.set_events(w1, weights=[1.0, 2.0, 3.0])
    flat = cm.Events([3.0, 3.0], [4.0, 4.0], [0.0, 0.01], [1, 1], SENSOR)
    with pytest.raises(TypeError, match="events must be cmax_taichi.Events"):
        prob.set_events(np.zeros((10, 4)))
    with pytest.raises(ValueError, match="weights has 2000 values for 2 events"):
        prob.set_events(flat, weights=np.ones(2000))
    # every rejected window left the previous one in place
    assert prob.n_events == len(w1)
    assert prob.value([50.0, 10.0]) == pytest.approx(before, rel=1e-12)


def test_set_events_rejects_a_flat_window_and_keeps_the_previous_one():
    w0 = window(2000, 6)
    prob = cm.ContrastMaximization(w0, "translation2", polarity="signed")
    before = prob.value([30.0, 0.0])
    # opposite polarities on one pixel cancel in the signed IWE: a flat image, nothing to maximise
    cancelling = cm.Events([5.0] * 4, [5.0] * 4, [0.0, 0.01, 0.02, 0.03], [1, 0, 1, 0], SENSOR)
    with pytest.raises(ValueError, match="the identity warp's variance is 0.0: the events give a flat image"):
        cm.ContrastMaximization(cancelling, "translation2", polarity="signed")
    with pytest.raises(ValueError, match="the identity warp's variance is 0.0: the events give a flat image"):
        prob.set_events(cancelling)
    assert prob.n_events == len(w0)
    assert prob.value([30.0, 0.0]) == pytest.approx(before, rel=1e-12)


def test_undistortion_table_gives_the_direct_undistortion():
    camera = cm.Camera(55.0, 54.0, 31.0, 24.5, dist=(-0.2, 0.05, 0.001, -0.002, 0.0))
    on_pixels = window(4000, 7, whole_pixels=True)
    direct_x, direct_y = camera.undistort_points(on_pixels.x, on_pixels.y)
    table_x, table_y = cm_events._undistort_pixels(camera, on_pixels.x, on_pixels.y, *SENSOR)
    np.testing.assert_array_equal(table_x, direct_x)  # bit for bit, NaN where it does not invert
    np.testing.assert_array_equal(table_y, direct_y)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", EventsDroppedWarning)  # the corners leave the sensor
        undistorted = on_pixels.undistort(camera)
    inside = np.isfinite(direct_x) & (direct_x >= 0) & (direct_x <= SENSOR[0] - 1)
    inside &= np.isfinite(direct_y) & (direct_y >= 0) & (direct_y <= SENSOR[1] - 1)
    np.testing.assert_array_equal(undistorted.x, direct_x[inside])
    np.testing.assert_array_equal(undistorted.y, direct_y[inside])
    # sub-pixel events take the direct computation
    sub = window(500, 8)
    sx, _ = cm_events._undistort_pixels(camera, sub.x, sub.y, *SENSOR)
    np.testing.assert_array_equal(sx, camera.undistort_points(sub.x, sub.y)[0])


def test_problems_sharing_pooled_arrays_keep_their_own_blur():
    # sigma 1.0 and 0.9 px have the same footprint (3 px), so the three problems share one workspace and
    # one compiled kernel: the taps travel in each problem's own parameters, never in the shared arrays
    events = window(2000, 4)
    theta = np.array([60.0, -20.0])
    a = cm.ContrastMaximization(events, warp="translation2", blur_sigma=1.0)
    b = cm.ContrastMaximization(events, warp="translation2", blur_sigma=0.9)
    c = cm.ContrastMaximization(events, warp="translation2", blur_sigma=1.0)
    assert a._fused._ws is b._fused._ws is c._fused._ws
    assert a._fused._schedules is b._fused._schedules is c._fused._schedules
    first = {id(p): p.value_and_grad(theta) for p in (a, b, c)}
    assert first[id(a)][0] != first[id(b)][0]  # the blur matters
    assert first[id(a)][0] == first[id(c)][0]
    for p in (a, c, b, a, c, b):
        value, grad = p.value_and_grad(theta)
        assert value == first[id(p)][0]
        np.testing.assert_array_equal(grad, first[id(p)][1])


@pytest.mark.parametrize("options", CASES)
def test_a_dropped_problem_is_freed_at_once(options):
    """A script that builds one problem per window must not keep the dropped ones until a cyclic
    garbage collection: no reference cycle holds a problem (its host arrays are megabytes, and glibc
    kept the freed blocks: ~150 MB over a hundred rotation3 windows of 30,000 events)."""
    import gc
    import weakref

    gc.collect()
    gc.disable()
    try:
        prob = cm.ContrastMaximization(window(3000, 1), **options)
        prob.value_and_grad(np.zeros(prob.model.n_params))
        ref = weakref.ref(prob)
        del prob
        assert ref() is None, "a reference cycle keeps the problem alive"
    finally:
        gc.enable()
