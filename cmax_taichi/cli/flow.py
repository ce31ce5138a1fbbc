"""Estimate the dense optical flow of every window of an event recording.

The flow lives on a grid of nodes over the sensor (bilinear between nodes), estimated coarse to fine by
L-BFGS-B on the exact gradient of the contrast objective, with the event-collapse regularizers
(divergence, deformation) and a smoothness term; each window is warm-started from the previous one.
Results go to OUT: flow/flow_NNNN.<format> (the displacement over --dt, px: .npz with its interval and
the recording's fingerprint, Middlebury .flo, or DSEC's 16-bit submission PNG), flow_timestamps.txt
(t_start t_end of each file, for 'cmax-taichi evaluate'), results.csv (a row per window, estimated or
not: status, time span, events, events dropped, J and its terms, evaluations, seconds, what the optimizer
did on each level (optimizer, levels), and AEE / NPE /
%Out where the recording has flow ground truth), summary.json (the means, where every event went, the
recording and the options) and figures/window_NNNN.png (IWE without and with the flow, the flow in
colour). Events not estimated (the partial last window, outside the sensor, lost in undistortion,
windows too small) are counted in one warning at the end. OUT is guarded as estimate's is: never an
input nor a folder holding one, no file replaced that this command did not write, everything in place
only when the run completes.

examples:
  cmax-taichi flow --example planes               # simulated depth scene, printed against its truth
  cmax-taichi flow --example boxroom              # a smooth depth-varying flow (box room)
  cmax-taichi flow ../shared/data/mvsec_indoor_flying1 --out out_flow
  cmax-taichi flow recording_data.hdf5 --window 30000 --dt 0.0625 --flow-format npz --out out_mvsec
  cmax-taichi flow events.h5 --duration 0.1 --grid 32 24 --levels 4 --reg deformation=2 --out out_dsec
  cmax-taichi evaluate out_mvsec/flow --data recording_data.hdf5   # score the files afterwards
  cmax-taichi flow --live tcp://127.0.0.1:7777 --out out_live     # while the camera records (docs/live.md)
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path

from cmax_taichi.cli import _common as common
from cmax_taichi.cli import _live

NAME = "flow"
HELP = "dense optical flow of every window of a recording or live stream (flow files, figures, metrics)"


def _defaults():
    from cmax_taichi.flow.solver import DEFAULT_REGULARIZERS

    return DEFAULT_REGULARIZERS


def _auto_padding() -> float:
    from cmax_taichi.flow.solver import AUTO_PADDING

    return AUTO_PADDING


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    from cmax_taichi.flow.smoothness import smoothness_names
    from cmax_taichi.io.writers import FLOW_FORMATS
    from cmax_taichi.models.objectives import objective_names
    from cmax_taichi.models.regularizers import regularizer_names

    parser.add_argument(
        "path", metavar="PATH", nargs="?", default=None, help="recording (any reader's format)"
    )
    parser.add_argument(
        "--example",
        default=None,
        metavar="NAME",
        help="instead of PATH, a simulated depth scene with exact dense ground truth: "
        + ", ".join(_example_names()),
    )
    parser.add_argument("--format", default=None, help="reader format (default: detected)")
    parser.add_argument(
        "--sensor-size",
        type=int,
        nargs=2,
        default=None,
        metavar=("W", "H"),
        help="the recording's sensor size in px when it is not the format's (e.g. a scaled simulation)",
    )
    model = parser.add_argument_group("flow model")
    model.add_argument(
        "--grid",
        type=int,
        nargs=2,
        default=[16, 16],
        metavar=("NX", "NY"),
        help="cells of the finest grid along x and y (default 16 16: nodes every (W-1)/16 px)",
    )
    model.add_argument("--levels", type=int, default=4, help="coarse-to-fine levels (default 4)")
    model.add_argument(
        "--objective",
        default="gradient_magnitude",
        help=f"{common.names(objective_names())} (default gradient_magnitude)",
    )
    model.add_argument(
        "--references",
        default="middle",
        type=_references,
        help="reference time(s) of the IWE: first | middle | last | a fraction of the window in [0, 1], "
        "several comma-separated (first,last), or multi (the reference's multi-focal first + middle x2 + "
        "last) (default middle)",
    )
    defaults = ", ".join(f"{k}={v:g}" for k, v in _defaults().items())
    model.add_argument(
        "--reg",
        action="append",
        default=None,
        metavar="NAME=WEIGHT",
        help=f"a regularizer with its weight (repeatable; NAME: "
        f"{common.names(regularizer_names() + smoothness_names())}); default {defaults}",
    )
    model.add_argument("--no-reg", action="store_true", help="no regularizer at all (shows the collapse)")
    common.add_plugin_argument(model)
    model.add_argument("--blur", type=float, default=1.0, help="Gaussian blur of the IWE, px (default 1)")
    model.add_argument(
        "--padding",
        type=int,
        default=None,
        metavar="PX",
        help=f"margin of the IWE around the sensor, px (default {_auto_padding() * 100:g}%% of the larger "
        "sensor side, less where the padded image would exceed the sensor size limit)",
    )
    win = common.add_window_arguments(parser)
    win.add_argument(
        "--dt",
        type=float,
        default=None,
        metavar="S",
        help="interval of each flow file and of the metrics, s from the window's first event (MVSEC dt = 1 "
        "or 4 frames, DSEC 0.1 s); default the window's duration",
    )
    win.add_argument("--no-warm-start", action="store_true", help="the global search in every window")
    run = parser.add_argument_group("run")
    common.add_backend_arguments(run)
    run.add_argument("--out", default="flow_out", metavar="DIR", help="output folder (default ./flow_out)")
    run.add_argument(
        "--flow-format",
        default="npz",
        choices=list(FLOW_FORMATS),
        help="npz: 'flow' (2, H, W) px with t_start, t_end; flo: Middlebury; png: DSEC 16-bit (default npz)",
    )
    run.add_argument(
        "--figures",
        type=int,
        default=None,
        metavar="K",
        help="figures of the first K windows (default 1; not with --live)",
    )
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    _live.add_arguments(parser, live_default="count")


#: the example that is not a simulator preset: the box room of cmax_taichi.testing.flow_scenes
BOXROOM = "boxroom"


def _example_names() -> list[str]:
    try:
        from cmax_taichi.sim import DEPTH_PRESETS
    except ImportError:  # a build without the depth scenes
        return [BOXROOM]
    return list(DEPTH_PRESETS) + [BOXROOM]


def parse_regularizers(items: list[str] | None, none: bool) -> dict[str, float]:
    """``--reg`` items (event-collapse regularizers and smoothness terms) or the defaults."""
    from cmax_taichi.cli import CliError
    from cmax_taichi.flow.smoothness import SMOOTHNESS

    if none:
        if items:
            raise CliError("--no-reg and --reg exclude each other")
        return {}
    if items is None:
        return dict(_defaults())
    return common.parse_regularizers(items, extra=SMOOTHNESS.names())


def _references(text: str) -> str | float | tuple:
    """--references as :func:`cmax_taichi.flow.problem.resolve_references` takes it: names and
    fractions (numbers), one or several comma-separated; resolve_references checks them."""
    items = []
    for part in text.split(","):
        try:
            items.append(float(part))
        except ValueError:
            items.append(part.strip())
    return items[0] if len(items) == 1 else tuple(items)


def _check(args: argparse.Namespace) -> None:
    from cmax_taichi.cli import CliError
    from cmax_taichi.flow.problem import resolve_references
    from cmax_taichi.models.objectives import OBJECTIVES

    OBJECTIVES.get(args.objective)
    try:
        resolve_references(args.references)
    except (TypeError, ValueError) as exc:
        raise CliError(f"--references: {exc}") from None
    common.check_windows(args)
    if args.dt is not None and not (math.isfinite(args.dt) and args.dt > 0):
        raise CliError(f"--dt must be a positive number of seconds, got {args.dt}")
    if args.levels < 1:
        raise CliError(f"--levels must be at least 1, got {args.levels}")
    if args.padding is not None and args.padding < 0:
        raise CliError(f"--padding must be a whole number of px >= 0, got {args.padding}")
    if not (math.isfinite(args.blur) and args.blur >= 0):
        raise CliError(f"--blur must be a finite number of px >= 0, got {args.blur}")


def _window_figure(path: Path, window, estimator) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from cmax_taichi import viz

    res = window.result
    prob = estimator.problem(window.events, 1)
    prob.set_grid(res.grid)
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6), constrained_layout=True)
    viz.show_iwe(axes[0], prob.iwe(np.zeros(res.grid.shape)), title="IWE, no motion")
    viz.show_iwe(axes[1], prob.iwe(res.nodes), title=f"IWE, dense flow (J = {res.value:.3f})")
    viz.show_flow(
        axes[2], res.flow(window.dt), unit="px", title=f"displacement over {window.dt * 1e3:.1f} ms"
    )
    note = ""
    if window.metrics is not None:
        note = f"; AEE {window.metrics['AEE']:.3f} px, 3PE {window.metrics['3PE']:.1f}%"
    fig.suptitle(
        f"window {window.index}: t = {res.t_start:.4f} .. {res.t_end:.4f} s, {res.n_events} events, grid "
        f"{res.grid.nx}x{res.grid.ny} cells{note}",
        fontsize=10,
    )
    fig.savefig(path, dpi=90)
    plt.close(fig)


COLUMNS = [
    "window",
    "status",
    "t_start",
    "t_end",
    "n_events",
    "n_dropped",
    "dt",
    "J",
    "data",
    "penalties",
    "smoothness",
    "evaluations",
    "seconds",
    "optimizer",
    "levels",
    "AEE",
    "3PE",
    "outlier",
    "note",
]


def _number(value: float, digits: int) -> str:
    return f"{value:.{digits}f}" if math.isfinite(value) else ""


def _row(window) -> dict:
    """The results.csv row of a window, estimated or not (empty cells for what it does not have)."""
    res, m = window.result, window.metrics or {}
    row = {
        "window": window.index,
        "status": window.status,
        "t_start": _number(window.t_start, 6),
        "t_end": _number(window.t_end, 6),
        "n_events": window.n_events,
        "n_dropped": window.n_dropped,
        "note": window.note,
    }
    if res is not None:
        ev = res.evaluation
        row.update(
            dt=f"{window.dt:.6f}",
            J=f"{res.value:.6f}",
            data=f"{ev.data:.6f}",
            penalties=";".join(f"{k}={v:.5g}" for k, v in ev.penalties.items()),
            smoothness=";".join(f"{k}={v:.5g}" for k, v in ev.smoothness.items()),
            evaluations=res.n_evaluations,
            seconds=f"{res.seconds:.3f}",
            optimizer=res.status,
            levels="; ".join(lv.summary() for lv in res.levels),
        )
    for key, digits in (("AEE", 4), ("3PE", 3), ("outlier", 3)):
        row[key] = _number(m[key], digits) if key in m else ""
    return row


def _open_example(name: str):
    """``(events, ground truth source, description)`` of a simulated depth preset."""
    from cmax_taichi import sim
    from cmax_taichi.cli import CliError

    if name == BOXROOM:
        return _open_boxroom()
    presets = getattr(sim, "DEPTH_PRESETS", {})
    if name not in presets:
        raise CliError(f"--example: unknown example {name!r}; valid: {', '.join(_example_names())}")
    preset = presets[name]
    t0 = 0.02  # after the simulator's first renders
    rec = sim.simulate_depth(name, duration=t0 + preset.window + 1e-3, seed=0)
    events = rec.events(t0, t0 + preset.window)
    return events, _ExampleTruth(rec), preset


class _BoxRoom:
    """The box room of :func:`cmax_taichi.testing.flow_scenes.depth_scene` as an example: its
    description, window (s) and ground truth (a steady velocity field: flow = velocity x interval)."""

    description = (
        "a camera moving sideways in a textured box room, 346x260: flow proportional to the inverse "
        "depth, 5.4-11.6 px over the 50 ms window, a factor 2.15 across the image, no discontinuity"
    )

    def __init__(self) -> None:
        from cmax_taichi.testing.flow_scenes import depth_scene

        self.scene = depth_scene((346, 260), duration=0.05, displacement=(5.0, 2.0), n_events=60000, seed=0)
        self.window = self.scene.duration

    def flow(self, t0: float, t1: float):
        return self.scene.velocity * (t1 - t0)

    def read_time(self, t0: float, t1: float):
        t = self.scene.events.t
        return self.scene.events[(t >= t0) & (t <= t1)]


def _open_boxroom():
    room = _BoxRoom()
    return room.scene.events, room, room


class _ExampleTruth:
    """The ground-truth interface of a recording (``flow``, ``read_time``) over a simulated one."""

    def __init__(self, rec) -> None:
        self._rec = rec

    def flow(self, t0: float, t1: float):
        return self._rec.flow(t0, t1)

    def read_time(self, t0: float, t1: float):
        return self._rec.events(t0, t1)


def make_estimator(args: argparse.Namespace, regs: dict):
    """The :class:`~cmax_taichi.flow.DenseFlowEstimator` of the command line."""
    from cmax_taichi.flow.solver import DenseFlowEstimator

    return DenseFlowEstimator(
        tuple(args.grid),
        levels=args.levels,
        objective=args.objective,
        references=args.references,
        regularizers=regs,
        blur_sigma=args.blur,
        padding=args.padding,
    )


def run_options(args: argparse.Namespace, regs: dict) -> dict:
    """The options of the run, as summary.json records them."""
    return {
        "grid": list(args.grid),
        "levels": args.levels,
        "objective": args.objective,
        "references": args.references,
        "regularizers": regs,
        "blur": args.blur,
        "padding": args.padding,
        "window_events": None if args.duration is not None else args.window,
        "window_duration": args.duration,
        "stride": args.stride,
        "keep_tail": args.keep_tail,
        "dt": args.dt,
        "flow_format": args.flow_format,
    }


def run(args: argparse.Namespace) -> int:
    from cmax_taichi.cli import CliError
    from cmax_taichi.io.outputs import OutputFolder

    regs = parse_regularizers(args.reg, args.no_reg)
    _check(args)
    if args.live is not None:
        from cmax_taichi.cli import _flow_live

        return _flow_live.run(args, regs)
    if args.window_mode == "adaptive":
        raise CliError("--window-mode adaptive: with --live (a recording's flow windows: count or duration)")
    _live.window_rule(args, live_default="count")  # the other window options, checked as for --live
    args.figures = 1 if args.figures is None else args.figures
    if args.figures < 0:
        raise CliError(f"--figures must be a number of windows >= 0, got {args.figures}")
    if (args.path is None) == (args.example is None):
        raise CliError("give a recording PATH or --example NAME (one of them)")
    inputs = [] if args.path is None else [Path(args.path)]
    if args.path is not None and not inputs[0].exists():
        raise CliError(f"{inputs[0]}: no such file or folder")
    patterns = [f"flow/flow_*.{args.flow_format}", "flow_timestamps.txt", "results.csv", "summary.json"]
    patterns.append("figures/window_*.png")
    folder = OutputFolder(args.out, inputs=inputs, patterns=patterns, command="flow")
    folder.check()  # an OUT that is an input, or holds files this run may not replace: before any work
    common.init_backend(args.arch, args.precision, args.compile)
    estimator = make_estimator(args, regs)
    with folder:
        windows, info, truth = _estimate_into(args, estimator, folder, regs)
        written = folder.commit()  # every file moved into place whole, now that the run is complete
    _report(args, windows, info, truth)
    out = Path(args.out)
    flows = [p for p in written if p.parent == out / "flow"]
    others = [p for p in written if p.parent != out / "flow"]
    shown = [str(out / "flow" / f"flow_*.{args.flow_format}") + f" ({len(flows)} files)"] + [
        str(p) for p in others
    ]
    print("wrote: " + ", ".join(shown))
    sys.stdout.flush()
    return 0


def _report(args, windows: list, info: dict, truth) -> None:
    """What the run did: windows, time, the metrics (or why none), where the events went."""
    from cmax_taichi.core.windows import ESTIMATED_STATUSES, describe_events
    from cmax_taichi.flow.sequence import BEYOND_SENSOR

    label = f"example {args.example}" if args.example is not None else str(args.path)
    grid = f"grid {args.grid[0]}x{args.grid[1]} cells, {args.levels} levels"
    print(f"{len(windows)} window(s) of {label}: {grid}")
    if info["mean_seconds_after_first"] is None:
        print(f"  time: {info['seconds']:.2f} s (one window, which compiles the kernels)")
    else:
        print(
            f"  time: {info['seconds']:.2f} s in all, {info['mean_seconds_after_first']:.3f} s per window "
            "after the first (which compiles the kernels)"
        )
    if "metrics" in info:
        m = info["metrics"]
        print(
            f"  against the ground truth ({info['scored_windows']} window(s)): AEE {m['AEE']:.3f} px, "
            f"3PE {m['3PE']:.2f}%, %Out {m['outlier']:.2f}%"
        )
        if args.example is not None:
            zero = _zero_flow_error(truth, windows[0])
            print(f"  (zero flow: AEE {zero:.3f} px)")
    for note, count in info.get("unscored", {}).items():
        print(f"  {count} window(s) not scored against the ground truth: {note}")
    if "metrics" not in info and "unscored" not in info and args.example is None:
        print("  no flow ground truth in this recording: no metrics")
    beyond = [w for w in windows if w.status == BEYOND_SENSOR]
    if beyond:
        print(f"  {len(beyond)} window(s) without a flow file: {beyond[0].note}")
    events = info["events"]
    left = events["total"] - events["estimated"]
    if left:
        reasons = describe_events(events, args.window if args.duration is None else None, args.max_windows)
        n_skipped = sum(n for status, n in events["windows"].items() if status not in ESTIMATED_STATUSES)
        skipped = f"; {n_skipped} window(s) skipped" if n_skipped else ""
        note = f"; {left} not estimated ({reasons}{skipped})"
    else:
        note = ""
    print(f"  events: {events['estimated']} of {events['total']} estimated{note}")
    stalled = [w.index for w in windows if w.result is not None and w.result.status == "stalled"]
    if stalled:
        print(
            f"  warning: {len(stalled)} window(s) ({', '.join(map(str, stalled[:10]))}"
            f"{', ...' if len(stalled) > 10 else ''}) have a level whose optimizer did not move the flow: "
            "their flow there is the level's start (results.csv, columns optimizer and levels)"
        )


def _estimate_into(args, estimator, folder, regs: dict):
    """Estimate every window into the staging folder of ``folder``; ``(windows, summary, truth)``."""
    from cmax_taichi import io
    from cmax_taichi.cli import CliError
    from cmax_taichi.flow.grid import check_padded_sensor
    from cmax_taichi.flow.sequence import iter_flow, summary
    from cmax_taichi.io.outputs import json_text
    from cmax_taichi.solve.sequence import ProgressBar

    truth = None
    source = None
    if args.example is not None:
        events, truth, preset = _open_example(args.example)
        print(f"example {args.example!r}: {preset.description}")
        print(f"  simulated: {len(events)} events over {preset.window * 1e3:.0f} ms (seed 0), one window")
        options = dict(n_events=len(events), max_windows=1, truth=truth)
    else:
        size = {} if args.sensor_size is None else {"sensor_size": tuple(args.sensor_size)}
        if args.topic is not None:
            size["topic"] = args.topic
        events = source = io.open_recording(Path(args.path), format=args.format, **size)
        options = dict(
            n_events=args.window,
            duration=args.duration,
            stride=common.window_stride(args),
            max_windows=args.max_windows,
            warm_start=not args.no_warm_start,
            keep_tail=args.keep_tail,
        )
    windows, stamps, bar = [], [], None
    started = time.perf_counter()
    with common.held_drop_warnings() as held:
        try:
            if source is not None and args.padding is not None:  # iter_flow checks it too, naming no option
                check_padded_sensor(source.sensor_size, args.padding, "--padding")
            with folder.path("results.csv").open("w", newline="") as fcsv:
                writer = csv.DictWriter(fcsv, fieldnames=COLUMNS)
                writer.writeheader()
                skipped_row = lambda w: writer.writerow(_row(w))  # noqa: E731 - rows in window order
                flows = iter_flow(events, estimator, dt=args.dt, on_skipped=skipped_row, **options)
                bar = None if args.quiet else ProgressBar(flows.total)
                for window in flows:
                    if window.estimated:
                        _write_window(args, folder, window, estimator, flows.source)
                        stamps.append((window.result.t_start, window.result.t_start + window.dt))
                    writer.writerow(_row(window))
                    if not windows:  # the first result as soon as it is there
                        _print_first_window(window, started)
                    window.events = window.displacement = None  # nothing of a window is kept but its summary
                    windows.append(window)
                    if bar is not None:
                        note = f"J={window.result.value:.3f}"
                        if window.metrics is not None:
                            note += f" AEE={window.metrics['AEE']:.3f}px"
                        bar.update(note)
        finally:
            if bar is not None:
                bar.close()
            if source is not None:
                source.close()
    if not windows:  # one line: the error says why, with the counts the held warning has
        raise CliError(f"{args.path}: no window to estimate: {common.why_no_window(args, flows.events)}")
    common.show_warnings(held)
    folder.path("flow_timestamps.txt").write_text("".join(f"{a:.9f} {b:.9f}\n" for a, b in stamps))
    info = summary(windows)
    info["events"] = flows.events
    info["recording"] = flows.source if args.example is None else {"source": f"example:{args.example}"}
    info["options"] = run_options(args, regs)
    folder.path("summary.json").write_text(json_text(info, indent=2))
    return windows, info, truth


def _print_first_window(window, started: float) -> None:
    """The first window's flow in brief, as soon as it is done (above a progress bar, if one is drawn)."""
    import numpy as np
    from tqdm import tqdm

    res = window.result
    if window.displacement is None:  # its flow over dt leaves the sensor (status beyond_sensor)
        shown = f"no displacement over dt: {window.note}"
    else:
        u, v = (float(np.median(c)) for c in window.displacement)
        shown = f"median displacement ({u:.2f}, {v:.2f}) px"
    aee = f", AEE {window.metrics['AEE']:.3f} px" if window.metrics is not None else ""
    tqdm.write(
        f"first window ({res.t_start:.4f} s + {window.dt:.4f} s): {shown}{aee} "
        f"({time.perf_counter() - started:.1f} s)",
        file=sys.stdout,
    )
    sys.stdout.flush()


