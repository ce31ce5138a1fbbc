"""Rigid 3-D motions and the exact image motion of a textured plane seen by a moving camera.

A plane is the one surface whose image motion is a homography for any rigid motion of the camera and
of the plane, so the simulator's layers (a texture, a homography per time) render it exactly, and its
flow, depth and occlusion order are known in closed form at every pixel.

Frames and conventions. The world frame is the camera frame at ``t = 0`` (x right, y down, z forward,
metres). A :class:`RigidMotion` moves points as ``X(t) = p + v t + R(t) (X(0) - p)`` with
``R(t) = exp(t [w]_x)``: the pivot ``p`` translates at the constant velocity ``v`` (m/s, world frame)
and the body turns about it at the constant angular velocity ``w`` (rad/s, world frame). The camera's
motion moves its own frame: its centre is ``c(t) = p + v t - R(t) p`` and its orientation ``R_c(t)``;
a world point is at ``X_c = R_c^T (X_w - c)`` in the camera frame at time t. The default pivot (the
origin) makes ``v`` the velocity of the camera centre.

A :class:`PlaneMotion` is the plane ``n . X = d`` (world frame at t = 0, ``d > 0``: ``n`` points away
from the camera) carried by a surface motion and seen by the camera motion. A point ``X0`` of the plane
is at ``X_c(t) = A(t) X0`` with ``A = R_c^T (R_s + (b_s - c) n^T / d)`` (``X_s(t) = R_s X0 + b_s``), so
its homography image(0) -> image(t) is ``G(t) = K A(t) K^-1``, scaled so that ``G(t) (Z0 x0~) = Z(t)
xt~`` (``x~`` homogeneous pixels, Z the depth): the simulator's renderer reads the inverse depth from
it. The instantaneous flow is ``d/dt`` of the projection of ``X_c(t)`` with ``dX_c/dt = A' A^-1 X_c``,
in closed form.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from cmax_taichi.core.events import Camera

__all__ = ["RigidMotion", "PlaneMotion", "STATIC"]


def _vec3(value, name: str) -> tuple[float, float, float]:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be three numbers, got {value!r}") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be three finite numbers, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def _hat(w: np.ndarray) -> np.ndarray:
    """``[w]_x`` for (..., 3) vectors: (..., 3, 3)."""
    w = np.asarray(w, dtype=np.float64)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def _rotation(w: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``exp(t [w]_x)`` for a fixed angular velocity ``w`` (3,) and times ``t`` (N,): (N, 3, 3)."""
    A = _hat(np.asarray(w)[None, :] * t[:, None])
    phi = np.abs(t) * float(np.linalg.norm(w))
    small = phi < 1e-6
    safe = np.where(small, 1.0, phi)
    a = np.where(small, 1.0 - phi**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - phi**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3)[None] + a[:, None, None] * A + b[:, None, None] * (A @ A)


@dataclass(frozen=True)
class RigidMotion:
    """A rigid motion at constant velocity: ``X(t) = p + v t + exp(t [w]_x) (X(0) - p)``.

    Parameters
    ----------
    velocity : 3 floats
        ``v``, m/s, world frame: the velocity of the pivot.
    angular_velocity : 3 floats
        ``w``, rad/s, world frame: the body turns about the (moving) pivot.
    pivot : 3 floats
        ``p``, m, world frame at t = 0.
    """

    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    angular_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("velocity", "angular_velocity", "pivot"):
            object.__setattr__(self, name, _vec3(getattr(self, name), name))

    def transform(self, t) -> tuple[np.ndarray, np.ndarray]:
        """``(R, b)`` with ``X(t) = R X(0) + b``: (N, 3, 3) and (N, 3) for times ``t`` (N,) s."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        R = _rotation(np.asarray(self.angular_velocity), t)
        p = np.asarray(self.pivot)
        b = p[None, :] + np.asarray(self.velocity)[None, :] * t[:, None] - R @ p
        return R, b

    def transform_rate(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Time derivatives ``(R', b')`` of :meth:`transform` (per second)."""
        R, _ = self.transform(t)
        W = _hat(np.asarray(self.angular_velocity))
        dR = W[None] @ R
        db = np.asarray(self.velocity)[None, :] - dR @ np.asarray(self.pivot)
        return dR, db


