"""Segment one window of an event recording into K independently moving clusters (multi-model CMax,
Stoffregen et al. ICCV 2019, with the event-collapse regularizers).

Writes OUT/labels.npy (cluster per event, -1 for events dropped by undistortion), OUT/labels.csv
(t, x, y, p, label and the K membership probabilities per event), OUT/segmentation.json (per-cluster
parameters with units, sizes, iterations, timings, settings) and two figures in OUT/figures/: the
events coloured by cluster (image plane and x-t), and each cluster's sharpened IWE next to the
unwarped events. OUT is never the recording nor a folder that holds it, files there that no cmax-taichi
run wrote are never replaced, and the files appear in OUT only when the run completes.

examples:
  cmax-taichi segment --example two-objects --out seg_example   # simulated, against the true labels
  cmax-taichi segment ../shared/data/ecd_rotation/dynamic_rotation -k 2 --warp rotation3 --out seg_dyn
  cmax-taichi segment recording_data.hdf5 -k 3 --warp mitrokhin4 \\
      --reg divergence=1 --reg deformation=1 --events 30000 --out seg_out
  cmax-taichi segment events.txt -k 2 --warp translation2,mitrokhin4 --hard --out seg_out
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from cmax_taichi.cli import _common as common

NAME = "segment"
HELP = "segment a window of events into K independently moving clusters (labels, figures)"
#: what a run may write into OUT (paths relative to it; see cmax_taichi.io.outputs)
OUTPUT_PATTERNS = (
    "labels.npy",
    "labels.csv",
    "segmentation.json",
    "figures/events_by_cluster.png",
    "figures/cluster_iwes.png",
    "truth.json",
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    from cmax_taichi.sim.examples import SEGMENT_EXAMPLES

    common.add_recording_arguments(
        parser,
        warp_default="mitrokhin4",
        warp_help="motion model of every cluster, or K comma-separated models (e.g. rotation3,mitrokhin4)",
        reg_help="add a regularizer in every cluster, e.g. --reg divergence=1 --reg deformation=1",
        sensor_size=True,
        path_nargs="?",
        examples=SEGMENT_EXAMPLES,
    )
    parser.add_argument("-k", "--clusters", type=int, default=2, metavar="K", help="clusters (default 2)")
    win = parser.add_argument_group("window")
    win.add_argument(
        "--events", type=int, default=30000, metavar="N", help="events in the window (default 30000)"
    )
    win.add_argument(
        "--start", type=int, default=None, metavar="I", help="index of the window's first event (default 0)"
    )
    win.add_argument(
        "--t-start", type=float, default=None, metavar="S", help="start time in seconds instead of --start"
    )
    win.add_argument(
        "--duration", type=float, metavar="S", help="window length in seconds instead of --events"
    )
    seg = parser.add_argument_group("segmentation")
    seg.add_argument(
        "--temperature", type=float, default=1.0, help="membership update P ~ I^(1/T) (default 1, Stoffregen)"
    )
    seg.add_argument("--hard", action="store_true", help="hard assignments (each event to one cluster)")
    seg.add_argument("--max-iterations", type=int, default=12, help="alternations (default 12)")
    seg.add_argument("--blur", type=float, default=1.0, help="Gaussian blur sigma, px (default 1)")
    common.add_t_ref_argument(seg)
    seg.add_argument("--seed", type=int, default=0, help="seed of the initialisation's subsample")
    run = parser.add_argument_group("run")
    common.add_backend_arguments(run)
    run.add_argument(
        "--out", default="cmax_segment", metavar="DIR", help="output folder (default ./cmax_segment)"
    )
    run.add_argument("--no-figures", action="store_true", help="labels and JSON only")
    run.add_argument("--quiet", action="store_true", help="no progress bar")


def _read_window(rec, args):
    from cmax_taichi.cli import CliError

    if args.events < 2:
        raise CliError(f"--events must be at least 2, got {args.events}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise CliError(f"--duration must be a positive number of seconds, got {args.duration}")
    if args.start is not None and (args.t_start is not None or args.duration is not None):
        raise CliError("--start gives the window by event index: not with --t-start or --duration (times)")
    args.start = 0 if args.start is None else args.start
    if args.t_start is not None and not math.isfinite(args.t_start):
        raise CliError(f"--t-start must be a finite number of seconds, got {args.t_start}")
    if args.t_start is not None or args.duration is not None:
        t0 = rec.t_start if args.t_start is None else args.t_start
        if args.duration is not None:
            events = rec.read_time(t0, t0 + args.duration)
        else:
            i0 = rec._search_time(t0)  # first event at or after t0 (the readers' binary search)
            events = rec.read(i0, i0 + args.events)
    else:
        if not 0 <= args.start < max(rec.n_events, 1):
            raise CliError(f"--start {args.start} is outside the recording's {rec.n_events} events")
        events = rec.read(args.start, args.start + args.events)
    if len(events) == 0:
        where = "" if args.t_start is None else f" from --t-start {args.t_start:g} s"
        raise CliError(
            f"{rec.path}: the window{where} is empty (no events there; the recording spans "
            f"{rec.t_start:.6f} .. {rec.t_end:.6f} s)"
        )
    return events


def _colors(k: int):
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return [cmap(j % 10) for j in range(k)]


def _events_figure(path: Path, events, res) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    K = res.n_clusters
    colors = _colors(K)
    W, H = events.sensor_size
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), constrained_layout=True)
    t_ms = (events.t - events.t[0]) * 1e3
    for j in range(K):
        sel = res.labels == j
        if not sel.any():
            continue
        label = f"cluster {j} ({res.warps[j]}): {int(sel.sum())} events"
        axes[0].scatter(events.x[sel], events.y[sel], s=0.3, color=colors[j], label=label, rasterized=True)
        axes[1].scatter(t_ms[sel], events.x[sel], s=0.3, color=colors[j], rasterized=True)
    dropped = res.labels < 0
    if dropped.any():
        axes[0].scatter(
            events.x[dropped], events.y[dropped], s=0.3, color="0.7", label="dropped", rasterized=True
        )
    axes[0].set_xlim(0, W - 1)
    axes[0].set_ylim(H - 1, 0)
    axes[0].set_aspect("equal")
    axes[0].set_xlabel("x [px]")
    axes[0].set_ylabel("y [px]")
    axes[0].set_title("Events coloured by cluster (raw positions)")
    axes[0].legend(loc="upper right", markerscale=12, fontsize=8, framealpha=0.8)
    axes[1].set_xlabel("time since window start [ms]")
    axes[1].set_ylabel("x [px]")
    axes[1].set_title("Events coloured by cluster, x over time")
    sizes = np.bincount(res.labels[res.labels >= 0], minlength=K)
    fig.suptitle(
        f"{len(events)} events, {events.duration * 1e3:.1f} ms; K = {K}, sizes {sizes.tolist()}, "
        f"{len(res.history)} iterations, {res.seconds:.2f} s",
        fontsize=10,
    )
    fig.savefig(path, dpi=100, format="png")
    plt.close(fig)


def _iwe_figure(path: Path, events, res, raw_iwe) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cmax_taichi import viz
    from cmax_taichi.models.warps import get_warp

    K = res.n_clusters
    fig, axes = plt.subplots(1, K + 1, figsize=(4.6 * (K + 1), 4.0), constrained_layout=True)
    viz.show_iwe(axes[0], raw_iwe, title="All events, not warped")
    thetas = list(res.thetas)
    for j in range(K):
        m = get_warp(res.warps[j])
        params = "\n".join(f"{n} = {v:.4g} {u}" for n, v, u in zip(m.params, thetas[j], m.units, strict=True))
        state = " (empty)" if res.empty[j] else ""
        viz.show_iwe(axes[j + 1], res.iwes[j], title=f"Cluster {j} sharpened IWE{state}")
        axes[j + 1].text(
            0.02, 0.02, params, transform=axes[j + 1].transAxes, fontsize=7, va="bottom",
            bbox=dict(facecolor="white", alpha=0.75, edgecolor="none"),
        )  # fmt: skip
    fig.suptitle("Per-cluster images of warped events (membership-weighted, blurred)", fontsize=10)
    fig.savefig(path, dpi=100, format="png")
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    import cmax_taichi as cm
    from cmax_taichi.cli import CliError

    regs = common.parse_regularizers(args.reg)
    if args.example is not None:
        from cmax_taichi.sim.examples import SEGMENT_EXAMPLES

        if args.path is not None:
            raise CliError("give a recording PATH or --example NAME, not both")
        window = ("start", "t_start", "duration")
        chosen = [f"--{n.replace('_', '-')}" for n in window if getattr(args, n) is not None]
        if chosen:
            raise CliError(f"{', '.join(chosen)}: options of a recording's window (an example is one window)")
        if args.example not in SEGMENT_EXAMPLES:
            valid = ", ".join(SEGMENT_EXAMPLES)
            raise CliError(f"--example: unknown example {args.example!r}; valid: {valid}")
        args.warp = args.warp or SEGMENT_EXAMPLES[args.example].warp
    elif args.path is None:
        raise CliError("give a recording PATH, or --example NAME for a simulated scene")
    if args.sensor_size is not None:
        from cmax_taichi.core.checks import sensor_size

        try:
            args.sensor_size = sensor_size(args.sensor_size)
        except (TypeError, ValueError) as exc:
            raise CliError(f"--sensor-size: {exc}") from None
    args.warp = args.warp or "mitrokhin4"
    if args.clusters < 1:
        raise CliError(f"-k/--clusters must be at least 1, got {args.clusters}")
    warps = [w.strip() for w in args.warp.split(",") if w.strip()]
    if len(warps) not in (1, args.clusters):
        raise CliError(f"--warp: give one model or {args.clusters} comma-separated models, got {len(warps)}")
    for w in warps:
        cm.get_warp(w)  # ValueError listing the valid names
    cm.OBJECTIVES.get(args.objective)
    t_ref = common.parse_t_ref(args.t_ref)
    if args.example is not None:  # the example's truths against the models, before anything is simulated
        from cmax_taichi.sim.examples import check_example

        check_example(args.example, warps)
    from cmax_taichi import io
    from cmax_taichi.io.outputs import OutputFolder

    folder = OutputFolder(
        args.out,
        inputs=[] if args.example is not None else [Path(args.path)],
        patterns=OUTPUT_PATTERNS,
        command="segment",
    )
    example = None
    if args.example is not None:
        from cmax_taichi.sim.examples import make_example

        folder.check()
        common.init_backend(args.arch, args.precision, args.compile)
        path = Path(f"example:{args.example}")
        example = make_example(args.example)
        events, camera = example.events, example.camera
    else:
        path = Path(args.path)
        if not path.exists():
            raise CliError(f"{path}: no such file or folder")
        folder.check()  # an OUT that is an input, or holds files this run may not replace: before any work
        common.init_backend(args.arch, args.precision, args.compile)
        options = {} if args.sensor_size is None else {"sensor_size": tuple(args.sensor_size)}
        with io.open_recording(path, format=args.format, **options) as rec:
            if any(cm.get_warp(w).needs_camera for w in warps) and rec.camera is None:
                raise CliError(f"warp {args.warp!r} needs a calibration, and {path} has none (calib.txt)")
            events = _read_window(rec, args)
            camera = rec.camera
    if len(events) < args.clusters:
        raise CliError(f"the window has {len(events)} events, fewer than the {args.clusters} clusters")
    res = cm.segment(
        events,
        args.clusters,
        warp=warps[0] if len(warps) == 1 else warps,
        objective=args.objective,
        regularizers=regs,
        camera=camera,
        t_ref=t_ref,
        blur_sigma=args.blur,
        temperature=args.temperature,
        hard=args.hard,
        max_iterations=args.max_iterations,
        seed=args.seed,
        progress=not args.quiet,
    )

    with folder:
        _write_outputs(folder, args, path, events, res, regs, t_ref, warps, example)
        written = folder.commit()  # every file moved into place whole, now that all are written
    print("wrote: " + ", ".join(str(p) for p in written))
    sys.stdout.flush()
    return 0


def _write_outputs(folder, args, path, events, res, regs, t_ref, warps, example) -> None:
    """The labels, the JSON summary and the figures, into the staging folder of ``folder``."""
    import numpy as np

    import cmax_taichi as cm
    from cmax_taichi.io.outputs import json_text
    from cmax_taichi.testing.reference import bilinear_votes, gaussian_blur

    with folder.path("labels.npy").open("wb") as fh:
        np.save(fh, res.labels)
    K = res.n_clusters
    table = np.column_stack([events.t, events.x, events.y, events.p, res.labels, res.probabilities])
    header = "t_s,x_px,y_px,p,label," + ",".join(f"p_{j}" for j in range(K))
    fmt = ["%.9f", "%.3f", "%.3f", "%d", "%d"] + ["%.4f"] * K
    np.savetxt(folder.path("labels.csv"), table, delimiter=",", header=header, comments="", fmt=fmt)
    thetas = list(res.thetas)
    clusters = []
    for j in range(K):
        m = cm.get_warp(res.warps[j])
        clusters.append(
            {
                "cluster": j,
                "warp": m.name,
                "parameters": {n: float(v) for n, v in zip(m.params, thetas[j], strict=True)},
                "units": dict(zip(m.params, m.units, strict=True)),
                "events": int(np.sum(res.labels == j)),
                "empty": bool(res.empty[j]),
            }
        )
    summary = {
        "path": str(path),
        "window": {
            "n_events": len(events),
            "t_start_s": float(events.t[0]),
            "t_end_s": float(events.t[-1]),
            "dropped_by_undistortion": int(np.sum(res.labels < 0)),
        },
        "settings": {
            "clusters": K,
            "warp": warps,
            "objective": args.objective,
            "regularizers": regs,
            "temperature": args.temperature,
            "hard": args.hard,
            "blur_sigma_px": args.blur,
            "t_ref": t_ref,
            "backend": cm.backend_info().arch,
            "precision": cm.backend_info().precision,
        },
        "clusters": clusters,
        "value": res.value,
        "iterations": len(res.history),
        "converged": res.converged,
        "seconds": res.seconds,
        "history": res.history,
    }
    folder.path("segmentation.json").write_text(json_text(summary))
    if not args.no_figures:
        _events_figure(folder.path("figures/events_by_cluster.png"), events, res)
        W, H = events.sensor_size
        used = res.events  # undistorted when a camera with distortion was given
        raw = gaussian_blur(bilinear_votes(used.x, used.y, 1.0, W, H), args.blur)
        _iwe_figure(folder.path("figures/cluster_iwes.png"), events, res, raw)
    segmented = int(np.sum(res.labels >= 0))
    dropped = f" ({len(events) - segmented} dropped by undistortion)" if segmented < len(events) else ""
    print(
        f"segmented {segmented} of {len(events)} events of {path}{dropped} into {K} clusters in "
        f"{res.seconds:.2f} s ({len(res.history)} iterations, converged={res.converged})"
    )
    for c in clusters:
        params = ", ".join(f"{n}={v:.4g} {c['units'][n]}" for n, v in c["parameters"].items())
        state = " (empty)" if c["empty"] else ""
        print(f"  cluster {c['cluster']} [{c['warp']}]: {c['events']} events{state}; {params}")
    if example is not None:
        _report_example(example, res, folder.path("truth.json"))


def _layer_truth(example, layer: int, warp: str) -> list[float]:
    """The true parameters of ``layer`` in the model of its cluster, else in the layer's own model."""
    try:
        return [float(v) for v in example.truth_in(warp, layer)]
    except ValueError:
        return [float(v) for v in example.recording.theta_at(0.0, layer=layer)]


