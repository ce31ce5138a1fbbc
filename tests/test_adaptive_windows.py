"""Motion-adaptive windows: the planner's rule (bounds, the first window, the tail), the speed at a window's
extreme pixels against the dense flow, and ``sequence.process(adaptive=...)`` on a translating scene:
windows that hold the target motion, a first window that grows, every event accounted for."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import test_sequence as sequence_tests

import cmax_taichi as cm
from cmax_taichi.core.windows import CATEGORIES
from cmax_taichi.pipeline.flow_field import dense_flow
from cmax_taichi.solve import sequence
from cmax_taichi.solve.adaptive import AdaptivePlanner, AdaptiveWindows, extreme_speed
from cmax_taichi.testing.samples import moderate_theta

SENSOR = (120, 90)
V = (150.0, 60.0)  # px/s


def _planner(n: int, spacing: float = 1e-3, **rule) -> AdaptivePlanner:
    rule.setdefault("target_px", 3.0)
    t = np.arange(n) * spacing
    return AdaptivePlanner(
        AdaptiveWindows(**rule), lambda i: float(t[i]), lambda s: int(np.searchsorted(t, s, side="left"))
    )


def test_planner_bounds_first_window_and_tail():
    p = _planner(1000, min_events=20, max_events=300, max_duration=0.2, first_events=50)
    assert p.stop(0, 1000) == 50  # no estimate yet: the first try's events
    assert p.stop(0, 40) is None  # not arrived yet
    p.predict(100.0)  # 3 px at 100 px/s: 30 ms, 30 events here
    assert p.duration == pytest.approx(0.03)
    assert p.stop(100, 1000) == 130
    p.predict(1e4)  # 0.3 ms: bounded below by min_events
    assert p.stop(100, 1000) == 120
    p.predict(0.0)  # a still camera: the longest window, max_duration (200 events) below max_events
    assert math.isinf(p.duration) and p.stop(0, 1000) == 200
    p.predict(1.0)  # 3 s: bounded by max_duration
    assert p.stop(0, 1000) == 200
    slow = _planner(1000, min_events=20, max_events=300, max_duration=10.0)
    slow.predict(0.0)
    assert slow.stop(0, 1000) == 300  # bounded by max_events
    p.predict(100.0)
    assert p.stop(980, 1000, final=False) is None  # the window is not complete yet
    assert p.stop(980, 1000, final=True) is None  # and never will be: the rest is a partial tail
    assert p.keeps_tail(980, 1000) is False  # 20 ms of the 30 the motion asks for: below accept = 0.7
    assert p.keeps_tail(970, 1000) is True
    # a window that would leave a tail too short to be kept takes it (a recording's end)
    assert p.stop(960, 1000, final=True) == 1000
    assert p.stop(960, 1000, final=False) == 990


def test_first_window_retry_rule():
    p = _planner(1000, first_tries=3, first_growth=4.0)
    assert p.retry_duration(duration=0.01, speed=100.0) == pytest.approx(0.03)  # 1 px of 3: grow to 30 ms
    assert p.retry_duration(duration=0.01, speed=10.0) == pytest.approx(0.04)  # at most 4x longer
    assert p.retry_duration(duration=0.03, speed=100.0) is None  # the tries are spent


@pytest.mark.parametrize(
    "kwargs, match",
    [({"target_px": 0}, "target_px"), ({"min_events": 5000, "max_events": 100}, "below min_events"),
     ({"accept": 1.5}, "accept"), ({"first_search": "grid"}, "first_search"),
     ({"first_growth": 1.0}, "above 1")],
)  # fmt: skip
def test_rule_checks(kwargs, match):
    with pytest.raises(ValueError, match=match):
        AdaptiveWindows(**kwargs)


@pytest.mark.parametrize("warp", cm.warp_names())
def test_extreme_speed_is_the_flow_at_the_corners(warp):
    """The one-pixel grid moved to each corner gives the dense flow of the whole sensor there."""
    model = cm.get_warp(warp)
    camera = cm.Camera(fx=110.0, fy=105.0, cx=57.0, cy=46.0)
    rng = np.random.default_rng(1)
    x = np.concatenate([[7.0, 101.0], rng.integers(8, 100, 200)]).astype(float)
    y = np.concatenate([[5.0, 80.0], rng.integers(6, 79, 200)]).astype(float)
    t = np.sort(rng.uniform(0, 0.02, len(x)))
    events = cm.Events(x, y, t, np.ones(len(x)), SENSOR)
    # what extreme_speed reads of a problem (a real one would compile the warp's whole pipeline)
    setup = SimpleNamespace(center=(camera.cx, camera.cy), focal=(camera.fx, camera.fy))
    prob = SimpleNamespace(events=events, model=model, setup=setup, duration=events.duration)
    theta = np.asarray(moderate_theta(model))
    flow = dense_flow(model, theta, SENSOR, camera=camera, duration=prob.duration)
    corners = [np.hypot(flow[0, yy, xx], flow[1, yy, xx]) for xx in (7, 101) for yy in (5, 80)]
    assert extreme_speed(prob, theta) == pytest.approx(max(corners), rel=1e-9)
    assert extreme_speed(prob, np.zeros(model.n_params)) == 0.0


def translating_edges(n=6000, duration=0.2, seed=3) -> cm.Events:
    return sequence_tests.translating_edges(V, n=n, duration=duration, seed=seed, sensor=SENSOR)


def test_process_adaptive_windows_hold_the_target_motion():
    events = translating_edges()
    rule = AdaptiveWindows(target_px=4.0, min_events=150, max_events=5000, first_events=120)
    result = sequence.process(events, "translation2", adaptive=rule, progress=False, keep_tail=True)
    speed = math.hypot(*V)
    rows = result.windows
    assert len(rows) >= 4
    assert rows[0].search.startswith("identity") and "warm" in rows[0].search  # the first window grew
    for w in rows[1:-1]:  # sized by the estimate before them: 4 px of the true motion, give or take
        assert 0.6 * 4.0 <= (w.t_end - w.t_start) * speed <= 1.6 * 4.0, w
    np.testing.assert_allclose(np.median(result.theta, axis=0), V, rtol=0.15)
    counts = result.events
    assert sum(counts[c] for c in CATEGORIES) + counts["after_max_windows"] == counts["total"] == len(events)
    assert result.settings["window_adaptive"]["target_px"] == 4.0
    assert result.settings["window_events"] is None


def test_process_adaptive_options_are_checked():
    events = translating_edges(n=800)
    with pytest.raises(ValueError, match="not with duration= or stride="):
        sequence.process(events, adaptive=True, duration=0.01, progress=False)
    with pytest.raises(TypeError, match="adaptive must be True or an AdaptiveWindows"):
        sequence.process(events, adaptive=3.0, progress=False)


def test_process_adaptive_on_a_recording_matches_events(tmp_path):
    """A Recording and the same Events plan the same adaptive windows (the reads by time agree)."""
    events = translating_edges(n=3000)
    path = tmp_path / "events.txt"
    np.savetxt(path, np.column_stack([events.t, events.x, events.y, (events.p > 0)]), fmt="%.9f %.6f %.6f %d")
    rule = AdaptiveWindows(target_px=4.0, min_events=150, first_events=300)
    options = dict(adaptive=rule, progress=False, compute_fwl=False, optimize_options={"max_iter": 5})
    with cm.io.open_recording(path, sensor_size=SENSOR) as rec:
        from_file = sequence.process(rec, "translation2", **options)
    from_events = sequence.process(
        cm.Events(np.loadtxt(path)[:, 1], np.loadtxt(path)[:, 2], np.loadtxt(path)[:, 0],
                  np.loadtxt(path)[:, 3], SENSOR), "translation2", **options
    )  # fmt: skip
    assert [(w.t_start, w.t_end, w.n_events) for w in from_file.windows] == [
        (w.t_start, w.t_end, w.n_events) for w in from_events.windows
    ]
