"""What the tests and the checker (:mod:`cmax_taichi.testing.checks`) derive from a model's declarations.

* :func:`edge_events`: a deterministic window of events on a few straight edges (plus noise), the
  synthetic input of the tests and of the checker;
* :func:`parameter_scales`: px of displacement over a window per unit of each parameter, from the
  declared parameter kinds (``WarpModel.parameter_kinds``: velocity, rate, focal), or numerically from
  the flow for a model with other units;
* :func:`moderate_theta`: a parameter vector that moves pixels by a few px over the window, with
  unequal, non-special magnitudes (so that no two parameters cancel: for an affine model
  ``a11 + a22 != 0`` and ``det != 1``, away from the regularizers' kinks);
* :func:`random_theta`: parameters drawn uniformly in a box of the same size.

A new model gets all of these from its registration; no table is kept per model.
"""

from __future__ import annotations

import math

import numpy as np

from cmax_taichi.core.events import Camera
from cmax_taichi.models.warps import WarpModel, get_warp

__all__ = [
    "CAMERA",
    "DURATION",
    "SENSOR",
    "edge_events",
    "moderate_theta",
    "parameter_scales",
    "random_theta",
    "rms_radius",
]

#: the small sensor (W, H), px, window duration (s) and camera of the tests and of the checker
SENSOR = (64, 48)
DURATION = 0.05
CAMERA = Camera(fx=50.0, fy=52.0, cx=31.3, cy=23.7)

#: golden-ratio steps: magnitudes in (0.55, 1], all distinct and none a simple fraction of another
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def edge_events(n: int = 400, seed: int = 0, sensor=SENSOR, duration: float = DURATION):
    """Events on a few straight edges (plus 10% noise), times uniform over ``duration`` (s).

    Returns
    -------
    x, y, t, p : ndarray
        Positions (px, inside the sensor), sorted times with ``t[0] = 0`` and ``t[-1] = duration``,
        polarities in {0, 1}.
    """
    rng = np.random.default_rng(seed)
    W, H = sensor
    n_edge = int(0.9 * n)
    starts = rng.uniform([8, 6], [W - 8, H - 6], size=(5, 2))
    angles = rng.uniform(0, np.pi, size=5)
    which = rng.integers(0, 5, size=n_edge)
    s = rng.uniform(-10, 10, size=n_edge)
    x = starts[which, 0] + s * np.cos(angles[which]) + rng.normal(0, 0.3, n_edge)
    y = starts[which, 1] + s * np.sin(angles[which]) + rng.normal(0, 0.3, n_edge)
    x = np.concatenate([x, rng.uniform(0, W - 1, n - n_edge)])
    y = np.concatenate([y, rng.uniform(0, H - 1, n - n_edge)])
    x = np.clip(x, 0, W - 1)
    y = np.clip(y, 0, H - 1)
    t = np.sort(rng.uniform(0, duration, n))
    t[0], t[-1] = 0.0, duration
    p = rng.integers(0, 2, n)
    return x, y, t, p


def rms_radius(sensor, center) -> float:
    """RMS distance (px) of the pixel centres of a ``(W, H)`` sensor from ``center`` (px)."""
    W, H = sensor
    cx, cy = center
    var_x = (W * W - 1) / 12.0 + (cx - (W - 1) / 2.0) ** 2
    var_y = (H * H - 1) / 12.0 + (cy - (H - 1) / 2.0) ** 2
    return math.sqrt(var_x + var_y)


def parameter_scales(
    model: str | WarpModel, *, duration: float = DURATION, sensor=SENSOR, camera: Camera | None = CAMERA
) -> np.ndarray:
    """Displacement (px) over a window of ``duration`` seconds per unit of each parameter.

    From the declared kinds: "velocity" ``T``, "rate" ``T r`` (``r`` the RMS pixel radius about the
    camera's principal point), "focal" ``T f``. A model whose units give no kind is scaled by the RMS
    of its flow over the pixel grid per unit of each parameter: from its float64 NumPy twin
    (:mod:`cmax_taichi.testing.reference_warps`) when one is registered, else from its Taichi flow
    (:func:`cmax_taichi.dense_flow`).
    """
    model = get_warp(model)
    T = float(duration)
    W, H = sensor
    center = (camera.cx, camera.cy) if camera is not None else ((W - 1) / 2.0, (H - 1) / 2.0)
    kinds = model.parameter_kinds
    if kinds is not None:
        f = math.sqrt(camera.fx * camera.fy) if camera is not None else 1.0
        per_kind = {"velocity": T, "rate": T * rms_radius(sensor, center), "focal": T * f}
        return np.array([per_kind[k] for k in kinds])
    return T * _flow_rms_per_unit(model, sensor, center, camera, T)


def _flow_rms_per_unit(model: WarpModel, sensor, center, camera, duration: float) -> np.ndarray:
    """RMS flow (px/s) over the pixel grid per unit of each parameter at theta = 0."""
    from cmax_taichi.testing import reference_warps

    focal = (camera.fx, camera.fy) if camera is not None else (1.0, 1.0)
    out = np.empty(model.n_params)
    twin = reference_warps.REFERENCE_WARPS.get(model.name)
    W, H = sensor
    ys, xs = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    for i in range(model.n_params):
        step = 1e-3  # small: the flow of a parameter is evaluated near theta = 0
        theta = np.zeros(model.n_params)
        theta[i] = step
        if twin is not None:
            vx, vy = twin.flow(theta, xs - center[0], ys - center[1], focal=focal, duration=duration)
            flow = np.stack([np.broadcast_to(vx, xs.shape), np.broadcast_to(vy, xs.shape)])
        else:
            from cmax_taichi.pipeline.flow_field import dense_flow

            flow = dense_flow(model, theta, sensor, camera=camera, duration=duration)
        rms = float(np.sqrt(np.mean(flow[0] ** 2 + flow[1] ** 2))) / step
        if not (math.isfinite(rms) and rms > 0):
            raise ValueError(f"warp {model.name!r}: parameter {model.params[i]} moves no pixel")
        out[i] = rms
    return out


def _multipliers(n: int) -> np.ndarray:
    """``n`` signed magnitudes in (0.55, 1]: distinct, non-special (golden-ratio steps), the first 1,
    every third one negative (so that a model's diagonal rates add up rather than cancel)."""
    i = np.arange(n)
    magnitudes = 1.0 - 0.45 * np.mod(i * _GOLDEN, 1.0)
    return np.where(i % 3 == 1, -magnitudes, magnitudes)


def moderate_theta(
    model: str | WarpModel,
    *,
    displacement: float = 3.0,
    duration: float = DURATION,
    sensor=SENSOR,
    camera: Camera | None = CAMERA,
) -> np.ndarray:
    """A parameter vector that moves pixels by about ``displacement`` px over ``duration`` seconds per
    parameter, with unequal magnitudes (see :func:`_multipliers`), in the model's physical units."""
    model = get_warp(model)
    scales = parameter_scales(model, duration=duration, sensor=sensor, camera=camera)
    return displacement * _multipliers(model.n_params) / scales


def random_theta(
    model: str | WarpModel,
    rng: np.random.Generator,
    *,
    displacement: float = 6.0,
    duration: float = DURATION,
    sensor=SENSOR,
    camera: Camera | None = CAMERA,
) -> np.ndarray:
    """Parameters drawn uniformly in ``[-d, d]`` px of displacement each (``d = displacement``)."""
    model = get_warp(model)
    scales = parameter_scales(model, duration=duration, sensor=sensor, camera=camera)
    return displacement * rng.uniform(-1.0, 1.0, model.n_params) / scales
