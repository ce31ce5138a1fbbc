"""Online estimation: the windows of a live stream estimated while the events arrive.

:func:`run_windows` reads an :class:`~cmax_taichi.io.streams.EventStream` on a reader thread into a
bounded buffer and estimates each window as soon as it is complete, with a per-window estimator
(:class:`WindowEstimator`); each window's row goes to ``on_window`` at once. :func:`run_live` estimates
a parametric warp, on the machinery of :func:`~cmax_taichi.solve.sequence.process` (one problem for
every window, the warm start and its tracking test: :class:`~cmax_taichi.solve.warm.WindowSolver`,
:class:`WarpWindows`); :func:`cmax_taichi.flow.live.run_live_flow` the dense flow, on the same loop.

* **The producer is never blocked**: the reader thread only copies each packet into the buffer. When the
  estimator falls behind and the buffer (``backlog_events``) is full, the reader skips *whole windows*
  from its front (as the window rule cuts them), and counts them (status ``behind``): memory stays
  bounded, and every event is estimated or counted (:class:`~cmax_taichi.core.windows.EventLedger` of a
  stream: ``late`` packets, ``malformed`` events, ``behind``, ``after_stop``).
* **Windows**: motion-adaptive by default (:class:`~cmax_taichi.solve.adaptive.AdaptiveWindows`), or a
  fixed number of events (an int) or duration (a float, s). A window is complete when the events that
  decide its end have arrived; when the stream ends, the last, partial window is estimated if it holds
  enough (``keep_tail``).
* **Latency** of a window: from the arrival of its last event (the packet that holds it) to its estimate.
* **Stopping**: the stream ends, ``idle_timeout`` s pass without a packet, ``max_windows`` windows are
  done, or ``stop`` (a :class:`threading.Event`, set by a signal handler) is set; the window in flight is
  finished first. A failing source (:class:`~cmax_taichi.io.streams.StreamError`) ends the run after the
  windows already complete, and is raised after :meth:`LiveResult` is filled (``error``).
"""

from __future__ import annotations

import bisect
import math
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from cmax_taichi.core import checks
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.core.windows import (
    BEHIND,
    ESTIMATED_STATUSES,
    EventLedger,
    Span,
    min_tail_events,
    window_status,
)
from cmax_taichi.models.warps import get_warp
from cmax_taichi.solve.adaptive import AdaptivePlanner, AdaptiveWindows, settle_window
from cmax_taichi.solve.results import WindowResult
from cmax_taichi.solve.warm import WindowSolver, check_sequence_t_ref

__all__ = ["LiveResult", "WarpWindows", "WindowEstimator", "run_live", "run_windows"]

#: latencies kept for the percentiles (the most recent ones; a fixed array: memory stays flat)
LATENCY_RING = 100_000
#: rows kept for a display (the most recent)
RECENT_ROWS = 500
#: seconds the reader waits for a packet before it checks whether to stop
_POLL = 0.02


class _CountWindows:
    """Windows of ``n`` events, with the interface of :class:`AdaptivePlanner` (``stop``, ``predict``)."""

    duration = None

    def __init__(self, n: int) -> None:
        self.n = checks.whole_number("window events", n, 2)
        self.max_events = self.n

    def stop(self, start: int, available: int, final: bool = False, **_) -> int | None:
        return start + self.n if start + self.n <= available else None

    def keeps_tail(self, start: int, end: int) -> bool:
        return end - start >= min_tail_events(self.n)

    def predict(self, speed: float) -> None:
        pass


class _DurationWindows(_CountWindows):
    """Windows of ``seconds`` of events (the event that reaches the window's end closes it)."""

    def __init__(self, seconds: float, time_of, search) -> None:
        self.seconds = checks.seconds("window duration", seconds, positive=True)
        self.time_of, self.search = time_of, search
        self.max_events = None

    def stop(self, start: int, available: int, final: bool = False, **_) -> int | None:
        if start >= available:
            return None
        end = self.search(self.time_of(start) + self.seconds)
        return end if end < available else None

    def keeps_tail(self, start: int, end: int) -> bool:
        return end - start >= 2 and self.time_of(end - 1) - self.time_of(start) >= self.seconds / 2


