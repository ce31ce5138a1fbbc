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
The flow files of a 'cmax-taichi flow' output folder need neither --data nor --timestamps: its
summary.json names the recording and its flow_timestamps.txt holds the intervals.

Writes OUT/metrics.csv and OUT/metrics.json (OUT defaults to the folder of the results or of the flow
files; RESULTS may also be a 'cmax-taichi flow' output folder) and prints a summary with the RMS
angular-velocity error (deg/s) and the mean AEE / NPE. OUT is guarded as every command's output folder
is: never the recording nor a folder holding it, no file replaced that evaluate did not write, the files
in place only when complete.

The results and the .npz flow files of 'estimate' and 'flow' carry the recording's fingerprint: --data
is refused when it is another recording (--ignore-fingerprint scores it all the same). A ground truth
that cannot be read is an error naming its file; windows with nothing to score (no valid ground truth,
no events) are counted and said, and a run that scores nothing is an error.

examples:
  cmax-taichi estimate ../shared/data/ecd_rotation/boxes_rotation --warp rotation3 --out out_boxes
  cmax-taichi evaluate out_boxes
  cmax-taichi evaluate flows/ --data indoor_flying1_data.hdf5
  cmax-taichi evaluate submission/zurich_city_01_a --data zurich_city_01_a --timestamps stamps.csv
"""

from __future__ import annotations

import argparse
import contextlib
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
        help="intervals of .flo / .png files: 't_start t_end' (s) per line, or DSEC's from_us, to_us[, idx] "
        "(default: the flow_timestamps.txt of the 'cmax-taichi flow' run that wrote them)",
    )
    parser.add_argument("--format", default=None, help=f"{names(FORMATS)} (default: detected)")
    add_sensor_size_argument(
        parser, "the recording's sensor size in px when it is not the format's (e.g. a scaled simulation)"
    )
    parser.add_argument(
        "--npe", default="3,10,20", metavar="N,N,...", help="NPE thresholds in px (default 3,10,20)"
    )
    parser.add_argument(
        "--out", default=None, metavar="DIR", help="output folder (default: the folder of RESULTS' files)"
    )
    parser.add_argument(
        "--ignore-fingerprint",
        action="store_true",
        help="score against --data even when it is not the recording the results were estimated on",
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
    from cmax_taichi.cli import CliError

    thresholds = _thresholds(args.npe)
    results_path = Path(args.results)
    flows = _flow_source(results_path)
    if flows is not None:
        return _run_flows(args, flows, thresholds)
    if args.timestamps is not None:
        raise CliError("--timestamps goes with flow files (.flo, .png), not with estimate results")
    if results_path.is_dir():
        if not (results_path / "results.json").is_file():
            raise CliError(
                f"{results_path}: neither the results of 'cmax-taichi estimate' (results.json) nor flow "
                f"files ({', '.join('.' + f for f in _flow_formats())})"
            )
        results_path = results_path / "results.json"
    if not results_path.is_file():
        raise CliError(f"{results_path}: no such results file (run 'cmax-taichi estimate' first)")
    return _run_results(args, results_path, thresholds)


def _run_results(args: argparse.Namespace, results_path: Path, thresholds: tuple[float, ...]) -> int:
    """The results of 'estimate' against the recording's ground truth (see the module docstring)."""
    import numpy as np

    import cmax_taichi as cm
    from cmax_taichi import io
    from cmax_taichi.cli import CliError
    from cmax_taichi.core.checks import UndistortionTally
    from cmax_taichi.flow.sequence import unscored_reason
    from cmax_taichi.io._flow import GroundTruthRangeError
    from cmax_taichi.metrics import angular_velocity_error, event_mask, flow_error, flow_from_warp, fwl
    from cmax_taichi.solve.sequence import read_results

    result = read_results(results_path)
    data = args.data or result.settings.get("source")
    if not data:
        raise CliError(f"{results_path} names no recording: pass --data PATH")
    fmt = args.format or result.settings.get("format")
    folder = _output_folder(args, results_path.parent, data)
    init_backend(args.arch, None)
    model = cm.get_warp(result.warp)
    rows = []
    lossy = UndistortionTally()
    with io.open_recording(data, format=fmt, **_size(args)) as rec, warnings.catch_warnings():
        _check_fingerprint(args, rec, [result.settings.get("fingerprint")], results_path)
        camera = rec.camera
        for w in result.windows:
            row: dict = {"index": w.index, "t_start": w.t_start, "t_end": w.t_end, "fwl": w.fwl}
            if w.t_end < rec.t_start or w.t_start > rec.t_end:  # an edited file: no truth there to trust
                row["note"] = "a time span outside the recording's"
                rows.append(row)
                continue
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
            try:
                gt_flow = rec.flow(w.t_start, w.t_end) if duration > 0 else None
            except GroundTruthRangeError:
                gt_flow, row["note"] = None, "outside the interval the ground truth covers"
            if gt_flow is not None:
                pred = flow_from_warp(
                    model, w.theta, rec.sensor_size, camera=camera, duration=duration, dt=duration
                )
                err = flow_error(pred, gt_flow, event_mask(events), thresholds)
                reason = unscored_reason(err)
                row.update({"note": reason} if reason else err)
            rows.append(row)
    lossy.report()
    if not any(("error_deg_s" in r) or ("AEE" in r) for r in rows):
        notes = _notes(rows)
        why = f": {notes}" if notes else " (angular velocity for rotation3, or optical flow)"
        raise CliError(f"{data}: no ground truth to compare with{why}")
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
    flows = [r for r in rows if "AEE" in r]
    if flows:
        summary["mean_AEE"] = float(np.mean([r["AEE"] for r in flows]))
        print(f"  flow: mean AEE {summary['mean_AEE']:.3f} px", end="")
        for t in thresholds:
            key = f"{t:g}PE"
            summary[f"mean_{key}"] = float(np.mean([r[key] for r in flows]))
            print(f", {key} {summary[f'mean_{key}']:.2f}%", end="")
        print()
    _print_unscored(rows, summary)
    fwls = [r["fwl"] for r in rows if math.isfinite(r["fwl"])]
    if fwls:
        summary["mean_fwl"] = float(np.mean(fwls))
        print(f"  FWL of the estimate: mean {summary['mean_fwl']:.4f}")
    return _write(folder, summary, rows)


