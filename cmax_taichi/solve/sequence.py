"""Motion estimation over a whole recording, window by window.

:func:`process` slides a window over the events (by event count, 30,000 by default as in the paper's
MVSEC setup, or by duration), gives each window to one :class:`~cmax_taichi.ContrastMaximization`
(:meth:`~cmax_taichi.ContrastMaximization.set_events`: its pooled Taichi fields, buffers and compiled
kernels serve every window), maximizes it warm-started from the previous window (:class:`WarmState`),
and records one row per window. :class:`SequenceResult` writes
the rows as CSV, JSON and HDF5, each file through a temporary name renamed when complete.

Every event is accounted for (:mod:`cmax_taichi.core.windows`): a window that cannot be estimated
(fewer than 2 events, all at one time, the partial tail of count windows) gets a row with its
``status``; each row counts the events its window dropped (``n_dropped``: outside the sensor, lost in
undistortion); :attr:`SequenceResult.events` has the totals by reason, and one
:class:`~cmax_taichi.core.checks.EventsDroppedWarning` at the end of :func:`process` gives them.
"""

from __future__ import annotations

import math
import os
import sys
import time
import warnings
from collections.abc import Callable, Iterator, Mapping
from typing import Any, TextIO

import numpy as np
from tqdm import tqdm

from cmax_taichi.core import checks
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.core.windows import (
    ESTIMATED_STATUSES,
    EventLedger,
    Span,
    WindowPlan,
    check_window_options,
    plan_windows,
    read_window,
)
from cmax_taichi.models.warps import get_warp
from cmax_taichi.pipeline.problem import ContrastMaximization
from cmax_taichi.solve.adaptive import AdaptivePlanner, AdaptiveWindows, settle_window
from cmax_taichi.solve.optimize import OptimizeResult
from cmax_taichi.solve.results import SequenceResult, WindowResult, read_results
from cmax_taichi.solve.warm import (
    TRACKING_LOSS_RATIO,
    WARM_XTOL,
    WarmState,
    WindowSolver,
    check_sequence_t_ref,
)

__all__ = [
    "TRACKING_LOSS_RATIO",
    "WARM_XTOL",
    "AdaptiveWindows",
    "WarmState",
    "WindowResult",
    "SequenceResult",
    "ProgressBar",
    "count_events",
    "process",
    "read_results",
]


