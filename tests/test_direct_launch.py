"""The fused kernel's direct launch (``pipeline/fused.py``, ``_DirectLaunch``): after the first call, value
and value_and_grad launch the compiled kernel from its C++ launch context instead of Taichi's Python
``Kernel.__call__``. The results must be the ordinary call's, bit for bit, whatever the order of calls,
windows and problems; a backend reset must still be refused clearly."""

import numpy as np
import pytest
from conftest import CAMERA, SENSOR, THETAS, edge_events

import cmax_taichi as cm

pytestmark = pytest.mark.usefixtures("f64")

CASES = [
    ("translation2", {}),
    ("rotation3", {"divergence": 1.0, "deformation": 1.0}),
    ("mitrokhin4", {"divergence": 1.0, "deformation": 1.0}),
]


def _problem(n: int, warp: str, regs: dict, seed: int = 0) -> cm.ContrastMaximization:
    x, y, t, p = edge_events(n, seed=seed)
    return cm.ContrastMaximization(cm.Events(x, y, t, p, SENSOR), warp=warp, regularizers=regs, camera=CAMERA)


def _ordinary(prob, theta, grad: bool):
    """The same evaluation through Taichi's ordinary kernel call (the launcher switched off once)."""
    fused = prob._fused
    launchers, fused._launchers = fused._launchers, {}
    try:
        return prob.value_and_grad(theta) if grad else prob.value(theta)
    finally:
        fused._launchers = launchers


@pytest.mark.parametrize("warp,regs", CASES, ids=[c[0] for c in CASES])
def test_direct_launches_equal_the_ordinary_call(warp, regs):
    prob = _problem(500, warp, regs)
    assert prob.path == "fused"
    base = np.asarray(THETAS[warp], dtype=np.float64)
    prob.value(base)
    assert prob._fused.launch_ready()
    for k in range(6):  # alternate value / value_and_grad and theta: every launch sets its arguments
        theta = base * (1.0 + 0.1 * k)
        value, grad = prob.value_and_grad(theta)
        expected_value, expected_grad = _ordinary(prob, theta, True)
        assert value == expected_value and np.array_equal(grad, expected_grad)
        assert prob.value(theta) == _ordinary(prob, theta, False)  # (1 ulp from value_and_grad's J)


def test_direct_launch_across_windows_and_problems():
    """Two problems sharing the pooled fields and kernels, and windows of other sizes through set_events
    (the same capacity bucket and a larger one): each call gives what a fresh problem gives."""
    theta = np.asarray(THETAS["mitrokhin4"], dtype=np.float64)
    regs = {"divergence": 1.0, "deformation": 1.0}
    a = _problem(400, "mitrokhin4", regs, seed=1)
    b = _problem(700, "mitrokhin4", regs, seed=2)
    for _ in range(2):
        va, _ = a.value_and_grad(theta)
        vb, _ = b.value_and_grad(theta)
        assert va == _problem(400, "mitrokhin4", regs, seed=1).value_and_grad(theta)[0]
        assert vb == _problem(700, "mitrokhin4", regs, seed=2).value_and_grad(theta)[0]
    for n, seed in ((300, 3), (3000, 4), (500, 5)):
        x, y, t, p = edge_events(n, seed=seed)
        a.set_events(cm.Events(x, y, t, p, SENSOR))
        value, grad = a.value_and_grad(theta)
        fresh_value, fresh_grad = _problem(n, "mitrokhin4", regs, seed=seed).value_and_grad(theta)
        assert value == fresh_value and np.array_equal(grad, fresh_grad)


def test_a_reset_backend_is_refused_after_direct_launches():
    prob = _problem(300, "translation2", {})
    theta = np.asarray(THETAS["translation2"], dtype=np.float64)
    prob.value_and_grad(theta)
    assert prob._fused.launch_ready()
    cm.init(arch="cpu", precision="f64")
    assert not prob._fused.launch_ready()
    with pytest.raises(RuntimeError, match="built before the Taichi backend was reset"):
        prob.value_and_grad(theta)
    with pytest.raises(RuntimeError, match="built before the Taichi backend was reset"):
        prob.value(theta)


@pytest.mark.parametrize("normalize", [True, False])
@pytest.mark.parametrize("warp,regs", CASES, ids=[c[0] for c in CASES])
def test_identity_value_known_from_the_set_up(warp, regs, normalize):
    """The window's set-up evaluates the identity (G0): value(0) then returns the J that the kernel gives
    there, bit for bit, without a launch; also after set_events."""
    x, y, t, p = edge_events(400)
    events = cm.Events(x, y, t, p, SENSOR)
    prob = cm.ContrastMaximization(events, warp=warp, regularizers=regs, camera=CAMERA, normalize=normalize)
    zero = np.zeros(prob.model.n_params)
    for seed in (None, 7):
        if seed is not None:
            x, y, t, p = edge_events(600, seed=seed)
            prob.set_events(cm.Events(x, y, t, p, SENSOR))
        memo = prob.value(zero)
        known, prob._identity_value = prob._identity_value, None
        try:
            assert prob.value(zero) == memo
            assert prob.value_and_grad(zero)[0] == pytest.approx(memo, rel=1e-14)
        finally:
            prob._identity_value = known
