"""Estimate the motion of every window of an event recording by Contrast Maximization.

The recording is read window by window (30,000 events per window by default, or --duration seconds);
each window's warp parameters are found by a global search and gradient ascent, warm-started from the
previous window. Results go to OUT/results.csv, OUT/results.json and OUT/results.h5 (one row per window:
time span, event count, parameters in physical units, objective value, FWL, iterations, seconds),
figures to OUT/figures/ (IWE before and after, flow colours; parameters over time); with --flow-out,
each window's dense flow (displacement over the window, px) as a Middlebury .flo or .npz file.

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
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import math
import sys
from pathlib import Path

from cmax_taichi.cli import _common as common
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
    win = parser.add_argument_group("windows")
    win.add_argument(
        "--window", type=int, default=30000, metavar="N", help="events per window (default 30000)"
    )
    win.add_argument(
        "--duration", type=float, default=None, metavar="S", help="window length in seconds instead"
    )
    win.add_argument(
        "--stride", type=float, default=None, help="start-to-start step (events, or s with --duration)"
    )
    win.add_argument("--max-windows", type=int, default=None, metavar="K", help="stop after K windows")
    opt = parser.add_argument_group("optimizer")
    opt.add_argument("--method", default="adam", help=f"{common.names(METHODS)} (default adam)")
    opt.add_argument(
        "--init",
        default="auto",
        help=f"{common.names(INITS)} (default auto: grid, then warm)",
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
    if args.window < 2:
        raise CliError(f"--window must be at least 2 events, got {args.window}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise CliError(f"--duration must be a positive number of seconds, got {args.duration}")
    if args.stride is not None:
        if args.duration is not None:
            if not (math.isfinite(args.stride) and args.stride > 0):
                raise CliError(f"--stride must be a positive number of seconds, got {args.stride:g}")
        elif not (math.isfinite(args.stride) and args.stride >= 1 and args.stride == math.floor(args.stride)):
            raise CliError(
                f"--stride must be a whole number of events >= 1 (or seconds with --duration), "
                f"got {args.stride:g}"
            )
    if args.max_windows is not None and args.max_windows < 1:
        raise CliError(f"--max-windows must be at least 1, got {args.max_windows}")
    common.parse_t_ref(args.t_ref)


def _window_figure(path: Path, row, prob, res) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from cmax_taichi import viz

    model = prob.model
    params = ", ".join(
        f"{n}={v:.4g} {u}" for n, v, u in zip(model.params, res.theta, model.units, strict=True)
    )
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6), constrained_layout=True)
    viz.show_iwe(axes[0], prob.iwe(np.zeros(model.n_params)), title="IWE, identity warp (no motion)")
    viz.show_iwe(axes[1], prob.iwe(res.theta), title=f"IWE, estimate (J = {res.value:.3f})")
    flow = prob.dense_flow(res.theta)
    viz.show_flow(axes[2], flow, unit="px/s", title=f"Flow of the estimate ({model.name})")
    fig.suptitle(
        f"window {row.index}: t = {row.t_start:.4f} .. {row.t_end:.4f} s, {row.n_events} events; {params}",
        fontsize=10,
    )
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _flow_dir(flow_out: str | None) -> Path | None:
    """The --flow-out folder, created (CliError when it cannot be)."""
    from cmax_taichi.cli import CliError

    if flow_out is None:
        return None
    flow_dir = Path(flow_out)
    try:
        flow_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"--flow-out: cannot create {flow_dir} ({exc.strerror or exc})") from None
    return flow_dir


def _write_window_flow(path: Path, row, prob, res) -> None:
    """The dense flow of a window's estimate: the displacement (px) over the window's time span."""
    from cmax_taichi.io.writers import write_flow

    flow = prob.dense_flow(res.theta, dt=row.t_end - row.t_start)
    meta = {"t_start": row.t_start, "t_end": row.t_end, "window": row.index, "warp": prob.model.name}
    write_flow(path, flow, unit="px", **meta)


def _parameters_figure(path: Path, result) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = len(result.param_names)
    fig, axes = plt.subplots(P + 1, 1, figsize=(8, 1.8 * (P + 1)), sharex=True, constrained_layout=True)
    t = result.t_mid
    theta = result.theta
    for i, (name, unit) in enumerate(zip(result.param_names, result.units, strict=True)):
        axes[i].plot(t, theta[:, i], ".-")
        axes[i].set_ylabel(f"{name} [{unit}]")
        axes[i].grid(alpha=0.3)
    axes[P].plot(t, [w.fwl for w in result.windows], ".-", color="C1")
    axes[P].set_ylabel("FWL")
    axes[P].set_xlabel("time (window middle) [s]")
    axes[P].grid(alpha=0.3)
    axes[0].set_title(f"{result.warp} estimates per window")
    fig.savefig(path, dpi=90)
    plt.close(fig)


def process_options(args: argparse.Namespace, regs: dict[str, float]) -> dict:
    """Keyword arguments of ``sequence.process`` (and ``solve.batch.run``) from the command line."""
    t_ref = common.parse_t_ref(args.t_ref)
    stride = None
    if args.stride is not None:
        stride = args.stride if args.duration is not None else int(args.stride)
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
        "problem_options": {
            "blur_sigma": args.blur,
            "t_ref": t_ref,
            "polarity": args.polarity,
            "whitening": args.whitening,
        },
        "optimize_options": optimize_options,
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
    example = None
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
    from cmax_taichi import io

    common.init_backend(args.arch, args.precision)
    if args.example is not None:
        from cmax_taichi.sim.examples import make_example

        example = make_example(args.example)
        truth = example.truth_in(args.warp)
        path = Path(f"example:{args.example}")
        source = contextlib.nullcontext(example.events)
        camera = example.camera
    else:
        path = Path(args.path[0])
        if not path.exists():
            raise CliError(f"{path}: no such file or folder")
        source = io.open_recording(path, format=args.format)
        camera = None
    out = Path(args.out)
    fig_dir = out / "figures"
    # per window, for the examples: the mean area scale of the warp at the estimate (a collapse
    # shrinks the events' neighbourhoods towards points: it drives the scale towards 0)
    area_scales: list[tuple[float, float]] = []  # (estimate, truth)
    with source as rec:
        n_events = len(rec) if example is not None else rec.n_events
        camera = camera if camera is not None else rec.camera
        if cm.get_warp(args.warp).needs_camera and camera is None:
            raise CliError(f"warp {args.warp!r} needs a calibration, and {path} has none (calib.txt)")
        out.mkdir(parents=True, exist_ok=True)
        flow_dir = _flow_dir(args.flow_out)
        figures_left = [max(0, args.figures)]

        def on_window(row, prob, res):
            if example is not None:
                area_scales.append((area_scale(prob, res.theta), area_scale(prob, truth)))
            if figures_left[0] > 0:
                fig_dir.mkdir(exist_ok=True)
                _window_figure(fig_dir / f"window_{row.index:04d}.png", row, prob, res)
                figures_left[0] -= 1
            if flow_dir is not None:
                _write_window_flow(flow_dir / f"flow_{row.index:04d}.{args.flow_format}", row, prob, res)

        result = process(
            rec, **process_options(args, regs), camera=camera, progress=not args.quiet, on_window=on_window
        )
    if not result.windows:
        raise CliError(
            f"{path}: no window to estimate ({n_events} events; --window {args.window} is too large?)"
        )
    csv_path = result.to_csv(out / "results.csv")
    json_path = result.to_json(out / "results.json")
    written = [csv_path, json_path, result.to_hdf5(out / "results.h5")]
    if args.flow_out is not None:
        written.append(Path(args.flow_out) / f"flow_*.{args.flow_format} ({len(result.windows)} files)")
    if len(result.windows) > 1:
        fig_dir.mkdir(exist_ok=True)
        _parameters_figure(fig_dir / "parameters.png", result)
        written.append(fig_dir / "parameters.png")
    if fig_dir.is_dir():
        written += sorted(p for p in fig_dir.glob("window_*.png"))
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
    if example is not None:
        written.append(_report_example(example, result, area_scales, regs, out / "truth.json"))
    print("wrote: " + ", ".join(str(p) for p in written))
    sys.stdout.flush()
    return 0


def _report_example(example, result, area_scales: list[tuple[float, float]], regs: dict, path: Path) -> Path:
    """Print the estimates of a simulated example against its truth; write them to ``path`` (JSON)."""
    import json

    import numpy as np

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
    path.write_text(json.dumps(report, indent=2) + "\n")
    return path


def _median(values) -> float:
    import numpy as np

    return float(np.median(np.asarray(values, dtype=np.float64)))
