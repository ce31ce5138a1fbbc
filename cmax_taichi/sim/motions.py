"""The exact image motion that a warp model undoes, derived from the model itself (docs/FORMULAS.md).

A motion is stored as a homography ``G(t)`` that moves image points at time 0 to time ``t``, so that the
core's warp ``W(x, t - t_ref; theta(t_ref)) = G(t_ref) G(t)^-1 x`` for every point of the moving plane.
It is derived from the model's warp as its float64 NumPy twin computes it (``testing/reference_warps.py``,
the twin every built-in has and a user model registers for its tests), for any registered model whose
warp is a homography of the image for every ``dt``:

* a **group** (``W(., a) W(., b) = W(., a + b)`` with constant parameters: ``translation2``, ``se2``,
  ``sim2``, ``rotation3``): ``G(t) = W(., t)^-1``, and the parameters are the same at every time;
* **first order in time** (``W(x, dt) = (I - dt M) x`` with a 3x3 ``M``: ``zoom1``, ``mitrokhin4``, an
  affine flow): ``G(t) = (I - t M0)^-1`` (for ``zoom1``, a camera translating at constant velocity
  towards a fronto-parallel plane, ``x~(t) = x~ / (1 - h_z t)``); the parameters of a window starting at
  ``t`` are those whose ``M`` is ``(I - t M0)^-1 M0`` (they grow as the plane approaches), solved on the
  model's own warp to rounding; the motion must not reach the plane (``det(I - t M0) > 0.01``).

A warp that depends on the window duration ``T`` (``mitrokhin4`` with an angle) is defined for windows
of one length: ``segment = T``. Any other warp (or a model without a NumPy twin) gives one ValueError that
says why. :meth:`Motion.theta_at` also expresses a motion in another model where that model can
(``--example collapse --warp affine6``: the truth of a translation in the affine model's parameters).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cmax_taichi.core.events import Camera
from cmax_taichi.models.warps import get_warp

__all__ = ["DEFAULT_THETAS", "Motion", "NotExpressedError", "default_theta"]

#: a moderate parameter vector per built-in warp model: a few px of motion per 50 ms on a DAVIS240
#: (any other model: :func:`default_theta`, from its declared parameter kinds)
DEFAULT_THETAS = {
    "zoom1": (0.8,),
    "translation2": (60.0, -35.0),
    "rotation3": (0.3, -0.4, 0.8),
    "se2": (50.0, -30.0, 0.6),
    "sim2": (50.0, -30.0, 0.6, 0.5),
    "mitrokhin4": (50.0, -30.0, 0.5, 0.6),
}

#: the times (s) at which the warp is probed to classify it, and the nominal camera of the early check
_PROBE_DT = (0.013, 0.029)
_NOMINAL_CAMERA = Camera(fx=200.0, fy=200.0, cx=120.0, cy=90.0)
#: px: what "exact" means for a fitted homography or solved parameters (rounding of float64)
_EXACT_PX = 1e-8


class NotExpressedError(ValueError):
    """A model cannot express a motion: its best parameters leave ``residual_px`` (px) over ``span_s``
    seconds of a window."""

    def __init__(self, message: str, residual_px: float, span_s: float) -> None:
        super().__init__(message)
        self.residual_px = residual_px
        self.span_s = span_s


def default_theta(warp: str) -> tuple[float, ...]:
    """A moderate parameter vector of ``warp`` for the simulator: :data:`DEFAULT_THETAS` for the
    built-ins, else a few px of motion per 50 ms on a DAVIS240 from the model's declared parameter kinds
    (:func:`cmax_taichi.testing.samples.moderate_theta`)."""
    if warp in DEFAULT_THETAS:
        return DEFAULT_THETAS[warp]
    from cmax_taichi.testing import samples

    model = get_warp(warp)
    camera = Camera(fx=200.0, fy=200.0, cx=119.5, cy=89.5)
    theta = samples.moderate_theta(model, displacement=3.0, duration=0.05, sensor=(240, 180), camera=camera)
    return tuple(float(v) for v in theta)


def _twin(warp: str):
    from cmax_taichi.testing.reference_warps import REFERENCE_WARPS

    twin = REFERENCE_WARPS.get(warp)
    if twin is None:
        raise ValueError(
            f"the simulator derives the exact motion of a warp from its float64 NumPy twin, and warp "
            f"{warp!r} has none: register one with cmax_taichi.testing.reference.register_reference_warp "
            "(docs/RECIPE_WARP.md)"
        )
    return twin


def _probe_points(camera: Camera) -> np.ndarray:
    """A 5 x 5 grid of image points around the principal point (px), shape (2, 25)."""
    u = np.linspace(-0.3, 0.3, 5)
    gx, gy = np.meshgrid(camera.cx + u * camera.fx, camera.cy + u * camera.fy)
    return np.stack([gx.ravel(), gy.ravel()])


def _fit_homography(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, float]:
    """The homography ``H`` (``H[2, 2] = 1``) with ``dst ~ H src`` (points (2, N)) by the normalised DLT,
    and its largest residual (px)."""
    ok = np.all(np.isfinite(dst), axis=0)
    if ok.sum() < 6:
        return np.full((3, 3), np.nan), math.inf
    s, d = src[:, ok], dst[:, ok]

    def normaliser(p):
        mean = p.mean(axis=1)
        scale = math.sqrt(2.0) / max(float(np.mean(np.hypot(*(p - mean[:, None])))), 1e-300)
        return np.array([[scale, 0.0, -scale * mean[0]], [0.0, scale, -scale * mean[1]], [0.0, 0.0, 1.0]])

    ts, td = normaliser(s), normaliser(d)
    sn = ts @ np.vstack([s, np.ones(s.shape[1])])
    dn = td @ np.vstack([d, np.ones(d.shape[1])])
    rows = []
    for (x, y, _), (u, v, _) in zip(sn.T, dn.T, strict=True):
        rows.append([-x, -y, -1.0, 0.0, 0.0, 0.0, u * x, u * y, u])
        rows.append([0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v])
    h = np.linalg.svd(np.asarray(rows))[2][-1].reshape(3, 3)
    H = np.linalg.solve(td, h @ ts)
    H = H / H[2, 2]
    q = H @ np.vstack([s, np.ones(s.shape[1])])
    return H, float(np.max(np.hypot(q[0] / q[2] - d[0], q[1] / q[2] - d[1])))


def _apply(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    q = H @ np.vstack([points, np.ones(points.shape[1])])
    return q[:2] / q[2]


def _solve_parameters(residual, x0: np.ndarray, scales: np.ndarray) -> tuple[np.ndarray, float]:
    """Levenberg-Marquardt on ``residual(theta)`` (px) from ``x0`` (Jacobian by central differences),
    in units where one step of ``scales`` moves the residual by about one px; returns ``theta`` and its
    largest residual (px)."""
    x = np.asarray(x0, dtype=np.float64).copy()
    r = residual(x)
    damping = 1e-3
    for _ in range(100):
        cols = []
        for j in range(x.size):
            h = 1e-6 / scales[j]
            up, down = x.copy(), x.copy()
            up[j] += h
            down[j] -= h
            cols.append((residual(up) - residual(down)) / (2.0 * h))
        J = np.stack(cols, axis=1)
        A = J.T @ J
        g = J.T @ r
        improved = False
        while damping < 1e12:
            step = np.linalg.solve(A + damping * np.diag(np.diag(A) + 1e-300), -g)
            trial = residual(x + step)
            if np.sum(trial**2) < np.sum(r**2):
                x, r, damping, improved = x + step, trial, max(damping / 10.0, 1e-12), True
                break
            damping *= 10.0
        if not improved or np.max(np.abs(r)) < 1e-13:
            break
    return x, float(np.max(np.abs(r))) if r.size else 0.0


@dataclass
class _Derived:
    """What the motion is for one camera: its kind and, first order, ``M0``."""

    kind: str
    M0: np.ndarray | None = None


@dataclass(frozen=True)
class Motion:
    """The exact image motion that the core's warp ``warp`` with parameters ``theta`` undoes.

    Parameters
    ----------
    warp : str
        A registered warp model with a float64 NumPy twin (every built-in; a user model registers one
        with ``cmax_taichi.testing.reference.register_reference_warp``).
    theta : sequence of float
        Parameters at time 0, in the model's physical units (px/s, 1/s, rad/s).
    segment : float, optional
        Seconds: the window duration ``T`` of a model whose warp depends on it (``mitrokhin4`` with a
        non-zero angular velocity; required there, ignored elsewhere). The ground truth is then exact
        for windows of ``segment`` seconds starting at any time.

    Notes
    -----
    See the module docstring: the motion is the group ``G(t) = W(., t)^-1`` or, for a warp of first
    order in time, ``G(t) = (I - t M0)^-1``; ``theta_at(t)`` gives the parameters of a window starting at
    ``t``. Raises ValueError where the simulator cannot express the model's motion (a warp that is not a
    homography of the image, neither a group nor first order in time, or no NumPy twin).
    """

    warp: str
    theta: tuple[float, ...]
    segment: float | None = None
    _derived: dict = field(default_factory=dict, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        model = get_warp(self.warp)
        try:
            theta = tuple(float(v) for v in np.asarray(self.theta, dtype=np.float64).reshape(-1))
        except (TypeError, ValueError):
            raise TypeError(f"theta must be a sequence of numbers, got {self.theta!r}") from None
        if len(theta) != model.n_params:
            raise ValueError(f"warp {self.warp!r} takes {model.n_params} parameter(s), got {len(theta)}")
        if not all(math.isfinite(v) for v in theta):
            raise ValueError(f"theta has non-finite values: {theta}")
        object.__setattr__(self, "theta", theta)
        twin = _twin(self.warp)
        if twin.n_params != model.n_params:
            raise ValueError(f"the NumPy twin of warp {self.warp!r} takes {twin.n_params} parameters")
        segment_ok = self.segment is not None and math.isfinite(self.segment) and self.segment > 0
        if self.windowed and not segment_ok:
            raise ValueError(
                f"{self.warp} with these parameters depends on the window duration T (a window-normalised "
                f"model): pass segment=<window duration in s> (got {self.segment!r})"
            )
        self._for(_NOMINAL_CAMERA)  # classify now: an error here, not in the middle of a simulation

    # --- the warp as homographies ----------------------------------------------------------------------
    def _duration(self) -> float:
        return float(self.segment) if self.segment is not None and self.segment > 0 else 1.0

    def _warp_points(self, warp: str, theta, points: np.ndarray, dt: float, camera: Camera, duration: float):
        twin = _twin(warp)
        x, y = points
        xw, yw, _, _ = twin.warp(
            np.asarray(theta, dtype=np.float64),
            x,
            y,
            np.full(x.shape, float(dt)),
            center=(camera.cx, camera.cy),
            focal=(camera.fx, camera.fy),
            duration=duration,
        )
        return np.stack([np.broadcast_to(xw, x.shape), np.broadcast_to(yw, x.shape)]).astype(np.float64)

    def _homography(self, dt: float, camera: Camera) -> np.ndarray:
        """``W(., dt; theta)`` as a homography (ValueError where the warp is not one)."""
        pts = _probe_points(camera)
        H, err = _fit_homography(
            pts, self._warp_points(self.warp, self.theta, pts, dt, camera, self._duration())
        )
        if not err <= _EXACT_PX * (1.0 + float(np.max(np.abs(pts)))):
            raise ValueError(
                f"the simulator cannot express the motion of warp {self.warp!r} with theta = {self.theta}: "
                f"its warp over {dt:g} s is not a homography of the image (residual {err:.3g} px)"
            )
        return H

    @property
    def windowed(self) -> bool:
        """True when the warp depends on the window duration T (``mitrokhin4`` with an angle): the motion
        is defined for windows of ``segment`` seconds."""
        twin = _twin(self.warp)
        if not twin.needs_duration or not any(self.theta):
            return False
        pts = _probe_points(_NOMINAL_CAMERA)
        a = self._warp_points(self.warp, self.theta, pts, 0.01, _NOMINAL_CAMERA, 1.0)
        b = self._warp_points(self.warp, self.theta, pts, 0.01, _NOMINAL_CAMERA, 0.37)
        return bool(np.max(np.abs(a - b)) > _EXACT_PX)

    def _for(self, camera: Camera) -> _Derived:
        """The kind of motion (and ``M0``) for ``camera``, derived once."""
        key = (camera.fx, camera.fy, camera.cx, camera.cy)
        if key in self._derived:
            return self._derived[key]
        a, b = _PROBE_DT
        Ha, Hb, Hab = (self._homography(dt, camera) for dt in (a, b, a + b))
        scale = 1.0 + max(camera.fx, camera.fy, abs(camera.cx), abs(camera.cy))
        pts = _probe_points(camera)
        if np.max(np.abs(_apply(Ha @ Hb, pts) - _apply(Hab, pts))) <= _EXACT_PX * scale:
            derived = _Derived("group")
        else:
            Ma, Mb = (np.eye(3) - Ha) / a, (np.eye(3) - Hb) / b
            linear = np.max(np.abs(_apply(np.eye(3) - (a + b) * Ma, pts) - _apply(Hab, pts)))
            same = np.max(np.abs(Ma - Mb)) <= 1e-6 * max(1.0, float(np.max(np.abs(Ma))))
            if not (linear <= _EXACT_PX * scale and same):
                raise ValueError(
                    f"the simulator cannot express the motion of warp {self.warp!r} with theta = "
                    f"{self.theta}: its warp is neither a one-parameter group of homographies (constant "
                    "parameters) nor first order in time (W(x, dt) = (I - dt M) x)"
                )
            derived = _Derived("first_order", 0.5 * (Ma + Mb))
        self._derived[key] = derived
        return derived

    # --- the motion --------------------------------------------------------------------------------
    def check(self, t_end: float) -> None:
        """Raise ValueError if the motion is not defined up to ``t_end`` seconds (a first-order motion
        that reaches the plane: ``det(I - t M0) <= 0.01``)."""
        derived = self._for(_NOMINAL_CAMERA)
        if derived.kind != "first_order":
            return
        for t in np.linspace(0.0, float(t_end), 401):
            if not np.linalg.det(np.eye(3) - t * derived.M0) > 0.01:
                raise ValueError(
                    f"{self.warp} with theta = {self.theta} reaches the plane (a singular warp, "
                    f"det(I - t M) <= 0.01) at t = {t:.4g} s, before t = {t_end} s: use smaller parameters "
                    "or a shorter simulation"
                )

    def matrix(self, t: float, camera: Camera) -> np.ndarray:
        """``G(t)``: 3x3 homography moving image points (px) from time 0 to time ``t`` (s)."""
        derived = self._for(camera)
        if derived.kind == "group":
            return np.linalg.inv(self._homography(float(t), camera))
        return np.linalg.inv(np.eye(3) - float(t) * derived.M0)

    def window_warp(self, t: float, dt: float, camera: Camera) -> np.ndarray:
        """The homography of the true warp of a window starting at ``t``: ``G(t) G(t + dt)^-1``."""
        return self.matrix(t, camera) @ np.linalg.inv(self.matrix(t + dt, camera))

    def theta_at(
        self,
        t: float,
        warp: str | None = None,
        *,
        duration: float | None = None,
        camera: Camera | None = None,
    ) -> np.ndarray:
        """Parameters (physical units) of the warp that undoes the motion of a window starting at ``t``
        seconds: of this motion's model, or of ``warp`` (another registered model with a NumPy twin,
        with the window ``duration`` in s where that model depends on it), for ``camera`` (default a
        nominal one: the parameters of the built-ins do not depend on it).

        Raises
        ------
        NotExpressedError
            (a ValueError) where ``warp`` cannot express the motion (e.g. a rotation in an affine model).
        """
        t = float(t)
        target = self.warp if warp is None else warp
        model = get_warp(target)
        if target == self.warp and self._for(_NOMINAL_CAMERA).kind == "group":
            return np.asarray(self.theta, dtype=np.float64).copy()
        T = self._duration() if duration is None else float(duration)
        camera = _NOMINAL_CAMERA if camera is None else camera
        pts = _probe_points(camera)
        windows = [(dt, _apply(self.window_warp(t, dt, camera), pts)) for dt in _PROBE_DT]

        def residual(theta):
            return np.concatenate(
                [
                    (self._warp_points(target, theta, pts, dt, camera, T) - want).ravel()
                    for dt, want in windows
                ]
            )

        from cmax_taichi.testing import samples

        scales = samples.parameter_scales(model, duration=_PROBE_DT[0], sensor=(240, 180), camera=camera)
        start = np.asarray(self.theta, dtype=np.float64) if target == self.warp else np.zeros(model.n_params)
        theta, err = _solve_parameters(residual, start, scales)
        if not err <= _EXACT_PX * 100:
            raise NotExpressedError(
                f"the motion of {self.warp} with theta = {self.theta} at t = {t:g} s is not a {target} warp: "
                f"the best {target} parameters leave {err:.3g} px over {max(_PROBE_DT) * 1e3:g} ms",
                err,
                max(_PROBE_DT),
            )
        return theta
