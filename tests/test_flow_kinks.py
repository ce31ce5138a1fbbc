"""The kinks of the event-collapse penalties, and optimizers that get past them.

At a constant flow (and at the identity of a global warp) every event has ``div = 0`` and ``det = 1``:
the divergence's hinge ``max(0, R)`` and the deformation's ``max(D, 1/D) - 1`` sit on their kinks,
where the exact gradient is one side's. Tested here: the penalty blocks at and near the kinks (exact:
one-sided differences at the kink, central ones beside it; rounded: central differences everywhere,
the bound on the rounding); the dense problem with rounded kinks against the float64 reference at a
constant flow; the dense levels iterating from a constant-flow start where the exact penalties stall
them (and the stall reported); the global optimizer's fallback.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import taichi as ti
from cmax_taichi.kernels import blocks as kb
from cmax_taichi.kernels import maps as km
from cmax_taichi.kernels import model_checks as kmc
from conftest import SENSOR, edge_events

import cmax_taichi as cm
from cmax_taichi.core.checks import OptimizerStallWarning
from cmax_taichi.flow import DenseFlowEstimator, DenseFlowProblem, FlowGrid
from cmax_taichi.models.regularizers import REGULARIZERS
from cmax_taichi.solve import local
from cmax_taichi.solve.optimize import _settle
from cmax_taichi.testing import dense_flow_reference as ref

WIDTH = 0.05
H = 1e-6  # difference step of the pixel penalties


def _evaluate(penalty, grad, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``penalty(v)`` and ``grad(v)`` (Taichi functions) at ``values`` (float64)."""
    n = values.size
    vals = ti.field(ti.f64, shape=n)
    out = ti.field(ti.f64, shape=(2, n))
    vals.from_numpy(values.astype(np.float64))
    kmc.make_penalty_kernel(penalty, grad)(n, vals, out)
    res = out.to_numpy()
    return res[0], res[1]


def _hinge(flag):
    """The divergence's hinge ``scaled_penalty(v, 1, flag)`` and its slope, as pixel functions."""

    @ti.func
    def value(v):
        return kb.scaled_penalty(v, 1.0, flag)

    @ti.func
    def slope(v):
        return kb.scaled_penalty_slope(v, 1.0, flag)

    return value, slope


def _around(kink: float) -> np.ndarray:
    return np.array([kink - 0.3, kink - 1e-3, kink, kink + 1e-3, kink + 0.3])


@pytest.mark.parametrize("which", ["deformation", "hinge"])
def test_exact_penalty_gradient_is_the_one_sided_difference_at_the_kink(f64, which):
    kink = 1.0 if which == "deformation" else 0.0
    fns = (km.deformation_penalty, km.deformation_penalty_grad) if which == "deformation" else _hinge(True)
    at = _around(kink)
    value, grad = _evaluate(*fns, at)
    left = (value - _evaluate(*fns, at - H)[0]) / H
    right = (_evaluate(*fns, at + H)[0] - value) / H
    # beside the kink: differentiable, the gradient is the central difference (both sides agree)
    beside = np.abs(at - kink) > 0
    np.testing.assert_allclose(grad[beside], left[beside], atol=1e-5)
    np.testing.assert_allclose(grad[beside], right[beside], atol=1e-5)
    # at the kink the one-sided differences differ, and the gradient is the left one (Taichi's side)
    k = int(np.flatnonzero(~beside)[0])
    assert right[k] - left[k] == pytest.approx(1.0 if which == "hinge" else 2.0, abs=1e-5)
    assert grad[k] == pytest.approx(left[k], abs=1e-5)


@pytest.mark.parametrize("which", ["deformation", "hinge"])
def test_rounded_penalty_is_smooth_and_within_its_bound(f64, which):
    kink = 1.0 if which == "deformation" else 0.0
    if which == "deformation":
        rounded, exact = km.rounded_deformation_penalty(WIDTH), (km.deformation_penalty, None)
    else:
        rounded, exact = _hinge(WIDTH), (_hinge(True)[0], None)
    at = np.concatenate([_around(kink), kink + np.linspace(-0.2, 0.2, 81)])
    value, grad = _evaluate(*rounded, at)
    central = (_evaluate(*rounded, at + H)[0] - _evaluate(*rounded, at - H)[0]) / (2 * H)
    np.testing.assert_allclose(grad, central, atol=1e-5)  # at the kink too: C1
    ex = _evaluate(exact[0], None, at)[0]
    excess = value - ex
    assert np.all(excess >= -1e-12) and np.all(excess <= WIDTH / 4 + 1e-12)
    assert excess[np.argmin(np.abs(at - kink))] == pytest.approx(WIDTH / 4, rel=1e-9)  # most at the kink
    # exact outside the band (|D - 1/D| >= width, |R| >= width)
    z = at - 1.0 / at if which == "deformation" else at
    np.testing.assert_allclose(excess[np.abs(z) >= WIDTH * (1 + 1e-9)], 0.0, atol=1e-12)
    # the slope at the kink is the mean of the exact one-sided slopes (0 for the deformation, 1/2 hinge)
    assert grad[np.argmin(np.abs(at - kink))] == pytest.approx(
        0.0 if which == "deformation" else 0.5, abs=1e-12
    )


