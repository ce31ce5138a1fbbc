"""Per-event Jacobian determinant and divergence: closed forms against Taichi autodiff, against the
reference, and against known values; dense flow against the reference."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CAMERA, SENSOR, THETAS, edge_events

import cmax_taichi as cm
from cmax_taichi.testing import reference

pytestmark = pytest.mark.usefixtures("f64")


def _problem(warp, seed=1, n=300):
    x, y, t, p = edge_events(n=n, seed=seed)
    return cm.ContrastMaximization(cm.Events(x, y, t, p, SENSOR), warp=warp, camera=CAMERA), (
        x,
        y,
        t,
    )


@pytest.mark.parametrize("warp", list(THETAS))
def test_closed_form_equals_autodiff(warp):
    prob, _ = _problem(warp)
    rng = np.random.default_rng(3)
    for scale in (1.0, 3.0):
        theta = np.asarray(THETAS[warp]) * scale * rng.uniform(0.5, 1.5, len(THETAS[warp]))
        closed = cm.event_jacobians(prob, theta, method="closed")
        ad = cm.event_jacobians(prob, theta, method="autodiff")
        np.testing.assert_allclose(closed["det"], ad["det"], rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(closed["div"], ad["div"], rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("warp", list(THETAS))
def test_closed_form_equals_reference(warp):
    prob, (x, y, t) = _problem(warp)
    theta = np.asarray(THETAS[warp])
    closed = cm.event_jacobians(prob, theta)
    xw, yw, det, div = reference.warp_events(
        warp,
        x,
        y,
        t - t[0],
        theta,
        center=(CAMERA.cx, CAMERA.cy),
        focal=(CAMERA.fx, CAMERA.fy),
        duration=t[-1] - t[0],
    )
    np.testing.assert_allclose(closed["det"], det, rtol=1e-10)
    np.testing.assert_allclose(closed["div"], div, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("warp", list(THETAS))
def test_identity_is_area_preserving(warp):
    prob, _ = _problem(warp)
    out = cm.event_jacobians(prob, np.zeros(len(THETAS[warp])), method="autodiff")
    np.testing.assert_allclose(out["det"], 1.0, atol=1e-12)
    np.testing.assert_allclose(out["div"], 0.0, atol=1e-12)
    np.testing.assert_allclose(out["jacobian"], np.broadcast_to(np.eye(2), out["jacobian"].shape), atol=1e-12)


def test_known_values():
    prob, (x, y, t) = _problem("zoom1")
    dt = t - t[0]
    h = 7.0
    out = cm.event_jacobians(prob, [h], method="autodiff")
    np.testing.assert_allclose(out["det"], (1 - dt * h) ** 2, rtol=1e-12)
    np.testing.assert_allclose(out["div"], 2 * h, rtol=1e-12)
    for warp in ("translation2", "se2"):
        prob, _ = _problem(warp)
        out = cm.event_jacobians(prob, THETAS[warp], method="autodiff")
        np.testing.assert_allclose(out["det"], 1.0, atol=1e-12)
        np.testing.assert_allclose(out["div"], 0.0, atol=1e-10)
    prob, _ = _problem("sim2")
    out = cm.event_jacobians(prob, [10.0, -5.0, 2.0, 3.0], method="autodiff")
    np.testing.assert_allclose(out["det"], np.exp(-2 * dt * 3.0), rtol=1e-12)
    np.testing.assert_allclose(out["div"], 6.0, rtol=1e-12)


@pytest.mark.parametrize("warp", list(THETAS))
def test_first_order_connection(warp):
    """det J ~ 1 - dt div v for small dt (SPEC: connection between the two maps)."""
    x, y, t, p = edge_events(n=200, seed=4)
    t = t * 1e-4 / t[-1]  # a 0.1 ms window
    prob = cm.ContrastMaximization(cm.Events(x, y, t, p, SENSOR), warp=warp, camera=CAMERA)
    theta = np.asarray(THETAS[warp])
    if warp == "mitrokhin4":
        theta = theta * 1.0  # T is the window duration here; theta per second still moderate
    out = cm.event_jacobians(prob, theta)
    dt = t - t[0]
    np.testing.assert_allclose(out["det"], 1 - dt * out["div"], atol=5e-6)


@pytest.mark.parametrize("warp", list(THETAS))
def test_dense_flow_matches_reference(warp):
    theta = THETAS[warp]
    got = cm.dense_flow(warp, theta, SENSOR, camera=CAMERA, duration=0.05)
    want = reference.flow_field(
        warp,
        theta,
        width=SENSOR[0],
        height=SENSOR[1],
        center=(CAMERA.cx, CAMERA.cy),
        focal=(CAMERA.fx, CAMERA.fy),
        duration=0.05,
    )
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-9)
    # displacement over a short interval ~ flow * dt
    dt = 1e-4
    disp = cm.dense_flow(warp, theta, SENSOR, camera=CAMERA, duration=0.05, dt=dt)
    np.testing.assert_allclose(disp / dt, want, rtol=1e-3, atol=1e-3 * np.abs(want).max())


def test_user_registered_warp_uses_autodiff_fallbacks():
    """A warp registered without closed forms gets finite-difference det/div that match autodiff."""
    import taichi as ti

    @ti.func
    def shear_warp(p, dt, th, ctx):
        return ti.Vector([p[0] - dt * th[0] * (p[1] - ctx[1]), p[1] - dt * th[1] * (p[0] - ctx[0])])

    @ti.func
    def shear_flow(p, th, ctx):
        return ti.Vector([th[0] * (p[1] - ctx[1]), th[1] * (p[0] - ctx[0])])

    model = cm.WarpModel("test_shear2", ("a", "b"), ("1/s", "1/s"), shear_warp, shear_flow)
    cm.register_warp(model, replace=True)
    assert "test_shear2" in cm.warp_names()
    prob, (x, y, t) = _problem("test_shear2")
    theta = [3.0, -2.0]
    closed = cm.event_jacobians(prob, theta)
    ad = cm.event_jacobians(prob, theta, method="autodiff")
    dt = t - t[0]
    np.testing.assert_allclose(ad["det"], 1 - dt * dt * 3.0 * -2.0, rtol=1e-12)
    np.testing.assert_allclose(closed["det"], ad["det"], rtol=1e-8)
    np.testing.assert_allclose(closed["div"], ad["div"], atol=1e-8)
    value, grad = prob.value_and_grad(theta)
    assert np.isfinite(value) and np.all(np.isfinite(grad))
