"""Per-window scales and default search box of :func:`cmax_taichi.maximize`.

Internal units
--------------
Parameters differ in scale by orders of magnitude (px/s, 1/s, rad/s, and all of them with the window
duration T). The optimizer works on ``u = theta * s`` where ``s`` (:func:`parameter_scales`) makes one
unit of ``u`` about **one pixel of displacement over the window**:

==============================================  =====================  ===========================
parameter                                        scale ``s`` (px per     default search range
                                                 unit of theta)          (:func:`search_bounds`)
==============================================  =====================  ===========================
velocity, px/s (``v_x``, ``v_y``, ``h_x``, ...)  ``T``                  ``|theta T| <= max(W, H)/2``
rate, 1/s (``h_z``, ``s``)                       ``T r``                ``|theta T| <= 1``
in-plane angular velocity, rad/s (``w``,         ``T r``                ``|theta T| <= 1`` rad
``theta``, rotation3 ``w_z``)
out-of-plane angular velocity, rad/s             ``T sqrt(f_x f_y)``    ``f |theta| T <= max(W, H)/2``
(rotation3 ``w_x``, ``w_y``)
==============================================  =====================  ===========================

``r`` is the RMS distance (px) of the pixel grid from the warp's centre (principal point or image
centre). Velocities are searched up to half the image per window. Rates are searched up to
``|h_z| T = 1``: at ``h_z T = 1`` the zoom sends the window's last events into the centre (time to
contact = T), and beyond it the events pass through the centre (a non-physical, mirrored warp).
The kind of each parameter comes from the model's registry entry (``WarpModel.parameter_kinds``: its
units px/s, 1/s, rad/s, unless it declares ``scale_kinds``, as rotation3 does for ``w_x, w_y``). A
model with another unit gets its scales numerically (the RMS over the pixel grid of the flow a unit
parameter causes, times T) and the velocity range for every parameter.

Learning rates, tolerances and grid spacings below are in these units (px over the window).
"""

from __future__ import annotations

import math

import numpy as np

from cmax_taichi.models.warps import WarpModel
from cmax_taichi.pipeline.problem import ContrastMaximization

__all__ = ["half_ranges_u", "parameter_scales", "rms_radius", "search_bounds"]


# --- scales and ranges ---------------------------------------------------------------------------
def rms_radius(prob: ContrastMaximization) -> float:
    """RMS distance (px) of the pixel centres from the warp's centre."""
    W, H = prob.width, prob.height
    cx, cy = prob.center
    var_x = (W * W - 1) / 12.0 + (cx - (W - 1) / 2.0) ** 2
    var_y = (H * H - 1) / 12.0 + (cy - (H - 1) / 2.0) ** 2
    return math.sqrt(var_x + var_y)


_NUMERIC_SCALES: dict = {}


def _kinds(model: WarpModel) -> tuple[str, ...] | None:
    """Per parameter "velocity" (range: half the image), "rate" (range: |theta T| <= 1) or "focal", as
    the model declares them (``WarpModel.parameter_kinds``: from its units unless declared); None:
    numeric scales."""
    return model.parameter_kinds


def _numeric_scales_per_second(prob: ContrastMaximization) -> np.ndarray:
    """RMS flow (px/s) over the pixel grid per unit of each parameter, at theta = 0 (cached)."""
    from cmax_taichi.pipeline.flow_field import dense_flow

    model = prob.model
    key = (model.name, id(model), prob.width, prob.height, prob.camera, prob.center)
    if key not in _NUMERIC_SCALES:
        out = np.empty(model.n_params)
        for i in range(model.n_params):
            # two passes: a unit step, then one sized to move pixels by about 1 px per second
            step = 1.0
            for _ in range(2):
                theta = np.zeros(model.n_params)
                theta[i] = step
                flow = dense_flow(model, theta, (prob.width, prob.height), camera=prob.camera, duration=1.0)
                rms = float(np.sqrt(np.nanmean(flow[0] ** 2 + flow[1] ** 2))) / step
                if not (math.isfinite(rms) and rms > 0):
                    rms = 1.0
                step = 1.0 / rms
            out[i] = rms
        _NUMERIC_SCALES[key] = out
    return _NUMERIC_SCALES[key]


def parameter_scales(prob: ContrastMaximization) -> np.ndarray:
    """Scale ``s`` of each parameter: px of displacement over the window per unit of theta.

    See the module docstring for the rule per parameter kind. ``u = theta * s`` are the optimizer's
    internal units.
    """
    T = prob.duration
    kinds = _kinds(prob.model)
    if kinds is None:
        return _numeric_scales_per_second(prob) * T
    r = rms_radius(prob)
    f = math.sqrt(prob.camera.fx * prob.camera.fy) if prob.camera is not None else 1.0
    per_kind = {"velocity": T, "rate": T * r, "focal": T * f}
    return np.array([per_kind[k] for k in kinds])


def half_ranges_u(prob: ContrastMaximization) -> np.ndarray:
    """Half-width of the default search box in internal units (px)."""
    half_image = 0.5 * max(prob.width, prob.height)
    kinds = _kinds(prob.model)
    if kinds is None:
        return np.full(prob.model.n_params, half_image)
    r = rms_radius(prob)
    return np.array([r if k == "rate" else half_image for k in kinds])


def search_bounds(prob: ContrastMaximization) -> tuple[np.ndarray, np.ndarray]:
    """Default global search box ``(lo, hi)`` in physical units (see the module docstring)."""
    half = half_ranges_u(prob) / parameter_scales(prob)
    return -half, half
