"""Tests of the float64 NumPy reference (cmax_taichi/testing/reference.py) alone.

The reference is checked against independent mathematics: finite differences, closed forms,
an independent quaternion rotation, matrix exponentials, the published Mitrokhin form and
scipy.ndimage filters.
"""

import math

import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi.testing import reference, reference_warps, samples

W, H = 64, 48
CENTER = (30.3, 24.6)  # deliberately not the image centre
FOCAL = (60.0, 55.0)
T = 0.05  # s


def random_theta(rng, warp):
    """Up to 5 px of displacement over T per parameter, from the model's declared parameter kinds:
    |dt theta| stays well inside the valid range of every model."""
    camera = cm.Camera(fx=FOCAL[0], fy=FOCAL[1], cx=CENTER[0], cy=CENTER[1])
    return samples.random_theta(warp, rng, displacement=5.0, duration=T, sensor=(W, H), camera=camera)


def random_events(rng, n=300, t_ref="first"):
    x = rng.uniform(0.0, W - 1.0, n)
    y = rng.uniform(0.0, H - 1.0, n)
    t = np.sort(rng.uniform(0.0, T, n))
    t[0], t[-1] = 0.0, T
    dt = t - {"first": 0.0, "middle": T / 2, "last": T}[t_ref]
    return x, y, t, dt


def warp(name, x, y, dt, theta):
    return reference.warp_events(name, x, y, dt, theta, center=CENTER, focal=FOCAL, duration=T)


def fd_jacobian(name, x, y, dt, theta, h=1e-5):
    """Central finite-difference Jacobian d(xw, yw)/d(x, y), as four arrays."""
    xp, yp, _, _ = warp(name, x + h, y, dt, theta)
    xm, ym, _, _ = warp(name, x - h, y, dt, theta)
    j00, j10 = (xp - xm) / (2 * h), (yp - ym) / (2 * h)
    xp, yp, _, _ = warp(name, x, y + h, dt, theta)
    xm, ym, _, _ = warp(name, x, y - h, dt, theta)
    j01, j11 = (xp - xm) / (2 * h), (yp - ym) / (2 * h)
    return j00, j01, j10, j11


def flow(name, theta, center=CENTER):
    return reference.flow_field(name, theta, width=W, height=H, center=center, focal=FOCAL, duration=T)


# ----------------------------------------------------------------------------------------------
# warps: determinant, divergence, flow
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", reference.WARP_NAMES)
@pytest.mark.parametrize("t_ref", ["first", "middle", "last"])
def test_det_matches_finite_difference_jacobian(name, t_ref):
    rng = np.random.default_rng(1)
    x, y, _, dt = random_events(rng, t_ref=t_ref)
    for _ in range(3):
        theta = random_theta(rng, name)
        _, _, det, _ = warp(name, x, y, dt, theta)
        j00, j01, j10, j11 = fd_jacobian(name, x, y, dt, theta)
        np.testing.assert_allclose(det, j00 * j11 - j01 * j10, rtol=1e-6, atol=0)
        assert np.all(det > 0.2)  # moderate theta: far from collapse


