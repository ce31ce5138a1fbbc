"""Hostile input to the pipeline and the solvers gets one clear error naming the
parameter (or a finite, correct result), and the process stays usable after every failure.

Each test provokes one case of the issue, checks the exception type and that the message names the
parameter, then builds and evaluates a normal small problem (:func:`assert_session_usable`). Cases of
the issue covered elsewhere: the input layer (Events, Camera, readers, windows, strides, CLI) in
``test_input_guarantees.py`` / ``test_input_properties.py``; theta of the wrong length, NaN in theta
and a string theta in ``test_bad_input.py::test_theta_validation``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import taichi as ti
from cmax_taichi.kernels.warps import common as kcommon
from conftest import CAMERA, SENSOR, edge_events, use_precision

import cmax_taichi as cm
from cmax_taichi.core import backend
from cmax_taichi.pipeline.clusters import MultiClusterCMax


def small_events(n: int = 200, seed: int = 2) -> cm.Events:
    x, y, t, p = edge_events(n=n, seed=seed)
    return cm.Events(x, y, t, p, SENSOR)


def assert_session_usable() -> None:
    """A normal small problem builds and evaluates to finite values after a failure."""
    prob = cm.ContrastMaximization(small_events(), warp="translation2", regularizers={"divergence": 1.0})
    value, grad = prob.value_and_grad([10.0, -5.0])
    assert math.isfinite(value) and np.all(np.isfinite(grad))


@pytest.fixture
def zoom_problem(f64):
    return cm.ContrastMaximization(small_events(), warp="zoom1")


# --- theta ------------------------------------------------------------------------------------------
def test_theta_none_names_theta(zoom_problem):
    with pytest.raises(TypeError, match=r"theta of warp 'zoom1'.*real numbers, got None"):
        zoom_problem.value(None)
    assert_session_usable()


def test_theta_element_none_names_the_entry(zoom_problem):
    with pytest.raises(TypeError, match=r"theta\[0\] = None \(NoneType\) is not a real number"):
        zoom_problem.value_and_grad([None])
    assert_session_usable()


def test_theta_python_int_beyond_float64_names_the_limit(zoom_problem):
    with pytest.raises(ValueError, match=r"theta\[0\] = 1e400 .*beyond the largest float64 \(1.8e\+308\)"):
        zoom_problem.value_and_grad([10**400])
    assert_session_usable()


def test_theta_complex_and_bool_are_refused(zoom_problem):
    with pytest.raises(TypeError, match=r"theta\[0\] = .*complex.*not a real number"):
        zoom_problem.value([1 + 2j])
    with pytest.raises(TypeError, match=r"theta\[0\] = True"):
        zoom_problem.value([True])
    assert_session_usable()


def test_theta_beyond_float32_names_theta_and_the_limit():
    use_precision("f32")
    try:
        prob = cm.ContrastMaximization(small_events(), warp="translation2")
        limit = r"theta\[1\] = 1e\+39 is beyond the largest f32 value \(3.4e\+38\)"
        with pytest.raises(ValueError, match=limit):
            prob.value_and_grad([0.0, 1e39])
        assert_session_usable()
    finally:
        use_precision("f64")


# --- non-finite results -----------------------------------------------------------------------------
@pytest.mark.parametrize("warp", ["se2", "sim2"])
def test_se2_sim2_gradient_finite_at_huge_rates_in_f32(warp):
    """The complex divisions of the exact Sim(2) exponential overflowed f32 (|z^2|^2) from w ~ 1e15 rad/s:
    a NaN gradient. Scaled divisions keep it finite up to the largest f32."""
    use_precision("f32")
    try:
        prob = cm.ContrastMaximization(small_events(), warp=warp)
        for rate in (1e15, 1e20, 1e30, 1e38):
            theta = [0.0, 0.0, rate] + ([0.0] if warp == "sim2" else [])
            value, grad = prob.value_and_grad(theta)
            assert math.isfinite(value) and np.all(np.isfinite(grad)), (rate, value, grad)
            assert value == pytest.approx(prob.value(theta), rel=1e-5)
        assert_session_usable()
    finally:
        use_precision("f64")


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_scaled_complex_divisions_match_numpy(precision):
    """_cexpm1_over_z and its derivative (the rewritten se2 / sim2 helpers) against complex128 NumPy,
    from the closed-form threshold up to magnitudes where |z|^2 overflowed f32."""
    use_precision(precision)
    try:
        mags = np.array([0.2, 1.0, 3.7, 50.0, 1e4, 1e9, 1e13, 1e18, 1e30])
        angles = np.array([0.3, 2.0, -1.1, 2.9, -2.5, 1.2, -0.4, 0.8, 1.9])
        zs = mags * np.exp(1j * angles)
        zs.real = np.where(mags > 100, -np.abs(zs.real), zs.real)  # e^z stays finite: Re z <= 0 when big
        n = len(zs)
        inp = ti.Vector.field(2, backend.real(), shape=n)
        out = ti.Vector.field(4, backend.real(), shape=n)
        inp.from_numpy(np.stack([zs.real, zs.imag], axis=1).astype(backend.numpy_real()))
        stored = inp.to_numpy().astype(np.float64)
        zs = stored[:, 0] + 1j * stored[:, 1]  # the reference at the z the kernel sees

        @ti.kernel
        def run():
            for i in range(n):
                a = kcommon._cexpm1_over_z(inp[i])
                b = kcommon._cexpm1_over_z_prime(inp[i])
                out[i] = ti.Vector([a[0], a[1], b[0], b[1]])

        run()
        got = out.to_numpy().astype(np.float64)
        want_f = np.expm1(zs) / zs
        want_p = (zs * np.exp(zs) - np.exp(zs) + 1.0) / zs**2
        assert np.all(np.isfinite(got))
        rtol = 1e-10 if precision == "f64" else 1e-4
        # the imprecision of a float32 z, not of the division, bounds the f32 error at large |z|
        for k, (g, w) in enumerate(zip(got, zip(want_f, want_p, strict=True), strict=True)):
            if precision == "f32" and mags[k] > 1e3:
                assert abs(complex(g[0], g[1])) <= 4.0 / mags[k] and abs(complex(g[2], g[3])) <= 4.0 / mags[k]
                continue
            np.testing.assert_allclose(complex(g[0], g[1]), w[0], rtol=rtol, atol=1e-300)
            np.testing.assert_allclose(complex(g[2], g[3]), w[1], rtol=rtol, atol=1e-300)
    finally:
        use_precision("f64")


def test_zoom_overflow_is_an_error_naming_theta(f64):
    """zoom1 with regularizers at 1e308: div = 2 theta overflows (J was -inf)."""
    prob = cm.ContrastMaximization(small_events(), warp="zoom1", regularizers={"divergence": 1.0})
    for call in (prob.value, prob.value_and_grad, prob.maps, prob.dense_flow):
        with pytest.raises(
            cm.NonFiniteResultError, match=r"not finite at theta = \[1e\+308\] .*overflow f64"
        ):
            call([1e308])
    assert issubclass(cm.NonFiniteResultError, ValueError)
    assert_session_usable()


def test_events_all_off_the_sensor_give_a_finite_value(f64):
    """A warp that sends every event but the reference one off the sensor is a legitimate (empty)
    image: finite J and gradient, no error."""
    prob = cm.ContrastMaximization(small_events(), warp="translation2", regularizers={"deformation": 1.0})
    value, grad = prob.value_and_grad([1e300, -1e300])
    assert math.isfinite(value) and np.all(np.isfinite(grad))
    # only the event at t_ref (dt = 0) stays: its blurred vote
    assert prob.iwe([1e300, -1e300]).sum() == pytest.approx(1.0, abs=1e-6)


def test_maximize_survives_overflowing_points_of_a_huge_box(f64):
    from cmax_taichi.solve.optimize import _Objective

    prob = cm.ContrastMaximization(small_events(), warp="zoom1", regularizers={"divergence": 1.0})
    # a point where J overflows reads as -inf to the searches and the local methods
    obj = _Objective(prob, np.ones(1))
    assert obj.value(np.array([1e308])) == -math.inf
    value, grad = obj.value_and_grad(np.array([1e308]))
    assert value == -math.inf and np.all(grad == 0.0)
    res = cm.maximize(prob, bounds=([-1e280], [1e280]), n_init=20, max_iter=5)
    assert math.isfinite(res.value) and np.all(np.isfinite(res.theta))
    assert np.all(np.isfinite(res.history.value))
    # a box the search cannot step through (its differences overflow float64) names the limit
    with pytest.raises(ValueError, match=r"bounds: h_z = -1e\+308 1/s is beyond .*\|h_z\| <= "):
        cm.maximize(prob, bounds=([-1e308], [1e308]))
    with pytest.raises(ValueError, match=r"theta0: h_z = 1e\+308 1/s is beyond"):
        cm.maximize(prob, theta0=[1e308])
    assert_session_usable()


@pytest.mark.parametrize(
    "dt,error,message",
    [
        (float("nan"), ValueError, "dt must be a finite number of seconds, got nan"),
        (float("inf"), ValueError, "dt must be a finite number of seconds, got inf"),
        ("1 ms", TypeError, "dt must be a number of seconds, got '1 ms'"),
        (None, TypeError, "dt must be a number of seconds, got None"),
    ],
)
def test_dense_flow_dt_must_be_finite(zoom_problem, dt, error, message):
    with pytest.raises(error, match=message):
        zoom_problem.dense_flow([3.0], dt=dt)
    with pytest.raises(error, match=message):
        cm.dense_flow("zoom1", [3.0], SENSOR, dt=dt)
    assert_session_usable()


def test_dense_flow_duration_must_be_positive(f64):
    with pytest.raises(ValueError, match="duration must be a positive number of seconds, got 0"):
        cm.dense_flow("mitrokhin4", [1.0, 0.0, 0.0, 0.0], SENSOR, duration=0.0)
    with pytest.raises(TypeError, match="duration must be a number of seconds"):
        cm.dense_flow("mitrokhin4", [1.0, 0.0, 0.0, 0.0], SENSOR, duration="1 s")
    assert_session_usable()


# --- maximize options ---------------------------------------------------------------------------------
@pytest.fixture
def translation_problem(f64):
    return cm.ContrastMaximization(small_events(), warp="translation2")


@pytest.mark.parametrize(
    "bounds,error,message",
    [
        (([-np.inf, -1.0], [np.inf, 1.0]), ValueError, r"non-finite value: bounds lo\[0\] = -inf"),
        (([-1.0, -1.0], [1.0, np.nan]), ValueError, r"bounds hi .*non-finite value: bounds hi\[1\] = nan"),
        (([1.0, 1.0], [-1.0, 2.0]), ValueError, r"bounds: lo\[0\] = 1 is not below hi\[0\] = -1 .*'v_x'"),
        (([0.0, 1.0], [1.0, 1.0]), ValueError, r"bounds: lo\[1\] = 1 is not below hi\[1\] = 1"),
        (([-1.0], [1.0]), ValueError, r"takes 2 parameter\(s\), got bounds lo of length 1"),
        ((None, None), TypeError, r"bounds lo .*got None"),
        ("box", TypeError, r"bounds must be a pair \(lo, hi\)"),
        (([-1.0, "a"], [1.0, 1.0]), TypeError, r"bounds lo\[1\] = 'a'"),
        (([-(10**400), -1.0], [1.0, 1.0]), ValueError, r"bounds lo\[0\] = -1e400 .*beyond the largest"),
    ],
)
def test_maximize_bounds_name_the_problem(translation_problem, bounds, error, message):
    with pytest.raises(error, match=message):
        cm.maximize(translation_problem, bounds=bounds)
    assert_session_usable()


@pytest.mark.parametrize(
    "option,value,error,message",
    [
        ("max_iter", -1, ValueError, "max_iter must be at least 0, got -1"),
        ("max_iter", 2.5, ValueError, "max_iter must be a whole number, got 2.5"),
        ("max_iter", "10", TypeError, "max_iter must be a whole number, got '10'"),
        ("n_init", 0, ValueError, "n_init must be at least 1, got 0"),
        ("n_init", -5, ValueError, "n_init must be at least 1, got -5"),
        ("n_starts", 0, ValueError, "n_starts must be at least 1, got 0"),
        ("patience", 0, ValueError, "patience must be at least 1, got 0"),
        ("gtol", float("nan"), ValueError, r"gtol must be a finite number \(1/px\), got nan"),
        ("gtol", -1e-3, ValueError, r"gtol must be a finite number >= 0 \(1/px\), got -0.001"),
        ("rtol", float("inf"), ValueError, r"rtol must be a finite number \(relative\), got inf"),
        ("lr", "big", TypeError, r"lr must be a number \(px\), got 'big'"),
        ("xtol", 0.0, ValueError, r"xtol must be a positive number \(px\), got 0.0"),
        ("min_spacing", None, TypeError, r"min_spacing must be a number \(px\), got None"),
    ],
)
def test_maximize_options_name_the_problem(translation_problem, option, value, error, message):
    with pytest.raises(error, match=message):
        cm.maximize(translation_problem, **{option: value})
    assert_session_usable()


def test_maximize_max_iter_zero_is_the_search_alone(translation_problem):
    res = cm.maximize(translation_problem, max_iter=0, n_init=27)
    assert res.n_iterations == 0 and math.isfinite(res.value)


def test_maximize_theta0_and_candidates_name_the_argument(translation_problem):
    with pytest.raises(TypeError, match=r"theta0\[0\] = None"):
        cm.maximize(translation_problem, theta0=[None, 1.0])
    with pytest.raises(ValueError, match=r"theta0\[0\] = 1e400 .*beyond the largest float64"):
        cm.maximize(translation_problem, theta0=[10**400, 1.0])
    with pytest.raises(ValueError, match=r"candidates\[1\] .*non-finite value: candidates\[1\]\[0\] = inf"):
        cm.maximize(translation_problem, candidates=[[1.0, 2.0], [np.inf, 0.0]])
    assert_session_usable()


# --- problem options -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs,error,message",
    [
        ({"blur_sigma": "big"}, TypeError, r"blur_sigma must be a number of px >= 0, got 'big' \(str\)"),
        ({"blur_sigma": None}, TypeError, r"blur_sigma must be a number of px >= 0, got None"),
        ({"blur_sigma": [1.0]}, TypeError, r"blur_sigma must be a number of px >= 0, got \[1.0\] \(list\)"),
        ({"blur_sigma": True}, TypeError, r"blur_sigma must be a number of px >= 0, got True"),
        ({"blur_sigma": 10**400}, ValueError, r"blur_sigma must be a finite number >= 0, got inf"),
        ({"blur_sigma": float("nan")}, ValueError, r"blur_sigma must be a finite number >= 0, got nan"),
        ({"t_ref": 10**400}, ValueError, r"t_ref must be finite, got inf"),
        ({"t_ref": True}, TypeError, r"t_ref must be 'first', 'middle', 'last' or seconds, got True"),
        ({"normalize": "no"}, TypeError, r"normalize must be True or False, got 'no'"),
        ({"regularizers": {"divergence": 10**400}}, ValueError, r"weight of regularizer 'divergence'"),
        ({"regularizers": {"divergence": "1"}}, TypeError, r"weight of regularizer 'divergence' must be"),
        ({"weights": ["a"] * 200}, TypeError, r"weights must be real numbers, got dtype <U1"),
    ],
)
def test_problem_options_name_the_problem(f64, kwargs, error, message):
    with pytest.raises(error, match=message):
        cm.ContrastMaximization(small_events(), warp="translation2", **kwargs)
    assert_session_usable()


def test_numeric_t_ref_must_lie_near_the_window(f64):
    """A t_ref on another clock (1e9 s: a Unix time; microseconds) warped every event over ~1e9 s and gave
    a meaningless estimate without a word. A number now lies within the window's span give or take its
    duration; the error names the value, the span and the unit."""
    ev = small_events()
    t0, t1 = float(ev.t[0]), float(ev.t[-1])
    T = t1 - t0
    for inside in (t0, 0.5 * (t0 + t1), t0 - 0.99 * T, t1 + 0.99 * T):
        prob = cm.ContrastMaximization(ev, warp="translation2", t_ref=inside)
        assert prob.t_ref == inside
    for outside in (1e9, t1 + 1.01 * T, t0 - 1.01 * T, -1e9):
        with pytest.raises(ValueError, match=r"t_ref .* s is outside the window: its events span \[.*\] s"):
            cm.ContrastMaximization(ev, warp="translation2", t_ref=outside)
    with pytest.raises(ValueError, match="outside the window"):
        MultiClusterCMax(ev, 2, "translation2", t_ref=1e9)
    assert_session_usable()


def test_a_sequence_refuses_one_numeric_t_ref_for_many_windows(f64):
    """Every window of a sequence was warped to one numeric t_ref (the later ones over many times their
    duration). A number is for a run of one window; the names follow each window."""
    from cmax_taichi.solve import sequence

    ev = small_events(n=600)
    with pytest.raises(ValueError, match=r"t_ref 0.0 s is one time .* this run has 3 windows"):
        sequence.process(ev, "translation2", n_events=200, progress=False, problem_options={"t_ref": 0.0})
    one = sequence.process(
        ev, "translation2", n_events=200, max_windows=1, progress=False, problem_options={"t_ref": 0.0}
    )
    assert [w.status for w in one.windows] == ["estimated"]
    with pytest.raises(ValueError, match="outside the window"):
        sequence.process(
            ev, "translation2", n_events=200, max_windows=1, progress=False, problem_options={"t_ref": 1e9}
        )
    with pytest.raises(ValueError, match="t_ref must be finite, got nan"):  # not "one time ... 3 windows"
        sequence.process(ev, "translation2", n_events=200, progress=False, problem_options={"t_ref": np.nan})
    # a live run: refused before the stream is read (its number of windows is not known)
    from cmax_taichi.io.streams import ReplayStream
    from cmax_taichi.solve.online import run_live

    refused = pytest.raises(ValueError, match=r"t_ref 0.0 s is one time .* an unknown")
    with ReplayStream(ev) as stream, refused:
        run_live(stream, "translation2", windows=200, problem_options={"t_ref": 0.0}, warm_up=False)


# --- segmentation on tiny windows -----------------------------------------------------------------------
def test_segment_tiny_window_does_not_mention_a_hidden_batch(f64):
    """segment(K=2) on 2-7 events said "n_clusters = 8 is more than the 5 events": 8 was the batch of
    translational candidates scored at once by the initialisation. It is now capped by the window."""
    x, y, t, p = edge_events(n=200, seed=4)
    tiny = cm.Events(x[:5], y[:5], t[:5], p[:5], SENSOR)
    res = cm.segment(tiny, n_clusters=2, max_iterations=2, steps=2)
    assert res.labels.shape == (5,) and res.n_clusters == 2
    with pytest.raises(ValueError, match=r"n_clusters = 3 is more than the 2 events"):
        cm.segment(cm.Events(x[:2], y[:2], t[:2], p[:2], SENSOR), n_clusters=3)
    assert_session_usable()


# --- maps: NaN is "no event here" -------------------------------------------------------------------------
def test_maps_are_nan_where_no_event_landed(f64):
    prob = cm.ContrastMaximization(
        small_events(), warp="zoom1", regularizers={"divergence": 1.0, "deformation": 1.0}
    )
    maps = prob.maps([4.0])
    hit = maps["count"] > 0
    assert 0 < np.count_nonzero(hit) < hit.size
    assert np.all(maps["count"][~hit] == 0)
    for name in ("divergence", "deformation", "divergence_penalty", "deformation_penalty"):
        assert np.all(np.isnan(maps[name][~hit])), name
        assert np.all(np.isfinite(maps[name][hit])), name
    # zoom1's divergence is 2 h_z and its deformation (1 - t h_z)^2 < 1 where events landed
    np.testing.assert_allclose(maps["divergence"][hit], 8.0, rtol=1e-9)
    assert np.all(maps["deformation"][hit] <= 1.0)
    assert math.isfinite(maps["R_divergence"]) and math.isfinite(maps["R_deformation"])


def test_reference_maps_use_the_same_convention(f64):
    from cmax_taichi.testing import reference

    ev = small_events()
    ref = reference.evaluate(ev.x, ev.y, ev.t, ev.p, [4.0], warp="zoom1", sensor_size=SENSOR, lambda_div=1.0)
    prob = cm.ContrastMaximization(ev, warp="zoom1", regularizers={"divergence": 1.0})
    maps = prob.maps([4.0])
    np.testing.assert_array_equal(np.isnan(ref["div_map"]), np.isnan(maps["divergence"]))
    np.testing.assert_allclose(ref["def_map"], maps["deformation"], rtol=1e-9, equal_nan=True)


def test_dense_flow_is_nan_where_a_ray_turns_behind_the_camera(f64):
    """rotation3 over a long dt turns some rays behind the camera: no displacement exists there."""
    flow = cm.dense_flow("rotation3", [0.0, 2.0, 0.0], SENSOR, camera=CAMERA, dt=1.0)
    nowhere = np.isnan(flow[0])
    assert np.any(nowhere) and np.any(~nowhere)
    np.testing.assert_array_equal(nowhere, np.isnan(flow[1]))
    assert np.all(np.isfinite(flow[:, ~nowhere]))
    assert np.all(np.abs(flow[:, ~nowhere]) < 1e6)  # no -1e7 "outside" sentinel leaks out
    # the instantaneous flow is defined everywhere
    assert np.all(np.isfinite(cm.dense_flow("rotation3", [0.0, 2.0, 0.0], SENSOR, camera=CAMERA)))


def test_viz_draws_nan_pixels_grey(f64):
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cmax_taichi import viz

    flow = np.zeros((2, 3, 4))
    flow[0, 0, 0] = 1.0
    flow[:, 1, 1] = np.nan
    rgb = viz.flow_to_rgb(flow)
    assert np.all(np.isfinite(rgb))
    np.testing.assert_allclose(rgb[1, 1], float(viz.NO_EVENT_COLOR))
    np.testing.assert_allclose(rgb[2, 2], 0.0)  # zero flow stays black, distinct from "no value"
    prob = cm.ContrastMaximization(small_events(), warp="zoom1", regularizers={"deformation": 1.0})
    maps = prob.maps([4.0])
    fig, ax = plt.subplots()
    artist = viz.show_regularizer_map(ax, {"deformation": maps["deformation"]}, "deformation")
    drawn = artist.get_array()
    np.testing.assert_array_equal(np.ma.getmaskarray(drawn), maps["count"] == 0)
    plt.close(fig)


@pytest.mark.parametrize(
    "init_thetas,error,message",
    [
        (
            [[None, 1.0], [0.0, 0.0]],
            ValueError,
            r"parameter 0 of cluster 0 \(translation2\) is non-finite",
        ),
        ([[0.0, 1.0], [0.0, np.inf]], ValueError, r"thetas: parameter 1 of cluster 1 \(translation2\)"),
        ([[10**400, 1.0], [0.0, 0.0]], ValueError, r"thetas has a value beyond the largest float64"),
        ("fast", TypeError, r"thetas must be a \(K, P\) array"),
    ],
)
def test_segment_init_thetas_name_the_problem(f64, init_thetas, error, message):
    with pytest.raises(error, match=message):
        cm.segment(small_events(), n_clusters=2, warp="translation2", init_thetas=init_thetas)
    assert_session_usable()


@pytest.mark.parametrize("method", ["closed", "autodiff"])
def test_event_jacobians_overflow_is_an_error_naming_theta(f64, method):
    prob = cm.ContrastMaximization(small_events(), warp="zoom1")
    with pytest.raises(
        cm.NonFiniteResultError, match=r"per-event det or div is not finite at theta = \[1e\+308\]"
    ):
        cm.event_jacobians(prob, [1e308], method=method)
    assert_session_usable()
    result = cm.event_jacobians(prob, [4.0], method=method)
    assert all(np.all(np.isfinite(v)) for v in result.values())
