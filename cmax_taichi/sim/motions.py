"""The exact image motion that each built-in warp model undoes (docs/FORMULAS.md).

A motion is stored as a homography ``G(t)`` that moves image points at time 0 to time ``t``, so that the
core's warp ``W(x, t - t_ref; theta(t_ref)) = G(t_ref) G(t)^-1 x`` for every point of the moving plane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cmax_taichi.core.events import Camera
from cmax_taichi.models.warps import get_warp

__all__ = ["DEFAULT_THETAS", "Motion"]

#: a moderate parameter vector per warp model: a few px of motion per 50 ms on a DAVIS240
DEFAULT_THETAS = {
    "zoom1": (0.8,),
    "translation2": (60.0, -35.0),
    "rotation3": (0.3, -0.4, 0.8),
    "se2": (50.0, -30.0, 0.6),
    "sim2": (50.0, -30.0, 0.6, 0.5),
    "mitrokhin4": (50.0, -30.0, 0.5, 0.6),
}


def _centre_conj(M: np.ndarray, cx: float, cy: float) -> np.ndarray:
    """``C M C^-1`` with ``C`` the translation by the centre (M acts on centred coordinates)."""
    C = np.array([[1.0, 0.0, cx], [0.0, 1.0, cy], [0.0, 0.0, 1.0]])
    Ci = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [0.0, 0.0, 1.0]])
    return C @ M @ Ci


def _rodrigues(a: np.ndarray) -> np.ndarray:
    """``exp([a]_x)`` (3x3) for a rotation vector ``a`` (rad)."""
    A = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    phi = float(np.linalg.norm(a))
    if phi < 1e-8:
        return np.eye(3) + A + A @ A / 2.0
    return np.eye(3) + math.sin(phi) / phi * A + (1.0 - math.cos(phi)) / phi**2 * (A @ A)


def _sim2_group(t: float, vx: float, vy: float, w: float, s: float) -> np.ndarray:
    """``expm(t xi^)`` for ``xi^ = [[s, -w, vx], [w, s, vy], [0, 0, 0]]`` (centred coordinates)."""
    z = complex(t * s, t * w)
    ez = complex(math.exp(z.real) * math.cos(z.imag), math.exp(z.real) * math.sin(z.imag))
    E = (ez - 1.0) / z if abs(z) > 1e-9 else 1.0 + z / 2.0 + z * z / 6.0
    u = E * complex(t * vx, t * vy)
    return np.array([[ez.real, -ez.imag, u.real], [ez.imag, ez.real, u.imag], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Motion:
    """The exact image motion that the core's warp ``warp`` with parameters ``theta`` undoes.

    Parameters
    ----------
    warp : str
        A built-in warp model (``cm.warp_names()``).
    theta : sequence of float
        Parameters at time 0, in the model's physical units (px/s, 1/s, rad/s).
    segment : float, optional
        Seconds. Required by ``mitrokhin4`` with a non-zero ``theta`` (its angular part): that model
        normalises time by the window duration T, so the motion is defined window by window; the
        motion restarts with the same parameters every ``segment`` seconds and the ground truth is
        exact for windows ``[k segment, (k+1) segment]`` with ``T = segment``. Ignored otherwise.

    Notes
    -----
    With ``G(t)`` the homography that moves image points from time 0 to time t (centre ``c``, the
    camera's principal point; ``x~ = x - c``):

    * ``translation2``: ``x(t) = x + t v``; ``theta`` is constant.
    * ``se2`` / ``sim2``: ``G(t) = expm(t xi^)`` in centred coordinates; ``theta`` is constant.
    * ``rotation3``: ``G(t) = K exp(-t [w]_x) K^-1`` (camera rotation); ``theta`` is constant.
    * ``zoom1`` and ``mitrokhin4`` with ``theta = 0`` (angular part): camera translation at constant
      velocity towards a fronto-parallel plane, ``x~(t) = (x~ + t h) / (1 - h_z t)``. The parameters
      grow as the plane approaches: ``theta(t) = theta(0) / (1 - h_z(0) t)``, exact for windows
      starting at any time. The plane must stay ahead: ``1 - h_z t > 0.1`` over the simulation.
    """

    warp: str
    theta: tuple[float, ...]
    segment: float | None = None

    def __post_init__(self) -> None:
        model = get_warp(self.warp)
        if self.warp not in DEFAULT_THETAS:
            raise ValueError(
                f"the simulator knows the exact motion of the built-in warps only "
                f"({', '.join(DEFAULT_THETAS)}), not {self.warp!r}"
            )
        try:
            theta = tuple(float(v) for v in np.asarray(self.theta, dtype=np.float64).reshape(-1))
        except (TypeError, ValueError):
            raise TypeError(f"theta must be a sequence of numbers, got {self.theta!r}") from None
        if len(theta) != model.n_params:
            raise ValueError(f"warp {self.warp!r} takes {model.n_params} parameter(s), got {len(theta)}")
        if not all(math.isfinite(v) for v in theta):
            raise ValueError(f"theta has non-finite values: {theta}")
        object.__setattr__(self, "theta", theta)
        segment_ok = self.segment is not None and math.isfinite(self.segment) and self.segment > 0
        if self.windowed and not segment_ok:
            raise ValueError(
                "mitrokhin4 with a non-zero angular velocity is defined per window: pass "
                f"segment=<window duration in s> (got {self.segment!r})"
            )

    @property
    def windowed(self) -> bool:
        """True for the window-normalised model (``mitrokhin4`` with a non-zero angle)."""
        return self.warp == "mitrokhin4" and self.theta[3] != 0.0

    @property
    def forward(self) -> bool:
        """True for camera translation towards a plane (``zoom1``, ``mitrokhin4`` without angle)."""
        return self.warp == "zoom1" or (self.warp == "mitrokhin4" and self.theta[3] == 0.0)

    def _hz(self) -> float:
        return self.theta[0] if self.warp == "zoom1" else self.theta[2]

    def check(self, t_end: float) -> None:
        """Raise ValueError if the motion is not defined up to ``t_end`` seconds."""
        if self.forward:
            hz = self._hz()
            if 1.0 - hz * t_end <= 0.1:
                raise ValueError(
                    f"{self.warp} with h_z = {hz} 1/s reaches the plane (1 - h_z t <= 0.1) before "
                    f"t = {t_end} s: use a smaller h_z or a shorter simulation"
                )
        if self.windowed:
            for tau in np.linspace(0.0, self.segment, 9):
                if abs(np.linalg.det(self._m4_warp(tau, 0.0, 0.0)[:2, :2])) < 1e-3:
                    raise ValueError("mitrokhin4 parameters give a singular warp within a segment")

    def _m4_warp(self, tau: float, cx: float, cy: float) -> np.ndarray:
        """The mitrokhin4 warp matrix over ``tau`` seconds (window T = segment)."""
        hx, hy, hz, ang = self.theta
        T = float(self.segment)
        sig = tau / T
        k = hz * T + 1.0
        ac, as_ = k * math.cos(ang * T), k * math.sin(ang * T)
        A = np.array([[ac, -as_], [as_, ac]])
        M = np.eye(3)
        M[:2, :2] = (1.0 + sig) * np.eye(2) - sig * A
        M[:2, 2] = [-tau * hx, -tau * hy]
        return _centre_conj(M, cx, cy)

    def matrix(self, t: float, camera: Camera) -> np.ndarray:
        """``G(t)``: 3x3 homography moving image points (px) from time 0 to time ``t`` (s)."""
        cx, cy = camera.cx, camera.cy
        th = self.theta
        if self.warp == "translation2":
            return np.array([[1.0, 0.0, t * th[0]], [0.0, 1.0, t * th[1]], [0.0, 0.0, 1.0]])
        if self.warp in ("se2", "sim2"):
            s = th[3] if self.warp == "sim2" else 0.0
            return _centre_conj(_sim2_group(t, th[0], th[1], th[2], s), cx, cy)
        if self.warp == "rotation3":
            return camera.K @ _rodrigues(-t * np.asarray(th)) @ np.linalg.inv(camera.K)
        if self.forward:
            hx, hy, hz = (0.0, 0.0, th[0]) if self.warp == "zoom1" else th[:3]
            k = 1.0 / (1.0 - hz * t)
            M = np.array([[k, 0.0, t * hx * k], [0.0, k, t * hy * k], [0.0, 0.0, 1.0]])
            return _centre_conj(M, cx, cy)
        # windowed mitrokhin4: G(t) = M(t - t_k)^-1 G(t_k), G(0) = I
        T = float(self.segment)
        n_seg = int(math.floor(t / T + 1e-12))
        step = np.linalg.inv(self._m4_warp(T, cx, cy))
        G = np.linalg.matrix_power(step, n_seg) if n_seg > 0 else np.eye(3)
        return np.linalg.inv(self._m4_warp(t - n_seg * T, cx, cy)) @ G

    def theta_at(self, t: float) -> np.ndarray:
        """Parameters (physical units) of the warp that undoes the motion of a window starting at
        ``t`` seconds (for the windowed mitrokhin4: of the segment holding ``t``, exact when ``t`` is a
        segment start)."""
        th = np.asarray(self.theta, dtype=np.float64)
        if self.forward:
            out = th / (1.0 - self._hz() * t)
            if self.warp == "mitrokhin4":
                out[3] = 0.0
            return out
        return th.copy()