def test_rounded_kinks_are_one_instance_per_width():
    reg = REGULARIZERS.get("deformation")
    assert reg.with_rounded_kinks(0.0) is reg and reg.hinge is False
    rounded = reg.with_rounded_kinks(WIDTH)
    assert rounded is reg.with_rounded_kinks(WIDTH) and rounded.kink_width == WIDTH
    assert REGULARIZERS.get("divergence").with_rounded_kinks(WIDTH).hinge == WIDTH
    assert REGULARIZERS.get("divergence").hinge is True
    with pytest.raises(ValueError, match="finite and >= 0"):
        reg.with_rounded_kinks(-1.0)
    with pytest.raises(ValueError, match="finite and >= 0"):
        DenseFlowProblem(cm.Events(*edge_events(n=50), SENSOR), (2, 2), kink_width=math.nan)


@pytest.mark.parametrize("refs", ["first", "multi"])
def test_rounded_dense_problem_against_the_reference_at_a_constant_flow(f64, refs):
    """Every event on both kinks: the rounded J and its gradient against the float64 reference (central
    differences), there and a little beside it; the exact terms and J_rounded from evaluate()."""
    x, y, t, p = edge_events(n=400, seed=3)
    events = cm.Events(x, y, t, p, SENSOR)
    grid = FlowGrid(*SENSOR, 3, 2)
    regs = {"divergence": 10.0, "deformation": 10.0}
    prob = DenseFlowProblem(events, grid, references=refs, regularizers=regs, kink_width=WIDTH)
    exact = DenseFlowProblem(events, grid, references=refs, regularizers=regs)
    from cmax_taichi.flow import resolve_references

    fractions, omega = resolve_references(refs)
    kwargs = dict(
        grid=(3, 2),
        sensor_size=SENSOR,
        references=fractions,
        reference_weights=omega,
        objective="gradient_magnitude",
        lambda_div=10.0,
        lambda_def=10.0,
        kink_width=WIDTH,
    )
    constant = np.broadcast_to(np.array([30.0, -12.0]), grid.shape).copy()
    beside = constant + np.random.default_rng(0).normal(0.0, 0.05, grid.shape)
    for U in (constant, beside):
        value, grad = prob.value_and_grad(U)
        expected = ref.dense_evaluate(x, y, t, p, U, **kwargs)
        assert value == pytest.approx(expected["J"], abs=1e-10)
        fd = ref.central_difference_grad(x, y, t, p, U, step=1e-4, **kwargs)
        assert np.max(np.abs(grad - fd)) <= 1e-6 * max(np.max(np.abs(fd)), 1e-12)
        ev, ev_exact = prob.evaluate(U), exact.evaluate(U)
        assert pytest.approx(ev_exact.J, abs=1e-12) == ev.J and ev.penalties == pytest.approx(
            ev_exact.penalties
        )
        assert ev.J_rounded == pytest.approx(value, abs=1e-12)
        assert 0.0 <= ev.J - ev.J_rounded <= 2 * 10.0 * WIDTH / 4 + 1e-12  # two penalties, lambda 10
    # at the constant flow the exact gradient is one side's and the rounded one the mean: they differ
    assert not np.allclose(exact.value_and_grad(constant)[1], prob.value_and_grad(constant)[1])


def _constant_start_scene():
    from cmax_taichi.testing.flow_scenes import depth_scene

    scene = depth_scene(SENSOR, duration=0.05, displacement=(4.0, 1.5), n_events=6000, seed=0)
    translation = cm.maximize(
        cm.ContrastMaximization(scene.events, warp="translation2", objective="gradient_magnitude")
    )
    return scene, np.asarray(translation.theta, dtype=np.float64)


def _aee(flow: np.ndarray, scene) -> float:
    from cmax_taichi.metrics import event_mask, flow_error

    return flow_error(flow, scene.displacement(), event_mask(scene.events))["AEE"]