class _Buffer:
    """The events received and not yet taken: columns of a fixed capacity (no growth), indexed by a
    running position (``base`` is the position of the first held event), with the arrival time of each
    packet's last event."""

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)
        # zeros written, not just allocated: the pages are the process's from the start, so its memory
        # does not grow the first time a backlog fills them
        self.t = np.full(self.capacity, 0.0)
        self.x = np.full(self.capacity, 0.0)
        self.y = np.full(self.capacity, 0.0)
        self.p = np.full(self.capacity, 0, dtype=np.int8)
        self.head = 0  # array index of position base
        self.count = 0
        self.base = 0
        self.arrivals: deque[tuple[int, float]] = deque()  # (position after a packet, its arrival)

    @property
    def end(self) -> int:
        return self.base + self.count

    def time_of(self, i: int) -> float:
        return float(self.t[self.head + i - self.base])

    def search(self, t: float) -> int:
        view = self.t[self.head : self.head + self.count]
        return self.base + int(np.searchsorted(view, t, side="left"))

    def arrival_of(self, i: int) -> float:
        """The arrival of the packet that held position ``i``."""
        k = bisect.bisect_right(self.arrivals, i, key=lambda item: item[0])
        return self.arrivals[min(k, len(self.arrivals) - 1)][1]

    def append(self, t, x, y, p, arrival: float) -> None:
        n = len(t)
        if self.head + self.count + n > self.capacity:  # move the held events to the front
            for column in (self.t, self.x, self.y, self.p):
                column[: self.count] = column[self.head : self.head + self.count]
            self.head = 0
        a = self.head + self.count
        self.t[a : a + n], self.x[a : a + n], self.y[a : a + n], self.p[a : a + n] = t, x, y, p
        self.count += n
        self.arrivals.append((self.end, arrival))

    def take(self, n: int) -> tuple[np.ndarray, ...]:
        """The first ``n`` held events (copies), no longer held."""
        a = self.head
        out = tuple(c[a : a + n].copy() for c in (self.t, self.x, self.y, self.p))
        self.head += n
        self.count -= n
        self.base += n
        while self.arrivals and self.arrivals[0][0] <= self.base:
            self.arrivals.popleft()
        return out


@dataclass
class LiveResult:
    """What a live run did (the rows themselves went to ``on_window`` / ``on_skipped``).

    Attributes
    ----------
    events : dict
        Where the events went (:meth:`~cmax_taichi.core.windows.EventLedger.as_dict` of a stream: they
        sum to ``total``, every event received).
    windows : int
        Windows estimated.
    skipped : int
        Windows not estimated (too few events, all at one time, a partial tail, ``behind``).
    busy_seconds : float
        Wall time spent on the windows (the first window's search and growth included, not the time it
        waited for the events it grew by), s; a row's ``seconds`` is its part.
    data_seconds : float
        Time spanned by the events taken into windows, s (of the source's clock).
    first_window_seconds : float
        Wall time of the first window, s.
    warm_up_seconds : float
        Wall time of the warm-up before the stream was read (kernels compiled or loaded), s.
    latencies : ndarray
        Seconds from each window's last event's arrival to its estimate (the most recent
        :data:`LATENCY_RING`), for the windows that their own events closed (not the last window,
        which the end of the stream closes: ``end_latency``).
    end_latency : float
        That of the window the end of the stream closed, which includes the wait for the end (NaN
        when none).
    recent : deque of WindowResult
        The most recent rows (:data:`RECENT_ROWS`).
    stop_reason : str
        ``"ended"`` (the source), ``"idle"``, ``"max_windows"``, ``"stopped"`` (``stop`` was set) or
        ``"error"``.
    error : str or None
        The source's failure, when it failed.
    """

    warp: str
    param_names: tuple[str, ...]
    units: tuple[str, ...]
    settings: dict = field(default_factory=dict)
    events: dict = field(default_factory=dict)
    windows: int = 0
    skipped: int = 0
    busy_seconds: float = 0.0
    data_seconds: float = 0.0
    first_window_seconds: float = math.nan
    warm_up_seconds: float = 0.0
    latencies: np.ndarray = field(default_factory=lambda: np.empty(0))
    end_latency: float = math.nan
    recent: deque = field(default_factory=lambda: deque(maxlen=RECENT_ROWS))
    stop_reason: str = ""
    error: str | None = None

    def real_time_factor(self) -> float:
        """Seconds of data per second of estimation, the first window included (above 1: keeps up)."""
        return self.data_seconds / self.busy_seconds if self.busy_seconds > 0 else math.nan

    def latency(self, q: float) -> float:
        """The ``q``-th percentile (0-100) of the latencies, s (NaN without windows)."""
        return float(np.percentile(self.latencies, q)) if len(self.latencies) else math.nan


