"""Estimate the motion of every window of an event recording by Contrast Maximization.

The recording is read window by window (30,000 events per window by default, or --duration seconds);
each window's warp parameters are found by a global search and gradient ascent, warm-started from the
previous window. Results go to OUT/results.csv, OUT/results.json and OUT/results.h5 (one row per window:
time span, event count, parameters in physical units, objective value, FWL, iterations, seconds, events
dropped, status: windows that could not be estimated have a row too), figures to OUT/figures/ (IWE
before and after, flow colours; parameters over time); with --flow-out, each window's dense flow
(displacement over the window, px) as a Middlebury .flo or .npz file. Events not estimated (the partial
last window, outside the sensor, ...) are counted in one warning at the end.

OUT is never the recording nor a folder that holds it, files there that no cmax-taichi run wrote are
never replaced, and everything appears in OUT only when the run completes (a Ctrl-C leaves OUT as it
was); a second run on the same OUT is refused while the first runs.

examples:
  cmax-taichi estimate --example rotation --out out_rotation   # simulated on the fly, against its truth
  cmax-taichi estimate --example collapse --reg divergence=10 --reg deformation=10
  cmax-taichi estimate ../shared/data/ecd_rotation/boxes_rotation --warp rotation3 --out out_boxes
  cmax-taichi estimate recording_data.hdf5 --warp mitrokhin4 --objective variance \\
      --reg divergence=10 --reg deformation=10 --window 30000 --arch cpu --out out_mvsec
  cmax-taichi evaluate out_boxes          # then compare against the recording's ground truth
  cmax-taichi estimate recording.raw --window 50000 --flow-out out_raw/flow --flow-format flo
  cmax-taichi estimate rec_a rec_b rec_c --workers 2 --out out_batch   # several recordings at once:
      # OUT/<name>/results.csv each, OUT/summary.csv; a re-run skips the windows already written
  cmax-taichi estimate rec_* --engine ray --address auto --workers 16 --out /shared/out  (docs/BATCH.md)
  cmax-taichi estimate --live tcp://127.0.0.1:7777 --out out_live   # while the camera records: rows
      # appended as they come, motion-adaptive windows, a live display (docs/live.md)
  cmax-taichi estimate recording.bag --topic /dvs/events --window-mode adaptive --out out_bag
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import math
import signal
import sys
import time
from pathlib import Path

from cmax_taichi.cli import _common as common
from cmax_taichi.cli import _live
from cmax_taichi.core.windows import describe_events
from cmax_taichi.models.regularizers import RECOMMENDED_LAMBDA
from cmax_taichi.pipeline.problem import POLARITY_MODES
from cmax_taichi.solve.optimize import INITS, METHODS

NAME = "estimate"
HELP = "estimate the motion of every window of a recording (results as CSV/JSON, figures)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    from cmax_taichi.sim.examples import EXAMPLES

    lam = RECOMMENDED_LAMBDA
    common.add_recording_arguments(
        parser,
        warp_default="translation2",
        warp_help="motion model",
        reg_help=f"add a regularizer with weight lambda, e.g. --reg divergence={lam:g} "
        f"--reg deformation={lam:g} ({lam:g} = cmax_taichi.RECOMMENDED_LAMBDA, the weight that prevented "
        "every collapse on the MVSEC cut)",
        path_nargs="*",
        path_note=" (several: a batch, see --workers)",
        examples=EXAMPLES,
    )
    parser.add_argument(
        "--whitening", action="store_true", help="whitening baseline (whitened warped events)"
    )
    common.add_window_arguments(parser)
    opt = parser.add_argument_group("optimizer")
    opt.add_argument("--method", default="bfgs", help=f"{common.names(METHODS)} (default bfgs)")
    opt.add_argument(
        "--init",
        default="auto",
        help=f"{common.names(INITS)} (default auto: pyramid, then warm)",
    )
    opt.add_argument("--n-init", type=int, default=None, help="evaluations of the global search")
    opt.add_argument("--no-warm-start", action="store_true", help="global search in every window")
    img = parser.add_argument_group("image of warped events")
    img.add_argument("--blur", type=float, default=1.0, help="Gaussian blur sigma, px (default 1, 0 = none)")
    common.add_t_ref_argument(img)
    img.add_argument("--polarity", default="ignore", help=f"{common.names(POLARITY_MODES)} (default ignore)")
    run = parser.add_argument_group("run")
    common.add_backend_arguments(run)
    run.add_argument("--out", default="cmax_out", metavar="DIR", help="output folder (default ./cmax_out)")
    run.add_argument(
        "--figures", type=int, default=1, metavar="K", help="figures of the first K windows (default 1)"
    )
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    many = parser.add_argument_group(
        "several recordings (batch: OUT/<name>/ per recording, OUT/summary.csv, resumable; docs/BATCH.md)"
    )
    many.add_argument(
        "--workers", type=int, default=None, metavar="N", help="recordings estimated at once (default 1)"
    )
    many.add_argument(
        "--engine",
        default=None,
        choices=["local", "ray"],
        help="local: worker processes on this machine (default); ray: Ray actors (pip install .[ray])",
    )
    many.add_argument(
        "--address", default=None, metavar="ADDR", help="Ray cluster address (e.g. auto); with --engine ray"
    )

    run.add_argument(
        "--flow-out",
        default=None,
        metavar="DIR",
        help="write each window's dense flow (displacement over the window, px) to DIR/flow_NNNN.<format>",
    )
    run.add_argument(
        "--flow-format",
        default="flo",
        choices=["flo", "npz"],
        help="flo: Middlebury (u, v float32); npz: 'flow' (2, H, W) with t_start, t_end (default flo)",
    )
    _live.add_arguments(parser)


def check_choices(args: argparse.Namespace) -> None:
    """Validate names before any data is read (one-line errors)."""
    import cmax_taichi as cm
    from cmax_taichi.cli import CliError

    cm.get_warp(args.warp)  # ValueError listing the valid names
    cm.OBJECTIVES.get(args.objective)
    if args.method not in METHODS:
        raise CliError(f"--method: unknown method {args.method!r}; valid: {', '.join(METHODS)}")
    if args.init not in INITS:
        raise CliError(f"--init: unknown init {args.init!r}; valid: {', '.join(INITS)}")
    common.check_windows(args)
    common.parse_t_ref(args.t_ref)
    if args.figures < 0:
        raise CliError(f"--figures must be a number of windows >= 0, got {args.figures}")


#: what a single run may write into OUT (paths relative to it; see cmax_taichi.io.outputs)
OUTPUT_PATTERNS = (
    "results.csv",
    "results.json",
    "results.h5",
    "figures/window_*.png",
    "figures/parameters.png",
    "truth.json",
)
FLOW_PATTERNS = ("flow_*.flo", "flow_*.npz")


def _save_figure(fig, path: Path, dpi: int) -> None:
    """``fig`` to ``path`` through a temporary name renamed when complete (never a half-written PNG)."""
    from cmax_taichi.io.outputs import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png")


def _figure(width: float, height: float):
    """A matplotlib figure drawn by the Agg canvas directly: no pyplot (its import and backend
    machinery are a third of a figure's cost on the command line), nothing left open."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    return fig


def _window_figure_data(row, prob, res) -> dict:
    """What the figure of a window shows (computed with the window's problem, drawn anywhere)."""
    import numpy as np

    model = prob.model
    params = ", ".join(
        f"{n}={v:.4g} {u}" for n, v, u in zip(model.params, res.theta, model.units, strict=True)
    )
    return {
        "identity": prob.iwe(np.zeros(model.n_params)),
        "estimate": prob.iwe(res.theta),
        "flow": prob.dense_flow(res.theta),
        "value": float(res.value),
        "warp": model.name,
        "title": f"window {row.index}: t = {row.t_start:.4f} .. {row.t_end:.4f} s, {row.n_events} events; "
        f"{params}",
    }


def _draw_window_figure(path: Path, data: dict) -> None:
    from cmax_taichi import viz

    fig = _figure(16, 4.6)
    axes = fig.subplots(1, 3)
    # fixed margins: the constrained layout engine took a third of the figure's time
    fig.subplots_adjust(left=0.035, right=0.965, bottom=0.08, top=0.86, wspace=0.42)
    viz.show_iwe(axes[0], data["identity"], title="IWE, identity warp (no motion)")
    viz.show_iwe(axes[1], data["estimate"], title=f"IWE, estimate (J = {data['value']:.3f})")
    viz.show_flow(axes[2], data["flow"], unit="px/s", title=f"Flow of the estimate ({data['warp']})")
    fig.suptitle(data["title"], fontsize=10)
    _save_figure(fig, path, dpi=90)


def _window_figure(path: Path, row, prob, res) -> None:
    _draw_window_figure(path, _window_figure_data(row, prob, res))


def _write_window_flow(path: Path, row, prob, res, fingerprint: str | None = None) -> None:
    """The dense flow of a window's estimate: the displacement (px) over the window's time span (an .npz
    file also carries the recording's fingerprint, which evaluate checks --data against)."""
    from cmax_taichi.io.writers import write_flow

    flow = prob.dense_flow(res.theta, dt=row.t_end - row.t_start)
    meta = {"t_start": row.t_start, "t_end": row.t_end, "window": row.index, "warp": prob.model.name}
    if fingerprint:
        meta["fingerprint"] = fingerprint
    write_flow(path, flow, unit="px", **meta)


def _parameters_figure_data(result) -> dict:
    return {
        "t": result.t_mid,
        "theta": result.theta,
        "fwl": [w.fwl for w in result.windows],
        "names": result.param_names,
        "units": result.units,
        "warp": result.warp,
    }


def _draw_parameters_figure(path: Path, data: dict) -> None:
    P = len(data["names"])
    fig = _figure(8, 1.8 * (P + 1))
    axes = fig.subplots(P + 1, 1, sharex=True)
    fig.subplots_adjust(left=0.14, right=0.97, bottom=0.3 / (P + 1), top=1 - 0.25 / (P + 1), hspace=0.15)
    t, theta = data["t"], data["theta"]
    for i, (name, unit) in enumerate(zip(data["names"], data["units"], strict=True)):
        axes[i].plot(t, theta[:, i], ".-")
        axes[i].set_ylabel(f"{name} [{unit}]")
        axes[i].grid(alpha=0.3)
    axes[P].plot(t, data["fwl"], ".-", color="C1")
    axes[P].set_ylabel("FWL")
    axes[P].set_xlabel("time (window middle) [s]")
    axes[P].grid(alpha=0.3)
    axes[0].set_title(f"{data['warp']} estimates per window")
    _save_figure(fig, path, dpi=90)


def _parameters_figure(path: Path, result) -> None:
    _draw_parameters_figure(path, _parameters_figure_data(result))


def _warm_up_drawing() -> None:
    """A small figure drawn into memory and dropped: the viz module, the fonts, the text layout caches
    and the PNG writer are then ready when the first window's figure arrives (they took 0.25 s of a
    first figure's 0.7 s, while the figure process is otherwise idle)."""
    import io

    import numpy as np

    from cmax_taichi import viz

    fig = _figure(3, 1.5)
    axes = fig.subplots(1, 2)
    viz.show_iwe(axes[0], np.zeros((8, 8)), title="warm-up (0)")
    viz.show_flow(axes[1], np.zeros((2, 8, 8)), unit="px/s", title="warm-up")
    fig.suptitle("warm-up", fontsize=10)
    fig.savefig(io.BytesIO(), dpi=30, format="png")


_DRAW = {"window": _draw_window_figure, "parameters": _draw_parameters_figure}


def _figure_worker(conn) -> None:
    """The figure process: import matplotlib at once (while the estimate runs), then draw each
    ``(kind, path, data)`` it receives until None; send back the list of errors."""
    # The fork inherited the command's SIGTERM handler (raise in the main thread): the parent, which
    # owns the outputs, decides; this child ends quietly when terminated and ignores the terminal's
    # Ctrl-C (the parent handles it and terminates the child).
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import matplotlib.backends.backend_agg  # noqa: F401 - the import is the point: it runs in parallel
    import matplotlib.figure  # noqa: F401

    with contextlib.suppress(Exception):  # only a head start: a failure shows in the real figures
        _warm_up_drawing()
    errors = []
    while True:
        job = conn.recv()
        if job is None:
            break
        kind, path, data = job
        try:
            _DRAW[kind](path, data)
        except Exception as exc:  # reported by the parent, which then draws nothing more
            errors.append(f"{path}: {type(exc).__name__}: {exc}")
    conn.send(errors)
    conn.close()


class FigureWriter:
    """Draws the command's figures in a child process where the platform can fork and Taichi has not
    started yet (else in this process).

    matplotlib's import and the drawing took 1.2 s of CPU time of a 38,000-event run whose estimate
    takes about as long: forked before the backend starts (no Taichi thread exists yet), the child
    imports matplotlib on the other core while the problem is built and solved, and draws each figure
    while the results are written. :meth:`close` waits for it and raises CliError if a figure failed.
    """

    def __init__(self) -> None:
        import multiprocessing

        from cmax_taichi.core import backend

        self._conn = self._process = None
        self._sent = 0  # figures sent to the child
        self._errors: list[str] = []  # of the figures drawn in this process
        # fork only a process without Taichi's thread pool (a thread holding a lock at the fork would
        # leave it held in the child): the command forks before it starts the backend
        if "fork" not in multiprocessing.get_all_start_methods() or backend.is_initialized():
            return
        ctx = multiprocessing.get_context("fork")
        sys.stdout.flush()  # the child flushes its copy of the buffers when it ends: empty them first
        sys.stderr.flush()
        parent, child = ctx.Pipe()
        self._process = ctx.Process(target=_figure_worker, args=(child,), daemon=True)
        self._process.start()
        child.close()
        self._conn = parent

    def draw(self, kind: str, path: Path, data: dict) -> None:
        if self._conn is not None:
            try:
                self._conn.send((kind, path, data))
                self._sent += 1
                return
            except OSError:  # the child is gone: draw here from now on
                self._conn = None
        try:
            _DRAW[kind](path, data)
        except Exception as exc:  # one error line at close(), as from the child
            self._errors.append(f"{path}: {type(exc).__name__}: {exc}")

    def close(self) -> None:
        from cmax_taichi.cli import CliError

        errors, self._errors = self._errors, []
        if self._conn is not None and not self._sent:  # nothing to draw: not waiting for its warm-up
            self.abandon()
        if self._conn is not None:
            conn, self._conn = self._conn, None
            try:
                conn.send(None)
                errors += conn.recv()
            except (OSError, EOFError):
                errors.append("the figure process ended before drawing every figure")
            conn.close()
            self._process.join(timeout=60)
        if errors:
            raise CliError("figures: " + "; ".join(errors))

    def abandon(self) -> None:
        """Stop the child without waiting for its figures (the run failed, or it has nothing to draw)."""
        if self._process is not None and self._process.is_alive():
            self._process.terminate()
            self._process.join(timeout=5)
        self._conn = None


def process_options(args: argparse.Namespace, regs: dict[str, float]) -> dict:
    """Keyword arguments of ``sequence.process`` (and ``solve.batch.run``) from the command line."""
    t_ref = common.parse_t_ref(args.t_ref)
    stride = common.window_stride(args)
    adaptive, _ = _live.window_rule(args)
    optimize_options = {}
    if args.init != "auto":
        optimize_options["init"] = args.init
    if args.n_init is not None:
        optimize_options["n_init"] = args.n_init
    return {
        "warp": args.warp,
        "objective": args.objective,
        "regularizers": regs,
        "n_events": args.window,
        "duration": args.duration,
        "stride": stride,
        "method": args.method,
        "warm_start": not args.no_warm_start,
        "max_windows": args.max_windows,
        "keep_tail": args.keep_tail,
        "problem_options": {
            "blur_sigma": args.blur,
            "t_ref": t_ref,
            "polarity": args.polarity,
            "whitening": args.whitening,
        },
        "optimize_options": optimize_options,
        **({"adaptive": adaptive} if adaptive is not None else {}),
    }


class BatchFigures:
    """The figures of a single run, made inside each batch worker (module level, so that it pickles)."""

    def __init__(self, first_windows: int) -> None:
        self.first_windows = first_windows

    def window(self, folder: Path, row, prob, res) -> None:
        if row.index < self.first_windows:
            (folder / "figures").mkdir(exist_ok=True)
            _window_figure(folder / "figures" / f"window_{row.index:04d}.png", row, prob, res)

    def finished(self, folder: Path, result) -> list[Path]:
        if len(result.windows) < 2:
            return []
        (folder / "figures").mkdir(exist_ok=True)
        _parameters_figure(folder / "figures" / "parameters.png", result)
        return [folder / "figures" / "parameters.png"]


def run_batch(args: argparse.Namespace) -> int:
    """Several recordings (or --workers / --engine): delegate to cmax_taichi.solve.batch."""
    from cmax_taichi.cli import CliError
    from cmax_taichi.solve import batch

    regs = common.parse_regularizers(args.reg)
    check_choices(args)
    if args.example is not None:
        raise CliError("--example estimates one simulated recording: not with --workers / --engine / PATHs")
    if args.flow_out is not None:
        raise CliError("--flow-out writes the flow of one recording: run the recordings one by one for it")
    if args.window_mode == "adaptive":
        raise CliError("--window-mode adaptive estimates one recording: run the recordings one by one for it")
    if args.address is not None and args.engine != "ray":
        raise CliError("--address is a Ray cluster address: it needs --engine ray")
    if args.engine == "ray" and importlib.util.find_spec("ray") is None:
        raise CliError('--engine ray needs Ray: pip install "cmax-taichi[ray]" (or pip install ray)')
    workers = 1 if args.workers is None else args.workers
    if workers < 1:
        raise CliError(f"--workers must be at least 1, got {workers}")
    for p in args.path:
        if not Path(p).exists():
            raise CliError(f"{p}: no such file or folder")
    result = batch.run(
        args.path,
        args.out,
        workers=workers,
        engine=args.engine or "local",
        address=args.address,
        format=args.format,
        arch=args.arch,
        precision=args.precision,
        progress=not args.quiet,
        hooks=BatchFigures(max(0, args.figures)),
        plugins=args.plugin,
        **process_options(args, regs),
    )
    done = len(result.recordings) - len(result.failed)
    print(
        f"{done} of {len(result.recordings)} recording(s) done in {result.wall_seconds:.1f} s "
        f"({result.engine} engine, {result.workers} worker(s)), warp {args.warp}"
    )
    for rec in result.recordings:
        resumed = f", resumed at window {rec.resumed_from}" if rec.resumed_from else ""
        if rec.new_windows == 0:
            resumed = " (already complete)"
        state = f"{rec.windows} window(s), {rec.new_windows} new{resumed}"
        if rec.not_estimated:
            state += f"; {rec.not_estimated} of {rec.events} event(s) not estimated"
        state = state if rec.status == "done" else f"FAILED: {rec.error}"
        print(f"  {rec.name}: {state}")
    print(f"wrote: {result.summary_csv}, {result.windows_csv}, {result.out}/<recording>/results.csv")
    sys.stdout.flush()
    if result.failed:
        print(
            f"estimate: error: {len(result.failed)} recording(s) failed: "
            + "; ".join(f"{r.name}: {r.error}" for r in result.failed),
            file=sys.stderr,
        )
        return 1
    return 0


def run(args: argparse.Namespace) -> int:
    import cmax_taichi as cm
    from cmax_taichi.cli import CliError
    from cmax_taichi.metrics import area_scale
    from cmax_taichi.solve.sequence import process

    regs = common.parse_regularizers(args.reg)
    if args.live is not None:
        args.warp = args.warp or "translation2"
        check_choices(args)
        return _live.run(args, regs, process_options(args, regs))
    if args.example is not None:
        if args.path:
            raise CliError("give a recording PATH or --example NAME, not both")
        from cmax_taichi.sim.examples import EXAMPLES

        if args.example not in EXAMPLES:
            raise CliError(f"--example: unknown example {args.example!r}; valid: {', '.join(EXAMPLES)}")
        args.warp = args.warp or EXAMPLES[args.example].warp
        if args.duration is None:
            args.duration = EXAMPLES[args.example].window
    elif not args.path:
        raise CliError("give a recording PATH, or --example NAME for a simulated one")
    args.warp = args.warp or "translation2"
    if len(args.path) > 1 or args.workers is not None or args.engine is not None or args.address is not None:
        return run_batch(args)
    check_choices(args)
    if args.example is not None:  # the example's truth against the model, before anything is simulated
        from cmax_taichi.sim.examples import check_example

        check_example(args.example, args.warp)
    inputs = [] if args.example is not None else [Path(args.path[0])]
    if inputs and not inputs[0].exists():
        raise CliError(f"{inputs[0]}: no such file or folder")
    out_folders = _output_folders(args, inputs)  # refuses, before any work, an OUT that would touch inputs
    figures = FigureWriter()  # before the backend starts: see FigureWriter
    try:
        common.init_backend(args.arch, args.precision, args.compile)
        unique = list(dict.fromkeys(out_folders))  # the flow folder may be OUT itself
        with contextlib.ExitStack() as stack:
            for f in unique:
                stack.enter_context(f)  # lock, checks, staging
            # on the way out, the figure child stops before the folders remove their staging: a child
            # still saving a PNG into it would leave the staging (and so OUT) behind
            stack.callback(figures.abandon)
            folder, flow_folder = out_folders[0], (out_folders[-1] if args.flow_out is not None else None)
            written = _estimate_one(
                args, regs, folder, flow_folder, process, area_scale, cm, CliError, figures
            )
            final = []
            for f in unique:
                final += f.commit()  # every file moved into place whole, now that the run is complete
    except BaseException:
        figures.abandon()
        raise
    if written["flows"]:
        flow_dir = out_folders[-1].out
        final = [p for p in final if p.parent != flow_dir or not p.name.startswith("flow_")]
        final.append(Path(flow_dir) / f"flow_*.{args.flow_format} ({written['flows']} files)")
    print("wrote: " + ", ".join(str(p) for p in final))
    sys.stdout.flush()
    return 0


def _output_folders(args: argparse.Namespace, inputs: list[Path]) -> list:
    """The OutputFolder of --out, and the one of --flow-out when it is another folder; both checked
    against the inputs now (one line, exit 2)."""
    from cmax_taichi.io.outputs import OutputFolder, check_inputs

    patterns = list(OUTPUT_PATTERNS)
    same = args.flow_out is not None and Path(args.flow_out).resolve() == Path(args.out).resolve()
    if same:
        patterns += FLOW_PATTERNS
    folders = [OutputFolder(args.out, inputs=inputs, patterns=patterns, command="estimate")]
    check_inputs(args.out, inputs, "--out")
    if args.flow_out is not None and not same:
        check_inputs(args.flow_out, inputs, "--flow-out")
        folders.append(
            OutputFolder(
                args.flow_out, inputs=inputs, patterns=FLOW_PATTERNS, command="estimate --flow-out",
                option="--flow-out",
            )
        )  # fmt: skip
    elif same:
        folders.append(folders[0])
    return folders


def _estimate_one(args, regs, folder, flow_folder, process, area_scale, cm, CliError, figures) -> dict:  # noqa: N803
    """Estimate the one recording (or example) of ``args`` into the staging folder of ``folder``
    (and ``flow_folder``), its figures drawn by ``figures`` (a FigureWriter, closed here: every figure
    is in the staging folder on return); prints the summary; returns ``{"flows": number of flow
    files}``."""
    from cmax_taichi import io

    example = None
    if args.example is not None:
        from cmax_taichi.sim.examples import make_example

        example = make_example(args.example)
        truth = example.truth_in(args.warp)
        path = Path(f"example:{args.example}")
        source = contextlib.nullcontext(example.events)
        camera = example.camera
    else:
        path = Path(args.path[0])
        source = io.open_recording(path, format=args.format, **({"topic": args.topic} if args.topic else {}))
        camera = None
    # per window, for the examples: the mean area scale of the warp at the estimate (a collapse
    # shrinks the events' neighbourhoods towards points: it drives the scale towards 0)
    area_scales: list[tuple[float, float]] = []  # (estimate, truth)
    flows = [0]
    with source as rec:
        camera = camera if camera is not None else rec.camera
        if cm.get_warp(args.warp).needs_camera and camera is None:
            raise CliError(f"warp {args.warp!r} needs a calibration, and {path} has none (calib.txt)")
        figures_left = [max(0, args.figures)]
        fingerprint = rec.fingerprint() if flow_folder is not None and example is None else None
        first, started = [True], time.perf_counter()

        def on_window(row, prob, res):
            if first[0]:  # the first result as soon as it is there
                first[0] = False
                _print_first_window(row, prob, started)
            if example is not None:
                area_scales.append((area_scale(prob, res.theta), area_scale(prob, truth)))
            if figures_left[0] > 0:
                data = _window_figure_data(row, prob, res)
                figures.draw("window", folder.path(f"figures/window_{row.index:04d}.png"), data)
                figures_left[0] -= 1
            if flow_folder is not None:
                name = f"flow_{row.index:04d}.{args.flow_format}"
                _write_window_flow(flow_folder.path(name), row, prob, res, fingerprint)
                flows[0] += 1

        with common.held_drop_warnings() as held:
            result = process(
                rec, **process_options(args, regs), camera=camera, progress=not args.quiet,
                on_window=on_window,
            )  # fmt: skip
    if not result.windows:  # one line: the error says why, with the counts the held warning has
        raise CliError(f"{path}: no window to estimate: {common.why_no_window(args, result.events)}")
    common.show_warnings(held)
    result.to_csv(folder.path("results.csv"))
    result.to_json(folder.path("results.json"))
    result.to_hdf5(folder.path("results.h5"))
    if len(result.windows) > 1:
        figures.draw("parameters", folder.path("figures/parameters.png"), _parameters_figure_data(result))
    theta = result.theta
    print(f"{len(result.windows)} window(s) of {path}, warp {result.warp}, objective {args.objective}")
    for i, (name, unit) in enumerate(zip(result.param_names, result.units, strict=True)):
        print(f"  {name}: median {float(_median(theta[:, i])):.6g} {unit}")
    evaluations = [w.evaluations for w in result.windows[1:]]
    if evaluations:
        print(
            f"  speed: real-time factor {result.real_time_factor():.2f} (seconds of data per second, "
            f"without the first window: {result.windows[0].seconds:.2f} s with compilation); "
            f"median {_median(evaluations):.0f} evaluations per warm-started window"
        )
    fwls = [w.fwl for w in result.windows if math.isfinite(w.fwl)]
    if fwls:
        print(f"  FWL: median {_median(fwls):.4f}")
    events = result.events
    if events.get("total"):
        left = events["total"] - events["estimated"]
        count_windows = args.window if args.duration is None and args.window_mode != "adaptive" else None
        reasons = describe_events(events, count_windows, args.max_windows)
        note = f"; {left} not estimated ({reasons}; {len(result.skipped)} window(s) skipped)" if left else ""
        print(f"  events: {events['estimated']} of {events['total']} estimated{note}")
    if example is not None:
        _report_example(example, result, area_scales, regs, folder.path("truth.json"))
    figures.close()
    return {"flows": flows[0]}


def _print_first_window(row, prob, started: float) -> None:
    """The first window's estimate, as soon as it is done (above a progress bar, if one is drawn)."""
    from tqdm import tqdm

    model = prob.model
    values = zip(model.params, row.theta, model.units, strict=True)
    params = ", ".join(f"{name} {value:.4g} {unit}" for name, value, unit in values)
    kernels = {"fast": "quick kernels", "full": "optimized kernels", "chain": "generic kernels"}[prob.kernels]
    tqdm.write(
        f"first window ({row.n_events} events, {row.t_start:.4f}-{row.t_end:.4f} s): {params} "
        f"({time.perf_counter() - started:.1f} s, {kernels})",
        file=sys.stdout,
    )
    sys.stdout.flush()


def _report_example(example, result, area_scales: list[tuple[float, float]], regs: dict, path: Path) -> Path:
    """Print the estimates of a simulated example against its truth; write them to ``path`` (JSON)."""
    import numpy as np

    from cmax_taichi.io.outputs import json_text
    from cmax_taichi.metrics import COLLAPSE_AREA_SCALE

    truth = example.truth_in(result.warp)
    theta = result.theta
    print(f"example {example.example.name!r}: {example.example.description}")
    print(f"  simulated: {len(example.events)} events, {example.events.duration * 1e3:.1f} ms (seed 0)")
    print(f"  {'parameter':<12}{'truth':>12}{'estimate (median)':>20}{'error':>12}")
    rows = []
    for i, (name, unit) in enumerate(zip(result.param_names, result.units, strict=True)):
        est = float(np.median(theta[:, i]))
        err = est - float(truth[i])
        rows.append(
            {"parameter": name, "unit": unit, "truth": float(truth[i]), "estimate": est, "error": err}
        )
        print(f"  {name + ' [' + unit + ']':<12}{truth[i]:>12.4g}{est:>20.4g}{err:>+12.3g}")
    scales = np.array(area_scales, dtype=np.float64).reshape(-1, 2)
    collapsed = [bool(c < COLLAPSE_AREA_SCALE) for c in scales[:, 0]]
    print(
        "  mean area scale |det dx'/dx| of the warp over the events (median over windows): "
        f"{np.median(scales[:, 0]):.3f} at the estimate, {np.median(scales[:, 1]):.3f} at the truth\n"
        f"  collapsed windows (scale below {COLLAPSE_AREA_SCALE}): {sum(collapsed)} of {len(collapsed)}"
        + ("  (try --reg divergence=10 --reg deformation=10)" if any(collapsed) and not regs else "")
    )
    report = {
        "example": example.example.name,
        "description": example.example.description,
        "warp": result.warp,
        "regularizers": regs,
        "parameters": rows,
        "area_scale_estimate": scales[:, 0].tolist(),
        "area_scale_truth": scales[:, 1].tolist(),
        "collapsed_windows": int(sum(collapsed)),
        "windows": len(collapsed),
    }
    path.write_text(json_text(report, indent=2))
    return path


def _median(values) -> float:
    import numpy as np

    return float(np.median(np.asarray(values, dtype=np.float64)))
