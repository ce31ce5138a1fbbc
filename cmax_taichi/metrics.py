"""Accuracy metrics of motion estimates, as the event-vision literature reports them.

=================  ===============================================================  ==============
metric             formula                                                          unit
=================  ===============================================================  ==============
AEE                mean over the evaluated pixels of ``|f_pred(x) - f_gt(x)|_2``    px (over the
                                                                                    GT interval)
NPE (N = 3, 10,    ``100 * #{x : |f_pred(x) - f_gt(x)|_2 > N} / #pixels``            % of pixels
20, any N)
FWL                ``Var(I(x; theta)) / Var(I(x; 0))``: IWE variance of the         dimensionless
                   estimate over that of the identity warp, same events and blur   (> 1: sharper)
RMS angular error  ``sqrt(mean_k |w_est,k - w_gt,k|^2) * 180 / pi`` over windows k  deg/s
                   (the norm of the 3-vector error; per-axis RMS also returned)
covered share      ``#{x : C_0(x) >= c and C_theta(x) >= c} / #{x : C_0(x) >= c}``  fraction
                   with C the vote count of the warped events, ``c = 0.25``
covered area       ``#{x : C_theta(x) >= c} / #{x : C_0(x) >= c}`` (< 1: the events   ratio
ratio              occupy less area than unwarped; collapse drives it towards 0)
=================  ===============================================================  ==============

The flow metrics use the pixels where the ground truth is valid (finite, and both components non-zero,
as in the authors' evaluation code) **and** at least one event of the interval occurred (its rounded
position). The flow of a parametric estimate over a ground-truth interval ``dt`` is
:func:`flow_from_warp` (the negated displacement of every pixel warped over ``dt``, in px).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from cmax_taichi.core.events import Camera, Events
from cmax_taichi.models.warps import WarpModel
from cmax_taichi.pipeline.flow_field import dense_flow
from cmax_taichi.pipeline.problem import ContrastMaximization

__all__ = [
    "angular_velocity_error",
    "COLLAPSE_AREA_SCALE",
    "COLLAPSE_SHARE",
    "area_scale",
    "covered_area_ratio",
    "covered_share",
    "event_mask",
    "flow_error",
    "flow_from_warp",
    "fwl",
    "valid_flow_mask",
]


def valid_flow_mask(flow_gt: np.ndarray) -> np.ndarray:
    """Pixels with valid ground truth: both components finite and non-zero. ``(2, H, W) -> (H, W)``."""
    flow_gt = np.asarray(flow_gt, dtype=np.float64)
    if flow_gt.ndim != 3 or flow_gt.shape[0] != 2:
        raise ValueError(f"flow must have shape (2, H, W), got {flow_gt.shape}")
    with np.errstate(invalid="ignore"):
        return np.all(np.isfinite(flow_gt), axis=0) & np.all(np.abs(flow_gt) > 0, axis=0)


def event_mask(events: Events) -> np.ndarray:
    """``(H, W)`` bool: pixels where at least one event occurred (its position rounded to the nearest
    pixel centre)."""
    W, H = events.sensor_size
    mask = np.zeros((H, W), dtype=bool)
    if len(events):
        xi = np.clip(np.rint(events.x).astype(np.int64), 0, W - 1)
        yi = np.clip(np.rint(events.y).astype(np.int64), 0, H - 1)
        mask[yi, xi] = True
    return mask


def flow_error(
    flow_pred: np.ndarray,
    flow_gt: np.ndarray,
    mask: np.ndarray | None = None,
    thresholds: Sequence[float] = (3.0, 10.0, 20.0),
) -> dict[str, float]:
    """AEE and NPE of a predicted flow against ground truth.

    Parameters
    ----------
    flow_pred, flow_gt : ndarray
        ``(2, H, W)`` flows (x, y) in px over the same interval.
    mask : ndarray of bool, optional
        ``(H, W)`` pixels to evaluate in addition to valid ground truth, normally
        :func:`event_mask` of the interval's events.
    thresholds : sequence of float
        The N of the NPE values, px.

    Returns
    -------
    dict
        ``"AEE"`` (px), ``"{N}PE"`` for each N (percent, N printed with ``:g``: ``"3PE"``), and
        ``"n_pixels"`` (the number evaluated). With no pixel to evaluate every value is NaN.
    """
    flow_pred = np.asarray(flow_pred, dtype=np.float64)
    flow_gt = np.asarray(flow_gt, dtype=np.float64)
    if flow_pred.shape != flow_gt.shape:
        raise ValueError(f"flow shapes differ: predicted {flow_pred.shape}, ground truth {flow_gt.shape}")
    valid = valid_flow_mask(flow_gt)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != valid.shape:
            raise ValueError(f"mask shape {mask.shape} does not match the flow's {valid.shape}")
        valid &= mask
    valid &= np.all(np.isfinite(flow_pred), axis=0)
    n = int(np.count_nonzero(valid))
    out: dict[str, float] = {"n_pixels": float(n)}
    if n == 0:
        out["AEE"] = math.nan
        for t in thresholds:
            out[f"{t:g}PE"] = math.nan
        return out
    err = np.hypot(flow_pred[0] - flow_gt[0], flow_pred[1] - flow_gt[1])[valid]
    out["AEE"] = float(err.mean())
    for t in thresholds:
        out[f"{t:g}PE"] = float(100.0 * np.count_nonzero(err > t) / n)
    return out


def flow_from_warp(
    warp: str | WarpModel,
    theta,
    sensor_size: tuple[int, int],
    *,
    camera: Camera | None = None,
    duration: float = 1.0,
    dt: float,
) -> np.ndarray:
    """Dense flow (px) that a parametric estimate implies over a ground-truth interval of ``dt`` s.

    ``-(W(x, dt; theta) - x)`` on every pixel, ``(2, H, W)``: the negated displacement of each pixel
    warped over ``dt`` (docs/FORMULAS.md, "Dense flow"). ``duration`` is the estimation window's T
    (used by ``mitrokhin4``, whose parameters are normalised by it).
    """
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt}")
    return dense_flow(warp, theta, sensor_size, camera=camera, duration=duration, dt=float(dt))


def fwl(
    events: Events,
    warp: str | WarpModel,
    theta,
    *,
    camera: Camera | None = None,
    blur_sigma: float = 1.0,
    t_ref: str | float = "first",
    polarity: str = "ignore",
) -> float:
    """Flow Warp Loss: ``Var(I(theta)) / Var(I(0))`` on ``events`` (all events of the interval).

    Same IWE (bilinear votes, Gaussian blur ``blur_sigma`` px) for both; > 1 means the estimate gives
    a sharper image than no motion.
    """
    prob = fwl_problem(events, warp, camera=camera, blur_sigma=blur_sigma, t_ref=t_ref, polarity=polarity)
    return float(prob.value(theta))


def fwl_problem(
    events: Events,
    warp: str | WarpModel,
    *,
    camera: Camera | None = None,
    blur_sigma: float = 1.0,
    t_ref: str | float = "first",
    polarity: str = "ignore",
) -> ContrastMaximization:
    """The problem whose value is the FWL: normalised IWE variance, no regularizer."""
    return ContrastMaximization(
        events,
        warp=warp,
        objective="variance",
        camera=camera,
        blur_sigma=blur_sigma,
        t_ref=t_ref,
        polarity=polarity,
        normalize=True,
    )


def angular_velocity_error(w_est, w_gt) -> dict[str, float | np.ndarray]:
    """Angular-velocity errors over windows.

    Parameters
    ----------
    w_est, w_gt : array_like
        ``(3,)`` or ``(K, 3)`` angular velocities, rad/s, same frame.

    Returns
    -------
    dict
        ``"rms_deg_s"``: ``sqrt(mean_k |w_est - w_gt|^2)`` in deg/s; ``"rms_axes_deg_s"``: per-axis RMS
        (3,) in deg/s; ``"error_deg_s"``: per-window error norms (K,); ``"relative"``: per-window
        ``|w_est - w_gt| / |w_gt|`` (K,) (NaN where ``w_gt = 0``).
    """
    est = np.atleast_2d(np.asarray(w_est, dtype=np.float64))
    gt = np.atleast_2d(np.asarray(w_gt, dtype=np.float64))
    if est.shape != gt.shape or est.shape[1] != 3:
        raise ValueError(f"angular velocities must both be (3,) or (K, 3), got {est.shape} and {gt.shape}")
    diff = np.degrees(est - gt)
    norms = np.linalg.norm(diff, axis=1)
    gt_norm = np.degrees(np.linalg.norm(gt, axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        relative = np.where(gt_norm > 0, norms / gt_norm, np.nan)
    return {
        "rms_deg_s": float(np.sqrt(np.mean(norms**2))),
        "rms_axes_deg_s": np.sqrt(np.mean(diff**2, axis=0)),
        "error_deg_s": norms,
        "relative": relative,
    }


#: below this share of the identity warp's covered pixels still covered at an estimate, the estimate
#: has gathered the events into a small area: "collapse" when its IWE is sharper than with no motion
COLLAPSE_SHARE = 0.5


#: below this mean area scale of the warp (see :func:`area_scale`) the estimate shrinks the events'
#: areas to less than half: a collapse
COLLAPSE_AREA_SCALE = 0.5


def area_scale(prob: ContrastMaximization, theta) -> float:
    """Mean area scale of the warp over the problem's events: the mean of ``|det dx'/dx|`` (unitless).

    1 for warps that keep areas (translation, rotation about the optical axis); an event collapse
    drives it towards 0, because the warp shrinks the neighbourhood of every event to a point.
    """
    from cmax_taichi.pipeline.jacobians import event_jacobians

    return float(np.mean(np.abs(event_jacobians(prob, theta)["det"])))


def covered_share(prob: ContrastMaximization, theta, min_count: float = 0.25) -> float:
    """Share of the identity warp's event-covered pixels that stay covered at ``theta`` (collapse
    gathers the events into a small area and drives it towards 0).

    A pixel is covered when its bilinear vote count (unblurred, polarity ignored) is at least
    ``min_count``; the default 0.25 is the least vote an event gives the nearest of its 4 pixels.
    """
    c0 = prob.maps(np.zeros(prob.model.n_params))["count"] >= min_count
    c1 = prob.maps(theta)["count"] >= min_count
    n0 = int(np.count_nonzero(c0))
    return float(np.count_nonzero(c0 & c1) / n0) if n0 else math.nan


def covered_area_ratio(prob: ContrastMaximization, theta, min_count: float = 0.25) -> float:
    """Pixels covered at ``theta`` over pixels covered by the identity warp (coverage as in
    :func:`covered_share`): below 1 when the warp gathers the events into less area (collapse), above
    1 when it spreads them."""
    n0 = int(np.count_nonzero(prob.maps(np.zeros(prob.model.n_params))["count"] >= min_count))
    n1 = int(np.count_nonzero(prob.maps(theta)["count"] >= min_count))
    return float(n1 / n0) if n0 else math.nan