def _flow_formats() -> tuple[str, ...]:
    from cmax_taichi.io.writers import FLOW_FORMATS

    return FLOW_FORMATS


def _output_folder(args: argparse.Namespace, default: Path, data):
    """The OutputFolder of --out (default ``default``), checked now, before any work: never the
    recording nor a folder that holds it, no file replaced that evaluate did not write."""
    from cmax_taichi.io.outputs import OutputFolder

    out = Path(args.out) if args.out else default
    folder = OutputFolder(
        out, inputs=[Path(data)], patterns=["metrics.csv", "metrics.json"], command="evaluate"
    )
    folder.check()
    return folder


def _write(folder, summary: dict, rows: list[dict]) -> int:
    """metrics.csv and metrics.json into ``folder``, committed together."""
    from cmax_taichi.io.outputs import json_text

    with folder:
        _write_metrics_csv(folder.path("metrics.csv"), rows)
        folder.path("metrics.json").write_text(json_text({"summary": summary, "windows": rows}))
        written = folder.commit()
    print("wrote: " + ", ".join(str(p) for p in written))
    return 0


def _notes(rows: list[dict]) -> str:
    """The reasons windows were not scored, with their counts ("" when none)."""
    counts: dict[str, int] = {}
    for r in rows:
        if r.get("note"):
            counts[r["note"]] = counts.get(r["note"], 0) + 1
    return "; ".join(f"{n} window(s) with {note}" for note, n in counts.items())


def _print_unscored(rows: list[dict], summary: dict) -> None:
    notes = _notes(rows)
    if notes:
        summary["not_scored"] = notes
        print(f"  not scored: {notes}")


def _write_metrics_csv(path: Path, rows: list[dict]) -> None:
    """``path``: a row per window, the columns every key of any row in first-seen order; a key a row
    lacks (or a number that is not finite) is empty, a list (per-threshold values) is written as JSON."""
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]

    def cell(value):
        if isinstance(value, list):
            return json.dumps(value)
        if isinstance(value, float) and not math.isfinite(value):
            return ""
        return value

    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(keys)
        for r in rows:
            writer.writerow([cell(r.get(k, "")) for k in keys])


