"""rotation3 and se2 evaluate Rodrigues' coefficients without the maths library (``common.rodrigues``):
Taylor polynomials of the half angle up to ``phi = pi / 2``, a reduction modulo ``pi / 2`` beyond. These
tests hold the error bound that docs/FORMULAS.md states, in f64 and f32, across every angle the default
search box allows (and far beyond it), against the exact rotation of the float64 reference, and the
slopes against the derivatives of the same expressions.

(No ``from __future__ import annotations``: it breaks the annotations of the Taichi kernels below.)"""

import math

import numpy as np
import pytest
import taichi as ti
from cmax_taichi.kernels.warps import common, rotation3, se2
from cmax_taichi.kernels.warps.common import (
    ONE_MINUS_COS_OVER_R2,
    SIN_TAIL_OVER_R3,
    float_epsilon,
    taylor_error,
)

import cmax_taichi as cm
from cmax_taichi.solve.optimize import search_bounds
from cmax_taichi.testing import reference
from tests.conftest import use_precision

SENSOR = (240, 180)
CAMERA = cm.Camera(fx=168.0, fy=168.0, cx=119.5, cy=89.5)  # the benchmark's ~70 degree pinhole
DURATION = 0.05


def _box_phi_max() -> float:
    """The largest ``|w| |dt|`` (rad) of the default search box of a rotation3 window (``dt <= T``)."""
    rng = np.random.default_rng(0)
    n = 500
    t = np.linspace(0.0, DURATION, n)
    events = cm.Events(rng.uniform(0, 239, n), rng.uniform(0, 179, n), t, rng.integers(0, 2, n), SENSOR)
    prob = cm.ContrastMaximization(events, warp="rotation3", camera=CAMERA)
    lo, hi = search_bounds(prob)
    return float(np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi)))) * DURATION


def _angles(phi_max: float) -> np.ndarray:
    """Angles (rad) from 0 through the series' range, its edge and the reduction, to ``phi_max``."""
    edge = 2.0 * common.HALF_ANGLE_MAX
    short = 2.0 * common.SHORT_HALF_ANGLE  # the short tier's edge
    dense = np.linspace(0.0, phi_max, 4001)
    dense_short = np.linspace(0.0, 1.5 * short, 2001)  # the short tier and past its edge
    special = [0, 1e-12, 1e-6, 1e-3, 0.1, edge * (1 - 1e-12), edge, edge * (1 + 1e-12), math.pi, 2 * math.pi]
    special += [short * (1 - 1e-12), short, short * (1 + 1e-12)]
    return np.unique(np.concatenate([dense, dense_short, np.array(special)]))


def _real():
    return (ti.f64, np.float64) if cm.backend_info().precision == "f64" else (ti.f32, np.float32)


def _coefficients(phi: np.ndarray) -> np.ndarray:
    """``(s1, s2, ds1/du, ds2/du)`` of the kernel at the angles ``phi`` (rounded to the precision in use;
    ``u = phi^2`` in that precision), as float64 ``(4, N)``."""
    real, npr = _real()
    out = ti.ndarray(real, shape=(4, phi.size))

    @ti.kernel
    def run(phi_in: ti.types.ndarray(), out: ti.types.ndarray()):
        for i in range(phi_in.shape[0]):
            a = phi_in[i]
            s1, s2, d1, d2 = common.rodrigues(a * a, ti.Vector([a]))
            out[0, i] = s1
            out[1, i] = s2
            out[2, i] = d1
            out[3, i] = d2

    run(phi.astype(npr), out)
    return out.to_numpy().astype(np.float64)


def _exact(phi: np.ndarray):
    """``(phi, sin(phi), 1 - cos(phi))`` at the angle the kernel sees (``phi`` rounded to the precision
    in use), in extended precision."""
    p = phi.astype(_real()[1]).astype(np.longdouble)
    return p, np.sin(p), 2 * np.sin(p / 2) ** 2