class ProgressBar:
    """Progress over windows on stderr (or ``stream``), drawn by :mod:`tqdm`.

    On a terminal, a tqdm bar redrawn in place. On anything else (a log file, CI, a pipe) no bar: one
    plain line per 10% of the total (per window when the total is unknown), in tqdm's format, so logs
    stay readable. The caller draws nothing at all when progress is off.

    Parameters
    ----------
    total : int or None
        Number of steps, None when unknown.
    label : str
        Shown before the bar (``"windows"``, an experiment's name).
    stream : text stream, optional
        Where to draw; default ``sys.stderr``.
    unit : str
        What one step is (``"window"``), for the rate.
    """

    def __init__(
        self, total: int | None, label: str = "windows", stream: TextIO | None = None, unit: str = "window"
    ) -> None:
        self.total = total
        self.label = label
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.count = 0
        self._t0 = time.perf_counter()
        self._last_decile = -1
        self._bar = (
            tqdm(total=total, desc=label, unit=unit, file=self.stream, dynamic_ncols=True, mininterval=0.2)
            if self.tty
            else None
        )

    def update(self, note: str = "") -> None:
        """One more step done; ``note`` (e.g. ``"J=1.234"``) is shown after the rate."""
        self.count += 1
        if self._bar is not None:
            self._bar.set_postfix_str(note, refresh=False)
            self._bar.update(1)
            return
        decile = int(10 * min(1.0, self.count / self.total)) if self.total else self.count
        if decile != self._last_decile:
            line = tqdm.format_meter(
                self.count,
                self.total,
                time.perf_counter() - self._t0,
                prefix=self.label,
                unit=self.unit,
                postfix=note or None,
                ascii=True,
                ncols=110,
            )
            self.stream.write(line.rstrip() + "\n")
            self.stream.flush()
        self._last_decile = decile

    def close(self) -> None:
        """End the bar (a terminal's line is kept)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def _plan(source, n_events: int, duration: float | None, stride, keep_tail: bool, adaptive=None):
    """The pass of windows over an Events or an open Recording: count or time windows
    (:func:`~cmax_taichi.core.windows.plan_windows`) or motion-adaptive ones."""
    if adaptive is not None:
        return _adaptive_plan(source, adaptive, keep_tail)
    return plan_windows(source, n_events, duration, stride, keep_tail)


def _adaptive_plan(source, rule: AdaptiveWindows, keep_tail: bool) -> WindowPlan:
    """The pass of motion-adaptive windows (:mod:`cmax_taichi.solve.adaptive`) over an Events or an open
    Recording: each span is planned when the previous window's estimate is known."""
    if isinstance(source, Events):
        plan = plan_windows(source, 2, None, None, keep_tail)  # the checks and the reads of count windows
        times = np.asarray(source.t)
        planner = AdaptivePlanner(
            rule, lambda i: float(times[i]), lambda t: int(np.searchsorted(times, t, side="left"))
        )
    elif hasattr(source, "window_spans"):
        plan = plan_windows(source, 2, None, None, keep_tail)
        planner = AdaptivePlanner(rule, lambda i: float(source._times(i, i + 1)[0]), source._search_time)
    else:
        raise TypeError(f"source must be Events, a Recording or a path, got {type(source).__name__}")
    plan.spans, plan.total, plan.planner = _adaptive_spans(planner, plan.n_total, keep_tail), None, planner
    return plan


def _adaptive_spans(planner: AdaptivePlanner, n_total: int, keep_tail: bool) -> Iterator[Span]:
    """Spans from ``planner``: each starts where the window before it ended (``planner.next_start``: an
    adaptive first window may grow); the events too few for a window are the partial tail, kept with
    ``keep_tail`` when they hold enough (:meth:`AdaptivePlanner.keeps_tail`)."""
    index = start = 0
    while start < n_total:
        stop = planner.stop(start, n_total, final=True)
        if stop is None:
            keep = keep_tail and planner.keeps_tail(start, n_total)
            yield Span(index, start, n_total, tail=True, keep=keep)
            return
        yield Span(index, start, stop)
        start = max(stop, planner.next_start)
        index += 1


def count_events(
    source: Events | Any | str | os.PathLike,
    *,
    camera: Camera | None = None,
    n_events: int = 30000,
    duration: float | None = None,
    stride: int | float | None = None,
    max_windows: int | None = None,
    keep_tail: bool = False,
    format: str | None = None,
) -> dict:
    """Where :func:`process` would take each event, without estimating anything: the
    :attr:`SequenceResult.events` dict of a run with these windows (``total``, ``estimated``, each
    reason of :data:`cmax_taichi.core.windows.CATEGORIES`, ``after_max_windows`` and the windows per
    status). The arguments are those of :func:`process` and are checked the same way. No warning."""
    if isinstance(source, (str, os.PathLike)):
        from cmax_taichi import io

        with io.open_recording(source, format=format) as rec:
            return count_events(
                rec, camera=camera, n_events=n_events, duration=duration, stride=stride,
                max_windows=max_windows, keep_tail=keep_tail,
            )  # fmt: skip
    n_events, duration, stride, max_windows = check_window_options(n_events, duration, stride, max_windows)
    plan = plan_windows(source, n_events, duration, stride, keep_tail)
    camera = camera if camera is not None else plan.camera
    undistort = camera is not None and camera.has_distortion and not plan.undistorted
    ledger = EventLedger(plan.n_total)
    stopped_early = False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", checks.EventsDroppedWarning)
        for span in plan.spans:
            if max_windows is not None and span.index >= max_windows:
                stopped_early = True
                break
            _, inside, kept, status = read_window(
                span, plan, camera if undistort else None, checks.UndistortionTally()
            )
            ledger.add(span, status, inside, kept)
    ledger.finish(stopped_early)
    return ledger.as_dict()


