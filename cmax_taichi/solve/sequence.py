"""Motion estimation over a whole recording, window by window.

:func:`process` slides a window over the events (by event count, 30,000 by default as in the paper's
MVSEC setup, or by duration), gives each window to one :class:`~cmax_taichi.ContrastMaximization`
(:meth:`~cmax_taichi.ContrastMaximization.set_events`: its pooled Taichi fields, buffers and compiled
kernels serve every window), maximizes it warm-started from the previous window (:class:`WarmState`),
and records one row per window. :class:`SequenceResult` writes
the rows as CSV and JSON.
"""

from __future__ import annotations

import csv
import json
import math
import os
import sys
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from tqdm import tqdm

from cmax_taichi.core import checks
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.metrics import fwl_problem
from cmax_taichi.models.warps import get_warp
from cmax_taichi.pipeline.problem import ContrastMaximization
from cmax_taichi.solve.optimize import OptimizeResult, maximize

__all__ = [
    "TRACKING_LOSS_RATIO",
    "WarmState",
    "WindowResult",
    "SequenceResult",
    "ProgressBar",
    "process",
    "read_results",
]

#: a warm-started window whose refined J falls below this fraction of the previous window's J, and whose
#: gain over the identity, J(theta) - J(0), falls below this fraction of the previous window's gain (scaled
#: down by the squared ratio of window durations when this window is shorter: the gain grows with the
#: identity's motion blur, as its square for blurs of a few px) has lost track of the motion (a sudden
#: change): the global search runs too. Windows of varying sizes or small fluctuations are not a loss
TRACKING_LOSS_RATIO = 0.8

#: problem options under which the estimate's own problem measures the FWL (variance, normalised, no
#: weights or whitening): then its J at the estimate is the FWL and no second problem is built
_FWL_COMPATIBLE_OPTIONS = {"blur_sigma", "t_ref", "polarity"}


@dataclass
class WindowResult:
    """The estimate of one window.

    Attributes
    ----------
    index : int
        Window number (0-based).
    t_start, t_end : float
        Time of the window's first and last event, s.
    n_events : int
        Events in the window (after undistortion, those that stay on the sensor).
    theta : ndarray
        Estimate, physical units.
    value : float
        Objective J at the estimate.
    fwl : float
        Flow Warp Loss of the estimate (NaN when not computed).
    iterations : int
        Local iterations of the optimizer.
    seconds : float
        Wall time of the window (problem, optimisation, FWL), s.
    converged : bool
        The optimizer met a stopping rule.
    evaluations : int
        Evaluations of J (with or without gradient) spent on the window.
    search : str
        How the window was solved: ``"global"`` (search, then local ascent), ``"warm"`` (refinement
        of the previous estimate) or ``"warm+global"`` (the refinement lost track, so a global
        search ran too).
    """

    index: int
    t_start: float
    t_end: float
    n_events: int
    theta: np.ndarray
    value: float
    fwl: float
    iterations: int
    seconds: float
    converged: bool
    evaluations: int = 0
    search: str = ""


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