@pytest.mark.parametrize("precision", ["f64", "f32"])
def test_coefficients_within_the_stated_bound(precision):
    """The documented bound: on the series side (``phi <= pi / 2``) s1 and s2 within 4 ulp (f64) of the
    exact values, relative; everywhere ``phi s1 = sin(phi)`` and ``phi^2 s2 = 1 - cos(phi)`` within
    ``4 eps (1 + phi)`` absolute (the reduction's error is about the rounding of phi itself)."""
    use_precision(precision)
    try:
        eps = float_epsilon()
        angles = _angles(max(4.0 * _box_phi_max(), 40.0))
        assert angles.max() > 3 * math.pi  # several reductions
        s1, s2, _, _ = _coefficients(angles)
        phi, sin, vers = _exact(angles)
        small = phi <= 2.0 * common.HALF_ANGLE_MAX
        nz = phi > 0
        s1_exact = np.where(nz, sin / np.where(nz, phi, 1), 1.0)
        s2_exact = np.where(nz, vers / np.where(nz, phi, 1) ** 2, 0.5)
        rel1 = np.abs(s1 - s1_exact) / np.abs(s1_exact)
        rel2 = np.abs(s2 - s2_exact) / np.abs(s2_exact)
        assert float(rel1[small].max()) <= 4 * eps and float(rel2[small].max()) <= 4 * eps
        err_sin = np.abs(phi * s1 - sin).astype(np.float64)
        err_vers = np.abs(phi**2 * s2 - vers).astype(np.float64)
        bound = 4 * eps * (1 + phi.astype(np.float64))
        assert np.all(err_sin <= bound), float((err_sin / bound).max())
        assert np.all(err_vers <= bound * np.maximum(1, phi)), float((err_vers / bound).max())
    finally:
        use_precision("f64")


@pytest.mark.parametrize("precision", ["f64", "f32"])
def test_huge_angles_stay_finite(precision):
    """Beyond ~1e7 rad (f32) the rounding of phi exceeds pi: the reduction keeps no digit, but the values
    stay finite and bounded up to the largest float (u = phi^2 overflows f32 from 1.8e19)."""
    use_precision(precision)
    try:
        top = 3e38 if precision == "f32" else 1e300
        phi = np.geomspace(1e6, top, 60)
        out = _coefficients(phi)
        assert np.all(np.isfinite(out))
        phi32 = phi.astype(_real()[1]).astype(np.float64)
        assert np.all(np.abs(phi32 * out[0]) <= 1 + 1e-6) and np.all(phi32 * (phi32 * out[1]) <= 2 + 1e-6)
    finally:
        use_precision("f64")


@pytest.mark.parametrize("precision", ["f64", "f32"])
def test_series_truncation_is_below_the_precision(precision):
    """The truncation bound of ``common.taylor_terms`` (first omitted term) of both series is under an
    eighth of the machine epsilon on the whole series range and on the short tier's, relative to the
    series' smallest value there; the short tier's polynomials are shorter (f64: 4 and 4 terms against
    8 and 8), else the tier would buy nothing."""
    use_precision(precision)
    try:
        for h in (common.HALF_ANGLE_MAX, common.SHORT_HALF_ANGLE):
            for series, terms, floor in (
                (SIN_TAIL_OVER_R3, common.tail_terms(h), (h - math.sin(h)) / h**3),
                (ONE_MINUS_COS_OVER_R2, common.versine_terms(h), (1 - math.cos(h)) / h**2),
            ):
                assert taylor_error(series, len(terms), h * h) <= float_epsilon() / 8 * floor
        assert len(common.tail_terms(common.SHORT_HALF_ANGLE)) < len(common.tail_terms())
        assert len(common.versine_terms(common.SHORT_HALF_ANGLE)) < len(common.versine_terms())
        if precision == "f64":
            short = common.SHORT_HALF_ANGLE
            assert len(common.tail_terms(short)) == 4 == len(common.versine_terms(short))
    finally:
        use_precision("f64")


