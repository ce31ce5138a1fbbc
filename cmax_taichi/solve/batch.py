"""Motion estimation over many recordings at once, resumable, on a local process pool or on Ray.

:func:`run` hands each recording to a worker. A worker is a long-lived process (a
:class:`concurrent.futures.ProcessPoolExecutor` worker for ``engine="local"``, a Ray actor for
``engine="ray"``) that initialises Taichi once and keeps its compiled kernels across the recordings it
gets; the windows of one recording run in order inside one worker (warm start, as in
:func:`~cmax_taichi.solve.sequence.process`). Recordings run in parallel.

Outputs, for an output folder ``OUT``:

- ``OUT/<name>/checkpoint.json``: the windows written so far (replaced atomically after every window,
  so a partial file never exists), with the settings that produced them;
- ``OUT/<name>/results.csv`` and ``results.json`` once the recording is complete (as a single run);
- ``OUT/summary.csv``: one row per recording (status, window count, median parameters and FWL);
- ``OUT/windows.csv``: every window of every recording, the recording's name in the first column.

A re-run with the same ``OUT`` skips the windows in the checkpoints and continues each recording from
its last written window, warm-started from that window's estimate, so that it gives the same results
as an uninterrupted run; a recording that changed since its checkpoint (size, modification time or
the content fingerprint of :func:`cmax_taichi.io._cache.content_fingerprint`) is refused. A worker
process that dies (killed, out of memory) is replaced; the recording it held continues from its
checkpoint, up to ``max_restarts`` times, and only that recording fails when they are used up. Workers
die with their driver (``PR_SET_PDEATHSIG`` on Linux, else a watchdog thread): a driver killed with
SIGKILL leaves no worker writing into ``OUT``.

Before any work, the driver refuses an ``OUT`` that is or holds a recording, recording names that
clash with its own tables, a second batch on the same ``OUT`` (a lock, see :mod:`cmax_taichi.io.outputs`)
and files it would replace that no batch wrote.

Ray is optional (``pip install -e ".[ray]"``) and imported only by ``engine="ray"``.
"""

from __future__ import annotations

import contextlib
import csv
import math
import os
import signal
import sys
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, TextIO

import numpy as np

from cmax_taichi.core.checks import EventsDroppedWarning
from cmax_taichi.io import outputs
from cmax_taichi.io._files import check_regular
from cmax_taichi.models.warps import get_warp
from cmax_taichi.solve.checkpoints import (
    CHECKPOINT_NAME,
    _changed,
    _jsonable,
    _mtime,
    _read_checkpoint,
    _write_checkpoint,
    read_progress,
    recording_identity,
)
from cmax_taichi.solve.sequence import (
    ProgressBar,
    SequenceResult,
    WarmState,
    WindowResult,
    process,
    read_results,
)

__all__ = [
    "ENGINES",
    "CHECKPOINT_NAME",
    "CRASH_HOOK_ENV",
    "BatchResult",
    "RecordingHooks",
    "RecordingSummary",
    "estimate_recording",
    "recording_names",
    "run",
]

ENGINES = ("local", "ray")
#: the batch's own files in ``OUT``: no recording may take these names
TABLE_NAMES = ("summary.csv", "windows.csv")

#: Test hook: ``NAME:K:MARKER`` makes the worker of recording NAME exit abruptly (``os._exit``) right
#: after writing the checkpoint of window K, once: only while the file MARKER does not exist (the hook
#: creates it). ``NAME:K:`` (no marker) makes it exit after every window from K on, in every attempt (a
#: recording that always kills its worker). Used by the tests to check that a dead worker is replaced,
#: its recording resumed, and that the deaths are charged to that recording alone.
CRASH_HOOK_ENV = "CMAX_TAICHI_BATCH_CRASH"

#: keyword arguments of :func:`~cmax_taichi.solve.sequence.process` that :func:`run` passes on
PROCESS_OPTIONS = (
    "warp",
    "objective",
    "regularizers",
    "camera",
    "n_events",
    "duration",
    "stride",
    "keep_tail",
    "method",
    "warm_start",
    "compute_fwl",
    "max_windows",
    "problem_options",
    "optimize_options",
)


