"""The results of a pass of windows: one :class:`WindowResult` per window (estimated or not), gathered
in a :class:`SequenceResult` that writes CSV, JSON and HDF5 (each file through a temporary name renamed
when complete) and that :func:`read_results` reads back (JSON or HDF5).

The rows of the files hold every window of the pass, the windows that were not estimated included
(their ``status`` says why, their parameters are NaN); each row counts its window's dropped events
(``n_dropped``), and :attr:`SequenceResult.events` has the totals of the pass by reason
(:mod:`cmax_taichi.core.windows`).
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cmax_taichi.core.windows import ESTIMATED, ESTIMATED_STATUSES, STATUSES
from cmax_taichi.io._files import check_regular
from cmax_taichi.io.outputs import atomic_path, atomic_write_text, json_text

__all__ = ["WindowResult", "SequenceResult", "read_results"]


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
    status : str
        ``"estimated"``, ``"short_tail"`` (the partial tail estimated as a shorter window,
        ``keep_tail``), or why the window was not estimated: ``"partial_tail"``,
        ``"too_few_events"`` (fewer than 2), ``"zero_duration"`` (all at one time); see
        :mod:`cmax_taichi.core.windows`. A window not estimated has NaN parameters and values.
    n_dropped : int
        Events of the window's index range dropped before estimation (outside the sensor, lost in
        undistortion): ``n_events + n_dropped`` is the range's size.
    kernels : str
        The kernels that computed the window: ``"full"`` (optimized), ``"fast"`` (quickly compiled,
        while the optimized ones compiled in the background: ``pipeline/tiers.py``), ``"chain"`` (the
        generic autodiff kernels), or "" (not estimated, or results of an older version).
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
    status: str = ESTIMATED
    n_dropped: int = 0
    kernels: str = ""

    @classmethod
    def of_optimization(cls, res, **window) -> WindowResult:
        """The row of a window estimated by ``res`` (an :class:`~cmax_taichi.OptimizeResult`): its
        estimate, value, iterations, convergence and evaluations; ``window`` gives the other fields."""
        return cls(
            theta=np.asarray(res.theta, dtype=np.float64),
            value=float(res.value),
            iterations=res.n_iterations,
            converged=res.converged,
            evaluations=res.n_evaluations,
            **window,
        )

    @property
    def estimated(self) -> bool:
        """Whether the window was estimated (``status`` ``"estimated"`` or ``"short_tail"``)."""
        return self.status in ESTIMATED_STATUSES


@dataclass
class SequenceResult:
    """Per-window estimates of a recording, with the settings that produced them.

    Attributes
    ----------
    windows : list of WindowResult
        The estimated windows, in order (``len(result)``, :attr:`theta` and :attr:`t_mid` are theirs).
    skipped : list of WindowResult
        The windows that were not estimated, with their ``status`` (NaN parameters).
    events : dict
        Where the source's events went: ``total``, ``estimated`` and the count of each reason of
        :data:`cmax_taichi.core.windows.CATEGORIES` plus ``after_max_windows`` (they sum to
        ``total``), and ``windows``, the window count per status (empty when unknown: results of an
        older version).
    """

    warp: str
    param_names: tuple[str, ...]
    units: tuple[str, ...]
    windows: list[WindowResult] = field(default_factory=list)
    settings: dict = field(default_factory=dict)
    skipped: list[WindowResult] = field(default_factory=list)
    events: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.windows)

    def rows(self) -> list[WindowResult]:
        """Every window, estimated or not, by index (the rows of the files)."""
        return sorted([*self.windows, *self.skipped], key=lambda w: w.index)

    def add(self, row: WindowResult) -> None:
        """Append ``row`` to :attr:`windows` (estimated) or :attr:`skipped` (not estimated)."""
        (self.windows if row.estimated else self.skipped).append(row)

    @property
    def theta(self) -> np.ndarray:
        """``(K, P)`` estimates, physical units."""
        return np.array([w.theta for w in self.windows]).reshape(len(self.windows), len(self.param_names))

    @property
    def t_mid(self) -> np.ndarray:
        """``(K,)`` window middle times, s."""
        return np.array([0.5 * (w.t_start + w.t_end) for w in self.windows])

    def identity_windows(self) -> int:
        """How many estimated windows came out at the identity warp exactly (every parameter 0).

        The signature of a window that holds too little motion: at about a pixel of motion or less the
        image of the events on their integer pixels is sharper than any warp of them (docs/estimation.md),
        and the search keeps the identity. A static camera gives it too.
        """
        return sum(1 for w in self.windows if not np.any(w.theta))

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
        "n_dropped",
        "status",
        "kernels",
    )

    def columns(self) -> list[str]:
        """CSV header :attr:`WINDOW_COLUMNS`, the parameters (``name [unit]``), :attr:`DIAGNOSTIC_COLUMNS`."""
        params = [f"{n} [{u}]" for n, u in zip(self.param_names, self.units, strict=True)]
        return [*self.WINDOW_COLUMNS, *params, *self.DIAGNOSTIC_COLUMNS]

    @staticmethod
    def csv_row(w: WindowResult) -> list:
        """The CSV fields of one window (in the order of :meth:`columns`)."""
        return (
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
                w.n_dropped,
                w.status,
                w.kernels,
            ]
        )

    def csv_rows(self) -> list[list]:
        """The CSV rows (without the header, :meth:`columns`): one per window, estimated or not."""
        return [self.csv_row(w) for w in self.rows()]

    def to_csv(self, path: str | os.PathLike) -> Path:
        """Write one row per window, estimated or not (see :meth:`columns`), through a temporary file
        renamed when complete; returns the path."""
        path = Path(path)
        with atomic_path(path) as tmp, tmp.open("w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(self.columns())
            writer.writerows(self.csv_rows())
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
            "events": self.events,
            "windows": [
                {
                    "index": w.index,
                    "t_start": num(w.t_start),
                    "t_end": num(w.t_end),
                    "n_events": w.n_events,
                    "theta": {n: num(v) for n, v in zip(self.param_names, w.theta, strict=True)},
                    "value": num(w.value),
                    "fwl": num(w.fwl),
                    "iterations": w.iterations,
                    "seconds": w.seconds,
                    "converged": w.converged,
                    "evaluations": w.evaluations,
                    "search": w.search,
                    "n_dropped": w.n_dropped,
                    "status": w.status,
                    "kernels": w.kernels,
                }
                for w in self.rows()
            ],
        }

    def to_json(self, path: str | os.PathLike) -> Path:
        """Write :meth:`as_dict` as JSON through a temporary file renamed when complete; returns the
        path."""
        path = Path(path)
        atomic_write_text(path, json_text(self.as_dict()))
        return path

    def to_hdf5(self, path: str | os.PathLike) -> Path:
        """Write one HDF5 dataset per column (length K, every window, estimated or not): ``index``,
        ``t_start``, ``t_end`` (s), ``n_events``, each parameter by name (attribute ``unit``),
        ``value``, ``fwl``, ``iterations``, ``evaluations``, ``seconds``, ``converged``,
        ``n_dropped``, ``status`` and ``kernels`` (strings). File attributes: ``warp``, ``params``, ``units``,
        ``columns`` (the dataset order), ``events_json`` (:attr:`events`) and each setting (numbers
        and strings as they are, anything else as JSON text; all of them also in ``settings_json``).
        Written through a temporary file renamed when complete; returns the path."""
        import h5py

        diagnostics = (
            "index", "t_start", "t_end", "n_events", "value", "fwl", "iterations", "evaluations", "seconds"
        )  # fmt: skip
        clash = set(self.param_names) & {*diagnostics, "converged", "n_dropped", "status", "kernels"}
        if clash:
            raise ValueError(f"parameter names {sorted(clash)} clash with the result columns")
        ws = self.rows()
        theta = np.array([w.theta for w in ws], dtype=np.float64).reshape(len(ws), len(self.param_names))
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
            n_dropped=(np.array([w.n_dropped for w in ws], dtype=np.int64), ""),
            status=(np.array([w.status for w in ws], dtype=h5py.string_dtype()), ""),
            kernels=(np.array([w.kernels for w in ws], dtype=h5py.string_dtype()), ""),
        )
        path = Path(path)
        with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
            for name, (data, unit) in columns.items():
                ds = f.create_dataset(name, data=data)
                if unit:
                    ds.attrs["unit"] = unit
            f.attrs["warp"] = self.warp
            f.attrs["params"] = list(self.param_names)
            f.attrs["units"] = list(self.units)
            f.attrs["columns"] = list(columns)
            f.attrs["events_json"] = json.dumps(self.events)
            f.attrs["settings_json"] = json.dumps(self.settings, default=str)
            for key, value in self.settings.items():
                plain = isinstance(value, (str, bool, int, float)) and not isinstance(value, np.generic)
                f.attrs[f"setting_{key}"] = value if plain else json.dumps(value, default=str)
        return path


def _number(value) -> float:
    """A float of a results file (None, the JSON form of NaN, is NaN)."""
    return math.nan if value is None else float(value)


def read_results(path: str | os.PathLike) -> SequenceResult:
    """Read the results that :meth:`SequenceResult.to_json` (``.json``) or
    :meth:`SequenceResult.to_hdf5` (``.h5`` / ``.hdf5``) wrote, every window with its ``status`` and
    ``n_dropped`` (results of older versions, without them, read as estimated windows).

    Raises
    ------
    FileNotFoundError, OSError
        A missing file, or a FIFO / device (refused, never read).
    ValueError
        Not a results file (not UTF-8 text, not JSON, entries missing): the message names the file.
    """
    path = check_regular(Path(path))
    if path.suffix.lower() in (".h5", ".hdf5"):
        return _check_order(path, _read_hdf5(path))
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(
            f"{path}: not a results JSON file (byte 0x{raw[exc.start]:02x} at offset {exc.start} is not "
            "UTF-8 text: give the results.json that 'estimate' wrote, or its folder)"
        ) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not a results JSON file ({exc})") from None
    try:
        if not isinstance(data, dict):
            raise TypeError(f"a {type(data).__name__} at the top, not an object")
        names = tuple(data["params"])
        settings, events = data.get("settings", {}), data.get("events") or {}
        for key, value in (("settings", settings), ("events", events)):
            if not isinstance(value, dict):
                raise TypeError(f"'{key}' is a {type(value).__name__}, not an object")
        if not isinstance(data["windows"], list):
            raise TypeError("'windows' is not a list")
        result = SequenceResult(
            warp=data["warp"],
            param_names=names,
            units=tuple(data["units"]),
            settings=settings,
            events=dict(events),
        )
        for k, w in enumerate(data["windows"]):
            if not isinstance(w, dict) or not isinstance(w.get("theta"), dict):
                what = "a window" if not isinstance(w, dict) else "its 'theta'"
                raise TypeError(f"window {k}: {what} is not an object (of the parameters {', '.join(names)})")
            row = WindowResult(
                index=int(w["index"]),
                t_start=_number(w["t_start"]),
                t_end=_number(w["t_end"]),
                n_events=int(w["n_events"]),
                theta=np.array([_number(w["theta"][n]) for n in names]),
                value=_number(w["value"]),
                fwl=_number(w["fwl"]),
                iterations=int(w["iterations"]),
                seconds=float(w["seconds"]),
                converged=bool(w["converged"]),
                evaluations=int(w.get("evaluations", 0)),
                search=str(w.get("search", "")),
                status=str(w.get("status", ESTIMATED)),
                n_dropped=int(w.get("n_dropped", 0)),
                kernels=str(w.get("kernels", "")),
            )
            _check_row(row)
            result.add(row)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: not a cmax-taichi results file ({_bad_entry(exc)})") from None
    return _check_order(path, result)


def _check_order(path: Path, result: SequenceResult) -> SequenceResult:
    """``result``, or ValueError when its windows are not in the order a run writes them (a window
    repeated, or out of order: an edited file, whose repeated window would be scored twice)."""
    for rows in (result.windows, result.rows()):  # in the file's order; every window by index
        _check_increasing(path, [w.index for w in rows])
    return result


def _check_increasing(path: Path, indices: list[int]) -> None:
    for before, after in itertools.pairwise(indices):
        if after <= before:
            raise ValueError(
                f"{path}: not a cmax-taichi results file (window {after} follows window {before}: "
                "repeated or out of order)"
            )


def _bad_entry(exc: Exception) -> str:
    """What a results file lacks or holds wrong, from the error of reading it."""
    return f"missing entry {exc}" if isinstance(exc, KeyError) else f"bad entry: {exc}"


def _check_row(row: WindowResult) -> None:
    """ValueError for a window that no run could have written: an unknown status, an estimated window
    without a finite time span (or one that ends before it starts) or parameters."""
    if row.status not in STATUSES:
        raise ValueError(f"window {row.index}: unknown status {row.status!r}")
    if row.n_events < 0 or row.n_dropped < 0:
        raise ValueError(f"window {row.index}: negative event counts")
    if row.estimated and not (
        math.isfinite(row.t_start) and math.isfinite(row.t_end) and row.t_end >= row.t_start
    ):
        raise ValueError(f"window {row.index}: t_start {row.t_start} .. t_end {row.t_end} is not a time span")
    if row.estimated and not np.all(np.isfinite(row.theta)):
        raise ValueError(f"window {row.index}: non-finite parameters")


def _read_hdf5(path: Path) -> SequenceResult:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            names = tuple(str(v) for v in f.attrs["params"])
            result = SequenceResult(
                warp=str(f.attrs["warp"]),
                param_names=names,
                units=tuple(str(v) for v in f.attrs["units"]),
                settings=json.loads(f.attrs.get("settings_json", "{}")),
                events=json.loads(f.attrs.get("events_json", "{}")),
            )
            col = {key: f[key][()] for key in f}
    except OSError as exc:
        raise OSError(f"{path}: not a readable HDF5 file ({exc})") from None
    except (KeyError, ValueError) as exc:
        raise ValueError(f"{path}: not a cmax-taichi results file ({_bad_entry(exc)})") from None
    try:
        if not (isinstance(result.settings, dict) and isinstance(result.events, dict)):
            raise ValueError("'settings_json' or 'events_json' is not a JSON object")
        n = len(col["index"])
        status = col.get("status", np.array([ESTIMATED] * n))
        kernels = col.get("kernels", np.array([""] * n))
        for k in range(n):
            row = WindowResult(
                index=int(col["index"][k]),
                t_start=float(col["t_start"][k]),
                t_end=float(col["t_end"][k]),
                n_events=int(col["n_events"][k]),
                theta=np.array([float(col[name][k]) for name in names]),
                value=float(col["value"][k]),
                fwl=float(col["fwl"][k]),
                iterations=int(col["iterations"][k]),
                seconds=float(col["seconds"][k]),
                converged=bool(col["converged"][k]),
                evaluations=int(col["evaluations"][k]) if "evaluations" in col else 0,
                status=status[k].decode() if isinstance(status[k], bytes) else str(status[k]),
                n_dropped=int(col["n_dropped"][k]) if "n_dropped" in col else 0,
                kernels=kernels[k].decode() if isinstance(kernels[k], bytes) else str(kernels[k]),
            )
            _check_row(row)
            result.add(row)
    except (KeyError, IndexError, ValueError) as exc:
        raise ValueError(f"{path}: not a cmax-taichi results file (missing or bad column {exc})") from None
    return result
