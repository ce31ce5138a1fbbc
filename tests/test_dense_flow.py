"""The dense flow model (kernels/dense_flow.py, cmax_taichi/flow/) against the float64 NumPy reference
(cmax_taichi/testing/dense_flow_reference.py): J and its terms, and dJ/dU against central differences of
the reference, on several grids, objectives, reference sets, polarity modes, weights and regularizer
sets (the divergence and deformation maps and the smoothness terms included); the grid's interpolation,
refinement and fit; the per-event quantities; the input checks."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DURATION, SENSOR, edge_events, use_precision

import cmax_taichi as cm
from cmax_taichi.flow import DenseFlowProblem, FlowGrid, resolve_references
from cmax_taichi.flow.smoothness import SMOOTHNESS
from cmax_taichi.testing import dense_flow_reference as ref

#: the regularizers of the first case (tests that need some kernel reuse its compiled variant)
BOTH = {"divergence": 2.0, "deformation": 3.0}
TOL = {"f64": dict(value=1e-10, grad=1e-6), "f32": dict(value=3e-4, grad=3e-2)}

#: (grid cells, objective, references, polarity, weighted, regularizers): every kernel option is covered
CASES = {
    "variance-first-both": (
        (4, 3),
        "variance",
        "first",
        "ignore",
        False,
        {"divergence": 2.0, "deformation": 3.0, "curvature": 0.1},
    ),
    "gradmag-multi-all": (
        (3, 2),
        "gradient_magnitude",
        "multi",
        "ignore",
        False,
        {"divergence": 1.0, "deformation": 1.0, "total_variation": 0.5},
    ),
    "meansq-last-signed-def": ((1, 1), "mean_square", "last", "signed", False, {"deformation": 2.0}),
    "variance-two-split-weighted": (
        (2, 3),
        "variance",
        ("first", 0.3),
        "split",
        True,
        {"divergence": 1.5, "quadratic": 0.7, "curvature": 0.2},
    ),
    "gradmag-middle-weighted-none": ((4, 3), "gradient_magnitude", "middle", "ignore", True, {}),
}


def _events(seed: int = 0, n: int = 400):
    x, y, t, p = edge_events(n=n, seed=seed)
    return cm.Events(x, y, t, p, SENSOR), (x, y, t, p)


def _nodes(grid: FlowGrid, seed: int = 1, scale: float = 40.0) -> np.ndarray:
    """Node flows of a few px over the window (px/s), varying enough that det and div vary."""
    return np.random.default_rng(seed).normal(0.0, scale, grid.shape)


def check_dense_against_reference(precision: str, case: str, seed: int = 0, n: int = 400) -> DenseFlowProblem:
    """J, its terms and dJ/dU of one case against the float64 reference (tests/test_dense_flow_gpu.py
    runs the same on a GPU)."""
    use_precision(precision)
    cells, objective, refs, polarity, weighted, regs = CASES[case]
    events, raw = _events(seed, n)
    weights = np.random.default_rng(seed + 7).uniform(0.5, 1.5, n) if weighted else None
    grid = FlowGrid(*SENSOR, *cells)
    prob = DenseFlowProblem(
        events,
        grid,
        objective=objective,
        references=refs,
        regularizers=regs,
        polarity=polarity,
        weights=weights,
    )
    U = _nodes(grid, seed + 1)
    value, grad = prob.value_and_grad(U)
    fractions, omega = resolve_references(refs)
    kwargs = dict(
        grid=cells,
        sensor_size=SENSOR,
        references=fractions,
        reference_weights=omega,
        objective=objective,
        polarity=polarity,
        weights=weights,
        lambda_div=regs.get("divergence", 0.0),
        lambda_def=regs.get("deformation", 0.0),
        smoothness={k: v for k, v in regs.items() if k in SMOOTHNESS},
    )
    expected = ref.dense_evaluate(*raw, U, **kwargs)
    tol = TOL[precision]
    assert np.isfinite(value) and np.all(np.isfinite(grad)) and grad.shape == grid.shape
    assert value == pytest.approx(expected["J"], rel=tol["value"], abs=tol["value"])
    fd = ref.central_difference_grad(*raw, U, step=1e-4, **kwargs)
    err = np.max(np.abs(grad - fd)) / max(np.max(np.abs(fd)), 1e-12)
    assert err < tol["grad"], f"gradient rel err {err:.2e}"
    ev = prob.evaluate(U)
    assert pytest.approx(value, rel=tol["value"], abs=tol["value"]) == ev.J
    assert ev.data == pytest.approx(expected["H"], rel=tol["value"], abs=tol["value"])
    np.testing.assert_allclose(ev.G, expected["G"], rtol=tol["value"] * 10)
    if "divergence" in regs:
        assert ev.penalties["divergence"] == pytest.approx(expected["R_div"], rel=tol["value"] * 10, abs=1e-9)
        np.testing.assert_allclose(ev.penalties_per_reference["divergence"], expected["R_div_r"], atol=1e-6)
    if "deformation" in regs:
        assert ev.penalties["deformation"] == pytest.approx(
            expected["R_def"], rel=tol["value"] * 10, abs=1e-9
        )
    for name, v in expected["smoothness"].items():
        assert ev.smoothness[name] == pytest.approx(v, rel=1e-12)
    for r in range(len(fractions)):
        np.testing.assert_allclose(prob.iwe(U, r), np.squeeze(expected["iwe"][r]), atol=tol["value"] * 10)
    return prob


@pytest.mark.parametrize("case", list(CASES))
def test_value_and_gradient_against_reference(case):
    check_dense_against_reference("f64", case)


@pytest.mark.parametrize("case", ["variance-first-both", "gradmag-multi-all"])
def test_value_and_gradient_f32(case):
    check_dense_against_reference("f32", case)


def test_identity_is_one_and_the_references_agree(f64):
    """At U = 0 every reference's IWE is the unwarped one: H = 1 (normalised), the penalties vanish."""
    events, _ = _events(2)
    grid = FlowGrid(*SENSOR, 4, 4)
    regs = {"divergence": 1.0, "deformation": 1.0, "total_variation": 0.5}
    prob = DenseFlowProblem(events, grid, references="multi", regularizers=regs)
    ev = prob.evaluate(np.zeros(grid.shape))
    assert ev.data == pytest.approx(1.0, rel=1e-12)
    assert pytest.approx(1.0, rel=1e-12) == ev.J
    assert pytest.approx([prob.g0] * 3, rel=1e-12) == ev.G
    # the deformation map is a vote-weighted mean of det = 1: 1 up to rounding
    assert ev.penalties == pytest.approx({"divergence": 0.0, "deformation": 0.0}, abs=1e-14)
    assert ev.smoothness == {"total_variation": 0.0}