class RecordingHooks(Protocol):
    """Extra outputs of a recording, called inside the worker (the object must pickle: a module-level
    class, so that a worker process can import it)."""

    def window(self, folder: Path, row: WindowResult, prob: Any, result: Any) -> None:
        """After each estimated window (e.g. a figure of the first windows)."""

    def finished(self, folder: Path, result: SequenceResult) -> list[Path]:
        """After the recording is complete; returns the files it wrote."""


@dataclass
class RecordingSummary:
    """What a worker reports for one recording.

    Attributes
    ----------
    name : str
        Sub-folder of the output folder.
    path : str
        The recording.
    status : str
        ``"done"`` or ``"failed"``.
    windows : int
        Windows in the results (including those of earlier runs).
    resumed_from : int
        Index of the first window this run was to estimate (0 for a fresh run).
    new_windows : int
        Windows estimated by this run (0 when the checkpoint was already complete).
    seconds : float
        Wall time of this run's windows, s.
    error : str
        Why the recording failed ("" when done).
    files : list of str
        Files written.
    events : int
        Events of the recording (0 when unknown).
    not_estimated : int
        Events not estimated (see ``SequenceResult.events`` for the reasons).
    """

    name: str
    path: str
    status: Literal["done", "failed"]
    windows: int = 0
    resumed_from: int = 0
    new_windows: int = 0
    seconds: float = 0.0
    error: str = ""
    files: list[str] = field(default_factory=list)
    events: int = 0
    not_estimated: int = 0


@dataclass
class BatchResult:
    """The outcome of :func:`run`: one summary per recording (input order) and the merged tables."""

    out: Path
    recordings: list[RecordingSummary]
    summary_csv: Path
    windows_csv: Path
    wall_seconds: float
    engine: str
    workers: int

    @property
    def failed(self) -> list[RecordingSummary]:
        return [r for r in self.recordings if r.status != "done"]

    def results(self, name: str) -> SequenceResult:
        """The per-window results of the recording ``name`` (read from its results.json)."""
        return read_results(self.out / name / "results.json")


# ---------------------------------------------------------------------------------------------------
# names and checkpoints


def recording_names(paths: Sequence[str | os.PathLike]) -> list[str]:
    """One output sub-folder name per recording: the folder name, or the file name without suffix;
    names that collide get their parent folders prepended (``a_events``, ``b_events``).

    Raises
    ------
    ValueError
        When the same recording is given twice.
    """
    resolved = [Path(p).resolve() for p in paths]
    seen: dict[Path, int] = {}
    for i, p in enumerate(resolved):
        if p in seen:
            raise ValueError(f"recording {paths[i]} is given twice (as argument {seen[p] + 1} and {i + 1})")
        seen[p] = i

    def name(p: Path, depth: int) -> str:
        last = p.name if p.is_dir() else p.stem
        parents = [q.name for q in list(p.parents)[: depth - 1] if q.name]
        return "_".join([*reversed(parents), last])

    depth = [1] * len(resolved)
    while True:
        names = [name(p, d) for p, d in zip(resolved, depth, strict=True)]
        clashes = {n for n in names if names.count(n) > 1}
        if not clashes:
            return names
        grown = False
        for i, n in enumerate(names):
            if n in clashes and depth[i] <= len(resolved[i].parents):
                depth[i] += 1
                grown = True
        if not grown:  # pragma: no cover - distinct resolved paths always differ at some depth
            return [f"{n}_{i}" for i, n in enumerate(names)]


# ---------------------------------------------------------------------------------------------------
# the worker


def _crash_hook(spec: str | None, name: str) -> Callable[[int], None]:
    """The test hook of :data:`CRASH_HOOK_ENV` for recording ``name`` (a no-op when unset)."""
    if not spec:
        return lambda index: None
    target, _, rest = spec.partition(":")
    at, _, marker = rest.partition(":")
    if target != name or not at:
        return lambda index: None

    def hook(index: int) -> None:
        if not marker:  # every attempt dies
            if index >= int(at):
                os._exit(70)
        elif index == int(at) and not os.path.exists(marker):
            Path(marker).touch()
            os._exit(70)  # abrupt, like a killed process: no cleanup, no exception

    return hook


