"""The float64 NumPy warp models of the oracle (:mod:`cmax_taichi.testing.reference`) and their registry.

Written from ``docs/FORMULAS.md`` ("Warp models"), independently of the Taichi kernels. The built-ins
register at the bottom (a new built-in adds its twin there: the tests, the checker and the simulator
read this registry); a user model registers its NumPy twin with :func:`register_reference_warp` (see
``examples/user_extensions.py``) without editing this package.

Units: positions in pixels (px), times in seconds (s), parameters in physical units (px/s, 1/s,
rad/s), flows in px/s, divergences in 1/s.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cmax_taichi.core.registry import track

#: rotation3: rays with ``X'_z <= Z_MIN`` (behind the camera) are dropped
Z_MIN = 1e-6
#: rotation3: below this angle ``phi = |dt| |w|`` (rad) the Rodrigues series is used
ROT_SERIES_PHI = 1e-4
#: se2 / sim2: below this ``|z|`` the series of ``E(z) = (e^z - 1) / z`` is used
EXP_SERIES_Z = 1e-4


# ----------------------------------------------------------------------------------------------
# the registry of reference warps
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ReferenceWarp:
    """A float64 NumPy warp model of the oracle.

    Parameters
    ----------
    name : str
        The model's name (the same as its Taichi registry entry).
    n_params : int
        Length of ``theta``.
    warp : callable
        ``warp(theta, x, y, dt, *, center, focal, duration) -> (xw, yw, det, div)``: warped positions
        (px; nan for events that are dropped), the signed ``det dx'/dx`` and ``div v`` (1/s) per event,
        for event arrays ``x, y`` (px) and ``dt = t - t_ref`` (s).
    flow : callable
        ``flow(theta, xt, yt, *, focal, duration) -> (vx, vy)``: the instantaneous flow (px/s) at the
        centred coordinates ``xt = x - c_x, yt = y - c_y`` (px).
    needs_focal : bool
        ``focal = (f_x, f_y)`` is required (px).
    needs_duration : bool
        The window duration ``T > 0`` (s) is required.
    """

    name: str
    n_params: int
    warp: Callable
    flow: Callable
    needs_focal: bool = False
    needs_duration: bool = False


#: name -> reference warp (the built-ins, then whatever tests and plugins register; a plugin that fails
#: leaves it as it was: :func:`cmax_taichi.core.registry.track`)
REFERENCE_WARPS: dict[str, ReferenceWarp] = track({})


def register_reference_warp(ref: ReferenceWarp, *, replace: bool = False) -> ReferenceWarp:
    """Add a NumPy twin to the oracle's registry (``replace=True`` to overwrite a name)."""
    if not isinstance(ref, ReferenceWarp):
        raise TypeError(f"expected a ReferenceWarp, got {type(ref).__name__}")
    if ref.name in REFERENCE_WARPS and not replace:
        raise ValueError(f"a reference warp named {ref.name!r} is already registered")
    REFERENCE_WARPS[ref.name] = ref
    return ref


def unregister_reference_warp(name: str) -> ReferenceWarp:
    """Remove the reference warp called ``name`` and return it (KeyError if absent)."""
    if name not in REFERENCE_WARPS:
        raise KeyError(f"no reference warp named {name!r}")
    return REFERENCE_WARPS.pop(name)


