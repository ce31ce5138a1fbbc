"""Estimate the motion of every window of an event recording by Contrast Maximization.

The recording is read window by window (30,000 events per window by default, or --duration seconds);
each window's warp parameters are found by a global search and gradient ascent, warm-started from the
previous window. Results go to OUT/results.csv and OUT/results.json (one row per window: time span,
event count, parameters in physical units, objective value, FWL, iterations, seconds), figures to
OUT/figures/ (IWE before and after, flow colours; parameters over time).

examples:
  cmax-taichi estimate ../shared/data/ecd_rotation/boxes_rotation --warp rotation3 --out out_boxes
  cmax-taichi estimate recording_data.hdf5 --warp mitrokhin4 --objective variance \\
      --reg divergence=10 --reg deformation=10 --window 30000 --arch cpu --out out_mvsec
  cmax-taichi evaluate out_boxes          # then compare against the recording's ground truth
"""

from __future__ import annotations

import argparse
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
    lam = RECOMMENDED_LAMBDA
    common.add_recording_arguments(
        parser,
        warp_default="translation2",
        warp_help="motion model",
        reg_help=f"add a regularizer with weight lambda, e.g. --reg divergence={lam:g} "
        f"--reg deformation={lam:g} ({lam:g} = cmax_taichi.RECOMMENDED_LAMBDA, the weight that prevented "
        "every collapse on the MVSEC cut)",
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
    from cmax_taichi.solve.sequence import process

    regs = common.parse_regularizers(args.reg)
    check_choices(args)
    path = Path(args.path)
    if not path.exists():
        raise CliError(f"{path}: no such file or folder")
    try:
        from cmax_taichi import io
    except ImportError as exc:  # pragma: no cover - the readers ship with the package
        raise CliError(f"the dataset readers are not available ({exc})") from None
    common.init_backend(args.arch, args.precision)
    out = Path(args.out)
    fig_dir = out / "figures"
    t_ref = common.parse_t_ref(args.t_ref)
    stride = None
    if args.stride is not None:
        stride = args.stride if args.duration is not None else int(args.stride)
    optimize_options = {}
    if args.init != "auto":
        optimize_options["init"] = args.init
    if args.n_init is not None:
        optimize_options["n_init"] = args.n_init

    with io.open_recording(path, format=args.format) as rec:
        if cm.get_warp(args.warp).needs_camera and rec.camera is None:
            raise CliError(f"warp {args.warp!r} needs a calibration, and {path} has none (calib.txt)")
        out.mkdir(parents=True, exist_ok=True)
        figures_left = [max(0, args.figures)]

        def on_window(row, prob, res):
            if figures_left[0] > 0:
                fig_dir.mkdir(exist_ok=True)
                _window_figure(fig_dir / f"window_{row.index:04d}.png", row, prob, res)
                figures_left[0] -= 1

        result = process(
            rec,
            args.warp,
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
            f"{path}: no window to estimate ({rec.n_events} events; --window {args.window} is too large?)"
        )
    csv_path = result.to_csv(out / "results.csv")
    json_path = result.to_json(out / "results.json")
    written = [csv_path, json_path]
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
    print("wrote: " + ", ".join(str(p) for p in written))
    sys.stdout.flush()
    return 0


def _median(values) -> float:
    import numpy as np

    return float(np.median(np.asarray(values, dtype=np.float64)))