def estimate_recording(
    path: str | os.PathLike,
    folder: str | os.PathLike,
    options: Mapping[str, Any],
    *,
    format: str | None = None,
    arch: str | None = None,
    precision: str | None = None,
    hooks: RecordingHooks | None = None,
    crash_hook: str | None = None,
) -> RecordingSummary:
    """Estimate one recording into ``folder``, resuming from its checkpoint (the worker's code; it can
    also be called directly).

    Parameters
    ----------
    path : path
        The recording (anything :func:`cmax_taichi.io.open_recording` reads).
    folder : path
        Its output folder (created).
    options : mapping
        Keyword arguments of :func:`~cmax_taichi.solve.sequence.process` (names in ``PROCESS_OPTIONS``).
    format, arch, precision : str, optional
        Reader format, Taichi arch and precision (default: detected, CPU, the arch's default).
    hooks : RecordingHooks, optional
        Extra outputs (figures).
    crash_hook : str, optional
        The value of :data:`CRASH_HOOK_ENV` (tests only).

    Returns
    -------
    RecordingSummary
        ``status="failed"`` with the error message when the recording cannot be estimated (bad file,
        settings that differ from the checkpoint's, ...); a dying process returns nothing.
    """
    from cmax_taichi.core import backend

    path = Path(path)
    folder = Path(folder)
    name = folder.name
    summary = RecordingSummary(name=name, path=str(path), status="failed")
    try:
        unknown = set(options) - set(PROCESS_OPTIONS)
        if unknown:
            raise TypeError(f"unknown estimation option(s) {sorted(unknown)}; valid: {list(PROCESS_OPTIONS)}")
        backend.init_if_needed(arch, precision)
        folder.mkdir(parents=True, exist_ok=True)
        with outputs.hold_lock(folder, f"batch worker of {name}"):  # one writer per recording folder
            precision = backend.info().precision
            _estimate_into(path, folder, options, format, precision, hooks, crash_hook, summary)
    except Exception as exc:  # one recording's failure (any error) must not stop the batch
        summary.status = "failed"
        summary.error = f"{type(exc).__name__}: {exc}"
    return summary


def _rows_expected(n_total: int, options: Mapping[str, Any]) -> int | None:
    """The rows a recording's results will have (every window, estimated or not), when known."""
    total = None
    n_events, duration = options.get("n_events", 30000), options.get("duration")
    if duration is None:
        step = int(n_events if options.get("stride") is None else options["stride"])
        full = 0 if n_total < n_events else (n_total - n_events) // step + 1
        total = full + (1 if full * step < n_total else 0)  # the partial tail has a row, kept or not
    if options.get("max_windows") is not None:
        limit = int(options["max_windows"])
        total = limit if total is None else min(total, limit)
    return total


