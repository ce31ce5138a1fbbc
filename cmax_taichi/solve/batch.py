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
as an uninterrupted run. A worker process that dies (killed, out of memory) is replaced and its
recording continues from its checkpoint, up to ``max_restarts`` times.

Ray is optional (``pip install -e ".[ray]"``) and imported only by ``engine="ray"``.
"""

from __future__ import annotations

import csv
import json
import math
import os
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TextIO

import numpy as np

from cmax_taichi.models.warps import get_warp
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
CHECKPOINT_NAME = "checkpoint.json"
CHECKPOINT_VERSION = 1

#: Test hook: ``NAME:K:MARKER`` makes the worker of recording NAME exit abruptly (``os._exit``) right
#: after writing the checkpoint of window K, once: only while the file MARKER does not exist (the hook
#: creates it). Used by the tests to check that a dead worker is replaced and its recording resumed.
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
    """

    name: str
    path: str
    status: str
    windows: int = 0
    resumed_from: int = 0
    new_windows: int = 0
    seconds: float = 0.0
    error: str = ""
    files: list[str] = field(default_factory=list)


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


def _atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and ``os.replace``, so
    that a reader (or a re-run after a crash) sees the old file or the new one, never a partial one."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _jsonable(value: Any) -> Any:
    """Settings as plain JSON values (to compare a checkpoint's settings with this run's)."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if hasattr(value, "fx"):  # a Camera
        return [value.fx, value.fy, value.cx, value.cy, *value.dist]
    return repr(value)


def _write_checkpoint(
    folder: Path,
    result: SequenceResult,
    key: dict,
    total: int | None,
    done: bool,
    warm_state: WarmState | None = None,
) -> None:
    data = result.as_dict()
    data["checkpoint"] = {
        "version": CHECKPOINT_VERSION,
        "key": key,
        "total_windows": total,
        "complete": done,
        # the last window's warm start for the next one (with that window's index): a run resumed
        # after it continues exactly as an uninterrupted one
        "warm_state": None
        if warm_state is None or not result.windows
        else {"index": result.windows[-1].index, **warm_state.as_dict()},
    }
    _atomic_write_text(folder / CHECKPOINT_NAME, json.dumps(data, indent=1))


def _read_checkpoint(folder: Path) -> tuple[SequenceResult, dict] | None:
    path = folder / CHECKPOINT_NAME
    if not path.exists():
        return None
    result = read_results(path)  # ValueError naming the file when it is not a results file
    meta = json.loads(path.read_text()).get("checkpoint")
    if not isinstance(meta, dict) or meta.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: not a cmax-taichi batch checkpoint (version {CHECKPOINT_VERSION})")
    return result, meta


def read_progress(folder: Path) -> tuple[int, int | None]:
    """(windows written, total windows if known) of a recording's checkpoint; (0, None) when none."""
    try:
        data = json.loads((folder / CHECKPOINT_NAME).read_text())
        return len(data["windows"]), data["checkpoint"]["total_windows"]
    except (OSError, ValueError, KeyError, TypeError):
        return 0, None


def _mtime(path: Path) -> int:
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return 0


# ---------------------------------------------------------------------------------------------------
# the worker


