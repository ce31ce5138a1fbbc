"""maximize(): the three local methods and the global searches recover known motion on synthetic
events; scales, bounds, warm start, history, stopping rules and bad arguments."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi.solve.optimize import parameter_scales, search_bounds

pytestmark = pytest.mark.usefixtures("f64")

SENSOR = (64, 48)
V_TRUE = np.array([120.0, -60.0])  # px/s


def moving_edges(v=V_TRUE, n=1500, duration=0.04, seed=0, sensor=SENSOR):
    """Events of a few straight edges of random orientation translating at ``v`` px/s."""
    rng = np.random.default_rng(seed)
    W, H = sensor
    k = 6
    centres = rng.uniform([12, 10], [W - 12, H - 10], size=(k, 2))
    angles = rng.uniform(0, np.pi, size=k)
    which = rng.integers(0, k, n)
    s = rng.uniform(-8, 8, n)
    t = np.sort(rng.uniform(0, duration, n))
    x = centres[which, 0] + s * np.cos(angles[which]) + v[0] * (t - duration / 2) + rng.normal(0, 0.2, n)
    y = centres[which, 1] + s * np.sin(angles[which]) + v[1] * (t - duration / 2) + rng.normal(0, 0.2, n)
    keep = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    return cm.Events(x[keep], y[keep], t[keep], rng.integers(0, 2, n)[keep], sensor)


def _hat(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def _expm_so3(w):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(w).as_matrix()


def rotating_points(w, camera, n=3000, n_points=80, duration=0.05, seed=1, sensor=SENSOR):
    """Events of static scene points seen by a camera rotating at ``w`` (rad/s, camera frame), with the
    convention of docs/FORMULAS.md: bearing_ref = exp(hat(w) (t - t_ref)) bearing_t, t_ref = 0."""
    pytest.importorskip("scipy")
    rng = np.random.default_rng(seed)
    W, H = sensor
    K = camera.K
    px = rng.uniform([4, 4], [W - 5, H - 5], size=(n_points, 2))
    bearings = np.linalg.solve(K, np.c_[px, np.ones(n_points)].T).T  # at t_ref = 0
    which = rng.integers(0, n_points, n)
    t = np.sort(rng.uniform(0, duration, n))
    xs, ys = np.empty(n), np.empty(n)
    for k in range(n):
        b = _expm_so3(-np.asarray(w) * t[k]) @ bearings[which[k]]
        q = K @ (b / b[2])
        xs[k], ys[k] = q[0], q[1]
    keep = (xs >= 0) & (xs <= W - 1) & (ys >= 0) & (ys <= H - 1)
    return cm.Events(xs[keep], ys[keep], t[keep], np.ones(int(keep.sum())), sensor, undistorted=True)


@pytest.fixture(scope="module")
def edges():
    return moving_edges()


def test_scales_and_bounds_follow_the_units(edges):
    T = edges.duration
    prob = cm.ContrastMaximization(edges, warp="translation2")
    np.testing.assert_allclose(parameter_scales(prob), [T, T])
    lo, hi = search_bounds(prob)
    np.testing.assert_allclose(hi, 0.5 * max(SENSOR) / T)  # half the image per window
    np.testing.assert_allclose(lo, -hi)
    zoom = cm.ContrastMaximization(edges, warp="zoom1")
    W, H = SENSOR
    r = math.sqrt((W * W - 1) / 12 + (H * H - 1) / 12)  # RMS radius about the image centre
    np.testing.assert_allclose(parameter_scales(zoom), [T * r])
    np.testing.assert_allclose(search_bounds(zoom)[1] * T, [1.0])  # |h_z T| <= 1
    cam = cm.Camera(fx=50.0, fy=52.0, cx=31.5, cy=23.5)
    rot = cm.ContrastMaximization(edges, warp="rotation3", camera=cam)
    f = math.sqrt(50.0 * 52.0)
    np.testing.assert_allclose(parameter_scales(rot)[:2], [T * f, T * f])


@pytest.mark.parametrize("method", ["adam", "armijo", "lbfgs"])
def test_methods_recover_translation(edges, method):
    prob = cm.ContrastMaximization(edges, warp="translation2")
    res = cm.maximize(prob, method=method)
    assert np.all(np.abs(res.theta - V_TRUE) < 0.05 * np.linalg.norm(V_TRUE)), res
    assert res.value > prob.value([0.0, 0.0]) and res.value >= res.value_init
    assert res.param_names == ("v_x", "v_y") and res.units == ("px/s", "px/s")
    # the history is the winning local run: iteration 0 is its start, theta in physical units
    assert len(res.history) == res.n_iterations + 1
    assert res.history.theta.shape == (len(res.history), 2)
    np.testing.assert_allclose(res.history.theta[0], res.theta_init)
    assert res.value == pytest.approx(np.max(res.history.value))
    assert res.seconds > 0 and res.n_evaluations > res.n_iterations
    assert isinstance(res.converged, bool) and res.message


def test_random_search_and_no_search(edges):
    prob = cm.ContrastMaximization(edges, warp="translation2")
    res = cm.maximize(prob, init="random", n_init=200, seed=3)
    assert np.all(np.abs(res.theta - V_TRUE) < 6.0)
    # without a global search, a start in the basin still converges; far away it need not
    near = cm.maximize(prob, theta0=V_TRUE + [15.0, -10.0], init="none")
    assert np.all(np.abs(near.theta - V_TRUE) < 6.0)
    assert near.init == "none"


def test_warm_start_searches_locally(edges):
    prob = cm.ContrastMaximization(edges, warp="translation2")
    cold = cm.maximize(prob)
    warm = cm.maximize(prob, theta0=cold.theta + [5.0, 5.0])
    assert warm.init == "local" and cold.init == "pyramid"
    assert warm.n_evaluations < cm.maximize(prob, init="grid", max_iter=0).n_evaluations
    assert np.allclose(warm.theta, cold.theta, atol=3.0)


def test_stopping_rules_and_callback(edges):
    prob = cm.ContrastMaximization(edges, warp="translation2")
    short = cm.maximize(prob, init="none", theta0=[100.0, -50.0], max_iter=3, n_starts=1)
    assert short.n_iterations == 3 and not short.converged and "max_iter" in short.message
    calls = []

    def stop_after_two(k, theta, value):
        calls.append((k, theta.copy(), value))
        return k >= 2

    res = cm.maximize(prob, init="none", theta0=[100.0, -50.0], callback=stop_after_two, n_starts=1)
    assert res.n_iterations == 2 and "callback" in res.message
    assert [c[0] for c in calls] == [0, 1, 2]
    loose = cm.maximize(prob, init="none", theta0=[100.0, -50.0], method="armijo", gtol=1e3)
    assert loose.converged and "gradient norm" in loose.message and loose.n_iterations == 0


def test_rotation_recovered_from_rotating_points():
    cam = cm.Camera(fx=60.0, fy=60.0, cx=31.5, cy=23.5)
    w_true = np.array([0.6, -0.9, 1.5])  # rad/s
    events = rotating_points(w_true, cam)
    prob = cm.ContrastMaximization(events, warp="rotation3", camera=cam)
    res = cm.maximize(prob, method="adam", n_init=343)
    assert np.linalg.norm(res.theta - w_true) < 0.1 * np.linalg.norm(w_true), res


def test_bad_arguments(edges, monkeypatch):
    prob = cm.ContrastMaximization(edges, warp="translation2")
    with pytest.raises(ValueError, match="unknown method 'newton'.*adam"):
        cm.maximize(prob, method="newton")
    with pytest.raises(ValueError, match="unknown init"):
        cm.maximize(prob, init="everywhere")
    with pytest.raises(ValueError, match=r"takes 2 parameter\(s\), got theta0 of length 3"):
        cm.maximize(prob, theta0=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="lr must be a positive"):
        cm.maximize(prob, lr=0.0)
    with pytest.raises(ValueError, match="bounds"):
        cm.maximize(prob, bounds=([1.0, 1.0], [0.0, 2.0]))
    with pytest.raises(TypeError, match="ContrastMaximization"):
        cm.maximize("not a problem")
    monkeypatch.setitem(sys.modules, "scipy.optimize", None)
    with pytest.raises(ImportError, match="needs SciPy"):
        cm.maximize(prob, method="lbfgs", init="none")


def test_tpe_search(edges, monkeypatch):
    prob = cm.ContrastMaximization(edges, warp="translation2")
    try:
        import optuna  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="needs optuna"):
            cm.maximize(prob, init="tpe")
        pytest.skip("optuna is not installed (optional extra 'tpe'): checked the error message only")
    res = cm.maximize(prob, init="tpe", n_init=80, seed=1)
    assert np.all(np.abs(res.theta - V_TRUE) < 6.0)


def test_far_warm_start_never_ends_below_the_identity():
    """A warm start far outside the search box (6000 px/s) gave J = 0.09 < J(identity) = 1
    reported as converged, because the identity was clipped into the local box and never evaluated."""
    prob = cm.ContrastMaximization(moving_edges(), "translation2")
    j_identity = prob.value([0.0, 0.0])
    for init in ("auto", "local", "warm"):
        method = "bfgs" if init == "warm" else "adam"
        res = cm.maximize(prob, theta0=[6000.0, 0.0], init=init, method=method)
        assert res.value >= j_identity, (init, res)
        assert res.value_identity == pytest.approx(j_identity)
        assert np.allclose(res.theta, V_TRUE, atol=10.0), (init, res.theta)


def test_warm_refinement_converges_in_few_evaluations():
    prob = cm.ContrastMaximization(moving_edges(), "translation2")
    res = cm.maximize(prob, theta0=V_TRUE + [15.0, -10.0], init="warm", method="bfgs")
    assert res.converged and res.init == "warm" and res.method == "bfgs"
    assert res.n_evaluations <= 25, res
    assert np.allclose(res.theta, V_TRUE, atol=6.0), res.theta
    # the candidates (earlier estimates) are evaluated with theta0 and the identity
    far = cm.maximize(prob, theta0=[-300.0, 200.0], init="warm", method="bfgs", candidates=[V_TRUE])
    assert np.allclose(far.theta, V_TRUE, atol=6.0), far.theta
    with pytest.raises(ValueError, match="init='warm' refines a warm start: pass theta0"):
        cm.maximize(prob, init="warm")
    with pytest.raises(ValueError, match=r"takes 2 parameter\(s\), got candidates\[0\] of length 1"):
        cm.maximize(prob, theta0=V_TRUE, init="warm", candidates=[[1.0]])


def test_bfgs_hands_its_curvature_to_the_next_window():
    """A warm refinement started with the previous window's inverse Hessian takes a quasi-Newton first
    step: no more evaluations than from a gradient step, the same estimate."""
    first = cm.ContrastMaximization(moving_edges(seed=0), "translation2")
    second = cm.ContrastMaximization(moving_edges(seed=3), "translation2")
    r1 = cm.maximize(first, theta0=V_TRUE + [10.0, 5.0], init="warm", method="bfgs")
    assert r1.hess_inv is not None and r1.hess_inv.shape == (2, 2)
    assert np.all(np.linalg.eigvalsh(r1.hess_inv) > 0)
    start = r1.theta + [8.0, -6.0]
    cold = cm.maximize(second, theta0=start, init="warm", method="bfgs")
    warm = cm.maximize(second, theta0=start, init="warm", method="bfgs", hess_inv0=r1.hess_inv)
    assert warm.converged and warm.n_evaluations <= cold.n_evaluations, (warm, cold)
    assert np.allclose(warm.theta, cold.theta, atol=1.0), (warm.theta, cold.theta)
    assert cm.maximize(second, init="grid", n_init=50, max_iter=5, method="adam").hess_inv is None  # none
    with pytest.raises(ValueError, match="hess_inv0 must be a finite symmetric positive definite 2x2"):
        cm.maximize(second, theta0=start, init="warm", method="bfgs", hess_inv0=-np.eye(2))
    with pytest.raises(ValueError, match="hess_inv0 must be a finite symmetric positive definite 2x2"):
        cm.maximize(second, theta0=start, init="warm", method="bfgs", hess_inv0=np.eye(3))
    with pytest.raises(ValueError, match="hess_inv0 is the initial inverse Hessian of method='bfgs'"):
        cm.maximize(second, theta0=start, method="adam", hess_inv0=np.eye(2))


@pytest.mark.parametrize("regularizers", [{"divergence": 10.0, "deformation": 10.0}, {"divergence": 10.0}])
def test_warm_refinement_moves_off_a_regularizer_kink(regularizers):
    """The divergence penalty's hinge makes a kink of J at h_z = 0: the gradient of one side points
    across it, so every step along it descended and the warm BFGS refinement stopped where it started
    (0 iterations on every MVSEC window with both regularizers). It now holds h_z at the kink and
    refines the other parameters."""
    prob = cm.ContrastMaximization(moving_edges(), "mitrokhin4", regularizers=regularizers)
    for offset in ([15.0, -10.0], [-20.0, 12.0]):
        start = np.r_[V_TRUE + offset, 0.0, 0.0]
        res = cm.maximize(prob, theta0=start, init="warm", method="bfgs")
        assert res.n_iterations > 0 and res.value > prob.value(start), res
        # within 0.5 px over the 40 ms window of the truth (the regularized optimum is not exactly it)
        assert np.allclose(res.theta[:2], V_TRUE, atol=12.0), res.theta
        assert res.n_evaluations <= 25, res
