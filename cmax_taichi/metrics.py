"""Accuracy metrics of motion estimates, as the event-vision literature reports them.

=================  ===============================================================  ==============
metric             formula                                                          unit
=================  ===============================================================  ==============
AEE                mean over the evaluated pixels of ``|f_pred(x) - f_gt(x)|_2``    px (over the
                                                                                    GT interval)
NPE (N = 3, 10,    ``100 * #{x : |f_pred(x) - f_gt(x)|_2 > N} / #pixels``            % of pixels
20, any N)
%Out ("outlier")   ``100 * #{x : EPE > 3 px and EPE > 0.05 |f_gt(x)|} / #pixels``   % of pixels
AE ("AE_deg")      mean angle between ``(u, v, 1)`` and ``(u_gt, v_gt, 1)``          degrees
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
as in the authors' evaluation code; for DSEC, whose PNGs carry a validity channel and where a zero
component is a valid flow, ``zero_is_invalid=False``) **and** at least one event of the interval
occurred (its rounded position). The flow of a parametric estimate over a ground-truth interval ``dt``
is :func:`flow_from_warp` (the negated displacement of every pixel warped over ``dt``, in px).

Which outlier rate is which (sources):

* ``3PE`` (any ``NPE``): EPE > N px. The nPE of tub-rip/event_based_optical_flow
  (``src/utils/flow_utils.py::calculate_flow_error_numpy``: 1PE, 2PE, 3PE, 5PE, 10PE, 20PE) and of the
  DSEC optical-flow benchmark's tables (1PE, 2PE, 3PE with EPE and AE). EV-FlowNet's test code
  (daniilidis-group/EV-FlowNet ``src/eval_utils.py::flow_error_dense``) prints its complement, the
  share of pixels with EPE < 3 px.
* ``outlier`` (%Out): EPE > 3 px **and** EPE > 5% of the ground-truth magnitude, KITTI 2015's Fl
  (torchvision's RAFT reference ``references/optical_flow/utils.py``: ``(epe > 3) & (epe / |gt| >
  0.05)``), the "% Outlier" of the MVSEC tables that follow Zhu et al. 2019.
* ``AE_deg``: the angular error of tub-rip's code (``arccos((1 + u u_gt + v v_gt) / (sqrt(1 + u^2 +
  v^2) sqrt(1 + u_gt^2 + v_gt^2)))``, radians there), in degrees.

All are computed per window; over a sequence the benchmarks average the per-window values.
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
    "score_flow",
    "valid_flow_mask",
]


def valid_flow_mask(flow_gt: np.ndarray, zero_is_invalid: bool = True) -> np.ndarray:
    """Pixels with valid ground truth: both components finite and (``zero_is_invalid``, MVSEC's
    convention) non-zero. ``(2, H, W) -> (H, W)``."""
    flow_gt = np.asarray(flow_gt, dtype=np.float64)
    if flow_gt.ndim != 3 or flow_gt.shape[0] != 2:
        raise ValueError(f"flow must have shape (2, H, W), got {flow_gt.shape}")
    valid = np.all(np.isfinite(flow_gt), axis=0)
    if zero_is_invalid:
        with np.errstate(invalid="ignore"):
            valid &= np.all(np.abs(flow_gt) > 0, axis=0)
    return valid


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
    *,
    zero_is_invalid: bool = True,
) -> dict[str, float]:
    """AEE, NPE, %Out and AE of a predicted flow against ground truth (module docstring: sources).

    Parameters
    ----------
    flow_pred, flow_gt : ndarray
        ``(2, H, W)`` flows (x, y) in px over the same interval.
    mask : ndarray of bool, optional
        ``(H, W)`` pixels to evaluate in addition to valid ground truth, normally
        :func:`event_mask` of the interval's events.
    thresholds : sequence of float
        The N of the NPE values, px.
    zero_is_invalid : bool
        Whether a ground-truth component exactly 0 marks an invalid pixel (MVSEC and the simulator's
        files: yes; DSEC, whose invalid pixels are NaN once read: no).

    Returns
    -------
    dict
        ``"AEE"`` (px), ``"{N}PE"`` for each N (percent, N printed with ``:g``: ``"3PE"``),
        ``"outlier"`` (%Out: EPE > 3 px and > 5% of ``|f_gt|``, percent), ``"AE_deg"`` (degrees),
        ``"n_pixels"`` (the number evaluated), ``"n_missing"`` (pixels that would be evaluated but
        whose prediction is not finite, e.g. NaN for no estimate: left out, and counted here) and
        ``"n_valid"`` (pixels with valid ground truth, events or not). With no pixel to evaluate every
        value is NaN: ``n_valid = 0`` says the ground truth itself is empty there (all NaN or zero).
    """
    flow_pred = np.asarray(flow_pred, dtype=np.float64)
    flow_gt = np.asarray(flow_gt, dtype=np.float64)
    if flow_pred.shape != flow_gt.shape:
        raise ValueError(f"flow shapes differ: predicted {flow_pred.shape}, ground truth {flow_gt.shape}")
    valid = valid_flow_mask(flow_gt, zero_is_invalid)
    n_valid = int(np.count_nonzero(valid))
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != valid.shape:
            raise ValueError(f"mask shape {mask.shape} does not match the flow's {valid.shape}")
        valid &= mask
    predicted = np.all(np.isfinite(flow_pred), axis=0)
    n_missing = int(np.count_nonzero(valid & ~predicted))
    valid &= predicted
    n = int(np.count_nonzero(valid))
    out: dict[str, float] = {"n_pixels": float(n), "n_missing": float(n_missing), "n_valid": float(n_valid)}
    if n == 0:
        out["AEE"] = math.nan
        for t in thresholds:
            out[f"{t:g}PE"] = math.nan
        out["outlier"] = out["AE_deg"] = math.nan
        return out
    u, v = flow_pred[0][valid], flow_pred[1][valid]
    ug, vg = flow_gt[0][valid], flow_gt[1][valid]
    err = np.hypot(u - ug, v - vg)
    out["AEE"] = float(err.mean())
    for t in thresholds:
        out[f"{t:g}PE"] = float(100.0 * np.count_nonzero(err > t) / n)
    out["outlier"] = float(100.0 * np.count_nonzero((err > 3.0) & (err > 0.05 * np.hypot(ug, vg))) / n)
    cos = (1.0 + u * ug + v * vg) / (np.sqrt(1.0 + u * u + v * v) * np.sqrt(1.0 + ug * ug + vg * vg))
    out["AE_deg"] = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).mean())
    return out


def score_flow(
    recording,
    flow_pred: np.ndarray,
    t0: float,
    t1: float,
    thresholds: Sequence[float] = (3.0, 10.0, 20.0),
) -> dict[str, float] | None:
    """Score a predicted flow over ``[t0, t1]`` against a recording's ground truth, as the benchmarks
    count it: :func:`flow_error` on the pixels with valid ground truth where at least one event of
    ``[t0, t1]`` occurred.

    Parameters
    ----------
    recording : cmax_taichi.io.Recording
        A reader with flow ground truth (``flow(t0, t1)``: MVSEC ``*_gt_flow_dist.npz``, DSEC flow
        PNGs, the simulator's MVSEC-like files) and ``read_time``.
    flow_pred : ndarray
        (2, H, W) predicted displacement over ``[t0, t1]``, px, on the recording's pixel grid (the
        grid of its ground truth: MVSEC's raw pixels, DSEC's rectified ones).
    t0, t1 : float
        The interval, s.
    thresholds : sequence of float
        NPE thresholds, px.

    Returns
    -------
    dict or None
        :func:`flow_error`'s values plus ``"n_events"``; None when the recording has no flow ground
        truth. For DSEC a zero ground-truth component counts as valid (its PNGs have a validity
        channel).
    """
    gt = recording.flow(t0, t1)
    if gt is None:
        return None
    events = recording.read_time(t0, float(np.nextafter(t1, np.inf)))
    err = flow_error(
        flow_pred,
        gt,
        event_mask(events),
        thresholds,
        zero_is_invalid=getattr(recording, "format", None) != "dsec",
    )
    err["n_events"] = float(len(events))
    return err


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