def test_every_level_iterates_from_a_constant_flow_start(f64):
    """t_ref at the first event, divergence 10 + deformation 10, started at the best global
    translation: with the exact penalties L-BFGS-B stalls on the kinks (reported: status, warning);
    with the rounded ones every level iterates, and the flow is no worse than the translation."""
    scene, v = _constant_start_scene()
    options = dict(references="first", regularizers={"divergence": 10.0, "deformation": 10.0}, levels=2)
    start = np.broadcast_to(v, FlowGrid(*SENSOR, 4, 4).pyramid(2)[0].shape).copy()
    with pytest.warns(OptimizerStallWarning, match="ended at its start"):
        stalled = DenseFlowEstimator((4, 4), kink_width=0.0, **options).estimate(scene.events, init=start)
    assert stalled.status == "stalled" and stalled.stalled_levels
    assert all(stalled.levels[k].change == 0.0 for k in stalled.stalled_levels)
    assert stalled.as_dict()["levels"][stalled.stalled_levels[0]]["status"] == "stalled"

    with warnings.catch_warnings():
        warnings.simplefilter("error", OptimizerStallWarning)
        res = DenseFlowEstimator((4, 4), **options).estimate(scene.events, init=start)
    assert res.status == "ok"
    for lv in res.levels:
        assert lv.status in ("converged", "limit", "fallback") and lv.iterations >= 1 and lv.change > 0.0
        assert lv.value > lv.value_start
    constant = np.broadcast_to(v, res.grid.shape).copy()
    assert res.evaluation.J_rounded > DenseFlowProblem(
        scene.events, res.grid, references="first", regularizers=options["regularizers"], kink_width=0.01
    ).value(constant)
    assert _aee(res.displacement(), scene) <= _aee(res.grid.dense(constant) * scene.duration, scene)


class _KinkedObjective:
    """``J(u) = -|u0| + 0.5 u0 - (u1 - 1)^2`` with the gradient of ``u0``'s left side at the kink (as the
    exact penalties give it): the gradient at ``(0, 1)`` says go left, the right side ascends."""

    def __init__(self) -> None:
        self.exhausted = False
        self.n = 0

    def value(self, u):
        self.n += 1
        return -abs(u[0]) + 0.5 * u[0] - (u[1] - 1.0) ** 2

    def value_and_grad(self, u):
        g0 = (-1.0 if u[0] > 0 else 1.0) + 0.5
        return self.value(u), np.array([g0, -2.0 * (u[1] - 1.0)])

    def theta(self, u):
        return u


def test_global_fallback_gets_past_a_kink_or_certifies_a_maximum():
    obj = _KinkedObjective()
    lo, hi = np.full(2, -10.0), np.full(2, 10.0)
    start = np.array([0.0, 1.0])
    rec = local.Recorder(None, obj)
    run = local.armijo(obj, start, lo, hi, lr=1.0, max_iter=20, gtol=1e-9, xtol=1e-3, rtol=1e-12, rec=rec)
    # the left side's slope is +1.5 there: Armijo steps right, where J falls by -0.5 per px
    assert run.failed and not run.converged and np.array_equal(run.u, start)
    settled, status = _settle(
        obj,
        run,
        start,
        "armijo",
        lo,
        hi,
        lr=1.0,
        max_iter=20,
        gtol=1e-9,
        xtol=1e-3,
        rtol=1e-12,
        callback=None,
    )
    # J(u0 < 0) = 1.5 u0 falls too: the kink is a maximum along u0, certified by the one-sided steps
    assert status == "converged" and settled.converged and "a maximum" in settled.message

    class Ascending(_KinkedObjective):  # the right side now ascends: J = -|u0| + 1.5 u0 - ...
        def value(self, u):
            return super().value(u) + u[0]

        def value_and_grad(self, u):
            v, g = super().value_and_grad(u)
            g[0] = 1.0 - 1.0 + 0.5 if u[0] <= 0 else g[0] + 1.0  # the left side's slope 0.5 - 1 + 1
            return self.value(u), g

    obj = Ascending()
    rec = local.Recorder(None, obj)
    run = local.lbfgs(obj, np.array([0.0, 1.0]), lo, hi, max_iter=20, gtol=1e-9, rtol=1e-12, rec=rec)
    settled, status = _settle(
        obj, run, start, "lbfgs", lo, hi, lr=1.0, max_iter=20, gtol=1e-9, xtol=1e-3, rtol=1e-12, callback=None
    )
    assert settled.value >= run.value
    assert status in ("fallback", "converged", "limit")


def test_maximize_reports_its_status(f64):
    x, y, t, p = edge_events(n=2000, seed=1)
    prob = cm.ContrastMaximization(
        cm.Events(x, y, t, p, SENSOR), warp="zoom1", regularizers={"divergence": 10.0, "deformation": 10.0}
    )
    res = cm.maximize(prob, method="lbfgs")  # L-BFGS-B fails at zoom 0, where every det is 1
    assert res.status in ("converged", "fallback") and "fallback" in res.message
    assert res.as_dict()["status"] == res.status
