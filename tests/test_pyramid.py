"""The coarse-to-fine search (``maximize()``'s default, ``solve/pyramid.py``): its coarse views, its
evaluation count on a first window (at most 150), its J against a thorough 2,000-point grid search
followed by the same local refinement (at least 0.99 of it), on the simulator and on a shared cut, and
no collapse on the 4-DOF collapse-enabled case."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import CAMERA, SENSOR, THETAS, edge_events, shared_data_dir

import cmax_taichi as cm
from cmax_taichi.metrics import COLLAPSE_AREA_SCALE, area_scale
from cmax_taichi.solve import pyramid
from cmax_taichi.solve.scales import parameter_scales, search_bounds

pytestmark = pytest.mark.usefixtures("f64")

BOTH = {"divergence": 10.0, "deformation": 10.0}
#: the search's claims (at most 150 evaluations, J near the grid's)
MAX_EVALUATIONS = 150
MIN_J_RATIO = 0.99


def thorough(prob: cm.ContrastMaximization) -> cm.OptimizeResult:
    """The reference: a 2,000-point grid (and its zooming beam), then the same local refinement."""
    return cm.maximize(prob, init="grid", n_init=2000)


def simulated(warp: str, theta, duration: float, sensor=(240, 180), regularizers=None):
    """A problem on the simulator's textured plane moving under ``warp`` at ``theta``."""
    from cmax_taichi.sim import default_camera, simulate, warp_scene
    from cmax_taichi.sim.examples import _SIM

    camera = default_camera(sensor)
    segment = duration if warp == "mitrokhin4" else None
    scene = warp_scene(warp, theta, sensor, texture="minduka", camera=camera, segment=segment)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        events = simulate(scene, duration, seed=0, **_SIM).events()
    return cm.ContrastMaximization(events, warp=warp, camera=camera, regularizers=regularizers)


@pytest.mark.parametrize("warp", ["translation2", "rotation3", "mitrokhin4"])
def test_a_view_of_factor_one_is_the_problem(warp):
    """The view's scaling (events, centre and focal lengths about the image centre; velocities by
    1 / factor) is the identity at factor 1: the same J everywhere, regularizers included."""
    x, y, t, p = edge_events(n=800, seed=3)
    events = cm.Events(x, y, t, p, SENSOR)
    prob = cm.ContrastMaximization(events, warp=warp, camera=CAMERA, regularizers={"divergence": 1.0})
    view = pyramid.coarse_view(prob, 1)
    np.testing.assert_array_equal(pyramid.view_parameter_factors(prob, 1), 1.0)
    for scale in (0.0, 0.5, 1.0):
        theta = scale * np.asarray(THETAS[warp])
        assert view.value(theta) == pytest.approx(prob.value(theta), rel=1e-12)


def test_coarse_views_share_the_fields_and_kernels_of_the_problem():
    """A coarse view runs on the problem's pooled fields and compiled kernels: nothing is compiled for
    it. Its events are the original ones scaled by 1 / k about the image centre (a subsample of them,
    first and last kept), and the centre of its warps scaled alike."""
    x, y, t, p = edge_events(n=3000, seed=4)
    prob = cm.ContrastMaximization(cm.Events(x, y, t, p, SENSOR), warp="mitrokhin4", regularizers=BOTH)
    schedules = prob._fused._schedules
    view = pyramid.coarse_view(prob, 4, max_events=1000)
    assert view._fused._ws is prob._fused._ws and view._fused._schedules is schedules
    assert view.n_events == 1000 and view.duration == prob.duration
    W, H = SENSOR
    c = np.array([(W - 1) / 2, (H - 1) / 2])
    np.testing.assert_allclose(view.events.x[[0, -1]], c[0] + (prob.events.x[[0, -1]] - c[0]) / 4)
    np.testing.assert_allclose(view.center, c)  # the image centre stays where it is
    np.testing.assert_allclose(pyramid.view_parameter_factors(prob, 4), [0.25, 0.25, 1.0, 1.0])
    assert view.value(np.zeros(4)) == pytest.approx(1.0)  # normalised by its own identity


def test_factors_follow_the_box():
    x, y, t, p = edge_events(n=500)
    small = cm.ContrastMaximization(cm.Events(x, y, t, p, SENSOR), warp="translation2")
    s = parameter_scales(small)
    half = search_bounds(small)[1] * s  # 32 px for a 64x48 sensor
    assert pyramid.coarse_factors(small, half) == [4, 2]
    assert pyramid.coarse_factors(small, half * 40) == [128, 32, 8, 2]  # at most MAX_LEVELS views
    assert pyramid.coarse_factors(small, np.array([4.0, 4.0])) == []  # a box of a few px: no view


