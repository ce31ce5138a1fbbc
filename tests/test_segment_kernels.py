"""Multi-cluster kernels (kernels/clusters.py via cmax_taichi.pipeline.clusters.MultiClusterCMax) against the
float64 NumPy reference: the multi-cluster J equals the sum over clusters of the reference J with the
cluster's memberships as event weights (per-cluster G0_j of the identity warp with the same weights),
its gradient equals central finite differences of that sum (f64 tight, f32 looser), and the per-event
lookup equals a NumPy bilinear lookup of the reference IWE."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CAMERA, SENSOR, THETAS, edge_events, use_precision

import cmax_taichi as cm
from cmax_taichi.core import workspace
from cmax_taichi.pipeline.clusters import MultiClusterCMax
from cmax_taichi.testing import reference

TOL = {"f64": dict(value=1e-10, grad=2e-6), "f32": dict(value=2e-4, grad=2e-2)}
BOTH = {"divergence": 0.7, "deformation": 1.3}

CASES = {
    # K = 2, two different warps, both regularizers
    "k2_mixed_regs": dict(warps=["translation2", "mitrokhin4"], regs=BOTH),
    # K = 3, one collapse-enabled warp for all, no regularizer
    "k3_mitrokhin_plain": dict(warps=["mitrokhin4"] * 3, regs={}),
    # K = 3, mixed warps, both regularizers; cluster 2 expands (the one-sided divergence hinge is active)
    "k3_mixed_regs": dict(warps=["mitrokhin4", "translation2", "mitrokhin4"], regs=BOTH, expand=2),
}


def _setup(case: str, n: int = 400, seed: int = 0):
    spec = CASES[case]
    x, y, t, p = edge_events(n=n, seed=seed)
    K = len(spec["warps"])
    rng = np.random.default_rng(seed + 1)
    P = rng.dirichlet(np.ones(K), size=n)
    P[P < 0.1] = 0.0  # exact zeros: the kernel skips those votes
    thetas = []
    for j, w in enumerate(spec["warps"]):
        th = np.asarray(THETAS[w], dtype=np.float64) * (1.0 + 0.3 * j)
        if spec.get("expand") == j:
            th[2] = -abs(th[2])  # mitrokhin4 h_z < 0: expansion, R_Div hinged to 0
        thetas.append(th)
    return spec, (x, y, t, p), P, thetas


def _ref_kwargs(spec, options):
    return dict(
        sensor_size=SENSOR,
        center=(CAMERA.cx, CAMERA.cy),
        focal=(CAMERA.fx, CAMERA.fy),
        t_ref=options.get("t_ref", "first"),
        objective="variance",
        normalize=options.get("normalize", True),
        blur_sigma=1.0,
        lambda_div=spec["regs"].get("divergence", 0.0),
        lambda_def=spec["regs"].get("deformation", 0.0),
    )


def _ref_sum(raw, P, warps, parts, kwargs) -> float:
    return sum(
        reference.evaluate(*raw, parts[j], warp=warps[j], weights=P[:, j], **kwargs)["J"]
        for j in range(len(warps))
    )


def _check(precision: str, case: str, **options) -> MultiClusterCMax:
    use_precision(precision)
    spec, raw, P, thetas = _setup(case)
    prob = MultiClusterCMax(
        cm.Events(*raw, SENSOR),
        len(spec["warps"]),
        spec["warps"],
        regularizers=spec["regs"],
        camera=CAMERA,
        t_ref=options.get("t_ref", "first"),
        normalize=options.get("normalize", True),
    )
    prob.set_memberships(P)
    kwargs = _ref_kwargs(spec, options)
    value, grad = prob.value_and_grad(thetas)
    flat = prob.flatten(thetas)
    ref = _ref_sum(raw, P, spec["warps"], thetas, kwargs)
    fd = reference.central_differences(
        lambda f: _ref_sum(raw, P, spec["warps"], prob.unpack(f), kwargs), flat, rel_step=1e-6
    )
    tol = TOL[precision]
    assert value == pytest.approx(ref, rel=tol["value"], abs=tol["value"])
    err = np.max(np.abs(grad - fd)) / max(np.max(np.abs(fd)), 1e-12)
    assert err < tol["grad"], f"gradient {grad} vs finite differences {fd} (rel err {err:.2e})"
    # per-cluster terms and penalties as reported
    ev = prob.evaluate(thetas)
    for j, w in enumerate(spec["warps"]):
        r = reference.evaluate(*raw, thetas[j], warp=w, weights=P[:, j], **kwargs)
        assert ev["J_k"][j] == pytest.approx(r["J"], rel=tol["value"] * 10, abs=tol["value"] * 10)
        assert ev["G_raw"][j] == pytest.approx(r["G_raw"], rel=tol["value"] * 10)
        assert ev["G0"][j] == pytest.approx(r["G0"], rel=tol["value"] * 10)
        if "divergence" in spec["regs"]:
            assert ev["R"]["divergence"][j] == pytest.approx(r["R_div"], rel=1e-6, abs=1e-7)
            assert ev["R"]["deformation"][j] == pytest.approx(r["R_def"], rel=1e-6, abs=1e-7)
    return prob


@pytest.mark.parametrize("case", list(CASES))
def test_value_and_gradient_f64(case):
    _check("f64", case)


def test_options_f64():
    """Raw objective (G0_j = 1) and t_ref = 'middle' (orientation of R_Div) on the same kernels."""
    _check("f64", "k3_mixed_regs", normalize=False)
    _check("f64", "k3_mixed_regs", t_ref="middle")


def test_value_and_gradient_f32():
    _check("f32", "k2_mixed_regs")


def _bilinear(img: np.ndarray, xw: np.ndarray, yw: np.ndarray) -> np.ndarray:
    H, W = img.shape
    out = np.zeros(xw.size)
    ok = np.isfinite(xw) & np.isfinite(yw) & (xw > -1) & (xw < W) & (yw > -1) & (yw < H)
    x0 = np.floor(xw[ok]).astype(int)
    y0 = np.floor(yw[ok]).astype(int)
    ax = xw[ok] - x0
    ay = yw[ok] - y0
    acc = np.zeros(ok.sum())
    for dx, dy, w in (
        (0, 0, (1 - ax) * (1 - ay)),
        (1, 0, ax * (1 - ay)),
        (0, 1, (1 - ax) * ay),
        (1, 1, ax * ay),
    ):
        c, r = x0 + dx, y0 + dy
        inside = (c >= 0) & (c < W) & (r >= 0) & (r < H)
        acc[inside] += w[inside] * img[r[inside], c[inside]]
    out[ok] = acc
    return out


def test_lookup_matches_reference(f64):
    spec, raw, P, thetas = _setup("k3_mixed_regs")
    prob = MultiClusterCMax(
        cm.Events(*raw, SENSOR), 3, spec["warps"], regularizers=spec["regs"], camera=CAMERA
    )
    prob.set_memberships(P)
    values, positions = prob.lookup(thetas)
    kwargs = _ref_kwargs(spec, {})
    images = prob.iwes(thetas)
    for j, w in enumerate(spec["warps"]):
        r = reference.evaluate(*raw, thetas[j], warp=w, weights=P[:, j], **kwargs)
        np.testing.assert_allclose(images[j], r["iwe"][0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(positions[:, j, 0], r["xw"], rtol=0, atol=1e-10)
        np.testing.assert_allclose(positions[:, j, 1], r["yw"], rtol=0, atol=1e-10)
        np.testing.assert_allclose(values[:, j], _bilinear(r["iwe"][0], r["xw"], r["yw"]), rtol=0, atol=1e-12)
    # an event warped outside the image reads 0
    far = [th.copy() for th in thetas]
    far[1] = np.array([1e5, 0.0])
    values, _ = prob.lookup(far)
    late = raw[2] > 0.01
    assert np.all(values[late, 1] == 0.0)


def test_inactive_and_empty_clusters(f64):
    """A cluster left out (active=False) or without any membership (flat identity image) adds 0 to J."""
    spec, raw, P, thetas = _setup("k3_mixed_regs")
    kwargs = _ref_kwargs(spec, {})
    ev = cm.Events(*raw, SENSOR)
    prob = MultiClusterCMax(ev, 3, spec["warps"], regularizers=spec["regs"], camera=CAMERA)
    prob.set_memberships(P, active=[True, False, True])
    expected = sum(
        reference.evaluate(*raw, thetas[j], warp=spec["warps"][j], weights=P[:, j], **kwargs)["J"]
        for j in (0, 2)
    )
    value, grad = prob.value_and_grad(thetas)
    assert value == pytest.approx(expected, rel=1e-10)
    assert np.all(prob.unpack(grad)[1] == 0.0)
    Q = P.copy()
    Q[:, 2] = 0.0
    g0 = prob.set_memberships(Q)
    assert g0[2] == 0.0 and list(prob.active) == [True, True, False]
    assert np.isfinite(prob.value(thetas))


def test_workspace_is_shared(f64):
    """A second window of the same shape reuses the fields and the compiled kernels."""
    spec, raw, P, thetas = _setup("k3_mixed_regs")
    first = MultiClusterCMax(
        cm.Events(*raw, SENSOR), 3, spec["warps"], regularizers=spec["regs"], camera=CAMERA
    )
    first.set_memberships(P)
    v1 = first.value(thetas)
    x, y, t, p = edge_events(n=380, seed=5)
    second = MultiClusterCMax(
        cm.Events(x, y, t, p, SENSOR), 3, spec["warps"], regularizers=spec["regs"], camera=CAMERA
    )
    assert second._ws is first._ws
    assert second._k_splat is first._k_splat
    second.set_memberships(np.full((380, 3), 1 / 3))
    second.value(thetas)
    assert first.value(thetas) == pytest.approx(v1, rel=1e-12)  # reloads its own events
    assert workspace.capacity_for(400) == first.capacity


def test_bad_input(f64):
    x, y, t, p = edge_events(n=50)
    ev = cm.Events(x, y, t, p, SENSOR)
    with pytest.raises(ValueError, match="at least 1"):
        MultiClusterCMax(ev, 0)
    with pytest.raises(ValueError, match="more than the 50 events"):
        MultiClusterCMax(ev, 51)
    with pytest.raises(TypeError, match="integer"):
        MultiClusterCMax(ev, 2.5)
    with pytest.raises(ValueError, match="one warp or one per cluster"):
        MultiClusterCMax(ev, 2, ["translation2"] * 3)
    prob = MultiClusterCMax(ev, 2, "translation2")
    with pytest.raises(RuntimeError, match="set_memberships"):
        prob.value(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="shape"):
        prob.set_memberships(np.ones((50, 3)))
    with pytest.raises(ValueError, match=">= 0"):
        prob.set_memberships(-np.ones((50, 2)))
    prob.set_memberships(np.ones((50, 2)))
    with pytest.raises(ValueError, match="takes 2 parameter"):
        prob.value([np.zeros(2), np.zeros(3)])
    with pytest.raises(ValueError, match="non-finite"):
        prob.value([np.zeros(2), np.array([np.nan, 0.0])])