def _rule(windows, buffer: _Buffer):
    if isinstance(windows, AdaptiveWindows):
        return AdaptivePlanner(windows, buffer.time_of, buffer.search)
    if isinstance(windows, bool) or not isinstance(windows, (int, float, np.integer, np.floating)):
        raise TypeError(
            f"windows must be an AdaptiveWindows, events per window (int) or seconds (float), got {windows!r}"
        )
    if isinstance(windows, (int, np.integer)):
        return _CountWindows(int(windows))
    return _DurationWindows(float(windows), buffer.time_of, buffer.search)


class WindowEstimator(Protocol):
    """What the live loop (:func:`run_windows`) needs of the per-window work: the reader, the buffer,
    the window rule, the skipping, the accounting and the latencies are the loop's; solving a window and
    making its row are this.

    Attributes
    ----------
    name : str
        What is estimated (the warp's name, ``"dense_flow"``): :attr:`LiveResult.warp`.
    param_names, units : tuple of str
        The quantities a row traces over time (a display's curves): :attr:`LiveResult.param_names`.
    settings : dict
        The estimator's settings, JSON-friendly (beside the loop's in :attr:`LiveResult.settings`).
    """

    name: str
    param_names: tuple[str, ...]
    units: tuple[str, ...]
    settings: dict

    def warm_up(self, sensor_size: tuple[int, int], n_events: int) -> float:
        """Compile (or load) the kernels on a synthetic window; the seconds it took."""

    def solve(self, used: Events, kept, planner: AdaptivePlanner | None, grow: Callable):
        """Solve the window ``used`` (its undistortion mask ``kept`` or None). With an adaptive
        ``planner``, the window settles by its rule: a first window may ``grow`` (``grow(duration,
        tail_duration)``: ``(used, kept, inside)`` of the longer window, or None), and the planner learns
        the next window's duration. Returns ``(solved, used, kept, inside)``: what :meth:`report` takes,
        the window as solved (grown or not), and ``grow``'s ``inside`` of the last growth (None
        without)."""

    def report(self, solved, used: Events, *, index: int, status: str, n_window: int, seconds: float):
        """``(row, prob, result)`` of a solved window (``n_window``: its events before the drops;
        ``seconds``: its wall time): what ``on_window`` gets. ``row`` has ``t_start`` and ``t_end``."""

    def skipped(self, *, index: int, t_start: float, t_end: float, n_events: int, status: str,
                n_dropped: int):  # fmt: skip
        """The row of a window that was not estimated (``status`` says why)."""

    def advance(self, row, result) -> None:
        """The window is done: the next one starts from it (a warm start)."""