def _size(args: argparse.Namespace) -> dict:
    return {} if args.sensor_size is None else {"sensor_size": tuple(args.sensor_size)}


def _flow_source(path: Path) -> Path | None:
    """The flow files to score (a flow file, a folder of them, or the ``flow/`` folder of a 'cmax-taichi
    flow' output folder), or None for estimate results."""
    formats = _flow_formats()

    def holds_flows(folder: Path) -> bool:
        return any(f.suffix.lower().lstrip(".") in formats and f.is_file() for f in folder.iterdir())

    if path.is_file():
        return path if path.suffix.lower().lstrip(".") in formats else None
    if not path.is_dir() or (path / "results.json").is_file():
        return None
    if holds_flows(path):
        return path
    if (path / "flow").is_dir() and holds_flows(path / "flow"):
        return path / "flow"  # the output folder of 'cmax-taichi flow'
    return None


def _check_fingerprint(args: argparse.Namespace, rec, carried: list, what: Path) -> None:
    """CliError when the recording ``rec`` (--data) is not the one the results were estimated on (their
    fingerprints, ``carried``, differ), unless --ignore-fingerprint."""
    from cmax_taichi.cli import CliError

    expected = {str(f) for f in carried if f}
    if not expected or args.ignore_fingerprint:
        return
    actual = rec.fingerprint()
    if actual is not None and actual not in expected:
        raise CliError(
            f"{rec.path} is not the recording {what} was estimated on (fingerprint {actual}, the results "
            f"name {', '.join(sorted(expected))}): give that recording as --data, or --ignore-fingerprint "
            "to score them all the same"
        )


def _flow_run(source: Path) -> tuple[Path, dict]:
    """``(folder, recording)``: the output folder of the 'cmax-taichi flow' run that wrote the flow files
    of ``source`` and the recording its summary.json names (``source``, ``format``, ``fingerprint``);
    an empty dict where ``source`` is not a flow run's ``flow/`` folder."""
    folder = source if source.is_dir() else source.parent
    summary = folder.parent / "summary.json"
    if folder.name == "flow" and summary.is_file():
        with contextlib.suppress(OSError, ValueError, KeyError, TypeError):  # not a flow run's summary
            recording = json.loads(summary.read_text())["recording"]
            if isinstance(recording, dict):
                return folder.parent, recording
    return folder.parent, {}


def _flow_fingerprints(source: Path, windows) -> list:
    """The fingerprints the flow files carry (.npz), or that the summary.json of the 'cmax-taichi flow'
    run that wrote them names."""
    carried = [w.fingerprint for w in windows if w.fingerprint]
    recorded = _flow_run(source)[1].get("fingerprint")
    if not carried and recorded:
        carried.append(recorded)
    return carried


def _needs_timestamps(source: Path) -> bool:
    """Whether some flow file of ``source`` carries no interval (.flo, .png: only .npz files do)."""
    from cmax_taichi.io.writers import FLOW_FORMATS

    files = source.iterdir() if source.is_dir() else [source]
    return any(f.suffix.lower().lstrip(".") in FLOW_FORMATS and f.suffix.lower() != ".npz" for f in files)


def _check_intervals(windows, rec, timestamps) -> None:
    """CliError when no interval of the flow files meets the recording's time span: the intervals are
    in another time base or unit than the recording (whole numbers read as microseconds...)."""
    from cmax_taichi.cli import CliError
    from cmax_taichi.io.writers import timestamps_unit

    t0, t1 = rec.t_start, rec.t_end
    if any(w.t_end >= t0 and w.t_start <= t1 for w in windows):
        return
    a, b = min(w.t_start for w in windows), max(w.t_end for w in windows)
    where = f"the flow files' intervals ({a:.6f} .. {b:.6f} s"
    hint = ""
    if timestamps is not None:
        unit = timestamps_unit(timestamps)
        where += f", {timestamps} read as {'microseconds: whole numbers' if unit == 'us' else 'seconds'}"
        factor = 1e6 if unit == "us" else 1e-6
        if b * factor >= t0 and a * factor <= t1:
            other = "seconds" if unit == "us" else "microseconds"
            hint = (
                f"; read as {other} they would fall inside it: write seconds with a decimal point "
                "(e.g. 1.0 2.0), microseconds as whole numbers"
            )
    raise CliError(f"{where}) lie outside the recording's {t0:.6f} .. {t1:.6f} s: nothing to score{hint}")


