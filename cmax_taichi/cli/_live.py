"""``cmax-taichi estimate --live SOURCE``: estimate while the events arrive (a dv-processing TCP stream, a
camera, or a recording replayed at its recorded speed), each window's row appended to OUT/results.csv and
flushed as soon as it is estimated, with an optional live display.

Output: ``OUT/results.csv`` holds the columns of a recorded run's results.csv and ``latency [s]`` (from
the arrival of the window's last event to its estimate); a window that was not estimated has its row
too (``status``: ``behind`` when the estimator had fallen behind and skipped it). The folder is checked
and locked as for every command (:mod:`cmax_taichi.io.outputs`): never an input, no file that no run
wrote is replaced, one run at a time; the rows are written in place (a crash loses at most the window in
flight), and when the run ends (the source ends, ``--idle-timeout``, ``--max-windows``, Ctrl-C or
SIGTERM: the window in flight is finished first; a second Ctrl-C stops at once) ``OUT/results.json``
gets every row, the settings and where every event went, and the manifest lists the files.

The display (a separate process, matplotlib's interactive window: the IWE of the latest window before
and after the estimate, and the parameters over time) takes the latest window about four times a
second; the estimator never waits for it.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

from cmax_taichi.cli import CliError

#: the files a live run writes into OUT
LIVE_FILES = ("results.csv", "results.json")
#: seconds between two frames of the display
DISPLAY_PERIOD = 0.25


def add_arguments(parser: argparse.ArgumentParser, live_default: str = "adaptive") -> None:
    """The options of live input and of the window rule, on ``estimate`` and ``flow`` (``live_default``:
    the window mode of --live without --window-mode, as :func:`window_rule` takes it)."""
    live = parser.add_argument_group(
        "live input (estimate while the events arrive; results appended to OUT/results.csv)"
    )
    live.add_argument(
        "--live",
        default=None,
        metavar="SOURCE",
        help="tcp://HOST:PORT (a dv-processing event stream), camera or camera:SERIAL (dv-processing), "
        "or a recording replayed at its recorded speed (--speed)",
    )
    live.add_argument("--speed", type=float, default=1.0, help="replay speed of a recording (default 1)")
    live.add_argument("--loops", type=int, default=1, help="times a replayed recording plays (default 1)")
    live.add_argument(
        "--idle-timeout", type=float, default=None, metavar="S", help="stop after S seconds without events"
    )
    live.add_argument(
        "--calib", default=None, metavar="FILE", help="the camera of a stream: a calib.txt (fx fy cx cy "
        "[k1 k2 p1 p2 k3]); a replayed recording's own by default",
    )  # fmt: skip
    shown = live.add_mutually_exclusive_group()
    shown.add_argument("--display", dest="display", action="store_true", default=None, help="live display")
    shown.add_argument("--no-display", dest="display", action="store_false", help="no live display")
    win = parser.add_argument_group("window rule")
    win.add_argument(
        "--window-mode",
        default=None,
        choices=["count", "duration", "adaptive"],
        help="count: --window events; duration: --duration seconds; adaptive: as long as the motion needs "
        "(--target-px at the window's extreme pixels). Default: "
        + ("adaptive with --live, else " if live_default == "adaptive" else "")
        + "count (or duration with --duration)"
        + ("" if live_default == "adaptive" else "; adaptive only with --live"),
    )
    win.add_argument("--target-px", type=float, default=None, help="adaptive: displacement per window, px")
    win.add_argument("--min-events", type=int, default=None, help="adaptive: fewest events per window")
    win.add_argument("--max-events", type=int, default=None, help="adaptive: most events per window")
    win.add_argument(
        "--max-duration", type=float, default=None, metavar="S", help="adaptive: longest window, s"
    )
    parser.add_argument("--topic", default=None, help="ROS bag: the event topic (listed when ambiguous)")


def window_rule(args: argparse.Namespace, live_default: str = "adaptive"):
    """The ``adaptive=`` of ``sequence.process`` (None: count or duration windows), and for --live the
    ``windows=`` of the live run; CliError for options that do not fit together. ``live_default``: the
    mode of --live without --window-mode (``"count"``: count windows, or duration ones with --duration)."""
    from cmax_taichi.solve.adaptive import AdaptiveWindows

    mode = args.window_mode
    if mode is None:
        mode = "duration" if args.duration is not None else "count"
        if args.live and live_default == "adaptive":
            mode = "adaptive"
    given = {
        name: getattr(args, name)
        for name in ("target_px", "min_events", "max_events", "max_duration")
        if getattr(args, name) is not None
    }
    if mode != "adaptive":
        if given:
            names = ", ".join("--" + n.replace("_", "-") for n in given)
            raise CliError(f"{names}: options of --window-mode adaptive")
        if mode == "duration" and args.duration is None:
            raise CliError("--window-mode duration needs --duration S")
        if mode == "count" and args.duration is not None:
            raise CliError("--duration gives windows by time: not with --window-mode count")
        return None, (args.window if mode == "count" else args.duration)
    if args.duration is not None or args.stride is not None or getattr(args, "window_given", False):
        raise CliError(
            "adaptive windows choose their own length: not with --window, --duration or --stride "
            "(--window-mode count for windows of --window events)"
        )
    try:
        rule = AdaptiveWindows(**given)
    except (TypeError, ValueError) as exc:
        raise CliError(f"adaptive windows: {exc}") from None
    return rule, rule


# --- output --------------------------------------------------------------------------------------------
class LiveOutput:
    """OUT for a live run: checked and locked on entry, results.csv appended and flushed row by row
    (and other files as the windows come: :meth:`write_file`, :meth:`append`), the summary and the
    manifest when the run ends (:meth:`finish`).

    ``patterns``: what the run may write (relative paths, ``fnmatch`` wildcards in the file name): those
    that exist and that no cmax-taichi run wrote are refused on entry; a previous run's are removed when
    the run begins (no stale flow file beside this run's)."""

    def __init__(
        self,
        out: str | os.PathLike,
        inputs: list[Path],
        columns: list[str],
        *,
        command: str = "estimate --live",
        patterns: tuple[str, ...] = LIVE_FILES,
    ) -> None:
        self.out = Path(out)
        self.inputs = inputs
        self.columns = columns
        self.command = command
        self.patterns = patterns
        self._stack = contextlib.ExitStack()
        self._file = None
        self._writer = None
        self._appended: dict[str, object] = {}
        self.rows = 0

    def __enter__(self) -> LiveOutput:
        from cmax_taichi.io import outputs

        outputs.check_inputs(self.out, self.inputs, "--out")
        self._created = not self.out.exists()
        try:
            self.out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OSError(f"--out: cannot create {self.out} ({exc.strerror or exc})") from None
        self._stack.callback(self._remove_if_unused)
        try:
            self._stack.enter_context(outputs.hold_lock(self.out, self.command))
            outputs.refuse_foreign(self.out, self._existing(), command=self.command)
        except BaseException:
            self._stack.close()
            raise
        return self

    def _existing(self) -> list[str]:
        """The files under OUT that match the patterns (relative paths)."""
        found = {p.relative_to(self.out).as_posix() for pat in self.patterns for p in self.out.glob(pat)}
        return sorted(found)

    def begin(self) -> None:
        """Start results.csv (the header) and remove a previous run's files (ours: checked on entry).
        Called by the first output of the run (a row, a file, the summary): a run that fails before
        it leaves OUT as it was."""
        if self._file is not None:
            return
        for relative in self._existing():
            if relative != "results.csv":
                (self.out / relative).unlink(missing_ok=True)
        self._file = self._stack.enter_context((self.out / "results.csv").open("w", newline=""))
        self._writer = csv.writer(self._file)
        self._writer.writerow([*self.columns, "latency [s]"])
        self._file.flush()

    def _remove_if_unused(self) -> None:
        """A run that failed before its first row leaves no folder it created behind."""
        from cmax_taichi.io import outputs

        if self._created and self._file is None:
            with contextlib.suppress(OSError):
                (self.out / outputs.LOCK_NAME).unlink(missing_ok=True)  # the lock, when still there
                self.out.rmdir()

    def write(self, fields: list, latency: float) -> None:
        """One row, flushed at once."""
        self.begin()
        self._writer.writerow([*fields, "" if math.isnan(latency) else f"{latency:.6f}"])
        self._file.flush()
        self.rows += 1

    def write_file(self, relative: str, write) -> None:
        """A whole file ``OUT/relative``: ``write(path)`` writes it under a hidden name beside it (with
        its suffix), renamed into place when complete (a crash leaves no partial file)."""
        self.begin()
        target = self.out / relative
        target.parent.mkdir(parents=True, exist_ok=True)
        partial = target.with_name(f".{target.stem}.partial{target.suffix}")
        try:
            write(partial)
            os.replace(partial, target)
        finally:
            partial.unlink(missing_ok=True)

    def append(self, relative: str, text: str) -> None:
        """``text`` appended to ``OUT/relative`` (created by the first call of the run) and flushed."""
        self.begin()
        fh = self._appended.get(relative)
        if fh is None:
            fh = self._appended[relative] = self._stack.enter_context((self.out / relative).open("w"))
        fh.write(text)
        fh.flush()

    def finish(self, summary: dict, name: str = "results.json", with_rows: bool = True) -> list[Path]:
        """The summary ``OUT/name`` (JSON: with every row of results.csv when ``with_rows``) and the
        manifest of the files of the patterns (this run's: a previous run's were removed when it began);
        their paths, results.csv and the summary first."""
        from cmax_taichi.io import outputs

        self.begin()  # (a run that ended before its first row: the header alone)
        self._file.flush()
        for fh in self._appended.values():
            fh.flush()
        if with_rows:
            with open(self.out / "results.csv", newline="") as fh:
                reader = csv.reader(fh)
                header = next(reader)
                rows = [dict(zip(header, row, strict=True)) for row in reader]
            summary = {**summary, "windows": rows}
        text = outputs.json_text(summary, indent=1 if with_rows else 2)  # strict: NaN is null
        outputs.atomic_write_text(self.out / name, text)
        written = ["results.csv", name]
        written += [relative for relative in self._existing() if relative not in written]
        outputs.write_manifest(self.out, written, self.command)
        return [self.out / relative for relative in written]

    def __exit__(self, *exc) -> None:
        self._stack.close()


# --- display -------------------------------------------------------------------------------------------
def display_available() -> bool:
    """Whether a window can be shown: a display server, and an interactive matplotlib backend."""
    server = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    if sys.platform.startswith("linux") and not server:
        return False
    backend = os.environ.get("MPLBACKEND", "").lower()
    return backend not in ("agg", "pdf", "svg", "ps", "cairo", "template")


def draw_frame(fig, frame: dict, artists: dict) -> None:
    """Draw (or update) one frame of the display into ``fig``: the IWE before and after the estimate,
    and the parameters over the recent windows."""
    from cmax_taichi import viz

    if not artists:
        axes = fig.subplots(1, 3)
        names, units = frame["names"], frame["units"]
        artists["before"] = viz.show_iwe(axes[0], frame["identity"], title="IWE, identity warp")
        artists["after"] = viz.show_iwe(axes[1], frame["estimate"], title="IWE, estimate")
        artists["lines"] = [
            axes[2].plot([], [], ".-", label=f"{n} [{u}]")[0] for n, u in zip(names, units, strict=True)
        ]
        axes[2].legend(loc="upper left", fontsize=8)
        axes[2].set_xlabel("time (window middle) [s]")
        axes[2].set_title("parameters")
        artists["axes"] = axes
    else:
        artists["before"].set_data(frame["identity"])
        artists["after"].set_data(frame["estimate"])
    for k, line in enumerate(artists["lines"]):
        line.set_data(frame["t"], frame["theta"][k])
    artists["axes"][2].relim()
    artists["axes"][2].autoscale_view()
    fig.suptitle(frame["title"], fontsize=10)


def _display_child(conn) -> None:
    """The display process: show each frame it receives, ask for the next one, until None."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and ends this process
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(14, 4.5))
    artists: dict = {}
    conn.send("ready")
    while True:
        if conn.poll(0.05):
            frame = conn.recv()
            if frame is None:
                break
            draw_frame(fig, frame, artists)
            conn.send("ready")
        if not plt.fignum_exists(fig.number):
            break  # the user closed the window: the run goes on without it
        plt.pause(0.01)


class LiveDisplay:
    """The display process (see the module docstring): :meth:`offer` sends the latest window when the
    display is ready and a period has passed, else drops it."""

    def __init__(self) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_display_child, args=(child,), daemon=True)
        self._process.start()
        child.close()
        self._ready = False
        self._last = 0.0
        self.history: list[tuple[float, list[float]]] = []

    def offer(self, row, values, names, units, images) -> None:
        """The window of ``row`` (``t_start``, ``t_end``, ``index``, ``n_events``) done: ``values`` (one
        per name of ``names``, in ``units``) join the traces; ``images()`` (the IWE before and after the
        estimate) is called only when a frame is sent."""
        self.history = (self.history + [(0.5 * (row.t_start + row.t_end), list(values))])[-300:]
        now = time.perf_counter()
        try:
            while self._conn.poll():
                self._ready = self._conn.recv() == "ready" or self._ready
        except (EOFError, OSError):
            return  # the window was closed
        if not self._ready or now - self._last < DISPLAY_PERIOD:
            return
        identity, estimate = images()
        frame = {
            "identity": identity,
            "estimate": estimate,
            "t": [t for t, _ in self.history],
            "theta": [[v[k] for _, v in self.history] for k in range(len(names))],
            "names": tuple(names),
            "units": tuple(units),
            "title": f"window {row.index}: t = {row.t_start:.4f} .. {row.t_end:.4f} s, {row.n_events} events",
        }
        with contextlib.suppress(OSError, BrokenPipeError):
            self._conn.send(frame)
            self._ready, self._last = False, now

    def close(self) -> None:
        with contextlib.suppress(OSError, BrokenPipeError):
            self._conn.send(None)
        self._process.join(timeout=2.0)
        if self._process.is_alive():
            self._process.terminate()


# --- signals ---------------------------------------------------------------------------------------------
@contextlib.contextmanager
def graceful_stop():
    """For the block: the first Ctrl-C or SIGTERM sets the yielded event (the run ends after the window
    in flight), a second raises as usual. The event's ``signal`` attribute names the first signal."""
    stop = threading.Event()
    stop.signal = None
    previous = {}

    def handler(signum, frame):
        if stop.is_set():
            signal.signal(signum, previous[signum])
            raise KeyboardInterrupt
        stop.signal = signum
        stop.set()

    for signum in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(ValueError):  # not the main thread
            previous[signum] = signal.signal(signum, handler)
    try:
        yield stop
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


# --- the run -------------------------------------------------------------------------------------------
class LiveSource:
    """What every live command checks and opens: ``--live SOURCE`` (a path among the inputs), ``--speed``,
    ``--loops``, ``--idle-timeout``, ``--calib`` and ``--display`` (CliError before anything opens)."""

    def __init__(self, args: argparse.Namespace) -> None:
        if args.stride is not None or args.keep_tail:
            raise CliError("--live keeps the last window when it holds enough, and has no --stride")
        if not (math.isfinite(args.speed) and args.speed > 0):
            raise CliError(f"--speed must be a positive number, got {args.speed}")
        if args.loops < 1:
            raise CliError(f"--loops must be at least 1, got {args.loops}")
        timeout = args.idle_timeout
        if timeout is not None and not (math.isfinite(timeout) and timeout > 0):
            raise CliError(f"--idle-timeout must be a positive number of seconds, got {timeout}")
        self.display = display_available() if args.display is None else args.display
        if args.display and not display_available():
            raise CliError("--display: no display here ($DISPLAY unset, or a non-interactive MPLBACKEND)")
        self.args = args
        self.source = source = args.live
        is_path = not (source.startswith("tcp://") or source == "camera" or source.startswith("camera:"))
        self.inputs = [Path(source)] if is_path else []
        if is_path and not Path(source).exists():
            raise CliError(f"--live {source}: no such file or folder (nor tcp://HOST:PORT, camera)")
        self.camera = None
        if args.calib is not None:
            from cmax_taichi.io.text import read_calib

            if not Path(args.calib).is_file():
                raise CliError(f"--calib {args.calib}: no such file")
            self.camera, _ = read_calib(Path(args.calib))

    def open(self, needs_camera: str | None = None):
        """The stream (CliError when it does not open; ``needs_camera``: what needs a calibration, when
        the stream must have one)."""
        from cmax_taichi.core import limits
        from cmax_taichi.io.streams import StreamError, open_stream

        args = self.args
        size = getattr(args, "sensor_size", None)  # a replayed recording's, where the command has it
        options = {"format": args.format, "topic": args.topic, "sensor_size": size and tuple(size)}
        options = {k: v for k, v in options.items() if v is not None}
        try:
            stream = open_stream(
                self.source, speed=args.speed, loops=args.loops, camera=self.camera, **options
            )
        except (ImportError, StreamError) as exc:
            raise CliError(str(exc)) from None
        if needs_camera is not None and stream.camera is None:
            stream.close()
            raise CliError(f"{needs_camera} needs a calibration, and {self.source} has none (--calib FILE)")
        try:  # a sensor above the limits: before the banner (the run would fail at its warm-up)
            limits.check_sensor(*stream.sensor_size, f"the stream {self.source}")
        except ValueError as exc:
            stream.close()
            raise CliError(str(exc)) from None
        return stream


def drive(start, shown: LiveDisplay | None):
    """Run ``start(stop)`` (the live run, ``stop`` the event that Ctrl-C / SIGTERM set) to its end:
    ``(result, error, signal)``, ``error`` the source's failure (StreamError, its ``live_result`` the
    result), ``signal`` the signal that ended the run or None. Closes the display."""
    from cmax_taichi.io.streams import StreamError

    error = None
    try:
        with graceful_stop() as stop:
            result = start(stop)
    except StreamError as exc:
        error, result = exc, exc.live_result
    finally:
        if shown is not None:
            shown.close()
    return result, error, stop.signal


def exit_code(result, error, signum, rows: int, csv_path: Path) -> int:
    """0; 130 / 143 when Ctrl-C / SIGTERM ended the run; CliError for a source that failed."""
    if error is not None:
        raise CliError(f"{error} (the {rows} row(s) before it are in {csv_path})")
    if result.stop_reason == "stopped":
        return 143 if signum == signal.SIGTERM else 130
    return 0


def run(args: argparse.Namespace, regs: dict, process_options: dict) -> int:
    """``estimate --live``: returns the exit code (0; 130 / 143 when Ctrl-C / SIGTERM ended the run)."""
    import numpy as np

    import cmax_taichi as cm
    from cmax_taichi.solve.online import run_live
    from cmax_taichi.solve.results import SequenceResult
    from cmax_taichi.solve.warm import check_sequence_t_ref

    if args.path or args.example is not None:
        raise CliError("--live SOURCE replaces PATH and --example")
    if args.workers is not None or args.engine is not None or args.flow_out is not None:
        raise CliError("--live estimates one stream: not with --workers, --engine or --flow-out")
    _, windows = window_rule(args)
    live = LiveSource(args)
    model = cm.get_warp(args.warp)
    columns = SequenceResult(model.name, model.params, model.units).columns()
    with LiveOutput(args.out, live.inputs, columns) as out:  # OUT checked and locked before anything opens
        common_init(args)
        stream = live.open(f"warp {model.name!r}" if model.needs_camera else None)
        try:  # a numeric t_ref is for one window: refused before the banner and the first row
            check_sequence_t_ref(process_options["problem_options"].get("t_ref", "first"), args.max_windows)
        except ValueError as exc:
            stream.close()
            raise CliError(f"--t-ref: {exc}") from None
        shown = LiveDisplay() if live.display else None

        def on_window(row, prob, res, latency):
            out.write(SequenceResult.csv_row(row), latency)
            if shown is not None:
                zero = np.zeros(model.n_params)
                shown.offer(row, res.theta, model.params, model.units,
                            lambda: (prob.iwe(zero), prob.iwe(res.theta)))  # fmt: skip

        def on_skipped(row):
            out.write(SequenceResult.csv_row(row), math.nan)

        announce(stream, f"warp {model.name}", out)
        result, error, signum = drive(
            lambda stop: run_live(
                stream, model.name, objective=args.objective, regularizers=regs, camera=stream.camera,
                windows=windows, method=process_options["method"], warm_start=process_options["warm_start"],
                problem_options=process_options["problem_options"],
                optimize_options=process_options["optimize_options"], max_windows=args.max_windows,
                idle_timeout=args.idle_timeout, stop=stop, on_window=on_window, on_skipped=on_skipped,
            ),
            shown,
        )  # fmt: skip
        files = out.finish(summary(result))
    print_summary(result, [str(p) for p in files])
    return exit_code(result, error, signum, out.rows, files[0])


def announce(stream, what: str, out: LiveOutput) -> None:
    """The run's first line (stderr): the source, what is estimated, where the rows go."""
    W, H = stream.sensor_size
    print(f"live: {stream.address} ({W}x{H}), {what}, writing {out.out / 'results.csv'}; Ctrl-C ends it",
          file=sys.stderr)  # fmt: skip


def common_init(args) -> None:
    from cmax_taichi.cli import _common as common

    common.init_backend(args.arch, args.precision, getattr(args, "compile", None))


def summary(result) -> dict:
    """The summary of a live run (JSON-friendly): what was estimated, the settings, where every event
    went, and the run's figures (``live``: real-time factor, latency median and 99th percentile)."""
    return {
        "warp": result.warp,
        "params": list(result.param_names),
        "units": list(result.units),
        "settings": result.settings,
        "events": result.events,
        "live": {
            "stop_reason": result.stop_reason,
            "error": result.error,
            "windows_estimated": result.windows,
            "windows_not_estimated": result.skipped,
            "real_time_factor": result.real_time_factor(),
            "busy_seconds": result.busy_seconds,
            "data_seconds": result.data_seconds,
            "first_window_seconds": result.first_window_seconds,
            "warm_up_seconds": result.warm_up_seconds,
            "latency_median_s": result.latency(50),
            "latency_p99_s": result.latency(99),
            "last_window_latency_s": result.end_latency,
        },
    }


def print_summary(result, files: list[str]) -> None:
    """What the run did (stdout): windows, real-time factor, latency, where the events went, the files."""
    from cmax_taichi.core.windows import describe_events

    events = result.events
    left = events.get("total", 0) - events.get("estimated", 0)
    if len(result.latencies):
        median, p99 = 1e3 * result.latency(50), 1e3 * result.latency(99)
        latency = f"latency median {median:.1f} ms, 99th percentile {p99:.1f} ms"
    else:  # the end of the stream closed the only window: its wait for the end is no latency
        latency = "no latency measured (no window was closed by its own events)"
    if result.windows:
        pace = (f"real-time factor {result.real_time_factor():.2f} (first window included: "
                f"{result.first_window_seconds:.3f} s); ")  # fmt: skip
    else:
        pace = "no real-time factor (no window estimated); "
    done = f"{result.windows} window(s) estimated, {result.skipped} not ({result.stop_reason}); "
    print(done + pace + latency)
    note = f"; {left} not estimated ({describe_events(events)})" if left else ""
    print(f"  events: {events.get('estimated', 0)} of {events.get('total', 0)} estimated{note}")
    print("wrote: " + ", ".join(files))
    sys.stdout.flush()