class WarpWindows:
    """The per-window work of a live run with a parametric warp (a :class:`WindowEstimator`): the
    windows of :func:`~cmax_taichi.solve.sequence.process`, on one :class:`~cmax_taichi.solve.warm.
    WindowSolver` (one problem, the warm start and its tracking test); an adaptive window settles by
    :func:`~cmax_taichi.solve.adaptive.settle_window` (the first one grows, searched from the identity).
    Its rows are :class:`~cmax_taichi.solve.results.WindowResult` s; ``on_window`` gets the problem and
    the :class:`~cmax_taichi.OptimizeResult`."""

    def __init__(self, model, solver: WindowSolver, settings: dict) -> None:
        self.solver = solver
        self.model = model
        self.name, self.param_names, self.units = model.name, model.params, model.units
        self.settings = settings

    def warm_up(self, sensor_size: tuple[int, int], n_events: int) -> float:
        return self.solver.warm_up(sensor_size, n_events)

    def solve(self, used: Events, kept, planner: AdaptivePlanner | None, grow):
        first = planner is not None and planner.duration is None
        solved = self.solver.solve(used, kept, planner.rule.first_search if first else "auto")
        if planner is None:
            return solved, used, kept, None
        res, search, fwl, used, kept, extra = settle_window(planner, self.solver, solved, used, kept, grow)
        return (res, search, fwl), used, kept, extra

    def report(self, solved, used: Events, *, index: int, status: str, n_window: int, seconds: float):
        res, search, fwl = solved
        prob = self.solver.prob
        row = WindowResult.of_optimization(
            res, index=index, t_start=float(used.t[0]), t_end=float(used.t[-1]), n_events=prob.n_events,
            fwl=fwl, seconds=seconds, search=search, status=status, n_dropped=n_window - prob.n_events,
            kernels=prob.kernels,
        )  # fmt: skip
        return row, prob, res

    def skipped(self, *, index: int, t_start: float, t_end: float, n_events: int, status: str,
                n_dropped: int) -> WindowResult:  # fmt: skip
        nan = math.nan
        return WindowResult(
            index=index, t_start=t_start, t_end=t_end, n_events=n_events,
            theta=np.full(self.model.n_params, nan), value=nan, fwl=nan, iterations=0, seconds=0.0,
            converged=False, status=status, n_dropped=n_dropped,
        )  # fmt: skip

    def advance(self, row: WindowResult, res) -> None:
        self.solver.advance(row, res)


def run_live(
    stream,
    warp: str = "translation2",
    *,
    objective: str = "variance",
    regularizers: Mapping[str, float] | None = None,
    camera: Camera | None = None,
    windows: AdaptiveWindows | int | float | None = None,
    method: str = "bfgs",
    warm_method: str = "bfgs",
    warm_start: bool = True,
    compute_fwl: bool = False,
    problem_options: Mapping[str, Any] | None = None,
    optimize_options: Mapping[str, Any] | None = None,
    **run_options,
) -> LiveResult:
    """Estimate the windows of ``stream`` with a parametric warp while it plays (see the module
    docstring): :func:`run_windows` with :class:`WarpWindows`.

    Parameters
    ----------
    stream : EventStream
        From :func:`cmax_taichi.io.streams.open_stream`; closed when the run ends.
    warp, objective, regularizers, camera, method, warm_method, warm_start, compute_fwl,
    problem_options, optimize_options
        As for :func:`~cmax_taichi.solve.sequence.process` (the camera defaults to the stream's;
        ``compute_fwl`` is off by default: it costs an evaluation per window with regularizers).
    windows : AdaptiveWindows, int or float, optional
        The window rule: motion-adaptive (default), events per window, or seconds per window.
    **run_options
        ``max_windows``, ``backlog_events``, ``idle_timeout``, ``keep_tail``, ``warm_up``, ``on_ready``,
        ``stop``, ``on_window``, ``on_skipped``: as for :func:`run_windows`. ``on_window(row, prob,
        result, latency)`` gets the :class:`~cmax_taichi.solve.results.WindowResult`, the
        :class:`~cmax_taichi.ContrastMaximization` holding the window and the
        :class:`~cmax_taichi.OptimizeResult`.

    Returns
    -------
    LiveResult

    Raises
    ------
    StreamError
        The source failed (see :func:`run_windows`).
    """
    model = get_warp(warp)
    max_windows = run_options.get("max_windows")
    if max_windows is not None:
        max_windows = checks.whole_number("max_windows", max_windows, 1)
    check_sequence_t_ref(dict(problem_options or {}).get("t_ref", "first"), max_windows)
    windows = AdaptiveWindows() if windows is None or windows is True else windows
    camera = camera if camera is not None else getattr(stream, "camera", None)
    if model.needs_camera and camera is None:
        raise ValueError(f"warp {model.name!r} needs a camera: the stream has none, pass camera=")
    solver = WindowSolver(
        model, objective=objective, regularizers=regularizers, camera=camera, problem_options=problem_options,
        optimize_options=optimize_options, method=method, warm_method=warm_method, warm_start=warm_start,
        compute_fwl=compute_fwl,
    )  # fmt: skip
    settings = {"warp": model.name, "objective": objective, "regularizers": dict(regularizers or {})}
    return run_windows(stream, WarpWindows(model, solver, settings), camera=camera, windows=windows,
                       **run_options)  # fmt: skip