@dataclass
class SequenceResult:
    """Per-window estimates of a recording, with the settings that produced them."""

    warp: str
    param_names: tuple[str, ...]
    units: tuple[str, ...]
    windows: list[WindowResult] = field(default_factory=list)
    settings: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.windows)

    @property
    def theta(self) -> np.ndarray:
        """``(K, P)`` estimates, physical units."""
        return np.array([w.theta for w in self.windows]).reshape(len(self.windows), len(self.param_names))

    @property
    def t_mid(self) -> np.ndarray:
        """``(K,)`` window middle times, s."""
        return np.array([0.5 * (w.t_start + w.t_end) for w in self.windows])

    def real_time_factor(self, skip_first: bool = True) -> float:
        """Seconds of data per wall second (above 1: faster than the camera records).

        The data seconds of a window are its span ``t_end - t_start``; ``skip_first`` leaves out the
        first window, whose time includes compiling the kernels (reported apart by the command line).
        NaN without windows to count.
        """
        rows = self.windows[1:] if skip_first else self.windows
        wall = sum(w.seconds for w in rows)
        data = sum(w.t_end - w.t_start for w in rows)
        return data / wall if rows and wall > 0 else math.nan

    #: the CSV columns before the parameters (times, event count) and after them (the diagnostics)
    WINDOW_COLUMNS = ("index", "t_start [s]", "t_end [s]", "n_events")
    DIAGNOSTIC_COLUMNS = (
        "value",
        "fwl",
        "iterations",
        "seconds",
        "converged",
        "evaluations",
        "search",
    )

    def columns(self) -> list[str]:
        """CSV header :attr:`WINDOW_COLUMNS`, the parameters (``name [unit]``), :attr:`DIAGNOSTIC_COLUMNS`."""
        params = [f"{n} [{u}]" for n, u in zip(self.param_names, self.units, strict=True)]
        return [*self.WINDOW_COLUMNS, *params, *self.DIAGNOSTIC_COLUMNS]

    def to_csv(self, path: str | os.PathLike) -> Path:
        """Write one row per window (see :meth:`columns`); returns the path."""
        path = Path(path)
        with path.open("w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(self.columns())
            for w in self.windows:
                writer.writerow(
                    [w.index, repr(w.t_start), repr(w.t_end), w.n_events]
                    + [repr(float(v)) for v in w.theta]
                    + [
                        repr(float(w.value)),
                        repr(float(w.fwl)),
                        w.iterations,
                        f"{w.seconds:.4f}",
                        int(w.converged),
                        w.evaluations,
                        w.search,
                    ]
                )
        return path

    def as_dict(self) -> dict:
        """JSON-friendly: warp, parameter names and units, settings, and one dict per window."""

        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "warp": self.warp,
            "params": list(self.param_names),
            "units": list(self.units),
            "settings": self.settings,
            "windows": [
                {
                    "index": w.index,
                    "t_start": w.t_start,
                    "t_end": w.t_end,
                    "n_events": w.n_events,
                    "theta": {n: float(v) for n, v in zip(self.param_names, w.theta, strict=True)},
                    "value": num(w.value),
                    "fwl": num(w.fwl),
                    "iterations": w.iterations,
                    "seconds": w.seconds,
                    "converged": w.converged,
                    "evaluations": w.evaluations,
                    "search": w.search,
                }
                for w in self.windows
            ],
        }

    def to_json(self, path: str | os.PathLike) -> Path:
        """Write :meth:`as_dict` as JSON; returns the path."""
        path = Path(path)
        path.write_text(json.dumps(self.as_dict(), indent=1))
        return path

    def to_hdf5(self, path: str | os.PathLike) -> Path:
        """Write one HDF5 dataset per column (length K, the windows): ``index``, ``t_start``,
        ``t_end`` (s), ``n_events``, each parameter by name (attribute ``unit``), ``value``, ``fwl``,
        ``iterations``, ``seconds``, ``converged``. File attributes: ``warp``, ``params``, ``units``,
        ``columns`` (the dataset order) and each setting (numbers and strings as they are, anything
        else as JSON text; all of them also in ``settings_json``). Returns the path."""
        import h5py

        diagnostics = (
            "index", "t_start", "t_end", "n_events", "value", "fwl", "iterations", "evaluations", "seconds"
        )  # fmt: skip
        clash = set(self.param_names) & {*diagnostics, "converged"}
        if clash:
            raise ValueError(f"parameter names {sorted(clash)} clash with the result columns")
        ws = self.windows
        theta = self.theta
        columns: dict[str, tuple[np.ndarray, str]] = {
            "index": (np.array([w.index for w in ws], dtype=np.int64), ""),
            "t_start": (np.array([w.t_start for w in ws], dtype=np.float64), "s"),
            "t_end": (np.array([w.t_end for w in ws], dtype=np.float64), "s"),
            "n_events": (np.array([w.n_events for w in ws], dtype=np.int64), ""),
        }
        for i, (name, unit) in enumerate(zip(self.param_names, self.units, strict=True)):
            columns[name] = (theta[:, i].astype(np.float64), unit)
        columns.update(
            value=(np.array([w.value for w in ws], dtype=np.float64), ""),
            fwl=(np.array([w.fwl for w in ws], dtype=np.float64), ""),
            iterations=(np.array([w.iterations for w in ws], dtype=np.int64), ""),
            evaluations=(np.array([w.evaluations for w in ws], dtype=np.int64), ""),
            seconds=(np.array([w.seconds for w in ws], dtype=np.float64), "s"),
            converged=(np.array([w.converged for w in ws], dtype=bool), ""),
        )
        path = Path(path)
        with h5py.File(path, "w") as f:
            for name, (data, unit) in columns.items():
                ds = f.create_dataset(name, data=data)
                if unit:
                    ds.attrs["unit"] = unit
            f.attrs["warp"] = self.warp
            f.attrs["params"] = list(self.param_names)
            f.attrs["units"] = list(self.units)
            f.attrs["columns"] = list(columns)
            f.attrs["settings_json"] = json.dumps(self.settings, default=str)
            for key, value in self.settings.items():
                plain = isinstance(value, (str, bool, int, float)) and not isinstance(value, np.generic)
                f.attrs[f"setting_{key}"] = value if plain else json.dumps(value, default=str)
        return path


