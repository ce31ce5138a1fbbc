"""Dense flow of every window of a recording, each warm-started from the previous one.

:func:`iter_flow` slides windows over a recording (by event count, 30,000 by default, or by duration),
estimates each with one :class:`~cmax_taichi.flow.DenseFlowEstimator` (its compiled kernels and fields
serve every window) warm-started from the previous window's flow, scores it against the recording's
ground truth where the reader has some (``Recording.flow``: MVSEC, DSEC, the simulator), and yields one
:class:`FlowWindow` at a time, so that a long recording never holds more than one flow in memory.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cmax_taichi.core.events import Events
from cmax_taichi.flow.solver import DenseFlowEstimator, FlowResult
from cmax_taichi.metrics import event_mask, flow_error

__all__ = ["FlowWindow", "iter_flow"]


@dataclass
class FlowWindow:
    """One window's dense flow.

    Attributes
    ----------
    index : int
        Window number (0-based).
    result : FlowResult
        The estimate (node flow, px/s; :meth:`FlowResult.flow` on the pixels).
    dt : float
        The interval of :attr:`displacement` and of the metrics, s (from the window's first event).
    metrics : dict or None
        AEE, NPE, ... of the displacement over ``dt`` against the recording's ground truth on the
        pixels with events of that interval (:func:`cmax_taichi.metrics.flow_error`); None without
        ground truth.
    events : Events
        The window's events (for figures).
    """

    index: int
    result: FlowResult
    dt: float
    metrics: dict | None = None
    events: Events | None = field(default=None, repr=False)

    @property
    def displacement(self) -> np.ndarray:
        """``(2, H, W)``: the flow times ``dt`` (px)."""
        return self.result.flow(self.dt)


def _windows(source, n_events: int, duration: float | None, stride) -> Iterator[Events]:
    if isinstance(source, Events):
        if duration is not None:
            return source.windows_by_duration(duration, stride)
        return source.windows_by_count(n_events, None if stride is None else int(stride))
    if hasattr(source, "windows"):
        return source.windows(n_events=n_events, duration=duration, stride=stride)
    raise TypeError(f"source must be Events or an open Recording, got {type(source).__name__}")


def _ground_truth(source, t0: float, t1: float, mask_events: Events | None):
    """``(flow over [t0, t1], event mask)`` from the source's ground truth, or None."""
    flow_of = getattr(source, "flow", None)
    if flow_of is None or not callable(flow_of):
        return None
    try:
        gt = flow_of(t0, t1)
    except ValueError:  # the interval is outside what the ground truth covers
        return None
    if gt is None:
        return None
    events = mask_events
    read_time = getattr(source, "read_time", None)
    if callable(read_time):
        events = read_time(t0, float(np.nextafter(t1, np.inf)))
    return gt, event_mask(events)


def iter_flow(
    source: Any,
    estimator: DenseFlowEstimator | None = None,
    *,
    n_events: int = 30000,
    duration: float | None = None,
    stride: int | float | None = None,
    dt: float | None = None,
    max_windows: int | None = None,
    warm_start: bool = True,
    score: bool = True,
) -> Iterator[FlowWindow]:
    """Estimate the dense flow of every window of ``source``.

    Parameters
    ----------
    source : Events or Recording
        The events, or a recording opened with :func:`cmax_taichi.io.open_recording` (its reader gives
        the ground truth).
    estimator : DenseFlowEstimator, optional
        The solver and its settings (default ``DenseFlowEstimator()``).
    n_events : int
        Events per window (used when ``duration`` is None).
    duration : float, optional
        Window length, s (windows by time).
    stride : int or float, optional
        Start-to-start step (events, or s with ``duration``); default the window size.
    dt : float, optional
        The interval of each window's displacement and metrics, s, from its first event (MVSEC's
        ``dt = 1`` or 4 frames, DSEC's 100 ms); default the window's own duration.
    max_windows : int, optional
        Stop after this many windows.
    warm_start : bool
        Start each window from the previous window's flow (the first window: the global search).
    score : bool
        Score each window against the source's ground truth when it has some.

    Yields
    ------
    FlowWindow
    """
    if dt is not None and not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
    if max_windows is not None and (not isinstance(max_windows, int) or max_windows < 1):
        raise ValueError(f"max_windows must be an integer >= 1, got {max_windows!r}")
    estimator = estimator if estimator is not None else DenseFlowEstimator()
    previous: FlowResult | None = None
    for index, window in enumerate(_windows(source, n_events, duration, stride)):
        if max_windows is not None and index >= max_windows:
            break
        if len(window) < 2 or not window.duration > 0:
            continue
        result = estimator.estimate(window, warm=previous if warm_start else None)
        interval = float(window.duration) if dt is None else float(dt)
        metrics = None
        if score:
            truth = _ground_truth(source, result.t_start, result.t_start + interval, window)
            if truth is not None:
                gt, mask = truth
                if gt.shape != (2, window.height, window.width):
                    raise ValueError(
                        f"the ground-truth flow is {gt.shape[2]}x{gt.shape[1]} px, the events' sensor "
                        f"{window.width}x{window.height}: open the recording with its sensor size "
                        "(sensor_size=, or --sensor-size)"
                    )
                metrics = flow_error(result.flow(interval), gt, mask)
        yield FlowWindow(index=index, result=result, dt=interval, metrics=metrics, events=window)
        previous = result


def summary(windows: list[FlowWindow]) -> dict:
    """Mean metrics and timing over windows (JSON-friendly)."""
    out: dict = {"windows": len(windows)}
    if not windows:
        return out
    out["seconds"] = float(sum(w.result.seconds for w in windows))
    out["stalled_windows"] = sum(w.result.status == "stalled" for w in windows)
    out["mean_seconds_after_first"] = (
        float(np.mean([w.result.seconds for w in windows[1:]])) if len(windows) > 1 else out["seconds"]
    )
    scored = [w.metrics for w in windows if w.metrics is not None]
    if scored:
        keys = [k for k in scored[0] if k not in ("n_pixels", "n_missing")]
        out["metrics"] = {k: float(np.nanmean([m[k] for m in scored])) for k in keys}
        out["scored_windows"] = len(scored)
    return out


def default_path_name(path: str | os.PathLike) -> str:
    """A short name for a recording path (its stem, or its folder's name)."""
    p = os.fspath(path)
    return os.path.splitext(os.path.basename(p.rstrip("/")))[0] or "recording"
