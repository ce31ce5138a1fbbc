"""The CPU loop schedules of the fused kernel (``pipeline/fused.py``): all its loops on the calling
thread ("serial", what a small window gets) or on Taichi's thread pool ("parallel"). Both give the
reference's value and gradient; they differ from each other by rounding only; "auto" runs small windows
serially, large ones on the pool, moves a window whose first serial call is too slow, and keeps one
schedule for all the calls of a window."""

from __future__ import annotations

import contextlib
import itertools

import numpy as np
import pytest
from conftest import CAMERA, SENSOR, THETAS, edge_events
from test_pipeline_gradients import OBJECTIVES, REGS, WARPS, check_against_reference

import cmax_taichi as cm
from cmax_taichi.pipeline.fused import FusedPipeline


@contextlib.contextmanager
def pipeline_settings(**settings):
    """Set ``FusedPipeline`` class attributes for the block (restored after)."""
    saved = {name: getattr(FusedPipeline, name) for name in settings}
    for name, value in settings.items():
        setattr(FusedPipeline, name, value)
    try:
        yield
    finally:
        for name, value in saved.items():
            setattr(FusedPipeline, name, value)


def _problem(n: int, warp: str = "mitrokhin4", regs: dict | None = None, seed: int = 0, **options):
    x, y, t, p = edge_events(n, seed=seed)
    return cm.ContrastMaximization(
        cm.Events(x, y, t, p, SENSOR), warp=warp, regularizers=regs, camera=CAMERA, **options
    )


# every model once, and every objective with every regularizer setting (as the optimized-compile
# covering set of test_pipeline_gradients)
PAIRS = list(itertools.product(OBJECTIVES, REGS))
PARALLEL_CASES = [(WARPS[k % len(WARPS)], *PAIRS[k % len(PAIRS)]) for k in range(max(len(WARPS), len(PAIRS)))]


@pytest.mark.parametrize("warp,objective,regs", PARALLEL_CASES)
def test_parallel_schedule_against_the_reference(warp, objective, regs):
    """The pool's schedule (the small windows of test_pipeline_gradients run serially)."""
    with pipeline_settings(loops="parallel"):
        prob = check_against_reference(
            "f64", dict(warp=warp, objective=objective, regularizers=REGS[regs], camera=CAMERA)
        )
    assert prob.path == "fused" and not prob._fused.serial


def test_parallel_cases_cover_every_pair():
    assert {w for w, *_ in PARALLEL_CASES} == set(WARPS)
    assert {(o, r) for _, o, r in PARALLEL_CASES} == set(PAIRS)


@pytest.mark.parametrize(
    "options",
    [
        dict(warp="mitrokhin4", regs=REGS["both"]),
        dict(warp="rotation3", regs=REGS["def"], objective="gradient_magnitude"),
        dict(warp="sim2", regs=REGS["both"], polarity="split"),
        dict(warp="translation2", regs=REGS["div"], weights=np.linspace(0.2, 1.5, 3000)),
    ],
    ids=["mitrokhin4-both", "rotation3-sobel", "sim2-split", "translation2-weights"],
)
def test_serial_and_parallel_schedules_agree(options):
    """The same window on both schedules: the same J and dJ/dtheta to rounding, at several theta."""
    options = dict(options)
    warp, regs = options.pop("warp"), options.pop("regs")
    base = np.asarray(THETAS[warp], dtype=np.float64)
    results = {}
    for loops in ("serial", "parallel"):
        with pipeline_settings(loops=loops):
            prob = _problem(3000, warp, regs, **options)
        assert prob._fused.serial == (loops == "serial")
        results[loops] = [prob.value_and_grad(base * s) for s in (0.5, 1.0, 1.7)]
        results[loops].append((prob.value(base), None))
    for (v_s, g_s), (v_p, g_p) in zip(results["serial"], results["parallel"], strict=True):
        assert v_s == pytest.approx(v_p, rel=1e-12, abs=1e-14)
        if g_s is not None:
            np.testing.assert_allclose(g_s, g_p, rtol=1e-10, atol=1e-12 * np.max(np.abs(g_p)))


