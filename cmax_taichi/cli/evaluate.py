"""Compare the estimates of 'cmax-taichi estimate', or dense flow files, with the recording's ground truth.

For each window of RESULTS (the results.json that 'estimate' wrote, or its folder):

* angular velocity (rotation3, recordings with a gyro or motion.txt): error |w_est - w_gt| in deg/s,
  relative to |w_gt|, and the FWL of the ground truth;
* optical flow (recordings with flow ground truth): AEE (px) and NPE (% of pixels with endpoint
  error > N px) of the flow the estimate implies over the window, on pixels with valid ground truth
  and at least one event;
* the estimate's FWL (variance of its IWE over the identity warp's) as 'estimate' computed it.

Dense flow (RESULTS a folder of flow files, or one file, with --data): each file's flow, the
displacement over its interval, against the ground truth over that interval (MVSEC *_gt_flow_dist.npz
accumulated as EV-FlowNet does, DSEC flow PNGs, the simulator's files): AEE, NPE, %Out (EPE > 3 px
and > 5% of the truth) and AE on the pixels with valid ground truth and at least one event. Files:
flow_*.npz with t_start, t_end (what 'estimate --flow-out DIR --flow-format npz' writes), or .flo /
DSEC .png files with --timestamps (t_start t_end in s per line, or DSEC's from_us, to_us[, file_index]).

Writes OUT/metrics.csv and OUT/metrics.json (OUT defaults to the results folder) and prints a summary
with the RMS angular-velocity error (deg/s) and the mean AEE / NPE.

examples:
  cmax-taichi estimate ../shared/data/ecd_rotation/boxes_rotation --warp rotation3 --out out_boxes
  cmax-taichi evaluate out_boxes
  cmax-taichi evaluate flows/ --data indoor_flying1_data.hdf5
  cmax-taichi evaluate submission/zurich_city_01_a --data zurich_city_01_a --timestamps stamps.csv
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import warnings
from pathlib import Path

from cmax_taichi.cli._common import (
    add_backend_arguments,
    add_plugin_argument,
    add_sensor_size_argument,
    init_backend,
    names,
)
from cmax_taichi.io import FORMATS

NAME = "evaluate"
HELP = "metrics of 'estimate' results or dense flow files against ground truth (angular error, AEE, NPE, FWL)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "results",
        metavar="RESULTS",
        help="results.json written by 'estimate' (or its folder), or dense flow files (a folder or one file)",
    )
    parser.add_argument(
        "--data", default=None, metavar="PATH", help="the recording (default: the one the results name)"
    )
    parser.add_argument(
        "--timestamps",
        default=None,
        metavar="FILE",
        help="intervals of .flo / .png files: 't_start t_end' (s) per line, or DSEC's from_us, to_us[, idx]",
    )
    parser.add_argument("--format", default=None, help=f"{names(FORMATS)} (default: detected)")
    add_sensor_size_argument(
        parser, "the recording's sensor size in px when it is not the format's (e.g. a scaled simulation)"
    )
    parser.add_argument(
        "--npe", default="3,10,20", metavar="N,N,...", help="NPE thresholds in px (default 3,10,20)"
    )
    parser.add_argument(
        "--out", default=None, metavar="DIR", help="output folder (default: the results folder)"
    )
    add_backend_arguments(parser, precision=False, compile_mode=False)
    add_plugin_argument(parser)  # results of a user's model: its plugin names its flow


def _thresholds(text: str) -> tuple[float, ...]:
    from cmax_taichi.cli import CliError

    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise CliError(f"--npe expects comma-separated numbers of pixels, got {text!r}") from None
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise CliError(f"--npe expects positive numbers of pixels, got {text!r}")
    return values


def run(args: argparse.Namespace) -> int:
    import numpy as np

    import cmax_taichi as cm
    from cmax_taichi import io
    from cmax_taichi.cli import CliError
    from cmax_taichi.core.checks import UndistortionTally
    from cmax_taichi.metrics import angular_velocity_error, event_mask, flow_error, flow_from_warp, fwl
    from cmax_taichi.solve.sequence import read_results

    thresholds = _thresholds(args.npe)
    results_path = Path(args.results)
    if _is_flow_source(results_path):
        return _run_flows(args, results_path, thresholds)
    if args.timestamps is not None:
        raise CliError("--timestamps goes with flow files (.flo, .png), not with estimate results")
    if results_path.is_dir():
        results_path = results_path / "results.json"
    if not results_path.is_file():
        raise CliError(f"{results_path}: no such results file (run 'cmax-taichi estimate' first)")
    result = read_results(results_path)
    data = args.data or result.settings.get("source")
    if not data:
        raise CliError(f"{results_path} names no recording: pass --data PATH")
    fmt = args.format or result.settings.get("format")
    init_backend(args.arch, None)
    model = cm.get_warp(result.warp)
    rows = []
    lossy = UndistortionTally()
    with io.open_recording(data, format=fmt, **_size(args)) as rec, warnings.catch_warnings():
        camera = rec.camera
        for w in result.windows:
            row: dict = {"index": w.index, "t_start": w.t_start, "t_end": w.t_end, "fwl": w.fwl}
            events = rec.read_time(w.t_start, float(np.nextafter(w.t_end, np.inf)))
            if camera is not None and camera.has_distortion and not events.undistorted:
                read, events = events, events.undistort(camera)
                lossy.add(read, events)  # one warning for the first window, the totals at the end
            t_mid = 0.5 * (w.t_start + w.t_end)
            w_gt = rec.angular_velocity(t_mid)
            if w_gt is not None and model.name == "rotation3":
                err = angular_velocity_error(w.theta, w_gt)
                row["w_gt"] = [float(v) for v in np.asarray(w_gt).reshape(-1)]
                row["error_deg_s"] = float(err["error_deg_s"][0])
                row["relative_error"] = float(err["relative"][0])
                row["fwl_gt"] = fwl(events, model, w_gt, camera=camera) if len(events) > 1 else math.nan
            duration = w.t_end - w.t_start
            gt_flow = rec.flow(w.t_start, w.t_end) if duration > 0 else None
            if gt_flow is not None:
                pred = flow_from_warp(
                    model, w.theta, rec.sensor_size, camera=camera, duration=duration, dt=duration
                )
                row.update(flow_error(pred, gt_flow, event_mask(events), thresholds))
            rows.append(row)
    lossy.report()
    if not any(("error_deg_s" in r) or ("AEE" in r) for r in rows):
        raise CliError(
            f"{data}: no ground truth to compare with (angular velocity for rotation3, or optical flow)"
        )
    out = Path(args.out) if args.out else results_path.parent
    _write_metrics_csv(out, rows)
    summary: dict = {"windows": len(rows), "warp": result.warp, "recording": str(data)}
    ang = [r for r in rows if "error_deg_s" in r]
    print(f"{len(rows)} window(s) of {data}, warp {result.warp}")
    if ang:
        err = angular_velocity_error(
            [result.windows[i].theta for i, r in enumerate(rows) if "error_deg_s" in r],
            [r["w_gt"] for r in ang],
        )
        summary["rms_angular_error_deg_s"] = err["rms_deg_s"]
        summary["rms_angular_error_axes_deg_s"] = [float(v) for v in err["rms_axes_deg_s"]]
        summary["mean_relative_error"] = float(np.mean([r["relative_error"] for r in ang]))
        print(
            f"  angular velocity: RMS error {err['rms_deg_s']:.3f} deg/s "
            f"(x, y, z: {', '.join(f'{v:.3f}' for v in err['rms_axes_deg_s'])}), "
            f"mean relative error {100 * summary['mean_relative_error']:.1f}%"
        )
        fwl_gt = [r["fwl_gt"] for r in ang if math.isfinite(r["fwl_gt"])]
        if fwl_gt:
            summary["mean_fwl_gt"] = float(np.mean(fwl_gt))
            print(f"  FWL of the ground truth: mean {summary['mean_fwl_gt']:.4f}")
    flows = [r for r in rows if "AEE" in r and math.isfinite(r["AEE"])]
    if flows:
        summary["mean_AEE"] = float(np.mean([r["AEE"] for r in flows]))
        print(f"  flow: mean AEE {summary['mean_AEE']:.3f} px", end="")
        for t in thresholds:
            key = f"{t:g}PE"
            summary[f"mean_{key}"] = float(np.mean([r[key] for r in flows]))
            print(f", {key} {summary[f'mean_{key}']:.2f}%", end="")
        print()
    fwls = [r["fwl"] for r in rows if math.isfinite(r["fwl"])]
    if fwls:
        summary["mean_fwl"] = float(np.mean(fwls))
        print(f"  FWL of the estimate: mean {summary['mean_fwl']:.4f}")
    (out / "metrics.json").write_text(json.dumps({"summary": summary, "windows": rows}, indent=1))
    print(f"wrote: {out / 'metrics.csv'}, {out / 'metrics.json'}")
    return 0


def _write_metrics_csv(out: Path, rows: list[dict]) -> None:
    """``out/metrics.csv`` (``out`` made if missing): a row per window, the columns every key of any row
    in first-seen order; a key a row lacks is empty, a list (per-threshold values) is written as JSON."""
    out.mkdir(parents=True, exist_ok=True)
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with (out / "metrics.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(keys)
        for r in rows:
            writer.writerow([json.dumps(r[k]) if isinstance(r.get(k), list) else r.get(k, "") for k in keys])


def _size(args: argparse.Namespace) -> dict:
    return {} if args.sensor_size is None else {"sensor_size": tuple(args.sensor_size)}


def _is_flow_source(path: Path) -> bool:
    """Flow files rather than estimate results: a flow file, or a folder of them without results.json."""
    from cmax_taichi.io.writers import FLOW_FORMATS

    if path.is_file():
        return path.suffix.lower().lstrip(".") in FLOW_FORMATS
    if path.is_dir() and not (path / "results.json").is_file():
        return any(f.suffix.lower().lstrip(".") in FLOW_FORMATS for f in path.iterdir())
    return False


def _run_flows(args: argparse.Namespace, source: Path, thresholds: tuple[float, ...]) -> int:
    """Dense flow files against the ground truth of --data (see the module docstring)."""
    import numpy as np

    from cmax_taichi import io
    from cmax_taichi.cli import CliError
    from cmax_taichi.io.writers import read_flow_windows
    from cmax_taichi.metrics import score_flow

    if not args.data:
        raise CliError("evaluating flow files needs the recording with the ground truth: --data PATH")
    try:
        windows = read_flow_windows(source, args.timestamps)
    except (OSError, KeyError, ValueError) as exc:
        raise CliError(str(exc)) from None
    rows = []
    with io.open_recording(args.data, format=args.format, **_size(args)) as rec:
        W, H = rec.sensor_size
        for k, w in enumerate(windows):
            try:
                flow = w.displacement()
            except (OSError, KeyError, ValueError) as exc:
                raise CliError(str(exc)) from None
            if flow.shape != (2, H, W):
                raise CliError(
                    f"{w.path}: flow of {flow.shape[2]}x{flow.shape[1]} px, the recording is {W}x{H}"
                )
            try:
                err = score_flow(rec, flow, w.t_start, w.t_end, thresholds)
            except ValueError as exc:  # an interval outside the ground truth
                raise CliError(f"{w.path}: {exc}") from None
            if err is None:
                raise CliError(f"{args.data}: no flow ground truth to compare with")
            rows.append({"index": k, "file": w.path.name, "t_start": w.t_start, "t_end": w.t_end, **err})
    out = Path(args.out) if args.out else (source if source.is_dir() else source.parent)
    _write_metrics_csv(out, rows)
    scored = [r for r in rows if math.isfinite(r["AEE"])]
    summary: dict = {
        "windows": len(rows),
        "scored": len(scored),
        "recording": str(args.data),
        "flows": str(source),
    }
    print(f"{len(rows)} flow file(s) of {source} against {args.data} ({len(scored)} with pixels to score)")
    if scored:
        names = ["AEE", *(f"{t:g}PE" for t in thresholds), "outlier", "AE_deg"]
        for name in names:
            summary[f"mean_{name}"] = float(np.mean([r[name] for r in scored]))
        summary["mean_n_pixels"] = float(np.mean([r["n_pixels"] for r in scored]))
        npe = ", ".join(f"{t:g}PE {summary[f'mean_{t:g}PE']:.2f}%" for t in thresholds)
        print(
            f"  flow: mean AEE {summary['mean_AEE']:.3f} px, {npe}, %Out {summary['mean_outlier']:.2f}%, "
            f"AE {summary['mean_AE_deg']:.2f} deg over {summary['mean_n_pixels']:.0f} px per window"
        )
    missing = sum(int(r["n_missing"]) for r in rows)
    if missing:
        print(f"  {missing} pixel(s) with ground truth and events had no finite flow (NaN): not scored")
    (out / "metrics.json").write_text(json.dumps({"summary": summary, "windows": rows}, indent=1))
    print(f"wrote: {out / 'metrics.csv'}, {out / 'metrics.json'}")
    return 0