def test_slopes_are_the_derivatives_of_the_coefficients():
    """ds1/du and ds2/du against central differences of s1 and s2 (f64), on both sides of the series edge
    and across reductions."""
    use_precision("f64")
    phi = np.concatenate([np.linspace(0.01, 1.5, 40), np.linspace(1.6, 30.0, 80)])
    u = phi**2
    step = 1e-6 * np.maximum(u, 1.0)
    _, _, d1, d2 = _coefficients(phi)
    hi = _coefficients(np.sqrt(u + step))
    lo = _coefficients(np.sqrt(u - step))
    fd1 = (hi[0] - lo[0]) / (2 * step)
    fd2 = (hi[1] - lo[1]) / (2 * step)
    np.testing.assert_allclose(d1, fd1, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(d2, fd2, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("precision", ["f64", "f32"])
def test_warp_and_det_against_the_exact_reference(precision):
    """Warped positions and determinants of rotation3 against the float64 reference (exact Rodrigues),
    across |w| dt up to four times the search box's largest: events behind the camera dropped by both;
    within 1e-10 px (f64) / 5e-3 px (f32) where they land within four sensor widths of the centre, and
    relatively (a ray near the horizon lands at 1e5 px, where 1/z amplifies every rounding) within
    1e-12 / 1e-3 of their distance from the centre; det within a relative 1e-12 / 1e-5. In f32 these are
    the errors of f32 arithmetic: the closed forms with libm sin / cos gave the same (measured when the
    series replaced them)."""
    use_precision(precision)
    try:
        phi_max = 4.0 * _box_phi_max()
        rng = np.random.default_rng(3)
        n = 6000
        x = rng.uniform(0, 239, n)
        y = rng.uniform(0, 179, n)
        dt = rng.uniform(0, DURATION, n)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        results = []
        for scale in (0.05, 0.5, 1.0):  # |w| dt up to scale * phi_max
            w = axis * scale * phi_max / DURATION
            out = _warp_kernel(x, y, dt, w)
            xw, yw, det, _ = reference.warp_events(
                "rotation3", x, y, dt, w, center=(CAMERA.cx, CAMERA.cy), focal=(CAMERA.fx, CAMERA.fy)
            )
            results.append((out, xw, yw, det))
        px_tol, rel_tol, det_tol = (1e-10, 1e-12, 1e-12) if precision == "f64" else (5e-3, 1e-3, 1e-5)
        for out, xw, yw, det in results:
            kept = np.isfinite(xw)
            assert np.array_equal(kept, out[0] != rotation3.OUTSIDE)
            err = np.hypot(out[0] - xw, out[1] - yw)[kept]
            radius = np.hypot(xw - CAMERA.cx, yw - CAMERA.cy)[kept]
            near = radius < 4 * SENSOR[0]
            assert near.sum() > n // 3
            assert float(err[near].max()) <= px_tol
            assert float((err / np.maximum(radius, 1.0)).max()) <= rel_tol
            rel = np.abs(out[2][kept] - det[kept]) / np.abs(det[kept])
            assert float(rel[near].max()) <= det_tol
    finally:
        use_precision("f64")


def _warp_kernel(x, y, dt, w) -> np.ndarray:
    """``(x', y', det)`` of rotation3's Taichi functions, float64 ``(3, N)``."""
    real, npr = _real()
    out = ti.ndarray(real, shape=(3, x.size))
    ctx = [CAMERA.cx, CAMERA.cy, CAMERA.fx, CAMERA.fy, DURATION]

    @ti.kernel
    def run(
        ev: ti.types.ndarray(), th: ti.types.ndarray(), c: ti.types.ndarray(), out: ti.types.ndarray()
    ):
        theta = ti.Vector([th[0], th[1], th[2]])
        cv = ti.Vector([c[0], c[1], c[2], c[3], c[4]])
        for i in range(ev.shape[1]):
            p = ti.Vector([ev[0, i], ev[1, i]])
            q = rotation3.warp(p, ev[2, i], theta, cv)
            out[0, i] = q[0]
            out[1, i] = q[1]
            out[2, i] = rotation3.det(p, ev[2, i], theta, cv)

    run(np.stack([x, y, dt]).astype(npr), np.asarray(w, npr), np.asarray(ctx, npr), out)
    return out.to_numpy().astype(np.float64)


@pytest.mark.parametrize("precision", ["f64", "f32"])
def test_se2_against_the_exact_reference(precision):
    """se2's exponential takes the same coefficients: positions against the float64 reference (exact
    complex exponential) for |w| dt from 0 to 20 rad (the default search box allows 1 rad): within
    1e-10 px (f64) / 2e-3 px (f32) on a 240x180 sensor."""
    use_precision(precision)
    try:
        rng = np.random.default_rng(4)
        n = 4000
        x, y = rng.uniform(0, 239, n), rng.uniform(0, 179, n)
        dt = rng.uniform(0, DURATION, n)
        for w_dt in (1e-3, 0.5, 1.0, 20.0):
            theta = np.array([300.0, -200.0, w_dt / DURATION])
            out = _se2_kernel(x, y, dt, theta)
            xw, yw, _, _ = reference.warp_events("se2", x, y, dt, theta, center=(119.5, 89.5))
            tol = 1e-10 if precision == "f64" else 2e-3
            assert float(np.max(np.hypot(out[0] - xw, out[1] - yw))) <= tol
    finally:
        use_precision("f64")


def _se2_kernel(x, y, dt, theta) -> np.ndarray:
    real, npr = _real()
    out = ti.ndarray(real, shape=(2, x.size))

    @ti.kernel
    def run(ev: ti.types.ndarray(), th: ti.types.ndarray(), out: ti.types.ndarray()):
        t = ti.Vector([th[0], th[1], th[2]])
        cv = ti.Vector([119.5, 89.5, 1.0, 1.0, DURATION])
        for i in range(ev.shape[1]):
            q = se2.warp(ti.Vector([ev[0, i], ev[1, i]]), ev[2, i], t, cv)
            out[0, i] = q[0]
            out[1, i] = q[1]

    run(np.stack([x, y, dt]).astype(npr), np.asarray(theta, npr), out)
    return out.to_numpy().astype(np.float64)