def test_auto_runs_small_windows_serially_and_large_ones_on_the_pool():
    with pipeline_settings(loops="auto", serial_max_events=2000):
        small = _problem(1500, seed=1)
        large = _problem(2500, seed=2)
        assert small._fused.serial and not large._fused.serial
        # a new window of the other size takes the other schedule (set_events reuses the pipeline)
        x, y, t, p = edge_events(2500, seed=3)
        small.set_events(cm.Events(x, y, t, p, SENSOR))
        assert not small._fused.serial


def _clocks(monkeypatch, serial_s: float, pool_s: float) -> None:
    """Fake clocks of the schedule's timing: every timed call on one thread takes ``serial_s`` of thread
    time, every timed call on the pool ``pool_s`` of wall time."""
    thread, wall = itertools.count(), itertools.count()
    monkeypatch.setattr("cmax_taichi.pipeline.fused.time.thread_time", lambda: next(thread) * serial_s)
    monkeypatch.setattr("cmax_taichi.pipeline.fused.time.perf_counter", lambda: next(wall) * pool_s)


# what "auto" learns is kept per compiled kernel for the process: the tests that teach it use a blur of
# their own (kernels no other test uses)
LEARNING_BLUR = dict(blur_sigma=1.25)


def test_auto_moves_a_slow_window_to_the_pool_and_remembers_it(monkeypatch):
    """A first serial call above the limit, and slower than the pool: the window runs on the pool from
    then on, and windows of that many events or more start there (no serial call)."""
    with pipeline_settings(loops="auto", serial_max_events=10**9, serial_limit_s=0.0):
        _clocks(monkeypatch, serial_s=1.0, pool_s=1e-3)
        prob = _problem(1200, seed=4, **LEARNING_BLUR)  # the set-up's identity call is the window's first
        monkeypatch.undo()
        fused = prob._fused
        assert not fused.serial
        assert fused._schedules.parallel_from == 1200
        theta = np.asarray(THETAS["mitrokhin4"], dtype=np.float64)
        value, grad = prob.value_and_grad(theta)
        with pipeline_settings(loops="parallel"):
            reference_run = _problem(1200, seed=4, **LEARNING_BLUR)
        ref_value, ref_grad = reference_run.value_and_grad(theta)
        assert value == ref_value and np.array_equal(grad, ref_grad)  # the pool's result, bit for bit
    with pipeline_settings(loops="auto", serial_max_events=10**9, serial_limit_s=1e9):
        assert not _problem(1300, seed=5, **LEARNING_BLUR)._fused.serial  # more events than learnt: the pool
        assert _problem(
            1100, seed=6, **LEARNING_BLUR
        )._fused.serial  # fewer: serial; under this limit it stays


def test_a_window_keeps_one_schedule(monkeypatch):
    """J at the identity, known from the window's set-up, is what a launch there gives, bit for bit,
    after the window moved to the pool as well."""
    # (the second window is larger than serial_probe_growth times the first: a size that passed once is
    # not timed again)
    for n, limit in ((900, 1e9), (1200, 0.0)):
        with pipeline_settings(loops="auto", serial_max_events=10**9, serial_limit_s=limit):
            _clocks(monkeypatch, serial_s=1.0, pool_s=1e-3)
            prob = _problem(n, seed=7, warp="translation2", **LEARNING_BLUR)
            monkeypatch.undo()
            zero = np.zeros(prob.model.n_params)
            memo = prob.value(zero)
            known, prob._identity_value = prob._identity_value, None
            try:
                assert prob.value(zero) == memo
            finally:
                prob._identity_value = known
            assert prob._fused.serial == (limit > 0)


def test_atomic_path_has_one_schedule():
    with pipeline_settings(loops="serial", force_atomic=True):
        prob = _problem(800, seed=8)
    assert not prob._fused.serial