def _run_flows(args: argparse.Namespace, source: Path, thresholds: tuple[float, ...]) -> int:
    """Dense flow files against the ground truth of --data (see the module docstring)."""
    import numpy as np

    from cmax_taichi import io
    from cmax_taichi.cli import CliError
    from cmax_taichi.flow.sequence import unscored_reason
    from cmax_taichi.io._flow import GroundTruthRangeError
    from cmax_taichi.io.writers import read_flow_windows
    from cmax_taichi.metrics import score_flow

    # a 'cmax-taichi flow' run's folder names its recording and holds the intervals of its files
    run_folder, recording = _flow_run(source)
    if recording:
        if not args.data and recording.get("source"):
            args.data, args.format = recording["source"], args.format or recording.get("format")
            if not Path(args.data).exists():
                raise CliError(
                    f"{run_folder / 'summary.json'} names the recording {args.data}, which is not there: "
                    "give it with --data PATH"
                )
        stamps = run_folder / "flow_timestamps.txt"
        if args.timestamps is None and stamps.is_file() and _needs_timestamps(source):
            args.timestamps = str(stamps)
    if not args.data:
        raise CliError("evaluating flow files needs the recording with the ground truth: --data PATH")
    windows = read_flow_windows(source, args.timestamps)
    folder = _output_folder(args, source if source.is_dir() else source.parent, args.data)
    rows = []
    with io.open_recording(args.data, format=args.format, **_size(args)) as rec:
        _check_fingerprint(args, rec, _flow_fingerprints(source, windows), source)
        _check_intervals(windows, rec, args.timestamps)
        W, H = rec.sensor_size
        for k, w in enumerate(windows):
            flow = w.displacement()
            if flow.shape != (2, H, W):
                raise CliError(
                    f"{w.path}: flow of {flow.shape[2]}x{flow.shape[1]} px, the recording is {W}x{H}"
                )
            row = {"index": k, "file": w.path.name, "t_start": w.t_start, "t_end": w.t_end}
            try:
                err = score_flow(rec, flow, w.t_start, w.t_end, thresholds)
            except GroundTruthRangeError as exc:  # an interval outside the ground truth
                raise CliError(f"{w.path}: {exc}") from None
            if err is None:
                raise CliError(f"{args.data}: no flow ground truth to compare with")
            reason = unscored_reason(err)
            row.update({"note": reason, "n_missing": err["n_missing"]} if reason else err)
            rows.append(row)
    scored = [r for r in rows if "AEE" in r]
    if not scored:
        raise CliError(f"{source} against {args.data}: nothing to score: {_notes(rows)}")
    summary: dict = {
        "windows": len(rows),
        "scored": len(scored),
        "recording": str(args.data),
        "flows": str(source),
    }
    print(f"{len(rows)} flow file(s) of {source} against {args.data} ({len(scored)} with pixels to score)")
    names = ["AEE", *(f"{t:g}PE" for t in thresholds), "outlier", "AE_deg"]
    for name in names:
        summary[f"mean_{name}"] = float(np.mean([r[name] for r in scored]))
    summary["mean_n_pixels"] = float(np.mean([r["n_pixels"] for r in scored]))
    npe = ", ".join(f"{t:g}PE {summary[f'mean_{t:g}PE']:.2f}%" for t in thresholds)
    print(
        f"  flow: mean AEE {summary['mean_AEE']:.3f} px, {npe}, %Out {summary['mean_outlier']:.2f}%, "
        f"AE {summary['mean_AE_deg']:.2f} deg over {summary['mean_n_pixels']:.0f} px per window"
    )
    _print_unscored(rows, summary)
    missing = sum(int(r["n_missing"]) for r in rows)
    if missing:
        print(f"  {missing} pixel(s) with ground truth and events had no finite flow (NaN): not scored")
    return _write(folder, summary, rows)