#: no motion
STATIC = RigidMotion()


@dataclass(frozen=True)
class PlaneMotion:
    """The image motion of the plane ``normal . X = distance`` under a camera and a surface motion.

    Used as the ``motion`` of a simulator :class:`~cmax_taichi.sim.Layer` (see the module docstring
    for the frames and formulas).

    Parameters
    ----------
    normal : 3 floats
        Plane normal (world frame at t = 0); normalised here.
    distance : float
        ``d > 0``, m: the plane's distance from the camera at t = 0 along ``normal`` (so ``normal``
        points from the camera towards the plane).
    camera : RigidMotion
        The camera's motion.
    surface : RigidMotion
        The plane's own motion (default: static, the world).
    """

    normal: tuple[float, float, float]
    distance: float
    camera: RigidMotion = field(default_factory=RigidMotion)
    surface: RigidMotion = field(default_factory=RigidMotion)

    #: not a warp model of the core (``SimulatedRecording.warp`` is None; ``theta_at`` says why)
    warp = None

    def __post_init__(self) -> None:
        n = np.asarray(_vec3(self.normal, "normal"))
        norm = float(np.linalg.norm(n))
        if norm < 1e-12:
            raise ValueError("normal must not be the zero vector")
        object.__setattr__(self, "normal", tuple(float(v) for v in n / norm))
        d = self.distance
        if not (isinstance(d, (int, float)) and math.isfinite(d) and d > 0):
            raise ValueError(f"distance must be a positive number of metres, got {d!r}")
        object.__setattr__(self, "distance", float(d))
        for name in ("camera", "surface"):
            if not isinstance(getattr(self, name), RigidMotion):
                raise TypeError(f"{name} must be a RigidMotion, got {type(getattr(self, name)).__name__}")

    # --- geometry ----------------------------------------------------------------------------
    def _point_map(self, t) -> np.ndarray:
        """``A(t)`` (N, 3, 3): camera-frame point at t of the plane point X0 (world, t = 0)."""
        Rc, c = self.camera.transform(t)
        Rs, bs = self.surface.transform(t)
        m = np.asarray(self.normal) / self.distance
        inner = Rs + (bs - c)[:, :, None] * m[None, None, :]
        return np.swapaxes(Rc, 1, 2) @ inner

    def _point_map_rate(self, t) -> np.ndarray:
        """``A'(t)`` (N, 3, 3)."""
        Rc, c = self.camera.transform(t)
        Rs, bs = self.surface.transform(t)
        dRc, dc = self.camera.transform_rate(t)
        dRs, dbs = self.surface.transform_rate(t)
        m = np.asarray(self.normal) / self.distance
        inner = Rs + (bs - c)[:, :, None] * m[None, None, :]
        dinner = dRs + (dbs - dc)[:, :, None] * m[None, None, :]
        RcT = np.swapaxes(Rc, 1, 2)
        return np.swapaxes(dRc, 1, 2) @ inner + RcT @ dinner

    def matrices(self, t, camera: Camera) -> np.ndarray:
        """``G(t)`` for times ``t`` (N,) s: (N, 3, 3) (see :meth:`matrix`)."""
        K = camera.K
        return K[None] @ self._point_map(t) @ np.linalg.inv(K)[None]

    def matrix(self, t: float, camera: Camera) -> np.ndarray:
        """``G(t)``: the 3x3 homography moving image points (px) of the plane from time 0 to ``t`` s,
        scaled by the depth ratio ``Z(t) / Z(0)`` (its third row gives the depth)."""
        return self.matrices(np.array([float(t)]), camera)[0]

    def plane_at(self, t: float) -> tuple[np.ndarray, float]:
        """The plane in the camera frame at time ``t``: ``(n_t, d_t)`` with ``n_t . X_c = d_t``."""
        A = self._point_map(np.array([float(t)]))[0]
        # n . X0 = d with X0 = A^-1 X_c
        n_t = np.linalg.solve(A.T, np.asarray(self.normal))
        scale = float(np.linalg.norm(n_t))
        return n_t / scale, self.distance / scale

    def depth(self, t: float, x, y, camera: Camera) -> np.ndarray:
        """Depth Z (m, along the optical axis) of the plane at pixels ``(x, y)`` at time ``t``; NaN
        where the pixel's ray does not meet the plane in front of the camera."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        n_t, d_t = self.plane_at(t)
        rx = (x - camera.cx) / camera.fx
        ry = (y - camera.cy) / camera.fy
        with np.errstate(divide="ignore", invalid="ignore"):
            Z = d_t / (n_t[0] * rx + n_t[1] * ry + n_t[2])
        return np.where(np.isfinite(Z) & (Z > 0), Z, np.nan)

    def velocity(self, t: float, x, y, camera: Camera) -> np.ndarray:
        """Instantaneous image velocity (px/s), shape ``(2,) + x.shape``, of the plane's points that
        are at pixels ``(x, y)`` at time ``t`` (closed form; NaN where the plane is not in front)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        tt = np.array([float(t)])
        A = self._point_map(tt)[0]
        M = self._point_map_rate(tt)[0] @ np.linalg.inv(A)  # dX_c/dt = M X_c
        Z = self.depth(t, x, y, camera)
        X = (x - camera.cx) / camera.fx * Z
        Y = (y - camera.cy) / camera.fy * Z
        P = np.stack([X, Y, Z])
        dP = np.tensordot(M, P, axes=1)
        u = camera.fx * (dP[0] * Z - X * dP[2]) / Z**2
        v = camera.fy * (dP[1] * Z - Y * dP[2]) / Z**2
        return np.stack([u, v])

    def clearance(self, t) -> np.ndarray:
        """Signed distance (m) of the camera centre in front of the plane at times ``t`` (N,): the
        plane is ahead while it is positive."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        Rs, bs = self.surface.transform(t)
        _, c = self.camera.transform(t)
        n_t = Rs @ np.asarray(self.normal)
        d_t = self.distance + np.einsum("ni,ni->n", n_t, bs)
        return d_t - np.einsum("ni,ni->n", n_t, c)

    def check(self, t_end: float) -> None:
        """Raise ValueError if the camera comes within a tenth of the initial distance of the plane (or
        crosses it) before ``t_end`` seconds."""
        ts = np.linspace(0.0, float(t_end), 65)
        gap = self.clearance(ts)
        bad = np.flatnonzero(gap <= 0.1 * self.distance)
        if len(bad):
            raise ValueError(
                f"the camera comes within {0.1 * self.distance:.3g} m of a plane (initial distance "
                f"{self.distance:.3g} m) at t = {ts[bad[0]]:.3g} s, before t = {t_end} s: use a slower "
                "motion or a shorter simulation"
            )

    def theta_at(self, t: float) -> np.ndarray:
        raise ValueError(
            "a plane seen by a moving camera (PlaneMotion) has no warp parameters: its ground truth "
            "is the dense flow (SimulatedRecording.flow / velocity) and the depth"
        )

    def describe(self) -> dict:
        """The motion as plain numbers (for the simulator's files)."""
        return {
            "normal": list(self.normal),
            "distance": self.distance,
            "camera_velocity": list(self.camera.velocity),
            "camera_angular_velocity": list(self.camera.angular_velocity),
            "camera_pivot": list(self.camera.pivot),
            "surface_velocity": list(self.surface.velocity),
            "surface_angular_velocity": list(self.surface.angular_velocity),
            "surface_pivot": list(self.surface.pivot),
        }


def orthonormal_axes(normal: Sequence[float], axis_u: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """In-plane unit axes ``(e_u, e_v)`` of a plane with ``normal``: ``axis_u`` projected onto the
    plane, and ``e_v = n x e_u`` (so a fronto-parallel plane with ``axis_u = x`` has ``e_v = y``, down)."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    u = np.asarray(axis_u, dtype=np.float64)
    u = u - n * float(n @ u)
    norm = float(np.linalg.norm(u))
    if norm < 1e-9:
        raise ValueError(f"axis_u {tuple(axis_u)} is parallel to the plane normal {tuple(normal)}")
    u = u / norm
    return u, np.cross(n, u)