def test_event_quantities_against_reference(f64):
    events, raw = _events(3)
    grid = FlowGrid(*SENSOR, 3, 4)
    prob = DenseFlowProblem(events, grid, objective="variance", regularizers=BOTH)
    U = _nodes(grid, 4, scale=200.0)
    for r, frac in enumerate(prob.fractions):
        got = prob.event_quantities(U, r)
        want = ref.dense_warp(
            *raw[:3], U, grid=(3, 4), sensor_size=SENSOR, t_ref=raw[2].min() + frac * DURATION
        )
        for key in ("xw", "yw", "det", "div"):
            np.testing.assert_allclose(got[key], want[key], rtol=1e-12, atol=1e-12)
    # det(I - dt Du) = 1 - dt div + dt^2 det(Du) (the closed form the kernels use)
    q = prob.event_quantities(U)
    dt = events.t - events.t[0]
    du_dx, du_dy = grid.derivatives(U, events.x, events.y)
    np.testing.assert_allclose(
        q["det"], 1 - dt * q["div"] + dt**2 * (du_dx[0] * du_dy[1] - du_dy[0] * du_dx[1])
    )


def test_coarse_grid_in_a_fine_problem_and_exact_prolongation(f64):
    """A coarse level evaluated in the fine problem's fields equals its prolongation on the fine grid (the
    kernel terms: the smoothness terms are means over the grid's edges, which refinement changes)."""
    events, _ = _events(5)
    fine = FlowGrid(*SENSOR, 8, 6)
    coarse = fine.pyramid(2)[0]
    assert (coarse.nx, coarse.ny) == (4, 3)
    prob = DenseFlowProblem(events, fine, objective="variance", regularizers=BOTH)
    U = _nodes(coarse, 6)
    prob.set_grid(coarse)
    j_coarse, g_coarse = prob.value_and_grad(U)
    prob.set_grid(fine)
    U_fine = coarse.prolong(U)
    j_fine, g_fine = prob.value_and_grad(U_fine)
    assert j_fine == pytest.approx(j_coarse, rel=1e-12)
    # the coarse gradient is the fine one pulled back through the (linear) prolongation
    P = np.stack(
        [coarse.prolong(e.reshape(coarse.shape)).reshape(-1) for e in np.eye(coarse.n_params)], axis=1
    )
    np.testing.assert_allclose(P.T @ g_fine.reshape(-1), g_coarse.reshape(-1), rtol=1e-9, atol=1e-12)


