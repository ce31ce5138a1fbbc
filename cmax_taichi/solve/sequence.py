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
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any, TextIO

import numpy as np
from tqdm import tqdm

from cmax_taichi.core import checks
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.core.windows import (
    ESTIMATED_STATUSES,
    EventLedger,
    Span,
    check_window_options,
    plan_windows,
    read_window,
)
from cmax_taichi.metrics import fwl_problem
from cmax_taichi.models.warps import get_warp
from cmax_taichi.pipeline.problem import ContrastMaximization
from cmax_taichi.solve.optimize import OptimizeResult, maximize
from cmax_taichi.solve.results import SequenceResult, WindowResult, read_results

__all__ = [
    "TRACKING_LOSS_RATIO",
    "WARM_XTOL",
    "WarmState",
    "WindowResult",
    "SequenceResult",
    "ProgressBar",
    "count_events",
    "process",
    "read_results",
]

#: a warm-started window whose refined J falls below this fraction of the previous window's J, and whose
#: gain over the identity, J(theta) - J(0), falls below this fraction of the previous window's gain (scaled
#: down by the squared ratio of window durations when this window is shorter: the gain grows with the
#: identity's motion blur, as its square for blurs of a few px) has lost track of the motion (a sudden
#: change): the global search runs too. Windows of varying sizes or small fluctuations are not a loss
TRACKING_LOSS_RATIO = 0.8

#: the warm refinement's ``xtol`` (px over the window): it stops at a quasi-Newton step, or an accepted
#: step, shorter than this, unless ``optimize_options`` gives an ``xtol``. ``maximize``'s default of
#: 0.01 px chased steps that the windows' data do not resolve: on the shared recordings and the simulated
#: streams this rule takes 25-60% fewer warm evaluations, with errors against the truth about the same
#: (docs/performance.md, "2026-12-05, evening")
WARM_XTOL = 0.03

#: problem options under which the estimate's own problem measures the FWL (variance, normalised, no
#: weights or whitening): then its J at the estimate is the FWL and no second problem is built
_FWL_COMPATIBLE_OPTIONS = {"blur_sigma", "t_ref", "polarity"}


