"""The fused pipeline (kernels/fused.py) against the generic autodiff kernel chain it replaces, and the
atomic (GPU-style) splat against the per-thread slices; finite differences of the reference are in
test_pipeline_gradients.py, the closed-form parameter Jacobians of every model column by column in
test_checks.py (``cm.check_model``)."""

import dataclasses
import warnings

import numpy as np
import pytest
import taichi as ti
from conftest import CAMERA, DURATION, SENSOR, THETAS, edge_events

import cmax_taichi as cm
from cmax_taichi.pipeline import problem as problem_module
from cmax_taichi.pipeline.fused import FusedPipeline
from cmax_taichi.testing import reference

pytestmark = pytest.mark.usefixtures("f64")

BOTH = {"divergence": 0.7, "deformation": 1.3}


def _problem(warp, variant="fused", seed=0, n=400, **kwargs):
    x, y, t, p = edge_events(n=n, seed=seed)
    flags = {"fused": {}, "chain": {"enabled": False}, "atomic": {"force_atomic": True}}[variant]
    saved = {k: getattr(FusedPipeline, k) for k in flags}
    for k, v in flags.items():
        setattr(FusedPipeline, k, v)
    try:
        kwargs.setdefault("camera", CAMERA)
        return cm.ContrastMaximization(cm.Events(x, y, t, p, SENSOR), warp=warp, **kwargs)
    finally:
        for k, v in saved.items():
            setattr(FusedPipeline, k, v)


CASES = [
    dict(objective="variance", regularizers=BOTH),
    dict(objective="gradient_magnitude", regularizers={"deformation": 1.0}),
    dict(objective="mean_square", regularizers={"divergence": 2.0}),
    dict(objective="variance", polarity="split", regularizers=BOTH),
    dict(objective="variance", polarity="signed", regularizers=BOTH, blur_sigma=2.0),
    dict(objective="variance", weights=np.linspace(0.2, 1.5, 400), regularizers=BOTH, t_ref="last"),
    dict(objective="variance", blur_sigma=0.0, regularizers=BOTH, normalize=False),
]


# every option on the richest model; the default configuration on every model (compile time)
# (rotation3's chain takes minutes to compile; its fused gradient is held against finite differences
# of the reference in test_pipeline_gradients.py and its Jacobians against autodiff below)
CHAIN_CASES = [("mitrokhin4", c) for c in range(len(CASES))] + [
    (w, 0) for w in THETAS if w not in ("mitrokhin4", "rotation3")
]