def run_windows(
    stream,
    estimator: WindowEstimator,
    *,
    camera: Camera | None = None,
    windows: AdaptiveWindows | int | float,
    max_windows: int | None = None,
    backlog_events: int | None = None,
    idle_timeout: float | None = None,
    keep_tail: bool = True,
    warm_up: bool = True,
    on_ready: Callable[[], None] | None = None,
    stop: threading.Event | None = None,
    on_window: Callable[[Any, Any, Any, float], None] | None = None,
    on_skipped: Callable[[Any], None] | None = None,
) -> LiveResult:
    """Estimate the windows of ``stream`` with ``estimator`` while it plays (see the module docstring):
    the one live loop of :func:`run_live` (a parametric warp) and
    :func:`cmax_taichi.flow.live.run_live_flow` (the dense flow).

    Parameters
    ----------
    stream : EventStream
        From :func:`cmax_taichi.io.streams.open_stream`; closed when the run ends.
    estimator : WindowEstimator
        The per-window work (:class:`WarpWindows`, :class:`cmax_taichi.flow.live.DenseFlowWindows`).
    camera : Camera, optional
        Undistorts each window's events when it has distortion (the losses counted).
    windows : AdaptiveWindows, int or float
        The window rule: motion-adaptive, events per window, or seconds per window.
    max_windows : int, optional
        Stop after this many windows (estimated or not).
    backlog_events : int, optional
        Events the buffer holds at most (default: 2 windows of the largest size, at least a million:
        25 bytes each, allocated at the start); beyond, whole windows are skipped from its front
        (``behind``).
    idle_timeout : float, optional
        Stop when no packet came for this many seconds (default: wait for the stream to end).
    keep_tail : bool
        When the stream ends, estimate the last, partial window if it holds enough (default True).
    warm_up : bool
        Before reading, compile (or load) the kernels on a synthetic window of the stream's sensor
        (``estimator.warm_up``; ``warm_up_seconds`` in the result): the first window then runs on ready
        kernels. Events that arrive meanwhile wait in the source.
    on_ready : callable, optional
        Called once the kernels are ready and the reader runs (a replay server may start then).
    stop : threading.Event, optional
        Set it to end the run after the window in flight.
    on_window : callable, optional
        ``on_window(row, prob, result, latency)`` after each estimated window, at once (what ``row``,
        ``prob`` and ``result`` are: the estimator's :meth:`WindowEstimator.report`).
    on_skipped : callable, optional
        ``on_skipped(row)`` for each window that is not estimated (``row.status`` says why).

    Returns
    -------
    LiveResult

    Raises
    ------
    StreamError
        The source failed; raised after every complete window was estimated and reported (the
        summary is in the exception's ``live_result``).
    """
    if max_windows is not None:
        max_windows = checks.whole_number("max_windows", max_windows, 1)
    if idle_timeout is not None:
        idle_timeout = checks.seconds("idle_timeout", idle_timeout, positive=True)
    rule_size = windows.max_events if isinstance(windows, AdaptiveWindows) else None
    if rule_size is None and isinstance(windows, (int, np.integer)) and not isinstance(windows, bool):
        rule_size = int(windows)
    capacity = backlog_events or max(1_000_000, 2 * (rule_size or 0))
    capacity = checks.whole_number("backlog_events", capacity, 2)
    buffer = _Buffer(capacity)
    planner = _rule(windows, buffer)
    settings = {
        "source": getattr(stream, "address", repr(stream)),
        **estimator.settings,
        "windows": windows.as_dict() if isinstance(windows, AdaptiveWindows) else windows,
        "backlog_events": capacity,
    }
    result = LiveResult(estimator.name, tuple(estimator.param_names), tuple(estimator.units), settings)
    live = _Live(stream, buffer, planner, idle_timeout, stop)
    run = _Run(live, estimator, camera, result, keep_tail, max_windows, on_window, on_skipped)
    error = None
    if warm_up:
        size = windows.first_events if isinstance(windows, AdaptiveWindows) else rule_size or 10_000
        result.warm_up_seconds = estimator.warm_up(stream.sensor_size, size)
    live.start()
    if on_ready is not None:
        on_ready()
    try:
        run.loop()
    finally:
        live.finish()
        error = live.error
        run.close(error)
    if error is not None:
        error.live_result = result
        raise error
    return result