def _estimate_into(
    path: Path,
    folder: Path,
    options: Mapping[str, Any],
    format: str | None,
    precision: str,
    hooks: RecordingHooks | None,
    crash_hook: str | None,
    summary: RecordingSummary,
) -> None:
    """The body of :func:`estimate_recording`, with the folder's lock held; fills ``summary``."""
    from cmax_taichi import io

    previous = _read_checkpoint(folder)
    if previous is None and any((folder / f).exists() for f in ("results.csv", "results.json")):
        raise ValueError(
            f"{folder} holds results that no batch run wrote (no {CHECKPOINT_NAME}): not overwritten"
        )
    crash = _crash_hook(crash_hook, folder.name)
    t0 = time.perf_counter()
    with io.open_recording(path, format=format) as rec:
        key = {
            "path": str(path.resolve()),
            "format": format,
            "precision": precision,
            "options": _jsonable(options),
            "identity": recording_identity(rec),
        }
        summary.events = rec.n_events
        done_rows: list[WindowResult] = []
        done_skipped: list[WindowResult] = []
        if previous is not None:
            prev_result, meta = previous
            old = meta.get("key") if isinstance(meta.get("key"), dict) else {}
            if old.get("identity") != key["identity"]:
                raise ValueError(
                    f"{path} changed since {folder / CHECKPOINT_NAME} was written "
                    f"({_changed(old.get('identity') or {}, key['identity'])}): not resumed, so that the "
                    f"windows of two recordings never mix; use another output folder, or delete {folder} "
                    "to start over"
                )
            if old != key:
                raise ValueError(
                    f"{folder / CHECKPOINT_NAME} was written with other settings; "
                    "use another output folder (or delete it) to start over"
                )
            done_rows, done_skipped = prev_result.windows, prev_result.skipped
            if meta.get("complete") and (folder / "results.json").exists():
                summary.status = "done"
                summary.windows = len(done_rows)
                summary.resumed_from = max((w.index + 1 for w in prev_result.rows()), default=0)
                summary.not_estimated = _not_estimated(prev_result)
                summary.files = [str(folder / "results.csv"), str(folder / "results.json")]
                return
        first = max((w.index + 1 for w in [*done_rows, *done_skipped]), default=0)
        summary.resumed_from = first
        warm_state = None
        if done_rows and options.get("warm_start", True):
            saved = (previous[1] if previous else {}).get("warm_state")
            if saved and saved.get("index") == done_rows[-1].index:
                warm_state = WarmState.from_dict(saved)
            else:  # a checkpoint without the last window's state: its estimate and J
                warm_state = WarmState(theta=done_rows[-1].theta, value=done_rows[-1].value)
        total = _rows_expected(rec.n_events, options)
        model = get_warp(options.get("warp", "translation2"))
        written = SequenceResult(warp=model.name, param_names=model.params, units=model.units)
        written.windows = list(done_rows)  # earlier runs' rows first, then this run's
        written.skipped = list(done_skipped)
        last_state: list[WarmState | None] = [warm_state]

        def on_window(row: WindowResult, prob: Any, res: Any) -> None:
            written.windows.append(row)
            last_state[0] = WarmState.after(row, res)
            _write_checkpoint(folder, written, key, total, done=False, warm_state=last_state[0])
            if hooks is not None:
                hooks.window(folder, row, prob, res)
            crash(row.index)

        result = process(
            rec,
            **options,
            progress=False,
            first_window=first,
            warm_state=warm_state,
            on_window=on_window,
            on_skipped=written.skipped.append,
        )
    result.windows, result.skipped = written.windows, written.skipped
    summary.seconds = time.perf_counter() - t0
    if not result.windows:
        raise ValueError(f"{path}: no window to estimate ({_why_none(result)})")
    extra = hooks.finished(folder, result) if hooks is not None else []
    with _termination_deferred():  # results.csv never stands beside an incomplete checkpoint
        files = [result.to_csv(folder / "results.csv"), result.to_json(folder / "results.json")]
        _write_checkpoint(folder, result, key, len(result.rows()), done=True, warm_state=last_state[0])
    files += extra
    summary.status = "done"
    summary.windows = len(result.windows)
    summary.new_windows = len(result.windows) - len(done_rows)
    summary.not_estimated = _not_estimated(result)
    summary.files = [str(f) for f in files]


@contextlib.contextmanager
def _termination_deferred():
    """SIGTERM held back for the block (a few file writes): the driver's stop on Ctrl-C / SIGTERM
    terminates a busy worker, which then ends after the block, not between two of its writes."""
    if not hasattr(signal, "pthread_sigmask"):  # not POSIX
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _not_estimated(result: SequenceResult) -> int:
    events = result.events or {}
    return int(events.get("total", 0)) - int(events.get("estimated", 0))


def _why_none(result: SequenceResult) -> str:
    """Why a pass estimated no window, from its event accounting."""
    events = result.events or {}
    if not events.get("total"):
        return "the recording has no events"
    reasons = {k: v for k, v in events.items() if k not in ("total", "estimated", "windows") and v}
    return f"{events['total']} events: " + ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in reasons.items())


class RecordingWorker:
    """One long-lived worker: Taichi initialised once, recordings estimated one after the other (the
    Ray engine wraps it as an actor; the local engine keeps one per pool process)."""

    def __init__(
        self, arch: str | None = None, precision: str | None = None, plugins: Sequence[str] = ()
    ) -> None:
        from cmax_taichi.core import backend
        from cmax_taichi.core.registry import load_plugin

        self.arch, self.precision = arch, precision
        for plugin in plugins:  # the user's warps, objectives, regularizers, in this fresh interpreter
            load_plugin(plugin)
        backend.init_if_needed(arch, precision)
        # the counts of the events not estimated are in each recording's results and in the summary;
        # the driver warns once with the totals
        warnings.simplefilter("ignore", EventsDroppedWarning)

    def estimate(self, path: str, folder: str, options: Mapping[str, Any], **kwargs: Any) -> RecordingSummary:
        return estimate_recording(path, folder, options, arch=self.arch, precision=self.precision, **kwargs)

    def pid(self) -> int:
        return os.getpid()


