"""Bad input gives a clear ValueError / TypeError naming the problem; collapse stays finite."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SENSOR, edge_events

import cmax_taichi as cm

pytestmark = pytest.mark.usefixtures("f64")


def _events(n=200):
    x, y, t, p = edge_events(n=n, seed=2)
    return cm.Events(x, y, t, p, SENSOR)


def test_events_validation():
    x, y, t, p = edge_events(n=50)
    with pytest.raises(ValueError, match="same length"):
        cm.Events(x[:-1], y, t, p, SENSOR)
    bad = x.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        cm.Events(bad, y, t, p, SENSOR)
    bad_t = t.copy()
    bad_t[5] = np.inf
    with pytest.raises(ValueError, match="non-finite"):
        cm.Events(x, y, bad_t, p, SENSOR)
    with pytest.raises(TypeError, match="numeric"):
        cm.Events(x.astype(str), y, t, p, SENSOR)
    with pytest.raises(ValueError, match="polarities"):
        cm.Events(x, y, t, p * 3, SENSOR)
    with pytest.raises(ValueError, match="one-dimensional"):
        cm.Events(x.reshape(5, 10), y, t, p, SENSOR)
    with pytest.raises(ValueError, match="sensor_size"):
        cm.Events(x, y, t, p, (0, 10))


def test_events_sorting_and_dropping_warn():
    x, y, t, p = edge_events(n=50)
    with pytest.warns(RuntimeWarning, match="sorting"):
        ev = cm.Events(x, y, t[::-1], p, SENSOR)
    assert np.all(np.diff(ev.t) >= 0)
    xo = x.copy()
    xo[:3] = 1000.0
    with pytest.warns(RuntimeWarning, match="dropped 3"):
        ev = cm.Events(xo, y, t, p, SENSOR)
    assert len(ev) == 47 and ev.n_dropped == 3
    # the caller's arrays are untouched
    assert xo[0] == 1000.0


def test_problem_rejects_bad_configuration():
    ev = _events()
    with pytest.raises(ValueError, match="unknown warp 'nope'.*zoom1"):
        cm.ContrastMaximization(ev, warp="nope")
    with pytest.raises(ValueError, match="unknown objective 'sharp'.*variance"):
        cm.ContrastMaximization(ev, objective="sharp")
    with pytest.raises(ValueError, match="unknown regularizer 'tv'.*divergence"):
        cm.ContrastMaximization(ev, regularizers={"tv": 1.0})
    with pytest.raises(ValueError, match="finite and >= 0"):
        cm.ContrastMaximization(ev, regularizers={"divergence": -1.0})
    with pytest.raises(ValueError, match="needs a camera"):
        cm.ContrastMaximization(ev, warp="rotation3")
    with pytest.raises(ValueError, match="polarity"):
        cm.ContrastMaximization(ev, polarity="both")
    with pytest.raises(ValueError, match="blur_sigma"):
        cm.ContrastMaximization(ev, blur_sigma=-1)
    with pytest.raises(ValueError, match="t_ref"):
        cm.ContrastMaximization(ev, t_ref="start")
    with pytest.raises(TypeError, match="Events"):
        cm.ContrastMaximization(np.zeros((10, 4)))
    with pytest.raises(ValueError, match="weights has 3 values"):
        cm.ContrastMaximization(ev, weights=[1, 2, 3])


def test_problem_rejects_degenerate_windows():
    x, y, t, p = edge_events(n=20)
    with pytest.raises(ValueError, match="at least 2 events"):
        cm.ContrastMaximization(cm.Events(x[:0], y[:0], t[:0], p[:0], SENSOR))
    with pytest.raises(ValueError, match="at least 2 events"):
        cm.ContrastMaximization(cm.Events(x[:1], y[:1], t[:1], p[:1], SENSOR))
    with pytest.raises(ValueError, match="zero time"):
        cm.ContrastMaximization(cm.Events(x, y, np.zeros_like(t), p, SENSOR))


def test_theta_validation():
    prob = cm.ContrastMaximization(_events(), warp="mitrokhin4")
    with pytest.raises(ValueError, match="takes 4 parameter"):
        prob.value_and_grad([1.0, 2.0])
    with pytest.raises(ValueError, match="non-finite"):
        prob.value_and_grad([1.0, np.nan, 0.0, 0.0])
    with pytest.raises(TypeError, match="sequence"):
        prob.value_and_grad("abc")


@pytest.mark.parametrize(
    "warp,theta_of_T",
    [
        ("zoom1", lambda T: [1.0 / T]),
        ("zoom1", lambda T: [1.5 / T]),
        ("zoom1", lambda T: [50.0 / T]),
        ("mitrokhin4", lambda T: [0.0, 0.0, 1.0 / T, 0.0]),
        ("mitrokhin4", lambda T: [0.0, 0.0, 1e4 / T, 7.0 / T]),
        ("sim2", lambda T: [0.0, 0.0, 0.0, 200.0 / T]),
    ],
)
@pytest.mark.parametrize("objective", ["variance", "gradient_magnitude"])
def test_collapse_is_finite(warp, theta_of_T, objective):
    """det J -> 0 (all events on the centre pixel) gives finite values and gradients."""
    ev = _events()
    for regs in ({}, {"divergence": 1.0, "deformation": 1.0}):
        prob = cm.ContrastMaximization(
            ev, warp=warp, objective=objective, regularizers=regs, whitening=not regs
        )
        value, grad = prob.value_and_grad(theta_of_T(ev.duration))
        assert np.isfinite(value) and np.all(np.isfinite(grad))
        maps = prob.maps(theta_of_T(ev.duration))
        hit = maps["count"] > 0
        for name, v in maps.items():
            if np.ndim(v) == 2 and name != "count":  # finite where events landed, NaN elsewhere
                assert np.all(np.isfinite(v[hit])) and np.all(np.isnan(v[~hit])), name
            else:
                assert np.all(np.isfinite(v)), name


def test_all_events_on_one_pixel():
    n = 100
    ev = cm.Events(np.full(n, 10.0), np.full(n, 12.0), np.linspace(0, 0.01, n), np.ones(n), SENSOR)
    prob = cm.ContrastMaximization(ev, warp="zoom1", regularizers={"deformation": 1.0}, whitening=True)
    value, grad = prob.value_and_grad([30.0])
    assert np.isfinite(value) and np.all(np.isfinite(grad))


def test_camera_validation():
    with pytest.raises(ValueError, match="positive"):
        cm.Camera(fx=0.0, fy=1.0, cx=0.0, cy=0.0)
    with pytest.raises(ValueError, match="finite"):
        cm.Camera(fx=np.nan, fy=1.0, cx=0.0, cy=0.0)
    with pytest.raises(ValueError, match="k1, k2"):
        cm.Camera(fx=1.0, fy=1.0, cx=0.0, cy=0.0, dist=(np.inf, 0, 0, 0, 0))


def test_reset_invalidates_old_problems():
    prob = cm.ContrastMaximization(_events(), warp="zoom1")
    cm.init(precision="f64")
    with pytest.raises(RuntimeError, match="build it again"):
        prob.value_and_grad([1.0])