def flow_name(args, window) -> str:
    """The flow file of an estimated window, relative to OUT."""
    return f"flow/flow_{window.index:04d}.{args.flow_format}"


def flow_meta(args, window, source: dict) -> dict:
    """The metadata of a window's flow file: its interval (s), unit, window, and the recording's
    fingerprint where it has one (evaluate checks --data against it)."""
    res = window.result
    meta = {"t_start": res.t_start, "t_end": res.t_start + window.dt, "unit": "px", "window": window.index}
    if args.flow_format == "npz" and source.get("fingerprint"):
        meta["fingerprint"] = source["fingerprint"]
    return meta


def row_fields(window) -> list:
    """The results.csv row of a window as a list, in the order of the columns."""
    row = _row(window)
    return [row.get(column, "") for column in COLUMNS]


def _write_window(args, folder, window, estimator, source: dict) -> None:
    """The flow file of an estimated window (and its figure among the first --figures)."""
    from cmax_taichi.io.writers import write_flow

    write_flow(folder.path(flow_name(args, window)), window.displacement, **flow_meta(args, window, source))
    if window.index < args.figures:
        _window_figure(folder.path(f"figures/window_{window.index:04d}.png"), window, estimator)


def _zero_flow_error(truth, window) -> float:
    import numpy as np

    from cmax_taichi.metrics import event_mask, flow_error

    t0, t1 = window.result.t_start, window.result.t_start + window.dt
    gt = truth.flow(t0, t1)
    return flow_error(np.zeros_like(gt), gt, event_mask(truth.read_time(t0, t1)))["AEE"]