@pytest.mark.parametrize("warp,case", CHAIN_CASES)
def test_fused_equals_generic_chain(warp, case):
    options = CASES[case]
    fused = _problem(warp, "fused", **options)
    chain = _problem(warp, "chain", **options)
    assert fused._fused is not None and chain._fused is None
    rng = np.random.default_rng(case)
    for scale in (0.0, 1.0, 2.5):
        theta = np.asarray(THETAS[warp]) * scale * rng.uniform(0.7, 1.3, len(THETAS[warp]))
        v1, g1 = fused.value_and_grad(theta)
        v2, g2 = chain.value_and_grad(theta)
        assert v1 == pytest.approx(v2, rel=1e-11, abs=1e-12)
        np.testing.assert_allclose(g1, g2, rtol=1e-8, atol=1e-10 * max(1.0, np.max(np.abs(g2))))
        assert fused.value(theta) == pytest.approx(v2, rel=1e-11, abs=1e-12)
    np.testing.assert_allclose(fused.iwe(theta), chain.iwe(theta), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("warp", ["mitrokhin4", "sim2"])
def test_atomic_splat_equals_thread_slices(warp):
    """The atomic splat (the GPU path, run here on the CPU) against the per-thread slices."""
    ref = _problem(warp, "fused", regularizers=BOTH)
    other = _problem(warp, "atomic", regularizers=BOTH)
    assert ref._fused is not None and other._fused is not None
    for scale in (0.5, 2.0):
        theta = np.asarray(THETAS[warp]) * scale
        v1, g1 = ref.value_and_grad(theta)
        v2, g2 = other.value_and_grad(theta)
        assert v1 == pytest.approx(v2, rel=1e-11)
        np.testing.assert_allclose(g1, g2, rtol=1e-8, atol=1e-10 * np.max(np.abs(g2)))


def test_no_allocation_per_call_and_kernels_reused(monkeypatch):
    """Repeated evaluations create no Taichi field or ndarray; a window of another size reuses the
    shared arrays and compiled kernels, and both problems keep evaluating correctly."""
    prob = _problem("mitrokhin4", regularizers=BOTH)
    arrays, kernels = prob._fused._ws, prob._fused._schedules
    theta = np.asarray(THETAS["mitrokhin4"])
    prob.value_and_grad(theta)
    created = []

    def counting(original):
        def wrapper(*args, **kwargs):
            created.append(args)
            return original(*args, **kwargs)

        return wrapper

    monkeypatch.setattr(ti, "field", counting(ti.field))
    monkeypatch.setattr(ti, "ndarray", counting(ti.ndarray))
    monkeypatch.setattr(ti.Vector, "field", counting(ti.Vector.field))
    for _ in range(5):
        prob.value_and_grad(theta)
        prob.value(theta)
    assert created == []
    monkeypatch.undo()
    other = _problem("mitrokhin4", n=300, seed=3, regularizers=BOTH)
    assert other._fused._ws is arrays and other._fused._schedules is kernels
    assert np.isfinite(other.value(theta))
    v1, _ = prob.value_and_grad(theta)
    chain = _problem("mitrokhin4", "chain", regularizers=BOTH)
    assert v1 == pytest.approx(chain.value(theta), rel=1e-11)


@pytest.mark.parametrize("warp", ["translation2", "rotation3"])
def test_another_sensor_compiles_no_quick_kernel(monkeypatch, warp):
    """The quick kernels take the sensor's size as arguments: problems on three other sensors (one
    larger than the first, one with a width that is not a multiple of the segment) reuse them (Taichi
    builds no kernel again); the optimized ones have the sensor compiled in (one kernel per sensor).
    Either way they agree with the float64 reference."""
    from taichi.lang import kernel_impl

    options = dict(regularizers=BOTH, camera=CAMERA)
    theta = np.asarray(THETAS[warp])
    first = cm.ContrastMaximization(cm.Events(*edge_events(n=500, seed=1), SENSOR), warp=warp, **options)
    first.value_and_grad(theta)
    first.value(theta)
    built = []
    materialize = kernel_impl.Kernel.materialize

    def counted(self, key=None, args=None, arg_features=None):
        if key not in self.compiled_kernels:  # (Taichi calls it before every launch)
            built.append(self)
        return materialize(self, key=key, args=args, arg_features=arg_features)

    monkeypatch.setattr(kernel_impl.Kernel, "materialize", counted)
    for size in ((96, 70), (203, 151), (37, 29)):
        rng = np.random.default_rng(size[0])
        n = 600
        x, y = rng.uniform(0, size[0] - 1, n), rng.uniform(0, size[1] - 1, n)
        t = np.sort(rng.uniform(0, DURATION, n))
        events = cm.Events(x, y, t, rng.integers(0, 2, n), size)
        camera = cm.Camera(fx=CAMERA.fx, fy=CAMERA.fy, cx=(size[0] - 1) / 2, cy=(size[1] - 1) / 2)
        prob = cm.ContrastMaximization(events, warp=warp, regularizers=BOTH, camera=camera)
        assert prob._fused._schedules is first._fused._schedules
        value, grad = prob.value_and_grad(theta)
        weights = dict(lambda_div=BOTH["divergence"], lambda_def=BOTH["deformation"])
        ref = reference.evaluate_window(events, theta, warp=warp, camera=camera, **weights)
        assert value == pytest.approx(ref["J"], rel=1e-10)
        assert prob.value(theta) == pytest.approx(value, rel=1e-12)
    if first.kernels == "fast":
        assert built == [], f"kernels built again for another sensor: {[k.func.__name__ for k in built]}"
    else:  # the optimized tier: a kernel of its own for each sensor
        assert built and {k.func.__name__ for k in built} == {"run"}


def test_user_objective_and_whitening_take_the_generic_chain():
    with warnings.catch_warnings():
        warnings.simplefilter("error", cm.ChainPathWarning)  # whitening is a choice: no warning
        prob = _problem("mitrokhin4", regularizers=BOTH, whitening=True)
    assert prob._fused is None and prob.path == "chain" and "whitening" in prob.path_reason
    v, g = prob.value_and_grad(THETAS["mitrokhin4"])
    assert np.isfinite(v) and np.all(np.isfinite(g))


def test_the_path_follows_the_regularizer_declarations(monkeypatch):
    """A user's divergence regularizer (its own penalty functions) that declares its quantity kind and
    penalty gradient takes the fused path; without penalty_grad, or with a quantity function instead of
    a kind, the chain, with the reason and one ChainPathWarning per reason; all give the built-in's J."""

    @ti.func
    def penalty(avg):
        return avg

    @ti.func
    def penalty_grad(avg):
        return 1.0 + 0.0 * avg

    monkeypatch.setattr(problem_module, "_WARNED_REASONS", set())
    declared = cm.Regularizer("test_div_declared", "div", penalty, lambda d, o: o * d, True)
    no_grad = dataclasses.replace(declared, name="test_div_no_grad")
    declared = dataclasses.replace(declared, penalty_grad=penalty_grad)
    own_quantity = dataclasses.replace(
        declared, name="test_div_own", quantity=lambda model: model.quantity("div")
    )
    regs = (declared, no_grad, own_quantity)
    for reg in regs:
        cm.register_regularizer(reg)
    try:
        theta = np.asarray(THETAS["zoom1"])
        builtin = _problem("zoom1", regularizers={"divergence": 2.0})
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            probs = [_problem("zoom1", regularizers={reg.name: 2.0}) for reg in regs]
            _problem("zoom1", regularizers={"test_div_no_grad": 1.0})  # the same reason again: no warning
        assert [p.path for p in probs] == ["fused", "chain", "chain"]
        assert "penalty_grad" in probs[1].path_reason and "quantity kind" in probs[2].path_reason
        messages = [str(w.message) for w in caught if issubclass(w.category, cm.ChainPathWarning)]
        assert messages == [probs[1].path_reason, probs[2].path_reason]
        v0, g0 = builtin.value_and_grad(theta)
        for prob in probs:
            v, g = prob.value_and_grad(theta)
            assert v == pytest.approx(v0, rel=1e-11)
            np.testing.assert_allclose(g, g0, rtol=1e-8, atol=1e-10 * np.max(np.abs(g0)))
    finally:
        for reg in regs:
            cm.unregister_regularizer(reg.name)


def test_event_buffers_are_pooled_not_made_per_problem():
    """Taichi 1.7.4 never frees a vector ndarray, so one per problem grew the process by ~24
    bytes per event per window. Problems of one capacity bucket now share one buffer."""
    from cmax_taichi.core import workspace

    def buffers():
        return sum(1 for key in workspace._POOL if key[0] == "events")

    rng = np.random.default_rng(3)
    problems = []
    for size in (1500, 1700, 2000, 1500):  # one capacity bucket (2048)
        x, y = rng.uniform(0, 63, size), rng.uniform(0, 47, size)
        t = np.sort(rng.uniform(0, 0.05, size))
        problems.append(cm.ContrastMaximization(cm.Events(x, y, t, rng.integers(0, 2, size), (64, 48))))
    before = buffers()
    for _ in range(3):
        for size in (1500, 1900):
            x, y = rng.uniform(0, 63, size), rng.uniform(0, 47, size)
            t = np.sort(rng.uniform(0, 0.05, size))
            problems.append(cm.ContrastMaximization(cm.Events(x, y, t, rng.integers(0, 2, size), (64, 48))))
    assert buffers() == before
    # problems sharing a buffer still give their own values (their events are uploaded when they run)
    theta = np.array([10.0, -5.0, 0.2, 0.1])
    values = [p.value(theta) for p in problems]
    again = [p.value(theta) for p in reversed(problems)][::-1]
    np.testing.assert_allclose(values, again, rtol=1e-12)
    assert len(set(np.round(values, 12))) > len(values) // 2


def test_cpu_events_packed_in_row_order_none_lost():
    """The CPU splat reads the events in the order of their pixel row (cache locality): every event,
    with its weight and channel, is still there once, time order is kept within a row, and the value and
    gradient equal those of the generic chain, whose events keep the input order."""
    options = dict(polarity="split", weights=np.linspace(0.2, 1.5, 400), regularizers=BOTH)
    fused = _problem("mitrokhin4", "fused", seed=5, **options)
    assert fused.path == "fused"
    packed = fused._fused._packed[:400]
    rows = np.floor(packed[:, 1]).astype(int)
    assert np.all(np.diff(rows) >= 0)
    ev = fused.events
    columns = [ev.x, ev.y, ev.t - fused.t_ref, fused.setup.vote_weights, (ev.p < 0).astype(float)]
    expected = np.stack(columns, axis=1)[np.lexsort((np.arange(400), np.floor(ev.y)))]
    np.testing.assert_array_equal(packed, expected)
    chain = _problem("mitrokhin4", "chain", seed=5, **options)
    theta = np.array(THETAS["mitrokhin4"])
    (jf, gf), (jc, gc) = fused.value_and_grad(theta), chain.value_and_grad(theta)
    np.testing.assert_allclose(jf, jc, rtol=1e-10)
    np.testing.assert_allclose(gf, gc, rtol=1e-8, atol=1e-10 * np.max(np.abs(gc)))


@pytest.mark.parametrize("loops", ["serial", "parallel"])
def test_stored_event_terms_equal_the_unstored_kernel(monkeypatch, loops):
    """rotation3 declares store_event_terms (its warp once per event and call, stored for the gather):
    on the pool's schedule, value and gradient equal the kernel that evaluates the warp in both event
    loops, to rounding, with both regularizers, vote weights and split polarity; the serial schedule
    stores them without voted quantities (equal to rounding) and not with them (both regularizers: the
    same kernel as without the declaration, to the last bit; fused.stores_terms); a bigger window after
    a small one reallocates the stored terms; the atomic (GPU-style) path ignores the declaration."""
    from cmax_taichi.kernels.warps import rotation3

    stored = cm.get_warp("rotation3")
    assert stored.store_event_terms
    unstored = cm.WarpModel.from_module(rotation3, store_event_terms=False)
    monkeypatch.setattr(FusedPipeline, "loops", loops)
    theta = np.asarray(THETAS["rotation3"])
    cases = [dict(regularizers=BOTH), dict(regularizers=BOTH, polarity="split"),
             dict(regularizers={"deformation": 1.0}, weights=np.linspace(0.2, 1.5, 400)), dict()]  # fmt: skip
    for options in cases if loops == "parallel" else cases[::3]:  # (each case compiles its kernels)
        a = _problem(stored, **options)
        b = _problem(unstored, **options)
        assert a._fused._terms_rows > 0 and b._fused._terms_rows == 0
        votes = bool(options.get("regularizers"))
        assert a._fused.stores_event_terms == (loops == "parallel" or not votes)
        for scale in (0.0, 1.0, -2.5):
            v1, g1 = a.value_and_grad(theta * scale)
            v2, g2 = b.value_and_grad(theta * scale)
            if not a._fused.stores_event_terms:
                assert v1 == v2 and np.array_equal(g1, g2) and a.value(theta * scale) == v2
            assert v1 == pytest.approx(v2, rel=1e-12, abs=1e-14)
            np.testing.assert_allclose(g1, g2, rtol=1e-10, atol=1e-12 * max(1.0, np.max(np.abs(g2))))
            assert a.value(theta * scale) == pytest.approx(v2, rel=1e-12, abs=1e-14)
    small = _problem(stored, n=100, regularizers=BOTH)
    big = _problem(stored, n=3000, seed=2, regularizers=BOTH)
    ref = _problem(unstored, n=3000, seed=2, regularizers=BOTH)
    assert small._fused._terms.shape[1] < big._fused._terms.shape[1]
    small.value_and_grad(theta)
    v1, g1 = big.value_and_grad(theta)
    v2, g2 = ref.value_and_grad(theta)
    assert v1 == pytest.approx(v2, rel=1e-12)
    np.testing.assert_allclose(g1, g2, rtol=1e-10, atol=1e-12 * np.max(np.abs(g2)))
    atomic = _problem(stored, "atomic", regularizers=BOTH)
    assert atomic._fused._terms_rows == 0
    v3, g3 = atomic.value_and_grad(theta)
    v4, g4 = _problem(unstored, regularizers=BOTH).value_and_grad(theta)
    assert v3 == pytest.approx(v4, rel=1e-11)
    np.testing.assert_allclose(g3, g4, rtol=1e-8, atol=1e-10 * np.max(np.abs(g4)))