@pytest.mark.slow
@pytest.mark.parametrize(
    "warp,theta,regularizers",
    [
        ("translation2", (2000.0, -1000.0), None),  # 40 x 20 px over the window
        ("rotation3", (3.0, -4.0, 8.0), None),
        ("mitrokhin4", (1500.0, -800.0, 0.0, 0.0), BOTH),  # the 4-DOF collapse-enabled model
    ],
)
def test_first_window_on_the_simulator(warp, theta, regularizers):
    prob = simulated(warp, theta, 0.02, regularizers=regularizers)
    res = cm.maximize(prob)
    ref = thorough(prob)
    assert res.init == "pyramid" and res.method == "bfgs"
    assert res.n_evaluations <= MAX_EVALUATIONS < ref.n_evaluations, (res, ref)
    assert res.value >= MIN_J_RATIO * ref.value, (res, ref)
    assert area_scale(prob, res.theta) > COLLAPSE_AREA_SCALE


@pytest.mark.slow
def test_no_collapse_with_both_regularizers():
    """The 4-DOF example that collapses without regularizers: with both (lambda = 10) the search lands
    on the lateral motion, not in the collapse, in at most 150 evaluations."""
    from cmax_taichi.sim.examples import make_example

    example = make_example("collapse")
    window = next(iter(example.events.windows_by_duration(example.example.window)))
    prob = cm.ContrastMaximization(window, warp="mitrokhin4", camera=example.camera, regularizers=BOTH)
    res = cm.maximize(prob)
    assert res.n_evaluations <= MAX_EVALUATIONS
    assert area_scale(prob, res.theta) > 0.95  # no shrinking of the events' areas
    assert res.value >= MIN_J_RATIO * thorough(prob).value
    np.testing.assert_allclose(res.theta[:2], example.truth[:2], atol=30.0)  # px/s, 25 ms window


@pytest.mark.slow
def test_a_moderate_zoom_is_found_where_the_coarse_views_prefer_the_collapse():
    """Without regularizers, the coarse views of a zoom prefer the collapse at the edge of the box
    (all events into the centre: sharp at every scale); the true zoom's peak shows on the finest view
    only, which therefore also climbs from the identity."""
    prob = simulated("zoom1", (8.0,), 0.02)
    res = cm.maximize(prob)
    ref = thorough(prob)
    assert res.n_evaluations <= MAX_EVALUATIONS
    assert res.value >= MIN_J_RATIO * ref.value, (res, ref)
    assert res.theta[0] == pytest.approx(8.0, abs=2.0)


def test_on_a_shared_cut_and_in_a_sequence():
    """slider_depth's first 5,000-event window (what ``bench --realtime`` starts with)."""
    from cmax_taichi import io

    folder = shared_data_dir("ecd_slider_depth")
    with io.open_recording(folder) as rec:
        window = next(iter(rec.windows(n_events=5000)))
        camera = rec.camera
    prob = cm.ContrastMaximization(window, warp="translation2", camera=camera)
    res = cm.maximize(prob)
    assert res.n_evaluations <= MAX_EVALUATIONS
    assert res.value >= MIN_J_RATIO * thorough(prob).value
    from cmax_taichi.solve.sequence import process

    result = process(folder, "translation2", n_events=5000, max_windows=2, progress=False)
    assert result.windows[0].search == "global" and result.windows[0].evaluations <= MAX_EVALUATIONS
    np.testing.assert_allclose(result.windows[0].theta, res.theta, atol=2.0)


def test_the_evaluation_budget_stops_the_local_runs():
    x, y, t, p = edge_events(n=1500, seed=5)
    prob = cm.ContrastMaximization(cm.Events(x, y, t, p, SENSOR), warp="translation2")
    free = cm.maximize(prob, max_evaluations=10_000)
    search_only = cm.maximize(prob, max_iter=0).n_evaluations
    assert free.n_evaluations > search_only + 3
    capped = cm.maximize(prob, max_evaluations=search_only + 3)
    assert capped.n_evaluations <= search_only + 3
    assert not capped.converged and "max_evaluations" in capped.message
    assert capped.value >= capped.value_init  # the best iterate so far
    with pytest.raises(ValueError, match="max_evaluations"):
        cm.maximize(prob, max_evaluations=0)