def _worker_state(arch: str | None, precision: str | None, plugins: Sequence[str] = ()) -> RecordingWorker:
    return RecordingWorker(arch, precision, plugins)


def _estimate_task(worker: RecordingWorker, path: str, folder: str, options: Mapping[str, Any], kwargs: dict):
    return worker.estimate(path, folder, options, **kwargs)


# ---------------------------------------------------------------------------------------------------
# the driver


class _Progress:
    """Progress over all recordings, read from the checkpoints (the same for both engines)."""

    def __init__(self, folders: Sequence[Path], stream: TextIO | None) -> None:
        self.folders = list(folders)
        self.counts = {f: read_progress(f) for f in self.folders}
        self.mtimes = {f: _mtime(f / CHECKPOINT_NAME) for f in self.folders}
        self.start = {f: c for f, (c, _) in self.counts.items()}
        self.bar = ProgressBar(None, label="windows", stream=stream) if stream is not None else None
        self.seen = 0
        self.done = 0

    def poll(self, recordings_done: int) -> None:
        if self.bar is None:
            return
        for f in self.folders:  # re-read only the checkpoints that changed
            mtime = _mtime(f / CHECKPOINT_NAME)
            if mtime != self.mtimes[f]:
                self.mtimes[f], self.counts[f] = mtime, read_progress(f)
        counts = list(self.counts.values())
        written = sum(c for c, _ in counts) - sum(self.start.values())
        totals = [t for _, t in counts]
        if all(t is not None for t in totals):
            self.bar.total = sum(totals) - sum(self.start.values())
        while self.seen < written:
            self.seen += 1
            self.bar.update(f"({recordings_done}/{len(self.folders)} recordings done)")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _failed(task: tuple, error: str) -> RecordingSummary:
    """The summary of a recording whose worker gave no answer."""
    return RecordingSummary(name=Path(task[1]).name, path=task[0], status="failed", error=error)


def _run_local(
    tasks, workers, arch, precision, kwargs, max_restarts, progress, plugins=()
) -> dict[int, RecordingSummary]:
    """The local engine: :func:`cmax_taichi.solve.workers.run_tasks` (a dead worker charges only the
    recording it held; workers die with the driver)."""
    import functools

    from cmax_taichi.solve.workers import run_tasks

    return run_tasks(
        [(_estimate_task, tuple(task), {"kwargs": kwargs}) for task in tasks],
        workers,
        functools.partial(_worker_state, arch, precision, plugins),
        max_restarts,
        on_poll=progress.poll,
        failed=lambda i, error: _failed(tasks[i], error),
    )


def _run_ray(
    tasks, workers, arch, precision, kwargs, max_restarts, progress, address, plugins=()
) -> dict[int, RecordingSummary]:
    """The Ray engine: :func:`cmax_taichi.solve.workers.run_ray` with :class:`RecordingWorker` actors."""
    from cmax_taichi.solve.workers import run_ray

    return run_ray(
        [(tuple(task), kwargs) for task in tasks],
        workers,
        RecordingWorker,
        (arch, precision, plugins),
        max_restarts,
        address,
        on_poll=progress.poll,
        failed=lambda i, error: _failed(tasks[i], error),
    )


def _loaded_plugins(plugins: Sequence[str]) -> tuple[str, ...]:
    """The plugins, loaded here too (the options name their entries), files as absolute paths."""
    from cmax_taichi.core.registry import load_plugin

    if isinstance(plugins, str):
        plugins = [plugins]
    out = []
    for plugin in plugins:
        load_plugin(plugin)
        is_file = plugin.endswith(".py") or Path(plugin).is_file()
        out.append(str(Path(plugin).expanduser().resolve()) if is_file else plugin)
    return tuple(out)