def _report_example(example, res, path: Path) -> Path:
    """Print a segmented example against its true labels and motions; write them to ``path`` (JSON)."""
    from cmax_taichi.io.outputs import json_text
    from cmax_taichi.lab.segment_eval import label_accuracy, match_clusters

    truth = example.labels
    mapping = match_clusters(res.labels, truth, res.n_clusters)
    accuracy = label_accuracy(res.labels, truth, res.n_clusters)
    print(f"example {example.example.name!r}: {example.example.description}")
    print(f"  simulated: {len(example.events)} events, {example.events.duration * 1e3:.1f} ms (seed 0)")
    objects = []
    for layer in sorted(mapping):
        cluster = mapping[layer]
        true_theta = _layer_truth(example, layer, res.warps[cluster])
        estimate = [float(v) for v in res.thetas[cluster]]
        name = "background" if layer == 0 else f"object {layer}"
        print(
            f"  {name}: {int((truth == layer).sum())} events -> cluster {cluster}; true "
            f"{[round(v, 3) for v in true_theta]}, estimated {[round(v, 3) for v in estimate]}"
        )
        objects.append({"layer": layer, "cluster": cluster, "truth": true_theta, "estimate": estimate})
    print(f"  events in the cluster matched to their true layer: {100 * accuracy:.1f}%")
    report = {"example": example.example.name, "accuracy": accuracy, "layers": objects}
    path.write_text(json_text(report, indent=2))
    return path