# ----------------------------------------------------------------------------------------------
# warps
# ----------------------------------------------------------------------------------------------
def _rotation_matrices(w: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """``Rot = exp(dt [w]_x)`` per event by the Rodrigues formula (series below 1e-4 rad).

    Returns an array of shape (N, 3, 3).
    """
    wx, wy, wz = w
    hat = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    hat2 = hat @ hat
    phi = np.abs(dt) * math.sqrt(wx * wx + wy * wy + wz * wz)
    small = phi < ROT_SERIES_PHI
    phi_safe = np.where(small, 1.0, phi)
    # Rot = I + (sin phi / phi) K + ((1 - cos phi) / phi^2) K^2 with K = dt [w]_x
    a = np.where(small, 1.0, np.sin(phi_safe) / phi_safe)
    b = np.where(small, 0.5, (1.0 - np.cos(phi_safe)) / phi_safe**2)
    eye = np.eye(3)[None, :, :]
    return eye + (a * dt)[:, None, None] * hat[None, :, :] + (b * dt * dt)[:, None, None] * hat2[None, :, :]


def _exp_series(z: np.ndarray) -> np.ndarray:
    """``E(z) = (e^z - 1) / z`` for complex z, with the series ``1 + z/2 + z^2/6 + z^3/24``."""
    small = np.abs(z) < EXP_SERIES_Z
    z_safe = np.where(small, 1.0 + 0.0j, z)
    exact = (np.exp(z_safe) - 1.0) / z_safe
    series = 1.0 + z / 2.0 + z * z / 6.0 + z * z * z / 24.0
    return np.where(small, series, exact)


# --- the built-ins (docs/FORMULAS.md, "Warp models") -----------------------------------------
def _zoom1_warp(theta, x, y, dt, *, center, focal, duration):
    (hz,) = theta
    cx, cy = center
    scale = 1.0 - dt * hz
    return cx + scale * (x - cx), cy + scale * (y - cy), scale**2, 2.0 * hz * np.ones_like(x)


def _zoom1_flow(theta, xt, yt, *, focal, duration):
    (hz,) = theta
    return hz * xt, hz * yt


def _translation2_warp(theta, x, y, dt, *, center, focal, duration):
    vx, vy = theta
    return x - dt * vx, y - dt * vy, np.ones_like(x), np.zeros_like(x)


def _translation2_flow(theta, xt, yt, *, focal, duration):
    vx, vy = theta
    return vx + 0.0 * xt, vy + 0.0 * yt


def _rotation3_warp(theta, x, y, dt, *, center, focal, duration):
    cx, cy = center
    fx, fy = focal
    ones = np.ones_like(x)
    rays = np.stack([(x - cx) / fx, (y - cy) / fy, ones], axis=-1)  # (N, 3) calibrated rays X
    rot = _rotation_matrices(theta, dt)
    rotated = np.einsum("nij,nj->ni", rot, rays)  # X' = Rot X
    zr = rotated[:, 2]  # X'_z = r_3 . X
    keep = zr > Z_MIN
    z_safe = np.where(keep, zr, 1.0)
    xw = np.where(keep, cx + fx * rotated[:, 0] / z_safe, np.nan)
    yw = np.where(keep, cy + fy * rotated[:, 1] / z_safe, np.nan)
    with np.errstate(divide="ignore"):
        det = 1.0 / zr**3
    wx, wy, _ = theta
    div = -3.0 * (wy * rays[:, 0] - wx * rays[:, 1])
    return xw, yw, det, div


def _rotation3_flow(theta, xt, yt, *, focal, duration):
    fx, fy = focal
    wx, wy, wz = theta
    X = xt / fx
    Y = yt / fy
    vx = -fx * (wy * (1.0 + X * X) - wx * X * Y - wz * Y)
    vy = -fy * (-wx * (1.0 + Y * Y) + wy * X * Y + wz * X)
    return vx, vy


def _sim2_exact(vx, vy, w, s, x, y, dt, center):
    cx, cy = center
    z = -dt * (s + 1j * w)
    u = -dt * (vx + 1j * vy)
    pos = np.exp(z) * ((x - cx) + 1j * (y - cy)) + _exp_series(z) * u
    det = np.exp(-2.0 * dt * s)
    return cx + pos.real, cy + pos.imag, det, 2.0 * s * np.ones_like(x)


def _se2_warp(theta, x, y, dt, *, center, focal, duration):
    vx, vy, w = theta
    return _sim2_exact(vx, vy, w, 0.0, x, y, dt, center)


def _se2_flow(theta, xt, yt, *, focal, duration):
    vx, vy, w = theta
    return -w * yt + vx, w * xt + vy


def _sim2_warp(theta, x, y, dt, *, center, focal, duration):
    vx, vy, w, s = theta
    return _sim2_exact(vx, vy, w, s, x, y, dt, center)


def _sim2_flow(theta, xt, yt, *, focal, duration):
    vx, vy, w, s = theta
    return s * xt - w * yt + vx, w * xt + s * yt + vy


def _mitrokhin4_matrix(theta, T):
    """``(a11, a21)`` of ``A = (h_z T + 1) R(theta T) = [[a11, -a21], [a21, a11]]``."""
    _, _, hz, th = theta
    amp = hz * T + 1.0
    return amp * math.cos(th * T), amp * math.sin(th * T)


def _mitrokhin4_warp(theta, x, y, dt, *, center, focal, duration):
    hx, hy = theta[0], theta[1]
    cx, cy = center
    xt, yt = x - cx, y - cy
    T = duration
    sigma = dt / T
    a11, a21 = _mitrokhin4_matrix(theta, T)
    # x' = x - dt h - sigma (A - I) x~
    xw = x - dt * hx - sigma * ((a11 - 1.0) * xt - a21 * yt)
    yw = y - dt * hy - sigma * (a21 * xt + (a11 - 1.0) * yt)
    det = (1.0 + sigma - sigma * a11) ** 2 + (sigma * a21) ** 2
    div = 2.0 * (a11 - 1.0) / T * np.ones_like(x)
    return xw, yw, det, div


def _mitrokhin4_flow(theta, xt, yt, *, focal, duration):
    hx, hy = theta[0], theta[1]
    T = duration
    a11, a21 = _mitrokhin4_matrix(theta, T)
    return hx + ((a11 - 1.0) * xt - a21 * yt) / T, hy + (a21 * xt + (a11 - 1.0) * yt) / T


register_reference_warp(ReferenceWarp("zoom1", 1, _zoom1_warp, _zoom1_flow))
register_reference_warp(ReferenceWarp("translation2", 2, _translation2_warp, _translation2_flow))
register_reference_warp(ReferenceWarp("rotation3", 3, _rotation3_warp, _rotation3_flow, needs_focal=True))
register_reference_warp(ReferenceWarp("se2", 3, _se2_warp, _se2_flow))
register_reference_warp(ReferenceWarp("sim2", 4, _sim2_warp, _sim2_flow))
register_reference_warp(
    ReferenceWarp("mitrokhin4", 4, _mitrokhin4_warp, _mitrokhin4_flow, needs_duration=True)
)