def run(
    paths: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    *,
    workers: int = 1,
    engine: str = "local",
    address: str | None = None,
    format: str | None = None,
    arch: str | None = None,
    precision: str | None = None,
    max_restarts: int = 3,
    progress: bool | TextIO = True,
    hooks: RecordingHooks | None = None,
    plugins: Sequence[str] = (),
    **options: Any,
) -> BatchResult:
    """Estimate the motion of every window of several recordings, in parallel and resumable.

    Parameters
    ----------
    paths : sequence of paths
        The recordings (anything :func:`cmax_taichi.io.open_recording` reads).
    out : path
        Output folder: ``OUT/<name>/`` per recording (names from :func:`recording_names`),
        ``OUT/summary.csv`` and ``OUT/windows.csv``.
    workers : int
        Recordings estimated at once (worker processes or Ray actors, one CPU each).
    engine : {"local", "ray"}
        ``"local"``: a pool of worker processes on this machine. ``"ray"``: Ray actors on a new local
        Ray instance with ``workers`` CPUs, or on the cluster at ``address`` (or ``$RAY_ADDRESS``).
    address : str, optional
        Ray cluster address (``"auto"``, ``"ray://head:10001"``, ...); only with ``engine="ray"``. The
        output folder must then be on storage that every node sees.
    format, arch, precision : str, optional
        Reader format, Taichi arch (default CPU) and precision of the workers.
    max_restarts : int
        How often a dead worker is replaced before its recordings are reported as failed.
    progress : bool or stream
        Progress over all recordings on stderr (or on the given stream).
    hooks : RecordingHooks, optional
        Extra per-recording outputs made inside the workers (must pickle).
    plugins : sequence of str
        Plugins (Python files or modules that register warps, objectives, regularizers:
        :func:`cmax_taichi.core.registry.load_plugin`) that every worker imports first; a file must be
        at a path every worker sees.
    **options
        Keyword arguments of :func:`~cmax_taichi.solve.sequence.process`: ``warp``, ``objective``,
        ``regularizers``, ``n_events``, ``duration``, ``stride``, ``method``, ``warm_start``,
        ``compute_fwl``, ``max_windows``, ``problem_options``, ``optimize_options``, ``camera``.

    Returns
    -------
    BatchResult
        One :class:`RecordingSummary` per recording; a recording that cannot be estimated is reported
        as failed (with the error) and does not stop the others.

    Raises
    ------
    ValueError
        Before any work: bad arguments; a recording given twice or whose name clashes with the batch's
        tables (``summary.csv``, ``windows.csv``) or machinery
        (:data:`cmax_taichi.io.outputs.RESERVED_NAMES`);
        an ``out`` that is or holds a recording; files in ``out`` that this batch would replace and that
        no batch wrote (:class:`~cmax_taichi.io.outputs.OutputConflictError`).
    OSError
        A missing recording, a FIFO or device given as one, or another batch running on ``out``
        (:class:`~cmax_taichi.io.outputs.OutputBusyError`).
    """
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    if address is not None and engine != "ray":
        raise ValueError("address is a Ray cluster address: it needs engine='ray'")
    if not isinstance(max_restarts, int) or max_restarts < 0:
        raise ValueError(f"max_restarts must be an integer >= 0, got {max_restarts!r}")
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    if not paths:
        raise ValueError("no recording given")
    plugins = _loaded_plugins(plugins)
    unknown = set(options) - set(PROCESS_OPTIONS)
    if unknown:
        raise TypeError(f"unknown option(s) {sorted(unknown)}; valid: {', '.join(PROCESS_OPTIONS)}")
    for p in paths:
        if not Path(p).exists():
            raise OSError(f"{p}: no such file or folder")
        if not Path(p).is_dir():
            check_regular(p)  # a FIFO or a device is refused here, not by a worker that blocks on it
    out = Path(out)
    names = recording_names(paths)
    _check_outputs(out, paths, names)
    with outputs.hold_lock(out, f"batch of {len(paths)} recording(s)"):
        _check_folders(out, names)
        folders = [out / n for n in names]
        tasks = [(str(p), str(f), dict(options)) for p, f in zip(paths, folders, strict=True)]
        kwargs = {"format": format, "hooks": hooks, "crash_hook": os.environ.get(CRASH_HOOK_ENV)}
        stream = None if progress is False else (sys.stderr if progress is True else progress)
        bar = _Progress(folders, stream)
        t0 = time.perf_counter()
        try:
            if engine == "local":
                results = _run_local(tasks, workers, arch, precision, kwargs, max_restarts, bar, plugins)
            else:
                results = _run_ray(
                    tasks, workers, arch, precision, kwargs, max_restarts, bar, address, plugins
                )
            bar.poll(sum(r.status == "done" for r in results.values()))
        finally:
            bar.close()
        summaries = [results[i] for i in range(len(tasks))]
        summary_csv, windows_csv = _write_tables(out, summaries)
    left = sum(s.not_estimated for s in summaries)
    if left:
        total = sum(s.events for s in summaries if s.status == "done")
        counted = sum(1 for s in summaries if s.not_estimated)
        warnings.warn(
            f"batch {out}: {left} of {total} event(s) not estimated in {counted} recording(s) (counts per "
            f"recording in {summary_csv.name}, by reason in each results.json)",
            EventsDroppedWarning,
            stacklevel=2,
        )
    return BatchResult(
        out=out,
        recordings=summaries,
        summary_csv=summary_csv,
        windows_csv=windows_csv,
        wall_seconds=time.perf_counter() - t0,
        engine=engine,
        workers=workers,
    )