@dataclass(frozen=True)
class WarmState:
    """What the warm start of a window takes from the window before it (see :func:`process`).

    Attributes
    ----------
    theta : ndarray
        The previous estimate, physical units.
    value : float
        Its J.
    value_identity : float
        J of the identity warp on that window (NaN: unknown; then the tracking test compares J alone).
    duration : float
        That window's duration, s (NaN: unknown).
    hess_inv : ndarray or None
        The BFGS inverse Hessian of its refinement (internal units, px^2), or None.
    """

    theta: np.ndarray
    value: float
    value_identity: float = math.nan
    duration: float = math.nan
    hess_inv: np.ndarray | None = None

    @classmethod
    def after(cls, row: WindowResult, result: OptimizeResult) -> WarmState:
        """The state a window leaves for the next one: its row and its optimizer result."""
        return cls(
            theta=np.asarray(row.theta, dtype=np.float64),
            value=float(row.value),
            value_identity=float(result.value_identity),
            duration=float(row.t_end - row.t_start),
            hess_inv=None if result.hess_inv is None else np.array(result.hess_inv, dtype=np.float64),
        )

    def as_dict(self) -> dict:
        """JSON-friendly (NaN as None)."""

        def number(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "theta": [float(v) for v in self.theta],
            "value": number(self.value),
            "value_identity": number(self.value_identity),
            "duration": number(self.duration),
            "hess_inv": None if self.hess_inv is None else np.asarray(self.hess_inv).tolist(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> WarmState:
        """The inverse of :meth:`as_dict`."""

        def number(v) -> float:
            return math.nan if v is None else float(v)

        hess = data.get("hess_inv")
        return cls(
            theta=np.asarray(data["theta"], dtype=np.float64),
            value=number(data.get("value")),
            value_identity=number(data.get("value_identity")),
            duration=number(data.get("duration")),
            hess_inv=None if hess is None else np.asarray(hess, dtype=np.float64),
        )

    def lost_track(self, value: float, value_identity: float, duration: float) -> bool:
        """Whether a refined window (``value``, its identity's J, its duration in s) lost track of the
        motion this state describes (see :data:`TRACKING_LOSS_RATIO`): J fell below the ratio times
        the previous J, and, where both identities' J are known, so did the gain over the identity
        (scaled for a shorter window). Either test alone misfires: J alone on windows of varying
        sizes, the gain alone on recordings of weak contrast (gains of a few % that fluctuate)."""
        if not math.isfinite(self.value) or value >= TRACKING_LOSS_RATIO * self.value:
            return False
        if math.isfinite(self.value_identity) and math.isfinite(value_identity):
            gain_before = self.value - self.value_identity
            if not gain_before > 0:
                return False  # the previous window gained nothing over the identity: nothing to lose
            scale = 1.0
            if math.isfinite(self.duration) and self.duration > 0 and duration > 0:
                scale = min(1.0, duration / self.duration) ** 2
            return value - value_identity < TRACKING_LOSS_RATIO * gain_before * scale
        return True


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
        events are counted as not estimated.
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
        ``whitening``, ...).
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
            )
    if first_window < 0:
        raise ValueError(f"first_window must be >= 0, got {first_window}")
    model = get_warp(warp)
    plan = plan_windows(source, n_events, duration, stride, keep_tail)
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
    settings = {
        **desc,
        "warp": model.name,
        "objective": objective,
        "regularizers": dict(regularizers or {}),
        "camera": None if camera is None else [camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist],
        "window_events": None if duration is not None else int(n_events),
        "window_duration": duration,
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
    if warm_state is not None and not isinstance(warm_state, WarmState):
        raise TypeError(f"warm_state must be a sequence.WarmState, got {type(warm_state).__name__}")
    state = warm_state  # what the previous window leaves for the next one's warm start
    fwl_is_value = (
        objective == "variance"
        and not any(float(w) for w in (regularizers or {}).values())
        and set(popts) <= _FWL_COMPATIBLE_OPTIONS
    )
    lossy = checks.UndistortionTally()  # holds back the undistortion warnings after the first lossy window
    ledger = EventLedger(plan.n_total)
    undistort = camera is not None and camera.has_distortion and not plan.undistorted
    weights = popts.pop("weights", None)
    prob = fprob = None  # built on the first window, then given each next window (set_events)
    stopped_early = False
    try:
        with warnings.catch_warnings():  # restores the filter that the tally adds
            for span in plan.spans:
                if max_windows is not None and span.index >= max_windows:
                    stopped_early = True
                    break
                index = span.index
                t0 = time.perf_counter()
                used, inside, kept, status = read_window(span, plan, camera if undistort else None, lossy)
                ledger.add(span, status, inside, kept)
                if index < first_window:
                    continue  # done by an earlier, interrupted run (accounted for all the same)
                if status not in ESTIMATED_STATUSES:
                    row = _skipped_row(span, used, len(used), status, model.n_params)
                    result.add(row)
                    if on_skipped is not None:
                        on_skipped(row)
                    if bar is not None and span.keep:  # the bar counts the windows that could be estimated
                        bar.update(status)
                    continue
                window_weights = weights
                if weights is not None and kept is not None and np.shape(weights) == kept.shape:
                    window_weights = np.asarray(weights)[kept]  # as the problem's own undistortion does
                if prob is None:
                    prob = ContrastMaximization(
                        used,
                        warp=model,
                        objective=objective,
                        regularizers=regularizers,
                        camera=camera,
                        weights=window_weights,
                        **popts,
                    )
                else:  # the same problem takes the next window: its fields, kernels and buffers stay
                    prob.set_events(used, weights=window_weights)
                res, search = _solve_window(prob, state if warm_start else None, method, warm_method, oopts)
                value_fwl = math.nan
                if compute_fwl:
                    if fwl_is_value:
                        value_fwl = res.value  # the estimate's problem is the FWL problem
                    else:
                        if fprob is None:
                            fprob = _fwl_problem(prob, model, camera, popts.get("t_ref", "first"))
                        else:
                            fprob.set_events(prob.events)
                        value_fwl = fprob.value(res.theta)
                row = WindowResult.of_optimization(
                    res,
                    index=index,
                    t_start=float(used.t[0]),
                    t_end=float(used.t[-1]),
                    n_events=prob.n_events,
                    fwl=float(value_fwl),
                    seconds=time.perf_counter() - t0,
                    search=search,
                    status=status,
                    n_dropped=len(span) - prob.n_events,
                    kernels=prob.kernels,
                )
                result.add(row)
                if on_window is not None:
                    on_window(row, prob, res)
                state = WarmState.after(row, res)
                if bar is not None:
                    bar.update(f"J={res.value:.3f}")
    finally:
        if bar is not None:
            bar.close()
    ledger.finish(stopped_early)
    result.events = ledger.as_dict()
    ledger.warn(desc["source"], n_events if duration is None else None, max_windows, stacklevel=2)
    at_identity = result.identity_windows()
    if at_identity:
        warnings.warn(
            checks.IdentityEstimateWarning(
                f"{desc['source']}: {at_identity} of {len(result)} estimated window(s) came out at the "
                "identity warp exactly (every parameter 0). Unless the camera and the scene were still, "
                "those windows hold too little motion: at about a pixel of it or less, the events on "
                "their integer pixels make a sharper image than any warp of them. Use windows of more "
                "events (n_events=, --window) or a longer duration."
            ),
            stacklevel=2,
        )
    return result


def _fwl_problem(prob: ContrastMaximization, model, camera: Camera | None, t_ref) -> ContrastMaximization:
    """The problem whose J is the FWL of ``prob``'s window (the same, already undistorted, events).

    For a variance problem with regularizers on the fused path: the same regularizers at weight 0, so
    that it runs on the estimate's compiled kernel (the weights are data); a problem without them would
    compile a kernel of its own on the first window (about a second of front end and code generation).
    """
    options = dict(camera=camera, blur_sigma=prob.blur_sigma, t_ref=t_ref, polarity=prob.polarity)
    if prob.regularizer_weights and prob.path == "fused" and prob.objective.name == "variance":
        zero = {name: 0.0 for name in prob.regularizer_weights}
        return ContrastMaximization(
            prob.events, warp=model, objective="variance", regularizers=zero, **options
        )
    return fwl_problem(prob.events, model, **options)


def _solve_window(
    prob: ContrastMaximization,
    state: WarmState | None,
    method: str,
    warm_method: str,
    oopts: dict,
) -> tuple[OptimizeResult, str]:
    """Solve one window: the global search, or the warm refinement with its tracking test.

    A BFGS refinement starts with the previous window's inverse Hessian (a quasi-Newton first step):
    consecutive windows of one motion have about the same curvature in the per-window pixel units of
    :func:`~cmax_taichi.maximize`."""
    if state is None:
        return maximize(prob, method=method, **oopts), "global"
    if "init" in oopts:  # the caller's init in every window, from the previous estimate
        return maximize(prob, theta0=state.theta, method=method, **oopts), oopts["init"]
    warm_options = dict(oopts)
    warm_options.setdefault("xtol", WARM_XTOL)
    if warm_method == "bfgs" and state.hess_inv is not None and "hess_inv0" not in warm_options:
        warm_options["hess_inv0"] = state.hess_inv
    res = maximize(prob, theta0=state.theta, method=warm_method, init="warm", **warm_options)
    if not state.lost_track(res.value, res.value_identity, prob.duration):
        return res, "warm"
    full = maximize(prob, method=method, candidates=[state.theta], **oopts)
    best = full if full.value > res.value else res
    return (
        replace(
            best,
            n_evaluations=res.n_evaluations + full.n_evaluations,
            seconds=res.seconds + full.seconds,
        ),
        "warm+global",
    )
