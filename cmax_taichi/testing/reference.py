"""Independent float64 NumPy reference ("oracle") of the Contrast Maximization pipeline.

This module implements, literally and in float64, every formula of ``docs/FORMULAS.md``: the
parametric warps (with their Jacobian determinants and flow divergences), the image of warped
events (bilinear voting and Gaussian blur), the objectives, the divergence and deformation
regularizers, the augmented objective and the whitening baseline. It is written independently of
the Taichi kernels and is used by the tests (as the oracle the kernels are held against) and by the
benchmark. It favours readability over speed and depends on NumPy only.

The warps form a small registry of their own (:class:`ReferenceWarp`, :func:`register_reference_warp`):
the built-ins register in ``reference_warps.py`` (a new built-in adds its twin there), and a user model
registers its own (see ``examples/user_extensions.py``) without editing this package.

Units: positions in pixels (px), times in seconds (s), parameters in physical units (px/s, 1/s,
rad/s), flows in px/s, divergences in 1/s.
"""

from __future__ import annotations

import math

import numpy as np

from cmax_taichi.testing.reference_warps import (  # noqa: F401 - re-exported: the oracle's public names
    EXP_SERIES_Z,
    REFERENCE_WARPS,
    ROT_SERIES_PHI,
    Z_MIN,
    ReferenceWarp,
    register_reference_warp,
    unregister_reference_warp,
)

OBJECTIVE_NAMES = ("variance", "gradient_magnitude", "mean_square")
POLARITY_MODES = ("ignore", "signed", "split")
T_REF_NAMES = ("first", "middle", "last")

#: soft-support constant of the regularizer maps, ``m(x) = C(x) / (C(x) + KAPPA)``
KAPPA = 0.05
#: guard of the deformation map against collapse, ``D = max(DEF(x), DEF_FLOOR)``
DEF_FLOOR = 1e-3
#: Tikhonov term of the whitening baseline (px^2)
WHITEN_EPS = 1e-6
# Sobel kernels (correlation; rows are y, columns x), divided by 8 as in FORMULAS.md.
_SOBEL_X = np.array([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]])
_SOBEL_Y = _SOBEL_X.T.copy()


# ----------------------------------------------------------------------------------------------
# validation helpers
# ----------------------------------------------------------------------------------------------
def _check_warp(warp: str) -> ReferenceWarp:
    if warp not in REFERENCE_WARPS:
        raise ValueError(f"unknown warp {warp!r}; expected one of {tuple(REFERENCE_WARPS)}")
    return REFERENCE_WARPS[warp]


def _check_theta(warp: str, theta) -> np.ndarray:
    n = _check_warp(warp).n_params
    theta = np.asarray(theta, dtype=np.float64).reshape(-1)
    if theta.size != n:
        raise ValueError(f"warp {warp!r} takes {n} parameter(s), got theta of length {theta.size}")
    return theta


def _check_focal(warp: str, focal) -> tuple[float, float]:
    if focal is None:
        raise ValueError(f"warp {warp!r} needs the focal lengths focal=(fx, fy) in px")
    fx, fy = (float(v) for v in focal)
    if fx == 0.0 or fy == 0.0:
        raise ValueError(f"focal lengths must be non-zero, got {(fx, fy)}")
    return fx, fy


def _check_duration(warp: str, duration) -> float:
    if not _check_warp(warp).needs_duration:
        return float("nan") if duration is None else float(duration)
    if duration is None or not float(duration) > 0.0:
        raise ValueError(f"warp {warp!r} needs a window duration T > 0 s, got {duration!r}")
    return float(duration)


def _context(warp: str, focal, duration) -> dict:
    """The validated keyword arguments ``focal`` and ``duration`` of a reference warp's functions."""
    rw = _check_warp(warp)
    focal = _check_focal(warp, focal) if rw.needs_focal else focal
    return {"focal": focal, "duration": _check_duration(warp, duration)}


#: the built-in warps and their parameter counts
WARP_NAMES = tuple(REFERENCE_WARPS)
N_PARAMS = {name: REFERENCE_WARPS[name].n_params for name in WARP_NAMES}


