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
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from pathlib import Path

NAME = "estimate"
HELP = "estimate the motion of every window of a recording (results as CSV/JSON, figures)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    from cmax_taichi.sim.examples import EXAMPLES

    parser.add_argument(
        "path",
        metavar="PATH",
        nargs="?",
        default=None,
        help="recording: an ECD folder or events.txt, MVSEC *_data.hdf5, DSEC events.h5, *.aedat4, "
        "Prophesee *.raw / *.dat, *.es",
    )
    parser.add_argument(
        "--example",
        default=None,
        metavar="NAME",
        help="instead of PATH, a recording simulated on the fly (fixed seed, exact truth), estimated and "
        "printed against the truth: "
        + "; ".join(f"{name}: {ex.description}" for name, ex in EXAMPLES.items()),
    )
    parser.add_argument(
        "--format",
        default=None,
        help="ecd | text | mvsec | dsec | aedat4 | raw | dat | es (default: detected)",
    )
    parser.add_argument(
        "--warp",
        default=None,
        help="motion model: zoom1, translation2, rotation3 (needs a calibration), se2, sim2, mitrokhin4 "
        "(default translation2, or the example's model; 'cmax-taichi info' lists them with units)",
    )
    parser.add_argument("--objective", default="variance", help="variance | gradient_magnitude | mean_square")
    parser.add_argument(
        "--reg",
        action="append",
        default=[],
        metavar="NAME=WEIGHT",
        help="add a regularizer with weight lambda, e.g. --reg divergence=10 --reg deformation=10 "
        "(repeatable; 10 = cmax_taichi.RECOMMENDED_LAMBDA, the weight that prevented every collapse "
        "on the MVSEC cut)",
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
    opt.add_argument("--method", default="adam", help="adam | armijo | lbfgs (default adam)")
    opt.add_argument(
        "--init",
        default="auto",
        help="auto | grid | random | tpe | local | none (default auto: grid, then warm)",
    )
    opt.add_argument("--n-init", type=int, default=None, help="evaluations of the global search")
    opt.add_argument("--no-warm-start", action="store_true", help="global search in every window")
    img = parser.add_argument_group("image of warped events")
    img.add_argument("--blur", type=float, default=1.0, help="Gaussian blur sigma, px (default 1, 0 = none)")
    img.add_argument("--t-ref", default="first", help="reference time: first | middle | last (default first)")
    img.add_argument("--polarity", default="ignore", help="ignore | signed | split (default ignore)")
    run = parser.add_argument_group("run")
    run.add_argument(
        "--arch", default=None, help="cpu | gpu | cuda | vulkan | metal (default $CMAX_TAICHI_ARCH or cpu)"
    )
    run.add_argument(
        "--precision", default=None, choices=["f32", "f64"], help="default f64 on cpu, f32 on gpu"
    )
    run.add_argument("--out", default="cmax_out", metavar="DIR", help="output folder (default ./cmax_out)")
    run.add_argument(
        "--figures", type=int, default=1, metavar="K", help="figures of the first K windows (default 1)"
    )
    run.add_argument("--quiet", action="store_true", help="no progress bar")
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


def init_backend(arch: str | None, precision: str | None):
    """Initialise Taichi unless it already runs with the requested arch and precision (a reset would
    throw away the compiled kernels of the calling process)."""
    from cmax_taichi.core import backend

    current = backend.info() if backend.is_initialized() else None
    if (
        current is not None
        and arch in (None, current.requested_arch)
        and precision in (None, current.precision)
    ):
        return current
    return backend.init(arch=arch, precision=precision)


def parse_regularizers(items: list[str]) -> dict[str, float]:
    """``["divergence=1", ...]`` -> ``{"divergence": 1.0}`` (CliError on bad syntax or names)."""
    from cmax_taichi.cli import CliError
    from cmax_taichi.models.regularizers import regularizer_names

    out: dict[str, float] = {}
    for item in items:
        name, sep, weight = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise CliError(f"--reg expects NAME=WEIGHT (e.g. divergence=1), got {item!r}")
        if name not in regularizer_names():
            raise CliError(f"--reg: unknown regularizer {name!r}; valid: {', '.join(regularizer_names())}")
        try:
            value = float(weight)
        except ValueError:
            raise CliError(f"--reg {name}: weight must be a number, got {weight!r}") from None
        if not (math.isfinite(value) and value >= 0):
            raise CliError(f"--reg {name}: weight must be finite and >= 0, got {weight!r}")
        out[name] = value
    return out


def check_choices(args: argparse.Namespace) -> None:
    """Validate names before any data is read (one-line errors)."""
    import cmax_taichi as cm
    from cmax_taichi.cli import CliError
    from cmax_taichi.solve.optimize import INITS, METHODS

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
    if args.t_ref not in ("first", "middle", "last"):
        try:
            float(args.t_ref)
        except ValueError:
            raise CliError(f"--t-ref must be first, middle, last or seconds, got {args.t_ref!r}") from None


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


def run(args: argparse.Namespace) -> int:
    import cmax_taichi as cm
    from cmax_taichi.cli import CliError
    from cmax_taichi.metrics import area_scale
    from cmax_taichi.solve.sequence import process

    regs = parse_regularizers(args.reg)
    example = None
    if args.example is not None:
        if args.path is not None:
            raise CliError("give a recording PATH or --example NAME, not both")
        from cmax_taichi.sim.examples import EXAMPLES

        if args.example not in EXAMPLES:
            raise CliError(f"--example: unknown example {args.example!r}; valid: {', '.join(EXAMPLES)}")
        args.warp = args.warp or EXAMPLES[args.example].warp
        if args.duration is None:
            args.duration = EXAMPLES[args.example].window
    elif args.path is None:
        raise CliError("give a recording PATH, or --example NAME for a simulated one")
    args.warp = args.warp or "translation2"
    check_choices(args)
    from cmax_taichi import io

    init_backend(args.arch, args.precision)
    if args.example is not None:
        from cmax_taichi.sim.examples import make_example

        example = make_example(args.example)
        path = Path(f"example:{args.example}")
        source = contextlib.nullcontext(example.events)
        camera = example.camera
    else:
        path = Path(args.path)
        if not path.exists():
            raise CliError(f"{path}: no such file or folder")
        source = io.open_recording(path, format=args.format)
        camera = None
    out = Path(args.out)
    fig_dir = out / "figures"
    t_ref: str | float = args.t_ref if args.t_ref in ("first", "middle", "last") else float(args.t_ref)
    stride = None
    if args.stride is not None:
        stride = args.stride if args.duration is not None else int(args.stride)
    optimize_options = {}
    if args.init != "auto":
        optimize_options["init"] = args.init
    if args.n_init is not None:
        optimize_options["n_init"] = args.n_init

    # per window, for the examples: the mean area scale of the warp at the estimate (a collapse
    # shrinks the events' neighbourhoods towards points: it drives the scale towards 0)
    covered: list[tuple[float, float]] = []  # (estimate, truth)
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
                covered.append((area_scale(prob, res.theta), area_scale(prob, example.truth)))
            if figures_left[0] > 0:
                fig_dir.mkdir(exist_ok=True)
                _window_figure(fig_dir / f"window_{row.index:04d}.png", row, prob, res)
                figures_left[0] -= 1
            if flow_dir is not None:
                _write_window_flow(flow_dir / f"flow_{row.index:04d}.{args.flow_format}", row, prob, res)

        result = process(
            rec,
            args.warp,
            camera=camera,
            objective=args.objective,
            regularizers=regs,
            n_events=args.window,
            duration=args.duration,
            stride=stride,
            method=args.method,
            warm_start=not args.no_warm_start,
            max_windows=args.max_windows,
            progress=not args.quiet,
            problem_options={
                "blur_sigma": args.blur,
                "t_ref": t_ref,
                "polarity": args.polarity,
                "whitening": args.whitening,
            },
            optimize_options=optimize_options,
            on_window=on_window,
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
    fwls = [w.fwl for w in result.windows if math.isfinite(w.fwl)]
    if fwls:
        print(f"  FWL: median {_median(fwls):.4f}")
    if example is not None:
        written.append(_report_example(example, result, covered, regs, out / "truth.json"))
    print("wrote: " + ", ".join(str(p) for p in written))
    sys.stdout.flush()
    return 0


def _report_example(example, result, covered: list[tuple[float, float]], regs: dict, path: Path) -> Path:
    """Print the estimates of a simulated example against its truth; write them to ``path`` (JSON)."""
    import json

    import numpy as np

    from cmax_taichi.metrics import COLLAPSE_AREA_SCALE

    truth = example.truth
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
    scales = np.array(covered, dtype=np.float64).reshape(-1, 2)
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