def test_grid_interpolation_fit_and_errors():
    grid = FlowGrid(40, 30, 4, 3)
    assert grid.spacing == (39 / 4, 29 / 3) and grid.n_params == 40
    X, Y = grid.node_positions()
    U = np.stack([0.5 * X - 0.2 * Y + 3.0, 0.1 * X * Y], axis=-1)  # bilinear in x, y: represented exactly
    dense = grid.dense(U)
    yy, xx = np.mgrid[0:30, 0:40]
    np.testing.assert_allclose(dense[0], 0.5 * xx - 0.2 * yy + 3.0, atol=1e-12)
    np.testing.assert_allclose(dense[1], 0.1 * xx * yy, atol=1e-12)
    np.testing.assert_allclose(grid.fit(dense), U, atol=1e-6)
    du_dx, du_dy = grid.derivatives(U, xx.astype(float), yy.astype(float))
    np.testing.assert_allclose(du_dx[0], 0.5, atol=1e-12)
    np.testing.assert_allclose(du_dy[1], 0.1 * xx, atol=1e-12)
    with pytest.raises(ValueError, match="multiples of 4"):
        FlowGrid(40, 30, 6, 4).pyramid(3)
    with pytest.raises(ValueError, match="finer than the pixels"):
        FlowGrid(10, 10, 12, 2)
    with pytest.raises(ValueError, match="takes 40"):
        grid.check_nodes(np.zeros(12))
    with pytest.raises(ValueError, match="non-finite"):
        grid.check_nodes(np.full(grid.shape, np.nan))


@pytest.mark.parametrize("name", ["total_variation", "quadratic", "curvature"])
@pytest.mark.parametrize("cells", [(5, 4), (1, 3)])
def test_smoothness_value_and_gradient(name, cells):
    grid = FlowGrid(50, 40, *cells)
    U = _nodes(grid, 8)
    T = 0.05
    value, g = SMOOTHNESS.get(name).value_and_grad(U * T, grid)
    assert value == pytest.approx(
        ref.smoothness_value(name, U, grid=cells, sensor_size=(50, 40), duration=T)
    )
    h = 1e-6
    fd = np.zeros(U.size)
    for k in range(U.size):
        e = np.zeros(U.size)
        e[k] = h
        vp = SMOOTHNESS.get(name).value_and_grad((U.reshape(-1) + e).reshape(U.shape) * T, grid)[0]
        vm = SMOOTHNESS.get(name).value_and_grad((U.reshape(-1) - e).reshape(U.shape) * T, grid)[0]
        fd[k] = (vp - vm) / (2 * h)
    np.testing.assert_allclose(g.reshape(-1) * T, fd, rtol=1e-5, atol=1e-9)


def test_bad_input_is_refused_with_one_clear_error(f64):
    events, _ = _events(0)
    grid = FlowGrid(*SENSOR, 2, 2)
    with pytest.raises(ValueError, match="unknown regularizer 'smooth'"):
        DenseFlowProblem(events, grid, regularizers={"smooth": 1.0})
    with pytest.raises(ValueError, match="finite and >= 0"):
        DenseFlowProblem(events, grid, regularizers={"total_variation": -1.0})
    with pytest.raises(ValueError, match="unknown reference"):
        DenseFlowProblem(events, grid, references=("first", "end"))
    with pytest.raises(ValueError, match="fraction of the window"):
        DenseFlowProblem(events, grid, references=1.5)
    with pytest.raises(ValueError, match="2 reference weight"):
        DenseFlowProblem(events, grid, references=("first", "last", "middle"), reference_weights=[1, 2])
    with pytest.raises(ValueError, match="sensor"):
        DenseFlowProblem(events, FlowGrid(32, 32, 2, 2))
    with pytest.raises(TypeError, match="Events"):
        DenseFlowProblem(np.zeros((10, 4)), grid)
    prob = DenseFlowProblem(events, grid, objective="variance", regularizers=BOTH)
    with pytest.raises(ValueError, match="holds"):
        prob.set_grid(FlowGrid(*SENSOR, 16, 16))
    with pytest.raises(ValueError, match="takes 18"):
        prob.value(np.zeros(5))
    with pytest.raises(ValueError, match="reference must be"):
        prob.iwe(np.zeros(grid.shape), reference=3)