def warp_events(
    warp: str,
    x,
    y,
    dt,
    theta,
    *,
    center,
    focal=None,
    duration=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Warp events to the reference time.

    Parameters
    ----------
    warp : str
        A registered reference warp (:data:`WARP_NAMES` and those of :func:`register_reference_warp`).
    x, y : array_like, shape (N,)
        Event positions (px), pixel centres at integers.
    dt : array_like, shape (N,)
        ``t_k - t_ref`` (s).
    theta : array_like, shape (n_params,)
        Warp parameters in physical units (px/s, 1/s, rad/s; see FORMULAS.md).
    center : tuple of float
        ``(c_x, c_y)`` (px), the origin of ``x~ = x - c``.
    focal : tuple of float, optional
        ``(f_x, f_y)`` (px); required by ``rotation3`` (ValueError otherwise).
    duration : float
        Window duration ``T`` (s); required (> 0) by ``mitrokhin4``, unused by the other warps.

    Returns
    -------
    xw, yw : ndarray, shape (N,)
        Warped positions ``x'`` (px). For ``rotation3``, events whose rotated ray has
        ``X'_z <= 1e-6`` get ``xw = yw = nan`` (they are dropped from every image).
    det : ndarray, shape (N,)
        Signed Jacobian determinant ``det dx'/dx`` (dimensionless); the deformation uses its
        absolute value.
    div : ndarray, shape (N,)
        Divergence of the flow ``div v`` at the event's unwarped position (1/s).
    """
    theta = _check_theta(warp, theta)
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    dt = np.broadcast_to(np.asarray(dt, dtype=np.float64), x.shape)
    center = tuple(float(v) for v in center)
    context = _context(warp, focal, duration)
    xw, yw, det, div = REFERENCE_WARPS[warp].warp(theta, x, y, dt, center=center, **context)
    shape = x.shape
    return tuple(np.broadcast_to(np.asarray(a, dtype=np.float64), shape).copy() for a in (xw, yw, det, div))


def flow_field(
    warp: str,
    theta,
    *,
    width: int,
    height: int,
    center,
    focal=None,
    duration=None,
) -> np.ndarray:
    """Instantaneous flow ``v(x)`` of a parametric warp on the pixel grid.

    Parameters
    ----------
    warp : str
        A registered reference warp.
    theta : array_like
        Warp parameters (physical units).
    width, height : int
        Grid size W, H (px); pixel ``(i, j)`` is at ``x = i, y = j``.
    center : tuple of float
        ``(c_x, c_y)`` (px).
    focal : tuple of float, optional
        ``(f_x, f_y)`` (px), required by ``rotation3``.
    duration : float
        Window duration ``T`` (s), required by ``mitrokhin4``.

    Returns
    -------
    ndarray, shape (2, H, W)
        ``(v_x, v_y)`` in px/s, the closed forms of FORMULAS.md (``v = -dW/d(dt)`` at ``dt = 0``).
    """
    theta = _check_theta(warp, theta)
    cx, cy = (float(v) for v in center)
    context = _context(warp, focal, duration)
    ys, xs = np.meshgrid(
        np.arange(int(height), dtype=np.float64),
        np.arange(int(width), dtype=np.float64),
        indexing="ij",
    )
    vx, vy = REFERENCE_WARPS[warp].flow(theta, xs - cx, ys - cy, **context)
    shape = xs.shape
    return np.stack([np.broadcast_to(np.asarray(v, np.float64), shape) for v in (vx, vy)], axis=0)


# ----------------------------------------------------------------------------------------------
# image of warped events
# ----------------------------------------------------------------------------------------------
def bilinear_votes(xw, yw, weights, width: int, height: int) -> np.ndarray:
    """Bilinear voting of weighted points into an image (FORMULAS.md IWE step 2).

    Parameters
    ----------
    xw, yw : array_like, shape (N,)
        Point positions (px).
    weights : array_like, shape (N,)
        Vote weight ``b_k`` of each point.
    width, height : int
        Image size W, H (px).

    Returns
    -------
    ndarray, shape (H, W)
        ``V(x)``. Points that are not finite or lie outside ``(-1, W) x (-1, H)`` add nothing;
        the part of a vote that falls on a pixel outside the image is dropped.
    """
    width = int(width)
    height = int(height)
    xw = np.asarray(xw, dtype=np.float64).reshape(-1)
    yw = np.asarray(yw, dtype=np.float64).reshape(-1)
    b = np.broadcast_to(np.asarray(weights, dtype=np.float64), xw.shape).reshape(-1)
    image = np.zeros((height, width), dtype=np.float64)

    ok = np.isfinite(xw) & np.isfinite(yw)
    ok[ok] = (xw[ok] > -1.0) & (xw[ok] < width) & (yw[ok] > -1.0) & (yw[ok] < height)
    xw, yw, b = xw[ok], yw[ok], b[ok]

    x0 = np.floor(xw)
    y0 = np.floor(yw)
    ax = xw - x0
    ay = yw - y0
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    for dx, dy, share in (
        (0, 0, (1.0 - ax) * (1.0 - ay)),
        (1, 0, ax * (1.0 - ay)),
        (0, 1, (1.0 - ax) * ay),
        (1, 1, ax * ay),
    ):
        col = x0 + dx
        row = y0 + dy
        inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
        np.add.at(image, (row[inside], col[inside]), b[inside] * share[inside])
    return image


def gaussian_kernel(sigma: float) -> np.ndarray:
    """Normalised truncated Gaussian ``g_i``, ``i = -r..r``, ``r = ceil(3 sigma)`` (sigma in px)."""
    sigma = float(sigma)
    r = int(math.ceil(3.0 * sigma))
    i = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-(i**2) / (2.0 * sigma**2))
    return g / g.sum()


def _correlate_axis(image: np.ndarray, kernel: np.ndarray, axis: int) -> np.ndarray:
    """Correlation with an odd-length centred kernel along ``axis``, zero padding."""
    r = (kernel.size - 1) // 2
    n = image.shape[axis]
    pad = [(0, 0)] * image.ndim
    pad[axis] = (r, r)
    padded = np.pad(image, pad, mode="constant", constant_values=0.0)
    out = np.zeros_like(image, dtype=np.float64)
    for j, gj in enumerate(kernel):  # out[i] = sum_j g[j] * image[i + j - r]
        out += gj * np.take(padded, np.arange(j, j + n), axis=axis)
    return out


def gaussian_blur(image, sigma: float) -> np.ndarray:
    """Separable Gaussian blur with zero padding (FORMULAS.md IWE step 3).

    Parameters
    ----------
    image : array_like, shape (..., H, W)
        Image(s); the blur acts on the last two axes.
    sigma : float
        Standard deviation (px). ``sigma = 0`` returns a copy.

    Returns
    -------
    ndarray, same shape as ``image``
        Rows (along x) correlated first, then columns (along y), with the normalised kernel of
        :func:`gaussian_kernel`; values outside the image are 0.
    """
    image = np.array(image, dtype=np.float64, copy=True)
    if sigma < 0:
        raise ValueError(f"blur sigma must be >= 0 px, got {sigma}")
    if sigma == 0:
        return image
    g = gaussian_kernel(sigma)
    out = _correlate_axis(image, g, axis=image.ndim - 1)  # along x
    return _correlate_axis(out, g, axis=image.ndim - 2)  # along y


def _correlate2d_3x3(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """2-D correlation of an (H, W) image with a 3x3 kernel, zero padding."""
    h, w = image.shape
    padded = np.pad(image, 1, mode="constant", constant_values=0.0)
    out = np.zeros((h, w), dtype=np.float64)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out += kernel[dy + 1, dx + 1] * padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
    return out


def objective_value(name: str, images: np.ndarray) -> float:
    """Contrast objective ``G`` of a stack of images (maximised).

    Parameters
    ----------
    name : str
        ``"variance"``, ``"gradient_magnitude"`` or ``"mean_square"``.
    images : ndarray, shape (C, H, W) or (H, W)
        The (blurred) IWE channels ``I_c``.

    Returns
    -------
    float
        Sum over the channels of the per-channel objective (units of ``I^2``):
        variance ``mean(I^2) - mean(I)^2``; gradient magnitude ``mean(g_x^2 + g_y^2)`` with
        ``g = Sobel(I) / 8`` (zero padding); mean square ``mean(I^2)``.
    """
    if name not in OBJECTIVE_NAMES:
        raise ValueError(f"unknown objective {name!r}; expected one of {OBJECTIVE_NAMES}")
    images = np.asarray(images, dtype=np.float64)
    if images.ndim == 2:
        images = images[None]
    total = 0.0
    for img in images:
        n = img.size
        if name == "variance":
            total += float(np.sum(img**2) / n - (np.sum(img) / n) ** 2)
        elif name == "mean_square":
            total += float(np.sum(img**2) / n)
        else:
            gx = _correlate2d_3x3(img, _SOBEL_X / 8.0)
            gy = _correlate2d_3x3(img, _SOBEL_Y / 8.0)
            total += float(np.sum(gx**2 + gy**2) / n)
    return total


# ----------------------------------------------------------------------------------------------
# whitening baseline
# ----------------------------------------------------------------------------------------------
def _mean_cov(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pts = np.stack([x, y], axis=0)
    mu = pts.mean(axis=1)
    d = pts - mu[:, None]
    return mu, (d @ d.T) / pts.shape[1]


def _sym_power(s: np.ndarray, power: float, shift: float = 0.0) -> np.ndarray:
    """``(S + shift I)^power`` of a symmetric PSD 2x2 matrix via eigendecomposition."""
    lam, vec = np.linalg.eigh(s)
    lam = np.maximum(lam + shift, 0.0)
    if power < 0:
        scaled = np.zeros_like(lam)
        pos = lam > 0
        scaled[pos] = lam[pos] ** power
    else:
        scaled = lam**power
    return (vec * scaled) @ vec.T


def whiten(xw, yw, x, y, *, eps: float = WHITEN_EPS) -> tuple[np.ndarray, np.ndarray]:
    """Whitening baseline: give the warped positions the mean and covariance of the unwarped ones.

    ``x''_k = mu0 + S0^(1/2) (S + eps I)^(-1/2) (x'_k - mu)`` with symmetric square roots.

    Parameters
    ----------
    xw, yw : array_like, shape (N,)
        Warped positions ``x'_k`` (px). Non-finite ones (dropped events) are excluded from
        ``mu, S`` and stay non-finite.
    x, y : array_like, shape (N,)
        Unwarped positions (px), for ``mu0, S0``.
    eps : float, optional
        Regulariser (px^2), default 1e-6 as in FORMULAS.md.

    Returns
    -------
    xww, yww : ndarray, shape (N,)
        Whitened positions ``x''_k`` (px).
    """
    xw = np.asarray(xw, dtype=np.float64)
    yw = np.asarray(yw, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    finite = np.isfinite(xw) & np.isfinite(yw)
    if not np.any(finite):
        return xw.copy(), yw.copy()
    mu0, s0 = _mean_cov(x, y)
    mu, s = _mean_cov(xw[finite], yw[finite])
    m = _sym_power(s0, 0.5) @ _sym_power(s, -0.5, shift=eps)
    dx = xw - mu[0]
    dy = yw - mu[1]
    return mu0[0] + m[0, 0] * dx + m[0, 1] * dy, mu0[1] + m[1, 0] * dx + m[1, 1] * dy


# ----------------------------------------------------------------------------------------------
# full pipeline
# ----------------------------------------------------------------------------------------------
def _resolve_t_ref(t_ref, t: np.ndarray) -> float:
    if isinstance(t_ref, str):
        if t_ref == "first":
            return float(t.min())
        if t_ref == "middle":
            return float((t.min() + t.max()) / 2.0)
        if t_ref == "last":
            return float(t.max())
        raise ValueError(f"unknown t_ref {t_ref!r}; expected one of {T_REF_NAMES} or seconds")
    return float(t_ref)


def polarity_iwe(
    xw, yw, weights, pol, polarity: str, width: int, height: int, blur_sigma: float
) -> np.ndarray:
    """The blurred IWE channels ``(C, H, W)`` of the warped events ``(xw, yw)``, px: one of the votes
    ``weights`` (``polarity="ignore"``), of ``weights * pol`` ("signed"), or two, of the positive and
    the negative events ("split"); ``pol`` is +1 or -1 per event."""
    if polarity == "ignore":
        channels = [weights]
    elif polarity == "signed":
        channels = [weights * pol]
    else:  # split
        channels = [np.where(pol > 0, weights, 0.0), np.where(pol < 0, weights, 0.0)]
    votes = np.stack([bilinear_votes(xw, yw, b, width, height) for b in channels], axis=0)
    return gaussian_blur(votes, blur_sigma)


def _support_mean(m: np.ndarray, p: np.ndarray) -> float:
    total = float(np.sum(m))
    if total <= 0.0:
        return 0.0
    return float(np.sum(m * p) / total)


def evaluate(
    x,
    y,
    t,
    p,
    theta,
    *,
    warp: str,
    sensor_size: tuple[int, int],
    center=None,
    focal=None,
    t_ref="first",
    objective: str = "variance",
    normalize: bool = True,
    blur_sigma: float = 1.0,
    polarity: str = "ignore",
    weights=None,
    lambda_div: float = 0.0,
    lambda_def: float = 0.0,
    whitening: bool = False,
) -> dict:
    """Run the whole pipeline of FORMULAS.md for one parameter vector.

    Parameters
    ----------
    x, y : array_like, shape (N,)
        Event positions (px).
    t : array_like, shape (N,)
        Event times (s).
    p : array_like, shape (N,)
        Polarities in {0, 1} or {-1, +1} (0 means -1).
    theta : array_like
        Warp parameters (physical units: px/s, 1/s, rad/s).
    warp : str
        A registered reference warp (:data:`WARP_NAMES` and those of :func:`register_reference_warp`).
    sensor_size : tuple of int
        ``(W, H)`` (px).
    center : tuple of float, optional
        Principal point ``(c_x, c_y)`` (px); default the image centre ``((W-1)/2, (H-1)/2)``.
    focal : tuple of float, optional
        ``(f_x, f_y)`` (px); required by ``rotation3``.
    t_ref : {"first", "middle", "last"} or float
        Reference time (float: seconds, same clock as ``t``).
    objective : str
        ``"variance"``, ``"gradient_magnitude"`` or ``"mean_square"``.
    normalize : bool
        Use ``G(theta) / G(0)`` in J (else the raw ``G(theta)``).
    blur_sigma : float
        Gaussian blur standard deviation (px); 0 disables the blur.
    polarity : {"ignore", "signed", "split"}
        How polarities enter the IWE.
    weights : array_like, shape (N,), optional
        Per-event weights ``w_k`` (default 1).
    lambda_div, lambda_def : float
        Weights of the divergence and deformation penalties in J.
    whitening : bool
        Build the IWE from whitened positions (the regularizer maps still use ``x'``).

    Returns
    -------
    dict
        ``J`` (float, augmented objective), ``G`` (objective used in J), ``G_raw``, ``G0`` (raw
        objective of the identity warp), ``R_div``, ``R_def`` (penalties, dimensionless),
        ``iwe`` (C, H, W), ``count`` C(x) (H, W), ``div_map`` DIV(x) (1/s, NaN where C = 0),
        ``def_map`` DEF(x) (NaN where C = 0), ``alpha_map`` alpha(x) (NaN where C = 0), and per
        event ``xw``, ``yw`` (px), ``det`` (signed ``det dx'/dx``), ``div`` (1/s).
    """
    _check_warp(warp)
    theta = _check_theta(warp, theta)
    if objective not in OBJECTIVE_NAMES:
        raise ValueError(f"unknown objective {objective!r}; expected one of {OBJECTIVE_NAMES}")
    if polarity not in POLARITY_MODES:
        raise ValueError(f"unknown polarity mode {polarity!r}; expected one of {POLARITY_MODES}")
    width, height = (int(v) for v in sensor_size)
    if width <= 0 or height <= 0:
        raise ValueError(f"sensor_size must be positive (W, H), got {sensor_size!r}")
    if blur_sigma < 0:
        raise ValueError(f"blur_sigma must be >= 0 px, got {blur_sigma}")

    x = np.asarray(x, dtype=np.float64).reshape(-1)
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    p = np.asarray(p, dtype=np.float64).reshape(-1)
    n = x.size
    if n == 0:
        raise ValueError("no events")
    if not (y.size == n and t.size == n and p.size == n):
        raise ValueError("x, y, t, p must have the same length")
    if not np.all(np.isin(p, (-1.0, 0.0, 1.0))):
        raise ValueError("polarities must be in {0, 1} or {-1, +1}")
    pol = np.where(p > 0, 1.0, -1.0)
    if weights is None:
        w = np.ones(n)
    else:
        w = np.broadcast_to(np.asarray(weights, dtype=np.float64), (n,)).copy()

    T = float(t.max() - t.min())
    if not T > 0.0:
        raise ValueError(f"the window duration T = max(t) - min(t) must be > 0 s, got {T}")
    t0 = _resolve_t_ref(t_ref, t)
    dt = t - t0
    s_t = 1.0 if t0 <= float(np.mean(t)) else -1.0
    if center is None:
        center = ((width - 1) / 2.0, (height - 1) / 2.0)
    _context(warp, focal, T)

    def positions_for_iwe(xw_, yw_):
        return whiten(xw_, yw_, x, y) if whitening else (xw_, yw_)

    # objective at theta and at the identity warp
    xw, yw, det, div = warp_events(warp, x, y, dt, theta, center=center, focal=focal, duration=T)
    iwe = polarity_iwe(*positions_for_iwe(xw, yw), w, pol, polarity, width, height, blur_sigma)
    g_raw = objective_value(objective, iwe)

    xw0, yw0, _, _ = warp_events(warp, x, y, dt, np.zeros_like(theta), center=center, focal=focal, duration=T)
    iwe0 = polarity_iwe(*positions_for_iwe(xw0, yw0), w, pol, polarity, width, height, blur_sigma)
    g0 = objective_value(objective, iwe0)
    if normalize:
        if g0 == 0.0:
            raise ValueError("G(0) = 0: the objective cannot be normalised on these events")
        g = g_raw / g0
    else:
        g = g_raw

    # regularizer maps from the unblurred votes of x' with weights |w_k|
    aw = np.abs(w)
    finite = np.isfinite(xw) & np.isfinite(yw)
    count = bilinear_votes(xw, yw, aw, width, height)
    with np.errstate(invalid="ignore"):  # dropped rotation3 events may have det = inf
        q_div = np.where(finite, aw * div, 0.0)
        q_def = np.where(finite, aw * np.abs(det), 0.0)
    n_div = bilinear_votes(xw, yw, q_div, width, height)
    n_def = bilinear_votes(xw, yw, q_def, width, height)
    support = count > 0.0
    safe = np.where(support, count, 1.0)
    div_map = np.where(support, n_div / safe, 0.0)
    def_map = np.where(support, n_def / safe, 0.0)
    d = np.maximum(def_map, DEF_FLOOR)
    alpha_map = np.where(support, np.maximum(d, 1.0 / d) - 1.0, 0.0)
    m = count / (count + KAPPA)
    # one-sided: net contraction is penalised, expansion is not rewarded (FORMULAS.md)
    r_div = max(0.0, _support_mean(m, s_t * T * div_map))
    r_def = _support_mean(m, alpha_map)

    j = g - lambda_div * r_div - lambda_def * r_def
    return {
        "J": float(j),
        "G": float(g),
        "G_raw": float(g_raw),
        "G0": float(g0),
        "R_div": float(r_div),
        "R_def": float(r_def),
        "iwe": iwe,
        "count": count,
        # NaN where no event landed: the library's "no event here" (ContrastMaximization.maps)
        "div_map": np.where(support, div_map, np.nan),
        "def_map": np.where(support, def_map, np.nan),
        "alpha_map": np.where(support, alpha_map, np.nan),
        "xw": xw,
        "yw": yw,
        "det": det,
        "div": div,
    }


def camera_geometry(camera) -> dict:
    """The ``center`` and ``focal`` keywords (px) of :func:`warp_events` and :func:`evaluate` from a
    :class:`~cmax_taichi.Camera`'s intrinsics."""
    return dict(center=(camera.cx, camera.cy), focal=(camera.fx, camera.fy))


def evaluate_window(events, theta, *, warp: str, camera=None, **kwargs) -> dict:
    """:func:`evaluate` of an :class:`~cmax_taichi.Events` window on its sensor, with the geometry of
    ``camera`` (:func:`camera_geometry`) where one is given; ``kwargs`` go to :func:`evaluate`."""
    geometry = {} if camera is None else camera_geometry(camera)
    x, y, t, p, size = events.x, events.y, events.t, events.p, events.sensor_size
    return evaluate(x, y, t, p, theta, warp=warp, sensor_size=size, **geometry, **kwargs)


def central_differences(fn, theta, *, rel_step: float) -> np.ndarray:
    """The gradient of the scalar function ``fn(theta)`` by central differences (2P evaluations), with
    the step ``rel_step * max(1, |theta_i|)`` per parameter."""
    theta = np.asarray(theta, dtype=np.float64)
    grad = np.empty_like(theta)
    for i in range(theta.size):
        h = rel_step * max(1.0, abs(theta[i]))
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        grad[i] = (fn(tp) - fn(tm)) / (2 * h)
    return grad


def central_difference_grad(x, y, t, p, theta, *, rel_step: float, **kwargs) -> np.ndarray:
    """dJ/dtheta by central differences of :func:`evaluate` (:func:`central_differences`); ``kwargs`` go
    to :func:`evaluate`.

    J is piecewise smooth (bilinear votes have kinks where a warped event crosses a pixel boundary), so
    the step must be small enough not to cross many kinks: see
    ``cmax_taichi.lab.bench_impls.reference_fd_grad``.
    """
    return central_differences(lambda th: evaluate(x, y, t, p, th, **kwargs)["J"], theta, rel_step=rel_step)