class _Live:
    """The reader thread and the buffer it fills (under one condition variable)."""

    def __init__(self, stream, buffer: _Buffer, planner, idle_timeout, stop) -> None:
        self.stream, self.buffer, self.planner = stream, buffer, planner
        self.idle_timeout, self.stop_event = idle_timeout, stop
        self.cond = threading.Condition()
        self.ledger = EventLedger(0, stream=True)
        self.done = False  # the reader stopped: no more events
        self.reason = ""
        self.error: BaseException | None = None
        self.t_last = -math.inf  # the latest event time received (later ones are late)
        self.behind_rows: list[tuple[int, float, float]] = []  # (events, t_start, t_end) skipped
        self._source_dropped = 0
        self._quit = threading.Event()
        self._thread = threading.Thread(target=self._read, name="cmax-taichi live reader", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _read(self) -> None:
        last = time.perf_counter()
        try:
            while not self._quit.is_set():
                packet = self.stream.read(_POLL)
                if self.stream.dropped > self._source_dropped:  # dropped by the source: counted
                    with self.cond:
                        self.ledger.drop("behind", self.stream.dropped - self._source_dropped)
                    self._source_dropped = self.stream.dropped
                if packet is None:
                    if self.stream.ended:
                        self.reason = "ended"
                        break
                    if self.idle_timeout is not None and time.perf_counter() - last > self.idle_timeout:
                        self.reason = "idle"
                        break
                    continue
                last = time.perf_counter()
                with self.cond:
                    self._ingest(packet)
                    self.cond.notify_all()
        except BaseException as exc:  # the source failed: the consumer finishes what is complete
            self.error, self.reason = exc, "error"
        with self.cond:
            self.done = True
            self.cond.notify_all()

    def _ingest(self, packet) -> None:
        t = np.asarray(packet.t, dtype=np.float64)
        x = np.asarray(packet.x, dtype=np.float64)
        y = np.asarray(packet.y, dtype=np.float64)
        finite = np.isfinite(t) & np.isfinite(x) & np.isfinite(y)
        if not finite.all():
            self.ledger.drop("malformed", int(np.count_nonzero(~finite)))
            t, x, y, p = t[finite], x[finite], y[finite], np.asarray(packet.p)[finite]
        else:
            p = np.asarray(packet.p)
        if not len(t):
            return
        before = np.maximum.accumulate(np.concatenate([[self.t_last], t]))[:-1]
        on_time = t >= before  # an event earlier than one received before it is late
        if not on_time.all():
            self.ledger.drop("late", int(np.count_nonzero(~on_time)))
            t, x, y, p = t[on_time], x[on_time], y[on_time], p[on_time]
            if not len(t):
                return
        self.t_last = float(t[-1])
        buffer = self.buffer
        if len(t) > buffer.capacity:  # one packet larger than the buffer: its oldest part is skipped
            extra = len(t) - buffer.capacity
            self._skip(t[0], t[extra - 1], extra)
            t, x, y, p = t[extra:], x[extra:], y[extra:], p[extra:]
        while buffer.count + len(t) > buffer.capacity:  # behind: skip a whole window from the front
            stop = self.planner.stop(buffer.base, buffer.end) or buffer.end
            first, last, n = buffer.time_of(buffer.base), buffer.time_of(stop - 1), stop - buffer.base
            buffer.take(n)
            self._skip(first, last, n)
        buffer.append(t, x, y, p, packet.arrival)

    def _skip(self, t_first: float, t_last: float, n: int) -> None:
        self.ledger.drop("behind", n, windows=1)
        self.behind_rows.append((n, float(t_first), float(t_last)))

    def finish(self) -> None:
        """Stop the reader, close the stream, count what is left in the buffer."""
        self._quit.set()
        self._thread.join(timeout=10.0)
        self.stream.close()
        with self.cond:
            if self.buffer.count:
                self.ledger.drop("after_stop", self.buffer.count)
                self.buffer.take(self.buffer.count)


class _Run:
    """The consumer: takes each complete window from the buffer, estimates it, reports it."""

    def __init__(self, live: _Live, estimator: WindowEstimator, camera, result: LiveResult, keep_tail: bool,
                 max_windows, on_window, on_skipped) -> None:  # fmt: skip
        self.live, self.estimator, self.camera, self.result = live, estimator, camera, result
        self.keep_tail, self.max_windows = keep_tail, max_windows
        self.on_window, self.on_skipped = on_window, on_skipped
        self.fate_camera = camera if camera is not None and camera.has_distortion else None
        self.lossy = checks.UndistortionTally()
        self.index = 0  # windows so far
        self.position = 0  # events taken into windows so far (the ledger's positions)
        self.latencies = np.full(LATENCY_RING, np.nan)
        self.n_latencies = 0
        self.t_first = self.t_last = math.nan
        self.waiting = 0.0  # seconds the window in hand waited for events (a growing first window)

    # --- taking windows -------------------------------------------------------------------------------
    def loop(self) -> None:
        live = self.live
        with warnings.catch_warnings():  # restores the filter that the undistortion tally adds
            while True:
                if live.stop_event is not None and live.stop_event.is_set():
                    self.result.stop_reason = "stopped"
                    return
                if self.max_windows is not None and self.index >= self.max_windows:
                    self.result.stop_reason = "max_windows"
                    return
                with live.cond:
                    behind, live.behind_rows = live.behind_rows, []
                    window = self._take()
                    if window is None and not behind:
                        if live.done:
                            self.result.stop_reason = live.reason
                            return
                        live.cond.wait(0.05)
                for n, t0, t1 in behind:
                    self._skipped(n, t0, t1, BEHIND)
                if window is not None:
                    self._estimate(*window)

    def _take(self):
        """The next complete window (held lock): ``(columns, arrival, span)``, or None."""
        live, buffer, planner = self.live, self.live.buffer, self.live.planner
        stop = planner.stop(buffer.base, buffer.end, final=live.done)
        tail = False
        if stop is None:
            if not (live.done and buffer.count):
                return None
            stop, tail = buffer.end, True
        keep = not tail or (self.keep_tail and planner.keeps_tail(buffer.base, stop))
        start = buffer.base
        arrival = buffer.arrival_of(stop - 1)
        by_end = live.done and stop == buffer.end  # the end of the stream closed it
        columns = buffer.take(stop - start)
        span = Span(self.index, self.position, self.position + stop - start, tail=tail, keep=keep)
        return columns, arrival, span, start, by_end

    def _grow(self, columns, start: int, t_start: float, duration: float, tail_duration: float):
        """The first window, longer (``duration`` s from its first event at buffer position ``start``):
        ``(columns, arrival of its last event, whether the stream's end closed it)`` once the events up to
        the new end arrived; ``(None, None, ended)`` when it cannot grow: the stream ended first
        (``ended`` True: its latency then includes that wait, like a window the end closed), the buffer
        skipped events after it meanwhile, or the run is stopping."""
        live, buffer, planner = self.live, self.live.buffer, self.live.planner
        taken_end = start + len(columns[0])
        waited = time.perf_counter()
        with live.cond:
            while True:
                if buffer.base != taken_end:
                    return None, None, False  # events after the window were skipped: it cannot grow
                stop = planner.stop(
                    start, buffer.end, final=live.done, duration=duration, t_start=t_start,
                    tail_duration=tail_duration,
                )  # fmt: skip
                if stop is None and live.done:
                    stop = buffer.end
                if stop is not None:
                    break
                if live.stop_event is not None and live.stop_event.is_set():
                    return None, None, False
                live.cond.wait(0.05)
            self.waiting += time.perf_counter() - waited  # for events: not the window's work
            if stop <= taken_end:  # the stream ended before the window could grow: the end closed it
                return None, None, live.done
            arrival = buffer.arrival_of(stop - 1)
            by_end = live.done and stop == buffer.end
            more = buffer.take(stop - taken_end)
        return tuple(np.concatenate([a, b]) for a, b in zip(columns, more, strict=True)), arrival, by_end

    # --- estimating ---------------------------------------------------------------------------------
    def _fate(self, columns, span: Span):
        """(events used, on-sensor mask, undistortion mask or None, status) of a window's columns."""
        t, x, y, p = columns
        W, H = self.live.stream.sensor_size
        inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
        events = Events(x[inside], y[inside], t[inside], p[inside], (W, H))
        used, kept = events, None
        if self.fate_camera is not None and span.keep and len(events):
            used, kept = events.undistort(self.fate_camera, return_mask=True)
            self.lossy.add(events, used)
        return used, inside, kept, window_status(span, len(used), used.duration)

    def _estimate(self, columns, arrival: float, span: Span, start: int, by_end: bool) -> None:
        t0 = time.perf_counter()
        self.waiting = 0.0
        used, inside, kept, status = self._fate(columns, span)
        estimator, planner = self.estimator, self.live.planner
        if status not in ESTIMATED_STATUSES:
            self._account(span, status, inside, kept)
            t = columns[0]
            self._skipped(len(used), float(t[0]), float(t[-1]), status, len(span) - len(used))
            return
        window = [columns, arrival, span, by_end]

        def grow(duration: float, tail_duration: float):
            """The first adaptive window, longer: ``(used, kept, inside)``, or None (see :meth:`_grow`)."""
            cols, at, wide, end = window
            grown, grown_arrival, grown_by_end = self._grow(cols, start, float(cols[0][0]), duration,
                                                            tail_duration)  # fmt: skip
            if grown is None:
                window[3] = window[3] or grown_by_end  # it waited for the stream's end
                return None
            wider = Span(wide.index, wide.start, wide.start + len(grown[0]), wide.tail, wide.keep)
            more_used, more_inside, more_kept, more_status = self._fate(grown, wider)
            if more_status not in ESTIMATED_STATUSES:
                return None
            window[:] = [grown, grown_arrival, wider, grown_by_end]
            return more_used, more_kept, more_inside

        adaptive = planner if isinstance(planner, AdaptivePlanner) else None
        solved, used, kept, grown_inside = estimator.solve(used, kept, adaptive, grow)
        columns, arrival, span, by_end = window
        inside = inside if grown_inside is None else grown_inside
        estimated_at = time.perf_counter()
        self._account(span, status, inside, kept)
        seconds = estimated_at - t0 - self.waiting
        row, prob, res = estimator.report(
            solved, used, index=self.index, status=status, n_window=len(span), seconds=seconds
        )
        latency = estimated_at - arrival
        if by_end:
            self.result.end_latency = latency
        else:
            self.latencies[self.n_latencies % LATENCY_RING] = latency
            self.n_latencies += 1
        result = self.result
        if result.windows == 0:
            result.first_window_seconds = seconds
        result.windows += 1
        result.busy_seconds += seconds
        self.t_first = row.t_start if math.isnan(self.t_first) else self.t_first
        self.t_last = row.t_end
        result.recent.append(row)
        self.index += 1
        if self.on_window is not None:
            self.on_window(row, prob, res, latency)
        estimator.advance(row, res)

    def _account(self, span: Span, status: str, inside, kept) -> None:
        ledger = self.live.ledger
        with self.live.cond:  # the reader counts its drops in the same ledger
            ledger.extend(len(span))
            ledger.add(span, status, inside, kept)
        self.position = span.stop

    def _skipped(self, n_used: int, t0: float, t1: float, status: str, n_dropped: int = 0) -> None:
        row = self.estimator.skipped(
            index=self.index, t_start=t0, t_end=t1, n_events=n_used, status=status, n_dropped=n_dropped
        )
        self.index += 1
        self.result.skipped += 1
        self.result.recent.append(row)
        if self.on_skipped is not None:
            self.on_skipped(row)

    def close(self, error) -> None:
        """Fill the result: the ledger, the latencies, the data span; one warning for the events not
        estimated."""
        result, ledger = self.result, self.live.ledger
        ledger.finish()
        result.events = ledger.as_dict()
        if error is not None:
            result.stop_reason, result.error = "error", str(error)
        n = min(self.n_latencies, LATENCY_RING)
        result.latencies = self.latencies[:n].copy()
        if not math.isnan(self.t_first):
            result.data_seconds = self.t_last - self.t_first
        ledger.warn(result.settings["source"], stacklevel=4)