def _crash_hook(spec: str | None, name: str) -> Callable[[int], None]:
    """The test hook of :data:`CRASH_HOOK_ENV` for recording ``name`` (a no-op when unset)."""
    if not spec:
        return lambda index: None
    target, _, rest = spec.partition(":")
    at, _, marker = rest.partition(":")
    if target != name or not at or not marker:
        return lambda index: None

    def hook(index: int) -> None:
        if index == int(at) and not os.path.exists(marker):
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
        from cmax_taichi import io

        folder.mkdir(parents=True, exist_ok=True)
        key = {
            "path": str(path.resolve()),
            "format": format,
            "precision": backend.info().precision,
            "options": _jsonable(options),
        }
        previous = _read_checkpoint(folder)
        if previous is None and (folder / "results.csv").exists():
            raise ValueError(
                f"{folder} holds results that no batch run wrote (no {CHECKPOINT_NAME}): not overwritten"
            )
        done_rows: list[WindowResult] = []
        if previous is not None:
            prev_result, meta = previous
            if meta.get("key") != key:
                raise ValueError(
                    f"{folder / CHECKPOINT_NAME} was written with other settings or another recording; "
                    "use another output folder (or delete it) to start over"
                )
            done_rows = prev_result.windows
            if meta.get("complete") and (folder / "results.json").exists():
                summary.status = "done"
                summary.windows = len(done_rows)
                summary.resumed_from = (done_rows[-1].index + 1) if done_rows else 0
                summary.files = [str(folder / "results.csv"), str(folder / "results.json")]
                return summary
        first = (done_rows[-1].index + 1) if done_rows else 0
        summary.resumed_from = first
        warm = options.get("warm_start", True)
        warm_state = None
        if done_rows and warm:
            saved = (previous[1] if previous else {}).get("warm_state")
            if saved and saved.get("index") == done_rows[-1].index:
                warm_state = WarmState.from_dict(saved)
            else:  # a checkpoint without the last window's state: its estimate and J
                warm_state = WarmState(theta=done_rows[-1].theta, value=done_rows[-1].value)
        crash = _crash_hook(crash_hook, name)
        t0 = time.perf_counter()
        with io.open_recording(path, format=format) as rec:
            total = None
            n_events, duration = options.get("n_events", 30000), options.get("duration")
            stride = options.get("stride")
            if duration is None:
                step = int(n_events if stride is None else stride)
                total = 0 if rec.n_events < n_events else (rec.n_events - n_events) // step + 1
            if options.get("max_windows") is not None:
                total = (
                    int(options["max_windows"]) if total is None else min(total, int(options["max_windows"]))
                )
            model = get_warp(options.get("warp", "translation2"))
            written = SequenceResult(warp=model.name, param_names=model.params, units=model.units)
            written.windows = list(done_rows)  # earlier runs' rows first, then this run's

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
            )
        result.windows = written.windows
        summary.seconds = time.perf_counter() - t0
        if not result.windows:
            raise ValueError(f"{path}: no window to estimate ({rec.n_events} events)")
        files = [result.to_csv(folder / "results.csv"), result.to_json(folder / "results.json")]
        if hooks is not None:
            files += hooks.finished(folder, result)
        _write_checkpoint(folder, result, key, len(result.windows), done=True, warm_state=last_state[0])
        summary.status = "done"
        summary.windows = len(result.windows)
        summary.new_windows = len(result.windows) - len(done_rows)
        summary.files = [str(f) for f in files]
    except Exception as exc:  # one recording's failure (any error) must not stop the batch
        summary.error = f"{type(exc).__name__}: {exc}"
    return summary


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

    def estimate(self, path: str, folder: str, options: Mapping[str, Any], **kwargs: Any) -> RecordingSummary:
        return estimate_recording(path, folder, options, arch=self.arch, precision=self.precision, **kwargs)

    def pid(self) -> int:
        return os.getpid()


_POOL_WORKER: RecordingWorker | None = None


def _pool_init(arch: str | None, precision: str | None, plugins: Sequence[str] = ()) -> None:
    global _POOL_WORKER
    _POOL_WORKER = RecordingWorker(arch, precision, plugins)


def _pool_estimate(path: str, folder: str, options: Mapping[str, Any], kwargs: dict) -> RecordingSummary:
    assert _POOL_WORKER is not None, "the pool initializer did not run"
    return _POOL_WORKER.estimate(path, folder, options, **kwargs)


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
    import multiprocessing

    results: dict[int, RecordingSummary] = {}
    restarts = 0
    context = multiprocessing.get_context("spawn")  # a fresh interpreter: Taichi does not survive fork
    while len(results) < len(tasks):
        pending = [i for i in range(len(tasks)) if i not in results]
        with ProcessPoolExecutor(
            max_workers=min(workers, len(pending)),
            mp_context=context,
            initializer=_pool_init,
            initargs=(arch, precision, plugins),
        ) as pool:
            futures: dict[Future, int] = {pool.submit(_pool_estimate, *tasks[i], kwargs): i for i in pending}
            broken = False
            while futures:
                finished, _ = wait(futures, timeout=0.5, return_when=FIRST_COMPLETED)
                for fut in finished:
                    i = futures.pop(fut)
                    try:
                        results[i] = fut.result()
                    except BrokenProcessPool:
                        broken = True  # a worker died: this recording resumes in a new pool
                    except Exception as exc:  # e.g. hooks that do not pickle
                        results[i] = _failed(tasks[i], f"{type(exc).__name__}: {exc}")
                progress.poll(len(results))
        if broken:
            restarts += 1
            if restarts > max_restarts:
                for i in range(len(tasks)):
                    if i not in results:
                        error = f"worker process died {restarts} times (max_restarts={max_restarts})"
                        results[i] = _failed(tasks[i], error)
    return results