@pytest.mark.parametrize("name", reference.WARP_NAMES)
def test_div_is_trace_of_flow_jacobian(name):
    # every flow depends on x only through x - c, so shifting the centre by -h evaluates the
    # closed-form field at x + h: a pointwise finite difference of flow_field on the pixel grid.
    rng = np.random.default_rng(2)
    h = 1e-4
    cx, cy = CENTER
    ys, xs = np.meshgrid(np.arange(H, dtype=float), np.arange(W, dtype=float), indexing="ij")
    for _ in range(3):
        theta = random_theta(rng, name)
        dvx_dx = (flow(name, theta, (cx - h, cy))[0] - flow(name, theta, (cx + h, cy))[0]) / (2 * h)
        dvy_dy = (flow(name, theta, (cx, cy - h))[1] - flow(name, theta, (cx, cy + h))[1]) / (2 * h)
        dt = rng.uniform(-T, T, xs.size)  # div is evaluated at the unwarped position
        _, _, _, div = warp(name, xs.ravel(), ys.ravel(), dt, theta)
        np.testing.assert_allclose(div.reshape(H, W), dvx_dx + dvy_dy, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("name", reference.WARP_NAMES)
def test_flow_is_minus_time_derivative_of_warp(name):
    rng = np.random.default_rng(3)
    e = 1e-5
    ys, xs = np.meshgrid(np.arange(H, dtype=float), np.arange(W, dtype=float), indexing="ij")
    xs, ys = xs.ravel(), ys.ravel()
    for _ in range(3):
        theta = random_theta(rng, name)
        xp, yp, _, _ = warp(name, xs, ys, np.full(xs.size, e), theta)
        xm, ym, _, _ = warp(name, xs, ys, np.full(xs.size, -e), theta)
        v = flow(name, theta)
        assert v.shape == (2, H, W)
        scale = np.abs(v).max()
        np.testing.assert_allclose(v[0], -((xp - xm) / (2 * e)).reshape(H, W), atol=1e-6 * scale)
        np.testing.assert_allclose(v[1], -((yp - ym) / (2 * e)).reshape(H, W), atol=1e-6 * scale)


def test_known_values_translation_se2_zoom_sim2():
    rng = np.random.default_rng(4)
    x, y, _, dt = random_events(rng, t_ref="middle")
    for name in ("translation2", "se2"):
        _, _, det, div = warp(name, x, y, dt, random_theta(rng, name))
        np.testing.assert_allclose(det, 1.0, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(div, 0.0)
    hz = 3.7
    xw, yw, det, div = warp("zoom1", x, y, dt, [hz])
    np.testing.assert_allclose(det, (1 - dt * hz) ** 2, rtol=1e-14)
    np.testing.assert_allclose(div, 2 * hz, rtol=1e-15)
    np.testing.assert_allclose(xw, CENTER[0] + (1 - dt * hz) * (x - CENTER[0]), rtol=1e-14)
    theta = [40.0, -70.0, 2.5, 1.8]
    _, _, det, div = warp("sim2", x, y, dt, theta)
    np.testing.assert_allclose(det, np.exp(-2 * dt * 1.8), rtol=1e-14)
    np.testing.assert_allclose(div, 2 * 1.8, rtol=1e-15)


def _homogeneous_expm_warp(x, y, dt, theta):
    """se2/sim2 by the 3x3 matrix exponential of the twist (independent of the complex form)."""
    expm = pytest.importorskip("scipy.linalg").expm
    vx, vy, w = theta[:3]
    s = theta[3] if len(theta) == 4 else 0.0
    xi = np.array([[s, -w, vx], [w, s, vy], [0.0, 0.0, 0.0]])
    out = np.empty((2, x.size))
    for k in range(x.size):
        g = expm(-dt[k] * xi)
        out[:, k] = (g @ np.array([x[k] - CENTER[0], y[k] - CENTER[1], 1.0]))[:2]
    return CENTER[0] + out[0], CENTER[1] + out[1]


@pytest.mark.parametrize("name", ["se2", "sim2"])
@pytest.mark.parametrize("tiny", [False, True])
def test_se2_sim2_match_matrix_exponential(name, tiny):
    rng = np.random.default_rng(5)
    x, y, _, dt = random_events(rng, n=60, t_ref="middle")
    theta = random_theta(rng, name)
    if tiny:  # exercises the series branch of E(z), |z| < 1e-4
        theta = theta * np.array([1.0, 1.0, 1e-4, 1e-4][: theta.size])
    xw, yw, _, _ = warp(name, x, y, dt, theta)
    xe, ye = _homogeneous_expm_warp(x, y, dt, theta)
    np.testing.assert_allclose(xw, xe, rtol=0, atol=1e-10)
    np.testing.assert_allclose(yw, ye, rtol=0, atol=1e-10)


def test_exp_series_branch_of_e_z():
    # E(z) = (e^z - 1) / z = sum_k z^k / (k + 1)!; both sides of the |z| = 1e-4 switch
    for r in (1e-7, 0.9e-4, 1.1e-4, 0.3):
        z = r * np.exp(1j * np.linspace(0.0, 2 * np.pi, 7))
        taylor = sum(z**k / math.factorial(k + 1) for k in range(12))
        np.testing.assert_allclose(reference_warps._exp_series(z), taylor, rtol=1e-11, atol=0)


def test_mitrokhin_matches_published_per_window_form():
    rng = np.random.default_rng(6)
    x, y, _, dt = random_events(rng, n=100)
    hx, hy, hz, th = random_theta(rng, "mitrokhin4")
    xw, yw, det, div = warp("mitrokhin4", x, y, dt, [hx, hy, hz, th])
    sigma = dt / T
    ht, hzt, tht = T * np.array([hx, hy]), T * hz, T * th  # per-window parameters
    xt, yt = x - CENTER[0], y - CENTER[1]
    rx = (hzt + 1) * (math.cos(tht) * xt - math.sin(tht) * yt)
    ry = (hzt + 1) * (math.sin(tht) * xt + math.cos(tht) * yt)
    np.testing.assert_allclose(xw, x - sigma * (ht[0] + rx - xt), rtol=1e-13)
    np.testing.assert_allclose(yw, y - sigma * (ht[1] + ry - yt), rtol=1e-13)
    np.testing.assert_allclose(div, 2 * ((hz * T + 1) * math.cos(th * T) - 1) / T, rtol=1e-13)


def _quaternion_rotation(axis_angle):
    """Rotation matrix of a rotation vector via a unit quaternion (no Rodrigues, no scipy)."""
    angle = np.linalg.norm(axis_angle)
    if angle == 0.0:
        return np.eye(3)
    a, (b, c, d) = math.cos(angle / 2), math.sin(angle / 2) * axis_angle / angle
    return np.array(
        [
            [a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
            [2 * (b * c + a * d), a * a - b * b + c * c - d * d, 2 * (c * d - a * b)],
            [2 * (b * d - a * c), 2 * (c * d + a * b), a * a - b * b - c * c + d * d],
        ]
    )


def test_rotation3_against_quaternion():
    rng = np.random.default_rng(7)
    x, y, _, dt = random_events(rng, n=200, t_ref="middle")
    dt[:5] = [0.0, 1e-9, -1e-9, 1e-7, -3e-6]  # series branch of the Rodrigues formula
    theta = random_theta(rng, "rotation3")
    xw, yw, det, _ = warp("rotation3", x, y, dt, theta)
    for k in range(x.size):
        rot = _quaternion_rotation(dt[k] * theta)
        ray = np.array([(x[k] - CENTER[0]) / FOCAL[0], (y[k] - CENTER[1]) / FOCAL[1], 1.0])
        r = rot @ ray
        assert xw[k] == pytest.approx(CENTER[0] + FOCAL[0] * r[0] / r[2], rel=0, abs=1e-10)
        assert yw[k] == pytest.approx(CENTER[1] + FOCAL[1] * r[1] / r[2], rel=0, abs=1e-10)
        assert det[k] == pytest.approx(1.0 / (rot[2] @ ray) ** 3, rel=1e-12)


def test_rotation3_drops_rays_behind_camera():
    x = np.array([10.0, 50.0, 31.0])
    y = np.array([20.0, 20.0, 24.0])
    dt = np.array([T, T, 0.0])
    theta = [0.0, math.pi / T, 0.0]  # half a turn about y at dt = T: rays end up behind
    xw, yw, _, _ = reference.warp_events(
        "rotation3", x, y, dt, theta, center=CENTER, focal=(5.0, 5.0), duration=T
    )
    assert np.all(np.isnan(xw[:2])) and np.all(np.isnan(yw[:2]))
    assert xw[2] == pytest.approx(31.0) and yw[2] == pytest.approx(24.0)
    out = reference.evaluate(
        x, y, np.array([T, T, 0.0]), np.ones(3), theta, warp="rotation3",
        sensor_size=(W, H), center=CENTER, focal=(5.0, 5.0), blur_sigma=0.0, normalize=False,
    )  # fmt: skip
    assert out["count"].sum() == pytest.approx(1.0)
    assert out["iwe"].sum() == pytest.approx(1.0)


@pytest.mark.parametrize("name", reference.WARP_NAMES)
def test_identity_theta_leaves_points_unchanged(name):
    rng = np.random.default_rng(8)
    x, y, _, dt = random_events(rng, t_ref="middle")
    xw, yw, det, div = warp(name, x, y, dt, np.zeros(reference.N_PARAMS[name]))
    np.testing.assert_allclose(xw, x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(yw, y, rtol=0, atol=1e-12)
    np.testing.assert_allclose(det, 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(div, 0.0, rtol=0, atol=1e-14)


@pytest.mark.parametrize("name", reference.WARP_NAMES)
def test_det_is_one_minus_dt_div_to_first_order(name):
    rng = np.random.default_rng(9)
    x, y, _, _ = random_events(rng, n=100)
    theta = random_theta(rng, name)
    errors = []
    for step in (1e-3, 1e-4):
        dt = step * rng.choice([-1.0, 1.0], size=x.size)
        _, _, det, div = warp(name, x, y, dt, theta)
        err = np.abs(det - (1.0 - dt * div))
        assert np.all(err <= 100.0 * step**2)  # |second-order term| <= C dt^2
        errors.append(err.max())
    # second-order remainder: 10x smaller dt gives ~100x smaller error (unless it vanishes)
    assert errors[1] <= errors[0] / 50.0 or errors[0] < 1e-13


# ----------------------------------------------------------------------------------------------
# image of warped events
# ----------------------------------------------------------------------------------------------
def test_bilinear_integer_pixel_gets_all_weight():
    img = reference.bilinear_votes([5.0], [7.0], [2.5], W, H)
    expected = np.zeros((H, W))
    expected[7, 5] = 2.5
    np.testing.assert_array_equal(img, expected)


def test_bilinear_split_and_conservation_inside():
    img = reference.bilinear_votes([5.25], [7.5], [1.0], W, H)
    assert img[7, 5] == pytest.approx(0.75 * 0.5)
    assert img[7, 6] == pytest.approx(0.25 * 0.5)
    assert img[8, 5] == pytest.approx(0.75 * 0.5)
    assert img[8, 6] == pytest.approx(0.25 * 0.5)
    rng = np.random.default_rng(10)
    xw, yw = rng.uniform(0, W - 1, 1000), rng.uniform(0, H - 1, 1000)
    wts = rng.uniform(-1, 2, 1000)
    assert reference.bilinear_votes(xw, yw, wts, W, H).sum() == pytest.approx(wts.sum(), rel=1e-12)


def test_bilinear_border_and_outside():
    assert reference.bilinear_votes([W - 0.5], [10.0], [1.0], W, H).sum() == pytest.approx(0.5)
    assert reference.bilinear_votes([-0.5], [10.0], [1.0], W, H).sum() == pytest.approx(0.5)
    assert reference.bilinear_votes([10.0], [H - 0.25], [1.0], W, H).sum() == pytest.approx(0.25)
    outside = [(-1.0, 5.0), (float(W), 5.0), (5.0, -1.5), (5.0, H + 3.0), (np.nan, 5.0)]
    for xo, yo in outside:
        assert reference.bilinear_votes([xo], [yo], [1.0], W, H).sum() == 0.0


@pytest.mark.parametrize("sigma", [0.5, 1.0, 1.7])
def test_blur_matches_scipy_correlate1d(sigma):
    ndimage = pytest.importorskip("scipy.ndimage")
    rng = np.random.default_rng(11)
    img = rng.uniform(0, 3, (H, W))
    r = math.ceil(3 * sigma)
    g = np.exp(-(np.arange(-r, r + 1) ** 2) / (2 * sigma**2))
    g /= g.sum()
    expected = ndimage.correlate1d(img, g, axis=1, mode="constant", cval=0.0)
    expected = ndimage.correlate1d(expected, g, axis=0, mode="constant", cval=0.0)
    np.testing.assert_allclose(reference.gaussian_blur(img, sigma), expected, rtol=1e-12, atol=1e-14)
    stack = np.stack([img, 2 * img])
    np.testing.assert_allclose(reference.gaussian_blur(stack, sigma)[1], 2 * expected, rtol=1e-12)


def test_blur_conserves_sum_away_from_border_and_sigma_zero_copies():
    rng = np.random.default_rng(12)
    img = np.zeros((H, W))
    img[10:-10, 10:-10] = rng.uniform(0, 1, (H - 20, W - 20))
    out = reference.gaussian_blur(img, 2.0)  # r = 6 < 10
    assert out.sum() == pytest.approx(img.sum(), rel=1e-12)
    assert not np.allclose(out, img)
    same = reference.gaussian_blur(img, 0.0)
    np.testing.assert_array_equal(same, img)
    assert same is not img


# ----------------------------------------------------------------------------------------------
# objectives
# ----------------------------------------------------------------------------------------------
def test_objectives_against_direct_formulas():
    ndimage = pytest.importorskip("scipy.ndimage")
    rng = np.random.default_rng(13)
    images = rng.uniform(-1, 2, (2, H, W))
    var = sum(np.var(ch) for ch in images)
    assert reference.objective_value("variance", images) == pytest.approx(var, rel=1e-12)
    ms = sum(np.mean(ch**2) for ch in images)
    assert reference.objective_value("mean_square", images) == pytest.approx(ms, rel=1e-12)
    sobel_x = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], dtype=float) / 8
    gm = 0.0
    for ch in images:
        gx = ndimage.correlate(ch, sobel_x, mode="constant", cval=0.0)
        gy = ndimage.correlate(ch, sobel_x.T, mode="constant", cval=0.0)
        gm += np.mean(gx**2 + gy**2)
    assert reference.objective_value("gradient_magnitude", images) == pytest.approx(gm, rel=1e-12)
    # closed form: an interior impulse v gives sum(g_x^2 + g_y^2) = (12 + 12) v^2 / 64
    impulse = np.zeros((H, W))
    impulse[10, 20] = 3.0
    expected = 24 * 9.0 / 64 / (H * W)
    got = reference.objective_value("gradient_magnitude", impulse)
    assert got == pytest.approx(expected, rel=1e-14)
    # at a corner the zero padding keeps only the (2, 1; 1) part of each kernel: (4+1+...)
    corner = np.zeros((H, W))
    corner[0, 0] = 1.0
    kept = (2**2 + 1**2) + (2**2 + 1**2)  # g_x at (0,1),(1,1); g_y at (1,0),(1,1)
    got = reference.objective_value("gradient_magnitude", corner)
    assert got == pytest.approx(kept / 64 / (H * W), rel=1e-14)


# ----------------------------------------------------------------------------------------------
# full pipeline: regularizers, J, normalisation
# ----------------------------------------------------------------------------------------------
def _events(rng, n=2000):
    x = rng.uniform(0, W - 1, n)
    y = rng.uniform(0, H - 1, n)
    t = np.sort(rng.uniform(0, T, n))
    t[0], t[-1] = 0.0, T
    p = rng.integers(0, 2, n)
    return x, y, t, p


def test_zoom_divergence_penalty_and_sign():
    rng = np.random.default_rng(14)
    x, y, t, p = _events(rng)
    hz = 6.0
    first = reference.evaluate(x, y, t, p, [hz], warp="zoom1", sensor_size=(W, H))
    assert first["R_div"] == pytest.approx(T * 2 * hz, rel=0, abs=1e-12)
    assert first["R_div"] > 0
    # with t_ref last, h_z > 0 expands the events: one-sided R_Div does not reward it
    last = reference.evaluate(x, y, t, p, [hz], warp="zoom1", sensor_size=(W, H), t_ref="last")
    assert last["R_div"] == 0.0
    last_contracting = reference.evaluate(x, y, t, p, [-hz], warp="zoom1", sensor_size=(W, H), t_ref="last")
    assert last_contracting["R_div"] == pytest.approx(T * 2 * hz, rel=0, abs=1e-12)
    expanding = reference.evaluate(x, y, t, p, [-hz], warp="zoom1", sensor_size=(W, H))
    assert expanding["R_div"] == 0.0
    support = first["count"] > 0
    np.testing.assert_allclose(first["div_map"][support], 2 * hz, rtol=1e-12)
    assert np.all(np.isnan(first["div_map"][~support]))  # "no event here" is NaN


def test_translation_has_zero_penalties():
    rng = np.random.default_rng(15)
    x, y, t, p = _events(rng)
    out = reference.evaluate(
        x, y, t, p, [120.0, -80.0], warp="translation2", sensor_size=(W, H),
        lambda_div=3.0, lambda_def=5.0,
    )  # fmt: skip
    assert out["R_def"] == pytest.approx(0.0, abs=1e-12)
    assert out["R_div"] == 0.0
    assert out["J"] == pytest.approx(out["G"], rel=1e-12)


def test_zoom_collapse_gives_large_finite_deformation():
    rng = np.random.default_rng(16)
    x, y, t, p = _events(rng)
    mild = reference.evaluate(x, y, t, p, [0.1 / T], warp="zoom1", sensor_size=(W, H))
    collapse = reference.evaluate(x, y, t, p, [1.0 / T], warp="zoom1", sensor_size=(W, H))
    assert np.isfinite(collapse["R_def"])
    assert collapse["R_def"] <= 1.0 / reference.DEF_FLOOR - 1.0
    assert collapse["R_def"] > 10.0 * mild["R_def"]
    # the pixel at the centre collects the collapsed events (a_k -> 0): alpha is large there,
    # but it is one pixel of the support, so the mean R_def only reaches ~2 on uniform events
    assert 100.0 < np.nanmax(collapse["alpha_map"]) <= 1.0 / reference.DEF_FLOOR - 1.0
    assert collapse["R_def"] > 1.5


@pytest.mark.parametrize("objective", ["variance", "gradient_magnitude", "mean_square"])
@pytest.mark.parametrize("polarity", ["ignore", "signed", "split"])
def test_augmented_objective_and_normalisation(objective, polarity):
    rng = np.random.default_rng(17)
    x, y, t, p = _events(rng, n=1500)
    theta = [60.0, -30.0, 1.5, 2.0]
    kw = dict(warp="sim2", sensor_size=(W, H), objective=objective, polarity=polarity)
    out = reference.evaluate(x, y, t, p, theta, lambda_div=0.7, lambda_def=1.3, **kw)
    assert out["J"] == pytest.approx(out["G"] - 0.7 * out["R_div"] - 1.3 * out["R_def"], rel=1e-14)
    assert out["G"] == pytest.approx(out["G_raw"] / out["G0"], rel=1e-14)
    assert out["iwe"].shape == ((2 if polarity == "split" else 1), H, W)
    raw = reference.evaluate(x, y, t, p, theta, normalize=False, **kw)
    assert raw["G"] == raw["G_raw"] == out["G_raw"]
    ident = reference.evaluate(x, y, t, p, np.zeros(4), **kw)
    assert ident["G_raw"] == pytest.approx(out["G0"], rel=1e-14)
    assert ident["G"] == pytest.approx(1.0, rel=1e-14)
    assert ident["R_def"] == pytest.approx(0.0, abs=1e-12) and ident["R_div"] == 0.0


def test_polarity_and_weights_conventions():
    rng = np.random.default_rng(18)
    x, y, t, p01 = _events(rng, n=500)
    x, y = 2 + x * (W - 5) / (W - 1), 2 + y * (H - 5) / (H - 1)  # stay inside after the shift
    pm = np.where(p01 > 0, 1, -1)
    kw = dict(warp="translation2", sensor_size=(W, H), blur_sigma=0.0, normalize=False)
    a = reference.evaluate(x, y, t, p01, [10.0, 5.0], polarity="signed", **kw)
    b = reference.evaluate(x, y, t, pm, [10.0, 5.0], polarity="signed", **kw)
    np.testing.assert_array_equal(a["iwe"], b["iwe"])
    assert a["iwe"].sum() == pytest.approx(pm.sum(), abs=1e-9)
    split = reference.evaluate(x, y, t, pm, [10.0, 5.0], polarity="split", **kw)
    assert split["iwe"][0].sum() == pytest.approx((pm > 0).sum())
    assert split["iwe"][1].sum() == pytest.approx((pm < 0).sum())
    wts = rng.uniform(-2, 2, x.size)
    c = reference.evaluate(x, y, t, pm, [10.0, 5.0], weights=wts, **kw)
    assert c["count"].sum() == pytest.approx(np.abs(wts).sum(), rel=1e-12)
    assert c["iwe"].sum() == pytest.approx(wts.sum(), rel=1e-9)


# ----------------------------------------------------------------------------------------------
# whitening
# ----------------------------------------------------------------------------------------------
def _mean_cov(a, b):
    pts = np.stack([a, b])
    d = pts - pts.mean(axis=1, keepdims=True)
    return pts.mean(axis=1), d @ d.T / pts.shape[1]


def test_whitening_identity_is_unchanged():
    rng = np.random.default_rng(19)
    x, y, _, _ = random_events(rng, n=1000)
    xw, yw = reference.whiten(x, y, x, y, eps=0.0)
    np.testing.assert_allclose(xw, x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(yw, y, rtol=0, atol=1e-9)
    # with the default eps = 1e-6 px^2 the identity moves by at most eps |x - mu| / (2 lambda_min)
    xd, yd = reference.whiten(x, y, x, y)
    mu, s = _mean_cov(x, y)
    bound = 1e-6 * np.hypot(x - mu[0], y - mu[1]).max() / (2 * np.linalg.eigvalsh(s)[0])
    assert np.hypot(xd - x, yd - y).max() <= 1.01 * bound + 1e-12


@pytest.mark.parametrize("eps, rtol", [(0.0, 1e-10), (1e-6, 1e-7)])
def test_whitened_positions_have_unwarped_moments(eps, rtol):
    rng = np.random.default_rng(20)
    x, y, _, dt = random_events(rng, n=1000)
    xw, yw, _, _ = warp("sim2", x, y, dt, [150.0, -80.0, 6.0, 12.0])
    xww, yww = reference.whiten(xw, yw, x, y, eps=eps)
    mu0, s0 = _mean_cov(x, y)
    mu, s = _mean_cov(xww, yww)
    np.testing.assert_allclose(mu, mu0, rtol=1e-12)
    np.testing.assert_allclose(s, s0, rtol=rtol, atol=rtol * np.abs(s0).max())
    assert not np.allclose(s, _mean_cov(xw, yw)[1], rtol=1e-3)  # the warp did change them


def test_whitening_in_pipeline_keeps_regularizers_on_warped_positions():
    rng = np.random.default_rng(21)
    x, y, t, p = _events(rng, n=1000)
    kw = dict(warp="zoom1", sensor_size=(W, H))
    plain = reference.evaluate(x, y, t, p, [8.0], **kw)
    white = reference.evaluate(x, y, t, p, [8.0], whitening=True, **kw)
    np.testing.assert_array_equal(white["count"], plain["count"])
    assert white["R_div"] == plain["R_div"] and white["R_def"] == plain["R_def"]
    assert white["G_raw"] != pytest.approx(plain["G_raw"], rel=1e-3)
    ident = reference.evaluate(x, y, t, p, [0.0], whitening=True, **kw)
    assert ident["G"] == pytest.approx(1.0, rel=1e-12)


# ----------------------------------------------------------------------------------------------
# bad input
# ----------------------------------------------------------------------------------------------
def test_bad_input_raises():
    x = np.array([1.0, 2.0, 3.0])
    y = np.array([1.0, 2.0, 3.0])
    t = np.array([0.0, 0.01, 0.02])
    p = np.array([1, 0, 1])
    ev = dict(sensor_size=(W, H))
    with pytest.raises(ValueError, match="warp"):
        reference.evaluate(x, y, t, p, [1.0], warp="affine6", **ev)
    with pytest.raises(ValueError, match="objective"):
        reference.evaluate(x, y, t, p, [1.0], warp="zoom1", objective="entropy", **ev)
    with pytest.raises(ValueError, match="polarity"):
        reference.evaluate(x, y, t, p, [1.0], warp="zoom1", polarity="both", **ev)
    with pytest.raises(ValueError, match="parameter"):
        reference.evaluate(x, y, t, p, [1.0, 2.0], warp="zoom1", **ev)
    with pytest.raises(ValueError, match="parameter"):
        reference.warp_events("se2", x, y, t, [1.0, 2.0], center=CENTER, duration=T)
    with pytest.raises(ValueError, match="focal"):
        reference.evaluate(x, y, t, p, [0.1, 0.2, 0.3], warp="rotation3", **ev)
    with pytest.raises(ValueError, match="focal"):
        reference.warp_events("rotation3", x, y, t, [0.1, 0.2, 0.3], center=CENTER, duration=T)
    with pytest.raises(ValueError, match="focal"):
        reference.flow_field("rotation3", [0.1, 0.2, 0.3], width=W, height=H, center=CENTER)
    with pytest.raises(ValueError, match="T"):
        reference.evaluate(x, y, np.full(3, 0.5), p, [1.0], warp="zoom1", **ev)
    with pytest.raises(ValueError, match="T"):
        reference.warp_events("mitrokhin4", x, y, t, np.zeros(4), center=CENTER, duration=0.0)
    with pytest.raises(ValueError, match="t_ref"):
        reference.evaluate(x, y, t, p, [1.0], warp="zoom1", t_ref="start", **ev)
    with pytest.raises(ValueError, match="polarit"):
        reference.evaluate(x, y, t, np.array([2, 0, 1]), [1.0], warp="zoom1", **ev)
    with pytest.raises(ValueError, match="objective"):
        reference.objective_value("contrast", np.zeros((1, 4, 4)))
