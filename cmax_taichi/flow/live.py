"""Dense flow of a live stream: each window's flow as soon as it is done, on the live loop of
:func:`cmax_taichi.solve.online.run_windows` (the reader thread, the bounded buffer, the skipped windows
counted, the stop conditions, the latencies), with one :class:`~cmax_taichi.flow.DenseFlowEstimator`
warm-started from window to window as :func:`~cmax_taichi.flow.iter_flow` does on a recording.

Windows: a number of events (30,000 by default, as ``iter_flow`` and ``cmax-taichi flow``: the same
windows as a recorded pass, so the same flows), a duration, or motion-adaptive
(:class:`~cmax_taichi.solve.adaptive.AdaptiveWindows`): each window holds the events of the time in which
the previous window's flow moves the fast pixels by the target (the speed: :func:`flow_speed`, the
:data:`SPEED_PERCENTILE` th percentile over the pixels of the window's events), and the first window
grows, warm-started from its last estimate, until its flow predicts enough motion over it.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import replace

import numpy as np

from cmax_taichi.core.events import Events
from cmax_taichi.flow.sequence import BEYOND_SENSOR, FlowWindow, check_dt, check_sensor, displace
from cmax_taichi.flow.solver import DenseFlowEstimator, FlowResult
from cmax_taichi.solve.adaptive import AdaptivePlanner, AdaptiveWindows
from cmax_taichi.solve.online import LiveResult, run_windows
from cmax_taichi.solve.warm import synthetic_window

__all__ = ["SPEED_PERCENTILE", "DenseFlowWindows", "flow_speed", "run_live_flow"]

#: the percentile of the flow's speed over a window's event pixels that sizes the next adaptive window:
#: the fast pixels, as a parametric warp's extreme pixels, without the nodes that no event constrains
#: (their flow is the smoothness terms' extrapolation)
SPEED_PERCENTILE = 95.0


def flow_speed(result: FlowResult, events: Events) -> float:
    """The :data:`SPEED_PERCENTILE` th percentile of the speed (px/s) of ``result``'s flow at the pixels
    of ``events`` (0 without events)."""
    if not len(events):
        return 0.0
    W, H = result.sensor_size
    u = result.flow()
    x = np.clip(np.rint(events.x), 0, W - 1).astype(np.intp)
    y = np.clip(np.rint(events.y), 0, H - 1).astype(np.intp)
    return float(np.percentile(np.hypot(u[0, y, x], u[1, y, x]), SPEED_PERCENTILE))


class DenseFlowWindows:
    """The per-window work of a live dense flow (a :class:`~cmax_taichi.solve.online.WindowEstimator`).

    Rows are :class:`~cmax_taichi.flow.FlowWindow` s with their displacement over ``dt`` (the window's
    duration by default; status ``beyond_sensor`` without one, as in ``iter_flow``) and their events
    while ``on_window`` runs; ``on_window(row, estimator, result, latency)`` gets the
    :class:`~cmax_taichi.flow.DenseFlowEstimator` and the :class:`~cmax_taichi.flow.FlowResult`.
    The rows kept afterwards (:attr:`LiveResult.recent`) hold neither events nor displacement (memory
    stays flat). The traced quantities are the median flow over the window's pixels with events.

    Parameters
    ----------
    estimator : DenseFlowEstimator
    dt : float, optional
        The interval of each displacement, s from the window's first event (default its duration).
    warm_start : bool
        Start each window from the previous window's flow (the first: the global search).
    """

    name = "dense_flow"
    param_names = ("median u", "median v")
    units = ("px/s", "px/s")

    def __init__(self, estimator: DenseFlowEstimator, *, dt: float | None = None, warm_start: bool = True):
        check_dt(dt)
        self.estimator, self.dt, self.warm_start = estimator, dt, bool(warm_start)
        self.previous: FlowResult | None = None
        options = estimator.problem_options
        grid = estimator._grid_arg
        self.settings = {
            "grid": [grid.nx, grid.ny] if hasattr(grid, "nx") else list(grid),
            "levels": estimator.levels,
            "objective": options["objective"],
            "references": options["references"],
            "regularizers": dict(options["regularizers"]),
            "blur": options["blur_sigma"],
            "padding": estimator.padding,
            "dt": dt,
            "warm_start": self.warm_start,
        }

    def warm_up(self, sensor_size: tuple[int, int], n_events: int) -> float:
        """Compile (or load) the dense flow's kernels on a synthetic window of ``sensor_size`` (the
        global search and every level); no warm state is left. Returns the seconds it took."""
        t0 = time.perf_counter()
        events = synthetic_window(sensor_size, n_events, self.estimator.camera)
        with warnings.catch_warnings():  # a synthetic window's stalled level is nobody's concern
            warnings.simplefilter("ignore")
            self.estimator.estimate(events)
        return time.perf_counter() - t0

    def solve(self, used: Events, kept, planner: AdaptivePlanner | None, grow):
        res = self.estimator.estimate(used, warm=self.previous if self.warm_start else None)
        inside = None
        if planner is not None:
            speed = flow_speed(res, used)
            if planner.duration is None:  # the first window grows until its flow holds enough motion
                while (longer := planner.retry_duration(res.duration, speed)) is not None:
                    grown = grow(longer, planner.predicted(speed))
                    if grown is None:
                        break
                    used, kept, inside = grown
                    before = res
                    res = self.estimator.estimate(used, warm=before)
                    res = replace(res, n_evaluations=before.n_evaluations + res.n_evaluations,
                                  seconds=before.seconds + res.seconds)  # fmt: skip
                    speed = flow_speed(res, used)
            planner.predict(speed)
        row = FlowWindow(index=-1, result=res, dt=math.nan, events=used, t_start=float(used.t[0]),
                         t_end=float(used.t[-1]), n_events=len(used))  # fmt: skip
        displace(row, self.dt)  # the displacement is part of the window's work (its latency)
        return row, used, kept, inside

    def report(self, solved: FlowWindow, used: Events, *, index: int, status: str, n_window: int,
               seconds: float):  # fmt: skip
        row = solved
        row.index, row.n_dropped = index, n_window - len(used)
        if row.status != BEYOND_SENSOR:
            row.status = status
        return row, self.estimator, row.result

    def skipped(self, *, index: int, t_start: float, t_end: float, n_events: int, status: str,
                n_dropped: int) -> FlowWindow:  # fmt: skip
        return FlowWindow(index=index, result=None, dt=math.nan, status=status, t_start=t_start, t_end=t_end,
                          n_events=n_events, n_dropped=n_dropped)  # fmt: skip

    def advance(self, row: FlowWindow, result: FlowResult) -> None:
        self.previous = result
        row.events = row.displacement = None  # the row stays in LiveResult.recent: nothing large in it


def run_live_flow(
    stream,
    estimator: DenseFlowEstimator | None = None,
    *,
    windows: AdaptiveWindows | int | float = 30000,
    dt: float | None = None,
    warm_start: bool = True,
    **run_options,
) -> LiveResult:
    """The dense flow of every window of ``stream`` while it plays.

    Parameters
    ----------
    stream : EventStream
        From :func:`cmax_taichi.io.streams.open_stream`; closed when the run ends.
    estimator : DenseFlowEstimator, optional
        The solver and its settings (default ``DenseFlowEstimator()``); its ``camera``, when set,
        replaces the stream's (the events are undistorted by it, the losses counted).
    windows : AdaptiveWindows, int or float
        Events per window (default 30,000, as :func:`~cmax_taichi.flow.iter_flow`), seconds per window,
        or motion-adaptive (see the module docstring).
    dt : float, optional
        The interval of each window's displacement, s (default the window's duration).
    warm_start : bool
        Start each window from the previous window's flow.
    **run_options
        ``max_windows``, ``backlog_events``, ``idle_timeout``, ``keep_tail``, ``warm_up``, ``on_ready``,
        ``stop``, ``on_window``, ``on_skipped``: as for :func:`~cmax_taichi.solve.online.run_windows`
        (``on_window(row, estimator, result, latency)``: :class:`DenseFlowWindows`).

    Returns
    -------
    LiveResult
        ``warp`` is ``"dense_flow"``; ``recent`` holds the latest rows (without their flows).

    Raises
    ------
    ValueError
        Bad arguments, grids that do not fit the stream's sensor, or an IWE above
        ``max_sensor_pixels``: before the stream is read.
    StreamError
        The source failed (see :func:`~cmax_taichi.solve.online.run_windows`).
    """
    estimator = estimator if estimator is not None else DenseFlowEstimator()
    check_sensor(estimator, stream.sensor_size)
    per_window = DenseFlowWindows(estimator, dt=dt, warm_start=warm_start)
    camera = estimator.camera if estimator.camera is not None else getattr(stream, "camera", None)
    return run_windows(stream, per_window, camera=camera, windows=windows, **run_options)