def _run_ray(
    tasks, workers, arch, precision, kwargs, max_restarts, progress, address, plugins=()
) -> dict[int, RecordingSummary]:
    try:
        import ray
    except ImportError:
        raise ImportError(
            'engine="ray" needs Ray: pip install "cmax-taichi[ray]" (or pip install ray)'
        ) from None

    started = False
    if not ray.is_initialized():
        if address is None and not os.environ.get("RAY_ADDRESS"):
            # a new local instance sized to the workers, even when a cluster runs on this machine
            ray.init(address="local", num_cpus=workers, include_dashboard=False, log_to_driver=False)
        else:  # the given cluster (or $RAY_ADDRESS, as ray.init reads it)
            ray.init(address=address, log_to_driver=False)
        started = True
    try:
        actor_class = ray.remote(num_cpus=1, max_restarts=max_restarts, max_task_retries=max_restarts)(
            RecordingWorker
        )
        actors = [actor_class.remote(arch, precision, plugins) for _ in range(min(workers, len(tasks)))]
        queue = list(range(len(tasks)))
        running: dict[Any, tuple[int, Any]] = {}
        results: dict[int, RecordingSummary] = {}
        idle = list(actors)
        while queue or running:
            while queue and idle:
                actor = idle.pop()
                i = queue.pop(0)
                running[actor.estimate.remote(*tasks[i], **kwargs)] = (i, actor)
            finished, _ = ray.wait(list(running), num_returns=1, timeout=0.5)
            for ref in finished:
                i, actor = running.pop(ref)
                try:
                    results[i] = ray.get(ref)
                    idle.append(actor)
                except ray.exceptions.RayActorError as exc:  # restarts used up: a fresh actor goes on
                    error = f"worker died (after {max_restarts} restarts): {str(exc).splitlines()[0]}"
                    results[i] = _failed(tasks[i], error)
                    idle.append(actor_class.remote(arch, precision, plugins))
                except ray.exceptions.RayError as exc:  # e.g. arguments that do not pickle
                    results[i] = _failed(tasks[i], f"{type(exc).__name__}: {str(exc).splitlines()[0]}")
                    idle.append(actor)
            progress.poll(len(results))
        for actor in idle:  # every actor is idle now (dead ones were replaced)
            ray.kill(actor)
        return results
    finally:
        if started:
            ray.shutdown()


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
    out = Path(out)
    names = recording_names(paths)
    out.mkdir(parents=True, exist_ok=True)
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
            results = _run_ray(tasks, workers, arch, precision, kwargs, max_restarts, bar, address, plugins)
        bar.poll(sum(r.status == "done" for r in results.values()))
    finally:
        bar.close()
    summaries = [results[i] for i in range(len(tasks))]
    summary_csv, windows_csv = _write_tables(out, summaries)
    return BatchResult(
        out=out,
        recordings=summaries,
        summary_csv=summary_csv,
        windows_csv=windows_csv,
        wall_seconds=time.perf_counter() - t0,
        engine=engine,
        workers=workers,
    )


def _write_tables(out: Path, summaries: Sequence[RecordingSummary]) -> tuple[Path, Path]:
    """OUT/summary.csv (one row per recording) and OUT/windows.csv (every window, merged)."""
    done = {s.name: read_results(out / s.name / "results.json") for s in summaries if s.status == "done"}
    first = next(iter(done.values()), None)
    params = [f"{n} [{u}]" for n, u in zip(first.param_names, first.units, strict=True)] if first else []
    header = ["recording", "path", "status", "windows", "seconds", *[f"median {p}" for p in params]]
    header += ["median fwl", "error"]
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
        rows.append([s.name, s.path, s.status, s.windows, seconds, *medians, s.error])
    summary_csv = out / "summary.csv"
    windows_csv = out / "windows.csv"
    with summary_csv.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(rows)
    with windows_csv.open("w", newline="") as fh:
        writer = csv.writer(fh)
        if first is not None:
            writer.writerow(["recording", *first.columns()])
        for name in done:
            with (out / name / "results.csv").open(newline="") as rf:
                for row in list(csv.reader(rf))[1:]:
                    writer.writerow([name, *row])
    return summary_csv, windows_csv