def _check_outputs(out: Path, paths: Sequence[str | os.PathLike], names: Sequence[str]) -> None:
    """Refuse, before any work, an ``out`` that is or holds a recording and names that clash with the
    batch's own files (ValueError)."""
    outputs.check_inputs(out, paths, option="out (--out)")
    reserved = set(TABLE_NAMES) | set(outputs.RESERVED_NAMES)
    for p, name in zip(paths, names, strict=True):
        if name in reserved or name.startswith(outputs.STAGING_PREFIX):
            raise outputs.OutputConflictError(
                f"recording {p} would be estimated into {out / name}, a name the batch uses for its own "
                f"{'table' if name in TABLE_NAMES else 'files'}: rename the recording (or its folder)"
            )


def _check_folders(out: Path, names: Sequence[str]) -> None:
    """Refuse, before any work, files the batch would replace and that no batch wrote: its tables
    (not in the folder's manifest) and recording folders with results but no checkpoint."""
    outputs.refuse_foreign(out, TABLE_NAMES, option="output folder", command="batch")
    for name in names:
        folder = out / name
        if folder.exists() and not folder.is_dir():
            raise outputs.OutputConflictError(f"{folder} is a file where the batch writes a recording folder")
        if folder.is_dir() and not (folder / CHECKPOINT_NAME).exists():
            foreign = [f for f in ("results.csv", "results.json") if (folder / f).exists()]
            if foreign:
                raise outputs.OutputConflictError(
                    f"{folder} holds {', '.join(foreign)} that no batch run wrote (no {CHECKPOINT_NAME}): "
                    "not overwritten; choose another output folder or move them away"
                )


def _write_tables(out: Path, summaries: Sequence[RecordingSummary]) -> tuple[Path, Path]:
    """OUT/summary.csv (one row per recording) and OUT/windows.csv (every window, merged from each
    recording's results.json, read and checked), each through a temporary file renamed when complete, and
    recorded in OUT's manifest."""
    done = {s.name: read_results(out / s.name / "results.json") for s in summaries if s.status == "done"}
    first = next(iter(done.values()), None)
    params = [f"{n} [{u}]" for n, u in zip(first.param_names, first.units, strict=True)] if first else []
    header = ["recording", "path", "status", "windows", "seconds", *[f"median {p}" for p in params]]
    header += ["median fwl", "events", "not estimated", "error"]
    rows = []
    for s in summaries:
        res = done.get(s.name)
        medians: list[str] = [""] * (len(params) + 1)
        seconds = ""
        if res is not None and res.windows:
            medians = [repr(float(np.median(res.theta[:, j]))) for j in range(res.theta.shape[1])]
            fwls = [w.fwl for w in res.windows if math.isfinite(w.fwl)]
            medians.append(repr(float(np.median(fwls))) if fwls else "")
            seconds = f"{sum(w.seconds for w in res.windows):.4f}"
        events = [s.events, s.not_estimated] if s.events else ["", ""]
        rows.append([s.name, s.path, s.status, s.windows, seconds, *medians, *events, s.error])
    summary_csv = out / "summary.csv"
    windows_csv = out / "windows.csv"
    with outputs.atomic_path(summary_csv) as tmp, tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(rows)
    with outputs.atomic_path(windows_csv) as tmp, tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        if first is not None:
            writer.writerow(["recording", *first.columns()])
        for name, res in done.items():  # from each results.json, checked as it was read
            writer.writerows([name, *row] for row in res.csv_rows())
    outputs.write_manifest(out, TABLE_NAMES, "batch")
    return summary_csv, windows_csv