def test_unknown_schedule_is_a_clear_error():
    with (
        pipeline_settings(loops="threads"),
        pytest.raises(ValueError, match="FusedPipeline.loops must be one of"),
    ):
        _problem(500, seed=9)


def test_a_size_that_passed_is_not_timed_again(monkeypatch):
    """Windows up to ``serial_probe_growth`` times the largest one whose timed serial call passed stay
    serial without a timed call, even under a limit that would move them (a stream of similar windows
    does not switch late); a window beyond it is timed."""
    with pipeline_settings(loops="auto", serial_max_events=10**9, serial_limit_s=1e9):
        first = _problem(700, seed=10, warp="se2", **LEARNING_BLUR)
        assert first._fused.serial and first._fused._schedules.serial_upto >= 700
    growth = FusedPipeline.serial_probe_growth
    with pipeline_settings(loops="auto", serial_max_events=10**9, serial_limit_s=0.0):
        _clocks(monkeypatch, serial_s=1.0, pool_s=1e-3)  # any timed window would move
        assert _problem(650, seed=11, warp="se2", **LEARNING_BLUR)._fused.serial
        assert _problem(int(700 * growth) - 10, seed=12, warp="se2", **LEARNING_BLUR)._fused.serial
        assert not _problem(int(700 * growth) + 10, seed=13, warp="se2", **LEARNING_BLUR)._fused.serial


def test_a_slow_first_launch_is_timed_again(monkeypatch):
    """A window whose first timed launch is over the limit but whose second is not stays serial (the
    first launch of a new window pays for its cold events and image rows): a timing blip does not move
    a stream to the pool."""
    # a blur of its own: a kernel whose learning no other test touched
    with pipeline_settings(loops="auto", serial_max_events=10**9, serial_limit_s=1e9):
        prob = _problem(600, seed=14, warp="translation2", blur_sigma=1.4)  # compiles and launches
    fused = prob._fused
    x, y, t, p = edge_events(1500, seed=15)
    reads = itertools.count()
    # the clock reads 0 s once, then 1 s: the first timed launch takes 1 s, every later one 0 s
    monkeypatch.setattr("cmax_taichi.pipeline.fused.time.thread_time", lambda: min(next(reads), 1) * 1.0)
    with pipeline_settings(loops="auto", serial_max_events=10**9, serial_limit_s=0.5):
        prob.set_events(cm.Events(x, y, t, p, SENSOR))
        prob.value_and_grad(np.zeros(prob.model.n_params))
    assert prob._fused is fused and fused.serial
    assert fused._schedules.serial_upto >= 1500 and fused._schedules.parallel_from is None


def test_a_window_over_the_limit_stays_serial_where_the_pool_is_slower(monkeypatch):
    """Over the limit on one thread, but slower still on the pool (its dispatch: 5,000 events on
    1280x720 took 0.86 ms serially and 1.18 ms on the pool): the window stays serial, and its result is
    the serial schedule's, bit for bit."""
    theta = np.asarray(THETAS["translation2"], dtype=np.float64)
    with pipeline_settings(loops="serial"):
        reference = _problem(1000, seed=16, warp="translation2", blur_sigma=1.6)
        ref_value, ref_grad = reference.value_and_grad(theta)
        ref_g0 = reference.G0
    with pipeline_settings(loops="auto", serial_max_events=10**9, serial_limit_s=1e-4):
        _clocks(monkeypatch, serial_s=1e-3, pool_s=1.0)
        prob = _problem(1000, seed=16, warp="translation2", blur_sigma=1.6)
        monkeypatch.undo()
        fused = prob._fused
        assert fused.serial
        assert fused._schedules.serial_upto >= 1000 and fused._schedules.parallel_from is None
        assert ref_g0 == prob.G0  # the identity call's result came from the serial schedule
        value, grad = prob.value_and_grad(theta)
    assert value == ref_value and np.array_equal(grad, ref_grad)
