"""Dense flow of every window of a recording, each warm-started from the previous one.

:func:`iter_flow` slides windows over a recording (by event count, 30,000 by default, or by duration),
estimates each with one :class:`~cmax_taichi.flow.DenseFlowEstimator` (its compiled kernels and fields
serve every window) warm-started from the previous window's flow, scores it against the recording's
ground truth where the reader has some (``Recording.flow``: MVSEC, DSEC, the simulator), and yields one
:class:`FlowWindow` at a time, so that a long recording never holds more than one flow in memory.

Every event is accounted for as :func:`cmax_taichi.solve.sequence.process` accounts for them (the same
window plan and ledger, :mod:`cmax_taichi.core.windows`): a window that cannot be estimated (fewer
than 2 events, all at one time, the partial tail of count windows without ``keep_tail``) is a row with
its status (:attr:`FlowPass.skipped`, or ``on_skipped``), the events dropped outside the sensor or in
undistortion are counted per window, :attr:`FlowPass.events` has the totals by reason, and one
:class:`~cmax_taichi.core.checks.EventsDroppedWarning` at the end gives them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cmax_taichi.core import checks
from cmax_taichi.core.events import Events
from cmax_taichi.core.windows import (
    ESTIMATED,
    ESTIMATED_STATUSES,
    EventLedger,
    check_window_options,
    plan_windows,
    read_window,
)
from cmax_taichi.flow.grid import FlowBeyondSensorError, auto_padding, check_padded_sensor
from cmax_taichi.flow.solver import AUTO_PADDING, DenseFlowEstimator, FlowResult
from cmax_taichi.io._flow import GroundTruthRangeError
from cmax_taichi.metrics import event_mask, flow_error

__all__ = ["BEYOND_SENSOR", "FlowPass", "FlowWindow", "check_dt", "check_sensor", "displace", "iter_flow"]

#: the status of an estimated window whose flow over ``dt`` would carry points beyond the sensor (no
#: displacement, no flow file; :class:`~cmax_taichi.flow.grid.FlowBeyondSensorError`)
BEYOND_SENSOR = "beyond_sensor"


@dataclass
class FlowWindow:
    """One window of a pass: its dense flow, or the row of a window that was not estimated.

    Attributes
    ----------
    index : int
        Window number (0-based).
    result : FlowResult or None
        The estimate (node flow, px/s; :meth:`FlowResult.flow` on the pixels); None for a window that
        was not estimated.
    dt : float
        The interval of :attr:`displacement` and of the metrics, s (from the window's first event).
    metrics : dict or None
        AEE, NPE, ... of the displacement over ``dt`` against the recording's ground truth on the
        pixels with events of that interval (:func:`cmax_taichi.metrics.flow_error`); None without
        ground truth there, or with nothing to score (:attr:`note` says why).
    events : Events
        The window's events (for figures).
    status : str
        ``"estimated"``, ``"short_tail"`` (the partial tail, kept), :data:`BEYOND_SENSOR`, or why the
        window was not estimated (:data:`cmax_taichi.core.windows.STATUSES`).
    t_start, t_end : float
        Time of its first and last event used, s (NaN for a window without events).
    n_events : int
        Events used (after the drops).
    n_dropped : int
        Events of the window outside the sensor or lost in undistortion.
    note : str
        Why a window has no metrics or no displacement ("" otherwise).
    displacement : ndarray or None
        ``(2, H, W)``: the flow's displacement over ``dt`` (px); None when not estimated.
    """

    index: int
    result: FlowResult | None
    dt: float
    metrics: dict | None = None
    events: Events | None = field(default=None, repr=False)
    status: str = ESTIMATED
    t_start: float = math.nan
    t_end: float = math.nan
    n_events: int = 0
    n_dropped: int = 0
    note: str = ""
    displacement: np.ndarray | None = field(default=None, repr=False)

    @property
    def estimated(self) -> bool:
        """Whether the window has a displacement (a flow file's worth)."""
        return self.displacement is not None


def unscored_reason(metrics: dict) -> str:
    """Why :func:`~cmax_taichi.metrics.flow_error` scored no pixel ("" when it scored some)."""
    if metrics["n_pixels"] > 0:
        return ""
    if metrics.get("n_valid", 1) == 0:
        return "no valid ground-truth pixel over the interval (all NaN or zero)"
    if metrics.get("n_missing", 0) > 0:
        return "no finite flow on the pixels with ground truth and events"
    return "no event on a pixel with valid ground truth"


class FlowPass:
    """What :func:`iter_flow` returns: an iterator of the estimated :class:`FlowWindow` s, in order,
    and, once it is exhausted, the accounting of the pass.

    Attributes
    ----------
    skipped : list of FlowWindow
        The rows of the windows that were not estimated (``status`` says why).
    events : dict
        Where every event went (``total``, ``estimated``, each reason of
        :data:`cmax_taichi.core.windows.CATEGORIES`, ``after_max_windows``, ``windows`` per status):
        complete when the iteration ended.
    total : int or None
        Windows that may be estimated, when known before the pass (for a progress bar).
    source : dict
        The source's name, and for a recording its format and :meth:`~cmax_taichi.io.Recording.fingerprint`.
    """

    def __init__(self, plan, run: Callable[[FlowPass], Iterator[FlowWindow]]) -> None:
        self.skipped: list[FlowWindow] = []
        self.events: dict = {}
        self.total = plan.total
        self.source = dict(plan.desc)
        self._run = run(self)

    def __iter__(self) -> FlowPass:
        return self

    def __next__(self) -> FlowWindow:
        return next(self._run)


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
    keep_tail: bool = False,
    truth: Any = None,
    on_skipped: Callable[[FlowWindow], None] | None = None,
) -> FlowPass:
    """Estimate the dense flow of every window of ``source``.

    Parameters
    ----------
    source : Events or Recording
        The events, or a recording opened with :func:`cmax_taichi.io.open_recording` (its reader gives
        the ground truth, its camera undistorts the events: the losses are counted).
    estimator : DenseFlowEstimator, optional
        The solver and its settings (default ``DenseFlowEstimator()``); its ``camera``, when set,
        replaces the recording's.
    n_events : int
        Events per window (used when ``duration`` is None).
    duration : float, optional
        Window length, s (windows by time).
    stride : int or float, optional
        Start-to-start step (events, or s with ``duration``); default the window size.
    dt : float, optional
        The interval of each window's displacement and metrics, s, from its first event (MVSEC's
        ``dt = 1`` or 4 frames, DSEC's 100 ms); default the window's own duration. A window whose flow
        over ``dt`` would carry points beyond the sensor gets the status :data:`BEYOND_SENSOR` (no
        displacement), instead of an integration whose cost grows with ``dt``.
    max_windows : int, optional
        Stop after this many windows (estimated or not); the events after them are counted.
    warm_start : bool
        Start each window from the previous window's flow (the first window: the global search).
    score : bool
        Score each window against the ground truth when there is some.
    keep_tail : bool
        Count windows: estimate the partial tail (the events after the last full window) when it holds at
        least half a window (status ``"short_tail"``); otherwise it is a row ``"partial_tail"``.
    truth : object, optional
        The ground truth (``flow(t0, t1)`` and ``read_time(t0, t1)``); default the source's own.
    on_skipped : callable, optional
        ``on_skipped(window)`` for each window that is not estimated, when its turn comes (a caller that
        writes rows in order).

    Returns
    -------
    FlowPass
        Iterate it for the estimated windows; :attr:`FlowPass.skipped` and :attr:`FlowPass.events` hold
        the rest of the accounting once it is exhausted (one warning then counts the events not
        estimated, by reason).

    Raises
    ------
    ValueError
        Bad arguments, a grid that does not fit the sensor or the levels, or an IWE (the sensor and the
        estimator's padding) above ``max_sensor_pixels``, before any window is read; timestamps out of
        order; a ground truth that cannot be read (naming its file) or of another size than the sensor.
    """
    check_dt(dt)
    n_events, duration, stride, max_windows = check_window_options(n_events, duration, stride, max_windows)
    estimator = estimator if estimator is not None else DenseFlowEstimator()
    sensor = getattr(source, "sensor_size", None)
    if sensor is not None:
        check_sensor(estimator, sensor)
    plan = plan_windows(source, n_events, duration, stride, keep_tail)
    if max_windows is not None:
        plan.total = max_windows if plan.total is None else min(plan.total, max_windows)
    truth = truth if truth is not None else source
    camera = estimator.camera if estimator.camera is not None else plan.camera
    undistort = camera is not None and camera.has_distortion and not plan.undistorted

    def run(state: FlowPass) -> Iterator[FlowWindow]:
        lossy = checks.UndistortionTally()  # one warning for the first lossy window, the totals at the end
        ledger = EventLedger(plan.n_total)
        previous: FlowResult | None = None
        stopped_early = False
        for span in plan.spans:
            if max_windows is not None and span.index >= max_windows:
                stopped_early = True
                break
            used, inside, kept, status = read_window(span, plan, camera if undistort else None, lossy)
            ledger.add(span, status, inside, kept)
            row = FlowWindow(
                index=span.index,
                result=None,
                dt=math.nan if dt is None else float(dt),
                events=used,
                status=status,
                t_start=float(used.t[0]) if len(used) else math.nan,
                t_end=float(used.t[-1]) if len(used) else math.nan,
                n_events=len(used),
                n_dropped=len(span) - len(used),
            )
            if status not in ESTIMATED_STATUSES:
                row.events = None
                state.skipped.append(row)
                if on_skipped is not None:
                    on_skipped(row)
                continue
            row.result = estimator.estimate(used, warm=previous if warm_start else None)
            previous = row.result
            displace(row, dt)
            if score and row.displacement is not None:
                _score(row, truth)
            yield row
        ledger.finish(stopped_early)
        state.events = ledger.as_dict()
        ledger.warn(plan.desc["source"], n_events if duration is None else None, max_windows, stacklevel=3)

    return FlowPass(plan, run)


def check_sensor(estimator: DenseFlowEstimator, sensor_size: tuple[int, int]) -> None:
    """ValueError, before any event is read, when ``estimator``'s grids do not fit a ``sensor_size``
    sensor or its IWE (the sensor and the padding) exceeds ``max_sensor_pixels``."""
    sensor = tuple(sensor_size)
    estimator._finest_for(sensor).pyramid(estimator.levels)
    padding = estimator.padding
    check_padded_sensor(sensor, auto_padding(sensor, AUTO_PADDING) if padding is None else padding)


def check_dt(dt) -> None:
    """ValueError unless ``dt`` is None or a positive number of seconds."""
    if dt is not None and not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")


def displace(row: FlowWindow, dt: float | None) -> None:
    """The displacement of an estimated window (``row.result``) over ``dt`` s (default its duration):
    ``row.dt`` and ``row.displacement``, or the status :data:`BEYOND_SENSOR` with its note."""
    row.dt = float(row.result.duration) if dt is None else float(dt)
    try:
        row.displacement = row.result.flow(row.dt)
    except FlowBeyondSensorError as exc:
        row.status, row.note = BEYOND_SENSOR, str(exc)


def _score(row: FlowWindow, truth) -> None:
    """The metrics of ``row``'s displacement against ``truth`` over its interval (or the note why none)."""
    flow_of = getattr(truth, "flow", None)
    if not callable(flow_of):
        return
    t0, t1 = row.result.t_start, row.result.t_start + row.dt
    try:
        gt = flow_of(t0, t1)
    except GroundTruthRangeError:
        row.note = "outside the interval the ground truth covers"
        return
    if gt is None:
        return
    H, W = row.displacement.shape[1:]
    if np.shape(gt) != (2, H, W):
        raise ValueError(
            f"the ground-truth flow is {np.shape(gt)[-1]}x{np.shape(gt)[-2]} px, the events' sensor {W}x{H}: "
            "open the recording with its sensor size (sensor_size=, or --sensor-size)"
        )
    events = row.events
    read_time = getattr(truth, "read_time", None)
    if callable(read_time):
        events = read_time(t0, float(np.nextafter(t1, np.inf)))
    metrics = flow_error(row.displacement, gt, event_mask(events))
    row.note = unscored_reason(metrics)
    row.metrics = None if row.note else metrics


def summary(windows: list[FlowWindow]) -> dict:
    """Mean metrics and timing over the estimated windows (JSON-friendly), and why windows were not
    scored (``"unscored"``: reason -> count)."""
    estimated = [w for w in windows if w.result is not None]
    out: dict = {"windows": len(estimated)}
    if not estimated:
        return out
    seconds = [w.result.seconds for w in estimated]
    out["seconds"] = float(sum(seconds))
    out["stalled_windows"] = sum(w.result.status == "stalled" for w in estimated)
    out["first_window_seconds"] = float(seconds[0])
    out["mean_seconds_after_first"] = float(np.mean(seconds[1:])) if len(seconds) > 1 else None
    scored = [w.metrics for w in estimated if w.metrics is not None]
    if scored:
        keys = [k for k in scored[0] if k not in ("n_pixels", "n_missing", "n_valid")]
        out["metrics"] = {k: float(np.mean([m[k] for m in scored])) for k in keys}
        out["scored_windows"] = len(scored)
    unscored: dict[str, int] = {}
    for w in estimated:
        if w.metrics is None and w.note and w.status != BEYOND_SENSOR:
            unscored[w.note] = unscored.get(w.note, 0) + 1
    if unscored:
        out["unscored"] = unscored
    beyond = sum(w.status == BEYOND_SENSOR for w in estimated)
    if beyond:
        out[BEYOND_SENSOR] = beyond
    return out


def default_path_name(path: str | os.PathLike) -> str:
    """A short name for a recording path (its stem, or its folder's name)."""
    p = os.fspath(path)
    return os.path.splitext(os.path.basename(p.rstrip("/")))[0] or "recording"