def _adaptive_rule(adaptive, duration, stride) -> AdaptiveWindows | None:
    """``adaptive=`` of :func:`process`: None, or the rule (True: the default one); not with a duration
    or a stride."""
    if adaptive is None or adaptive is False:
        return None
    rule = AdaptiveWindows() if adaptive is True else adaptive
    if not isinstance(rule, AdaptiveWindows):
        raise TypeError(f"adaptive must be True or an AdaptiveWindows, got {type(adaptive).__name__}")
    if duration is not None or stride is not None:
        raise ValueError("adaptive windows choose their own length: not with duration= or stride=")
    return rule


def _skipped_row(span: Span, events: Events, n_used: int, status: str, n_params: int) -> WindowResult:
    """The row of a window that is not estimated (NaN parameters and values)."""
    nan = math.nan
    return WindowResult(
        index=span.index,
        t_start=float(events.t[0]) if len(events) else nan,
        t_end=float(events.t[-1]) if len(events) else nan,
        n_events=n_used,
        theta=np.full(n_params, nan),
        value=nan,
        fwl=nan,
        iterations=0,
        seconds=0.0,
        converged=False,
        status=status,
        n_dropped=len(span) - n_used,
    )


def process(
    source: Events | Any | str | os.PathLike,
    warp: str = "translation2",
    *,
    objective: str = "variance",
    regularizers: Mapping[str, float] | None = None,
    camera: Camera | None = None,
    n_events: int = 30000,
    duration: float | None = None,
    stride: int | float | None = None,
    method: str = "bfgs",
    warm_start: bool = True,
    compute_fwl: bool = True,
    max_windows: int | None = None,
    progress: bool | TextIO = True,
    problem_options: Mapping[str, Any] | None = None,
    optimize_options: Mapping[str, Any] | None = None,
    on_window: Callable[[WindowResult, ContrastMaximization, OptimizeResult], None] | None = None,
    format: str | None = None,
    first_window: int = 0,
    warm_state: WarmState | None = None,
    warm_method: str = "bfgs",
    keep_tail: bool = False,
    on_skipped: Callable[[WindowResult], None] | None = None,
    adaptive: AdaptiveWindows | bool | None = None,
) -> SequenceResult:
    """Estimate the motion of every window of a recording.

    Parameters
    ----------
    source : Events, Recording or path
        The events: an :class:`~cmax_taichi.Events`, a recording opened with
        :func:`cmax_taichi.io.open_recording`, or a path that is opened with it (and closed after).
    warp, objective, regularizers
        As for :class:`~cmax_taichi.ContrastMaximization`.
    camera : Camera, optional
        Intrinsics; default the recording's own (needed by ``rotation3``).
    n_events : int
        Events per window (default 30,000), used when ``duration`` is None.
    duration : float, optional
        Window length, s (then windows are by time).
    stride : int or float, optional
        Start-to-start step (events, or s for time windows); default the window size.
    keep_tail : bool
        Count windows: estimate the partial tail (the events after the last full window) as a shorter
        window when it holds at least half a window (:func:`cmax_taichi.core.windows.min_tail_events`;
        status ``"short_tail"``). Default: the tail gets a row with status ``"partial_tail"`` and its
        events are counted as not estimated. Adaptive windows: the events after the last window, too
        few to reach the duration the motion asks for, are the tail, kept when they hold at least
        ``min_events`` and ``accept`` times the target motion.
    adaptive : AdaptiveWindows or True, optional
        Motion-adaptive windows (:class:`~cmax_taichi.solve.adaptive.AdaptiveWindows`; True: the
        default rule): each window holds the events of the time in which the previous estimate moves
        the window's extreme pixels by ``target_px`` (8 px), bounded by a minimum and maximum number of
        events and a maximum duration; the first window grows until its own estimate does. Replaces
        ``n_events``; not with ``duration`` or ``stride``. The first window's ``search`` names its
        solves: ``"identity"`` (a local ascent from the identity warp), then ``"warm"`` when it grew
        (refinements of the longer window), ``"global"`` when the global search ran too.
    method : str
        Local optimizer of :func:`~cmax_taichi.maximize` after a global search (the first window, and
        every window without ``warm_start`` or after a tracking loss); default ``"bfgs"``, which with
        the default coarse-to-fine search solves a first window in at most 150 evaluations.
    warm_start : bool
        Refine the previous window's estimate (``maximize(init="warm", method=warm_method)``: the
        previous estimate and the identity are the candidates, a few quasi-Newton steps follow, to a
        step of :data:`WARM_XTOL` px unless ``optimize_options`` gives ``xtol``); the first window gets
        the global search. When the refined gain over the identity falls below
        :data:`TRACKING_LOSS_RATIO` times the previous window's, tracking is lost: the global
        search runs too and the better result is kept. An ``init`` in ``optimize_options`` replaces
        this (that init in every window, from the previous estimate).
    compute_fwl : bool
        Compute the FWL of each estimate on the window's events.
    max_windows : int, optional
        Stop after this many windows (estimated or not); the events after them are counted
        (``after_max_windows``).
    progress : bool or stream
        Show progress on stderr (or on the given stream): a tqdm bar on a terminal, one line per 10%
        elsewhere (:class:`ProgressBar`); False shows nothing.
    problem_options : mapping, optional
        More keyword arguments of ``ContrastMaximization`` (``blur_sigma``, ``t_ref``, ``polarity``,
        ``whitening``, ...). A numeric ``t_ref`` (seconds on the events' clock) is refused unless the
        run has one window: the windows after it would all be warped to that one time.
    optimize_options : mapping, optional
        More keyword arguments of ``maximize`` (``init``, ``n_init``, ``lr``, ...). An ``init`` given
        here applies to every window (no warm-start search).
    on_window : callable, optional
        ``on_window(row, prob, result)`` after each estimated window (e.g. to save figures). ``prob``
        is one problem for the whole sequence (:meth:`~cmax_taichi.ContrastMaximization.set_events`
        gives it each next window): use it inside the callback; it holds the next window afterwards.
    on_skipped : callable, optional
        ``on_skipped(row)`` after each window that is not estimated (its row, with the status).
    format : str, optional
        Format name when ``source`` is a path.
    first_window : int
        Skip (read but do not estimate) the windows before this index: resuming an interrupted run.
    warm_state : WarmState, optional
        The warm start of the first estimated window: what the window before ``first_window`` left
        (:meth:`WarmState.after`), so that a resumed run gives the same results as an uninterrupted
        one (the batch runner keeps it in its checkpoints).
    warm_method : str
        Local optimizer of the warm-start refinement (default the quasi-Newton ``"bfgs"``).

    Returns
    -------
    SequenceResult
        ``windows``: the estimated windows; ``skipped``: the rows of the others (``status`` says why);
        ``events``: where every event went (they sum to the source's events).

    Raises
    ------
    TypeError
        ``n_events``, ``stride``, ``duration`` or ``max_windows`` is not a number (e.g. None for
        ``n_events`` without ``duration``).
    ValueError
        Before any window is read: ``n_events < 2``; a count ``stride`` below 1 or not whole (0,
        0.5); a ``duration`` or time ``stride`` that is not a positive finite number of seconds;
        ``max_windows < 1``; time windows far shorter than the event spacing or too many of them;
        timestamps out of order or not finite (naming the file, the dataset and the first bad
        row), or all equal (see :meth:`cmax_taichi.io.Recording.windows`).

    Every event that is not estimated is counted: one
    :class:`~cmax_taichi.core.checks.EventsDroppedWarning` at the end gives the totals by reason
    (partial tail, outside the sensor, undistortion, windows too small or of zero duration, gaps
    between windows, after ``max_windows``). Undistortion also warns once for the first window that
    loses events, with the details. Windows estimated at the identity warp exactly (too little motion
    in them, or a still camera: :meth:`SequenceResult.identity_windows`) are counted in one
    :class:`~cmax_taichi.core.checks.IdentityEstimateWarning` at the end.
    """
    n_events, duration, stride, max_windows = check_window_options(n_events, duration, stride, max_windows)
    adaptive = _adaptive_rule(adaptive, duration, stride)
    if isinstance(source, (str, os.PathLike)):
        from cmax_taichi import io

        with io.open_recording(source, format=format) as rec:
            return process(
                rec,
                warp,
                objective=objective,
                regularizers=regularizers,
                camera=camera,
                n_events=n_events,
                duration=duration,
                stride=stride,
                method=method,
                warm_start=warm_start,
                compute_fwl=compute_fwl,
                max_windows=max_windows,
                progress=progress,
                problem_options=problem_options,
                optimize_options=optimize_options,
                on_window=on_window,
                first_window=first_window,
                warm_state=warm_state,
                warm_method=warm_method,
                keep_tail=keep_tail,
                on_skipped=on_skipped,
                adaptive=adaptive,
            )
    if first_window < 0:
        raise ValueError(f"first_window must be >= 0, got {first_window}")
    model = get_warp(warp)
    plan = _plan(source, n_events, duration, stride, keep_tail, adaptive)
    total, desc = plan.total, plan.desc
    camera = camera if camera is not None else plan.camera
    if model.needs_camera and camera is None:
        raise ValueError(f"warp {model.name!r} needs a camera: the recording has none, pass camera=")
    popts = dict(problem_options or {})
    oopts = dict(optimize_options or {})
    if max_windows is not None:
        total = min(total, int(max_windows)) if total is not None else int(max_windows)
    if total is not None:
        total = max(0, total - first_window)
    check_sequence_t_ref(popts.get("t_ref", "first"), total)
    by_count = duration is None and adaptive is None
    settings = {
        **desc,
        "warp": model.name,
        "objective": objective,
        "regularizers": dict(regularizers or {}),
        "camera": None if camera is None else [camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist],
        "window_events": int(n_events) if by_count else None,
        "window_duration": duration,
        "window_adaptive": None if adaptive is None else adaptive.as_dict(),
        "stride": stride,
        "keep_tail": bool(keep_tail),
        "method": method,
        "warm_start": warm_start,
        "problem_options": {k: v for k, v in popts.items() if isinstance(v, (int, float, str, bool))},
        "optimize_options": {k: v for k, v in oopts.items() if isinstance(v, (int, float, str, bool))},
    }
    result = SequenceResult(warp=model.name, param_names=model.params, units=model.units, settings=settings)
    bar = None
    if progress:
        bar = ProgressBar(total, stream=progress if not isinstance(progress, bool) else None)
    solver = WindowSolver(
        model, objective=objective, regularizers=regularizers, camera=camera, problem_options=popts,
        optimize_options=oopts, method=method, warm_method=warm_method, warm_start=warm_start,
        compute_fwl=compute_fwl, state=warm_state,
    )  # fmt: skip
    lossy = checks.UndistortionTally()  # holds back the undistortion warnings after the first lossy window
    ledger = EventLedger(plan.n_total)
    fate_camera = camera if camera is not None and camera.has_distortion and not plan.undistorted else None
    stopped_early = False
    try:
        with warnings.catch_warnings():  # restores the filter that the tally adds
            for span in plan.spans:
                if max_windows is not None and span.index >= max_windows:
                    stopped_early = True
                    break
                index = span.index
                t0 = time.perf_counter()
                used, inside, kept, status = read_window(span, plan, fate_camera, lossy)
                if index < first_window or status not in ESTIMATED_STATUSES:
                    ledger.add(span, status, inside, kept)
                    if plan.planner is not None:
                        plan.planner.next_start = span.stop
                    if index < first_window:
                        continue  # done by an earlier, interrupted run (accounted for all the same)
                    row = _skipped_row(span, used, len(used), status, model.n_params)
                    result.add(row)
                    if on_skipped is not None:
                        on_skipped(row)
                    if bar is not None and span.keep:  # the bar counts the windows that could be estimated
                        bar.update(status)
                    continue
                first_adaptive = plan.planner is not None and plan.planner.duration is None
                start = plan.planner.rule.first_search if first_adaptive and solver.state is None else "auto"
                res, search, value_fwl = solver.solve(used, kept, start)
                if plan.planner is not None:  # the window follows the motion (an adaptive first one grows)
                    span, used, inside, kept, res, search, value_fwl = _adapt(
                        plan, solver, span, used, inside, kept, (res, search, value_fwl), fate_camera, lossy
                    )
                ledger.add(span, status, inside, kept)
                prob = solver.prob
                row = WindowResult.of_optimization(
                    res,
                    index=index,
                    t_start=float(used.t[0]),
                    t_end=float(used.t[-1]),
                    n_events=prob.n_events,
                    fwl=value_fwl,
                    seconds=time.perf_counter() - t0,
                    search=search,
                    status=status,
                    n_dropped=len(span) - prob.n_events,
                    kernels=prob.kernels,
                )
                result.add(row)
                if on_window is not None:
                    on_window(row, prob, res)
                solver.advance(row, res)
                if bar is not None:
                    bar.update(f"J={res.value:.3f}")
    finally:
        if bar is not None:
            bar.close()
    ledger.finish(stopped_early)
    result.events = ledger.as_dict()
    ledger.warn(desc["source"], n_events if by_count else None, max_windows, stacklevel=2)
    at_identity = result.identity_windows()
    if at_identity:
        warnings.warn(
            checks.IdentityEstimateWarning(
                f"{desc['source']}: {at_identity} of {len(result)} estimated window(s) came out at the "
                "identity warp exactly (every parameter 0). Unless the camera and the scene were still, "
                "those windows hold too little motion: at about a pixel of it or less, the events on "
                "their integer pixels make a sharper image than any warp of them. Use windows of more "
                "events (n_events=, --window), a longer duration, or motion-adaptive windows."
            ),
            stacklevel=2,
        )
    return result


def _adapt(plan: WindowPlan, solver: WindowSolver, span, used, inside, kept, solved, fate_camera, lossy):
    """An adaptive window after its solve (:func:`~cmax_taichi.solve.adaptive.settle_window`; the first
    one may grow). Returns the window as kept and its solve: ``(span, used, inside, kept, result,
    search, fwl)``."""
    planner = plan.planner

    def grow(duration: float, tail_duration: float):
        stop = planner.stop(span.start, plan.n_total, True, duration=duration, tail_duration=tail_duration)
        stop = stop or plan.n_total  # no further than the events go
        current = grown_span[0]
        if stop <= current.stop:
            return None
        wider = Span(current.index, current.start, stop, current.tail, current.keep)
        more_used, more_inside, more_kept, status = read_window(wider, plan, fate_camera, lossy)
        if status not in ESTIMATED_STATUSES:
            return None
        grown_span[0] = wider
        return more_used, more_kept, more_inside

    grown_span = [span]
    res, search, fwl, used, kept, extra = settle_window(planner, solver, solved, used, kept, grow)
    span, inside = grown_span[0], inside if extra is None else extra
    planner.next_start = span.stop
    return span, used, inside, kept, res, search, fwl