def read_results(path: str | os.PathLike) -> SequenceResult:
    """Read a JSON file written by :meth:`SequenceResult.to_json` (ValueError naming what is wrong)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not a results JSON file ({exc})") from None
    try:
        names = tuple(data["params"])
        result = SequenceResult(
            warp=data["warp"],
            param_names=names,
            units=tuple(data["units"]),
            settings=data.get("settings", {}),
        )
        for w in data["windows"]:
            result.windows.append(
                WindowResult(
                    index=int(w["index"]),
                    t_start=float(w["t_start"]),
                    t_end=float(w["t_end"]),
                    n_events=int(w["n_events"]),
                    theta=np.array([float(w["theta"][n]) for n in names]),
                    value=math.nan if w["value"] is None else float(w["value"]),
                    fwl=math.nan if w["fwl"] is None else float(w["fwl"]),
                    iterations=int(w["iterations"]),
                    seconds=float(w["seconds"]),
                    converged=bool(w["converged"]),
                    evaluations=int(w.get("evaluations", 0)),
                    search=str(w.get("search", "")),
                )
            )
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a cmax-taichi results file (missing or bad entry {exc})") from None
    return result


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


def _count_windows(n_total: int, n_events: int, stride: int | None) -> int:
    step = n_events if stride is None else stride
    return 0 if n_total < n_events else (n_total - n_events) // step + 1


def _windows_of(
    source, n_events: int, duration: float | None, stride
) -> tuple[Iterator[Events], int | None, Camera | None, dict]:
    """(window iterator, number of windows if known, the source's camera, a description)."""
    if isinstance(source, Events):
        if duration is not None:
            it: Iterator[Events] = source.windows_by_duration(duration, stride)
            total = None
            if len(source) > 1:
                step = duration if stride is None else float(stride)
                total = int((source.t[-1] - source.t[0]) // step) + 1
        else:
            it = source.windows_by_count(n_events, None if stride is None else int(stride))
            total = _count_windows(len(source), n_events, None if stride is None else int(stride))
        return it, total, None, {"source": f"Events(n={len(source)})"}
    if hasattr(source, "windows"):  # an open Recording
        it = source.windows(n_events=n_events, duration=duration, stride=stride)
        total = None
        if duration is None:
            total = _count_windows(source.n_events, n_events, None if stride is None else int(stride))
        desc = {"source": str(getattr(source, "path", source)), "format": getattr(source, "format", None)}
        return it, total, getattr(source, "camera", None), desc
    raise TypeError(f"source must be Events, a Recording or a path, got {type(source).__name__}")


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
    method : str
        Local optimizer of :func:`~cmax_taichi.maximize` after a global search (the first window, and
        every window without ``warm_start`` or after a tracking loss); default ``"bfgs"``, which with
        the default coarse-to-fine search solves a first window in at most 150 evaluations.
    warm_start : bool
        Refine the previous window's estimate (``maximize(init="warm", method=warm_method)``: the
        previous estimate and the identity are the candidates, a few quasi-Newton steps follow); the
        first window gets the global search. When the refined gain over the identity falls below
        :data:`TRACKING_LOSS_RATIO` times the previous window's, tracking is lost: the global
        search runs too and the better result is kept. An ``init`` in ``optimize_options`` replaces
        this (that init in every window, from the previous estimate).
    compute_fwl : bool
        Compute the FWL of each estimate on the window's events.
    max_windows : int, optional
        Stop after this many windows.
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
        ``on_window(row, prob, result)`` after each window (e.g. to save figures). ``prob`` is one
        problem for the whole sequence (:meth:`~cmax_taichi.ContrastMaximization.set_events` gives it
        each next window): use it inside the callback; it holds the next window afterwards.
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

    Raises
    ------
    TypeError
        ``n_events``, ``stride``, ``duration`` or ``max_windows`` is not a number (e.g. None for
        ``n_events`` without ``duration``).
    ValueError
        Before any window is read: ``n_events < 2``; a count ``stride`` below 1 or not whole (0,
        0.5); a ``duration`` or time ``stride`` that is not a positive finite number of seconds;
        ``max_windows < 1``; time windows far shorter than the event spacing or too many of them
        (see :meth:`cmax_taichi.io.Recording.windows`).

    Events dropped by undistortion are reported by the first window that drops some, then once
    more at the end with the totals over all windows (not once per window).
    """
    if duration is None:
        n_events = checks.whole_number("n_events", n_events, 2)
        stride = None if stride is None else checks.whole_number("stride (events)", stride, 1)
    else:
        duration = checks.seconds("duration", duration, positive=True)
        stride = None if stride is None else checks.seconds("stride", stride, positive=True)
    if max_windows is not None:
        max_windows = checks.whole_number("max_windows", max_windows, 1)
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
            )
    if first_window < 0:
        raise ValueError(f"first_window must be >= 0, got {first_window}")
    model = get_warp(warp)
    windows, total, rec_camera, desc = _windows_of(source, n_events, duration, stride)
    camera = camera if camera is not None else rec_camera
    if model.needs_camera and camera is None:
        raise ValueError(f"warp {model.name!r} needs a camera: the recording has none, pass camera=")
    popts = dict(problem_options or {})
    oopts = dict(optimize_options or {})
    if max_windows is not None:
        total = min(total, int(max_windows)) if total is not None else int(max_windows)
    settings = {
        **desc,
        "warp": model.name,
        "objective": objective,
        "regularizers": dict(regularizers or {}),
        "camera": None if camera is None else [camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist],
        "window_events": None if duration is not None else int(n_events),
        "window_duration": duration,
        "stride": stride,
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
    lossy = checks.UndistortionTally()
    prob = fprob = None  # built on the first window, then given each next window (set_events)
    try:
        with warnings.catch_warnings():  # restores the filter that the tally adds
            for index, events in enumerate(_limited(windows, max_windows)):
                if index < first_window:
                    continue  # done by an earlier, interrupted run
                t0 = time.perf_counter()
                if len(events) < 2 or not events.duration > 0:
                    continue  # nothing to estimate (a window with all events at one time stamp)
                if prob is None:
                    prob = ContrastMaximization(
                        events,
                        warp=model,
                        objective=objective,
                        regularizers=regularizers,
                        camera=camera,
                        **popts,
                    )
                else:  # the same problem takes the next window: its fields, kernels and buffers stay
                    prob.set_events(events, weights=popts.get("weights"))
                lossy.add(events, prob.events)
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
                row = WindowResult(
                    index=index,
                    t_start=float(events.t[0]),
                    t_end=float(events.t[-1]),
                    n_events=prob.n_events,
                    theta=np.asarray(res.theta, dtype=np.float64),
                    value=float(res.value),
                    fwl=float(value_fwl),
                    iterations=res.n_iterations,
                    seconds=time.perf_counter() - t0,
                    converged=res.converged,
                    evaluations=res.n_evaluations,
                    search=search,
                )
                result.windows.append(row)
                if on_window is not None:
                    on_window(row, prob, res)
                state = WarmState.after(row, res)
                if bar is not None:
                    bar.update(f"J={res.value:.3f}")
    finally:
        if bar is not None:
            bar.close()
    lossy.report()
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


def _limited(windows: Iterable[Events], max_windows: int | None) -> Iterator[Events]:
    for k, w in enumerate(windows):
        if max_windows is not None and k >= max_windows:
            return
        yield w
