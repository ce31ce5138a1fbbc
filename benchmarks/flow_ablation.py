"""What each regularizer of the dense flow does: an ablation over regularizers, weights and reference times.

    python -m benchmarks.flow_ablation [--quick] [--out DIR] [--datasets sim ecd mvsec]
                                       [--variants LABEL ...] [--references first middle multi]
                                       [--kink-widths W ...] [--max-events N]

Every variant (a set of regularizers and weights: none, total variation, curvature, divergence,
deformation, both, and the combinations of those with the curvature prior, over a decade of weights)
runs at every reference time (``first``, ``middle``, ``multi``) on every window of three kinds of data:

* ``sim``: the simulator's depth scenes of ``benchmarks/dense_flow_accuracy.py`` (box room, planes, room,
  object, corridor; 346x260, exact flow): AEE px (the displacement over the window on the pixels with
  events, :func:`cmax_taichi.metrics.flow_error`);
* ``ecd``: the four ECD rotation cuts of ``../shared/data/ecd_rotation`` (240x180, raw events undistorted
  by the estimator): AEE px against the gyro's flow (``flow.npy``; the gyro reads 9-23% low on these
  hand-held cuts, ``../shared/data/README.md``), and the FWL of the gyro's rotation for scale;
* ``mvsec``: the MVSEC indoor_flying1 cut of ``../shared/data`` (346x260, no flow truth): all its
  37,050 events on the sensor, its first 30,000 and its three consecutive 12,350-event windows.

Each row gives, per window: AEE (where there is truth), the FWL (variance of the IWE of the events warped
to the first event over that of the unwarped ones, blur 1 px), the share of events whose neighbourhood
the warp shrinks below half its area (``|det(I - dt Du)| < 0.5`` at the event, the collapse's
signature), and what the optimizer did on each level (:attr:`cmax_taichi.flow.LevelReport.status`,
iterations, the largest node move in px). A collapse claim needs a row whose levels moved: the table
marks rows with a stalled level. Beside the variants, the best global translation of each window
(``translation2``, gradient magnitude, ``cm.maximize``) as a constant flow, scored the same way.

Writes ``OUT/flow_ablation.json`` (every row), ``OUT/flow_ablation.csv`` (one line per run) and
``OUT/flow_ablation.md`` (the summary table of benchmarks/NOTES.md). ``--quick`` runs a subset (two windows of
each kind, the variants that docs/flow.md argues from, first and middle reference) in a few minutes.
Kernels compile in the fast mode (``CMAX_TAICHI_COMPILE=fast`` unless set): the same values and
gradients to rounding, 1.4-3.7x slower evaluations, 10-23x quicker compiles for the 20-odd kernel
variants the run needs.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

os.environ.setdefault("CMAX_TAICHI_COMPILE", "fast")

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("CMAX_SHARED_DATA", REPO.parent / "shared" / "data"))
SIM_SCENES = ("boxroom", "planes", "room", "object", "corridor")
ECD_CUTS = ("boxes_rotation", "dynamic_rotation", "poster_rotation", "shapes_rotation")
MVSEC_WINDOWS = ("all", "first 30000", "third 1", "third 2", "third 3")
REFERENCES = ("first", "middle", "multi")
#: share of events shrunk below half their area from which a row counts as collapsed (the collapsed
#: rows of the first runs had 20-45%, every row that the eye sees uncollapsed under 0.5%)
COLLAPSE_SHARE = 0.02

#: (label, regularizers): the variants, in the order of the table
VARIANTS = (
    ("none", {}),
    ("tv 0.1", {"total_variation": 0.1}),
    ("tv 1", {"total_variation": 1.0}),
    ("curv 0.03", {"curvature": 0.03}),
    ("curv 0.1", {"curvature": 0.1}),
    ("curv 0.3", {"curvature": 0.3}),
    ("div 1", {"divergence": 1.0}),
    ("div 10", {"divergence": 10.0}),
    ("def 1", {"deformation": 1.0}),
    ("def 10", {"deformation": 10.0}),
    ("div+def 1", {"divergence": 1.0, "deformation": 1.0}),
    ("div+def 3", {"divergence": 3.0, "deformation": 3.0}),
    ("div+def 10", {"divergence": 10.0, "deformation": 10.0}),
    ("div+def 1 + curv 0.1", {"divergence": 1.0, "deformation": 1.0, "curvature": 0.1}),
    ("div+def 10 + curv 0.1", {"divergence": 10.0, "deformation": 10.0, "curvature": 0.1}),
    ("def 1 + curv 0.1", {"deformation": 1.0, "curvature": 0.1}),
    ("div+def 1 + tv 0.1", {"divergence": 1.0, "deformation": 1.0, "total_variation": 0.1}),
)
QUICK_VARIANTS = ("none", "tv 1", "curv 0.1", "def 10", "div+def 1", "div+def 10", "div+def 1 + curv 0.1")


@dataclass
class Window:
    """One window of events and what it is scored against."""

    dataset: str
    name: str
    events: object  # cm.Events as recorded (raw pixels where the recording has a lens to undistort)
    undistorted: object  # the same, undistorted: what the FWL and the shrink are computed on
    camera: object  # cm.Camera or None
    truth: np.ndarray | None  # (2, H, W) px over the window, NaN where unknown
    true_fwl: float = float("nan")  # the FWL of the true motion (ECD: the gyro's rotation)


# --- data -----------------------------------------------------------------------------------------------
def sim_windows(names, max_events: int | None) -> list[Window]:
    from benchmarks.dense_flow_accuracy import scene_window

    out = []
    for name in names:
        w = scene_window(name)
        ev = _subsampled(w["events"], max_events)
        out.append(Window("sim", name, ev, ev, None, w["truth"]))
    return out


def ecd_windows(names, max_events: int | None) -> list[Window]:
    from cmax_taichi.io import open_recording
    from cmax_taichi.metrics import fwl

    out = []
    for name in names:
        folder = DATA / "ecd_rotation" / name
        if not (folder / "events.txt").exists():
            print(f"skipped ECD {name}: no {folder / 'events.txt'}")
            continue
        with open_recording(folder) as rec:
            ev = rec.read()
            camera = rec.camera
            gyro = np.asarray(rec.angular_velocity(0.5 * (ev.t[0] + ev.t[-1])), dtype=np.float64)
            truth = rec.flow(float(ev.t[0]), float(ev.t[-1]))
        ev = _subsampled(ev, max_events)
        with warnings.catch_warnings():
            warnings.simplefilter(
                "ignore"
            )  # the events undistorted outside the sensor: counted by the reader
            und = ev.undistort(camera)
            true_fwl = fwl(ev, "rotation3", gyro, camera=camera)
        out.append(Window("ecd", name, ev, und, camera, truth, true_fwl))
    return out


def mvsec_windows(names, max_events: int | None) -> list[Window]:
    from cmax_taichi.io import open_recording

    folder = DATA / "mvsec_indoor_flying1"
    if not (folder / "events.txt").exists():
        print(f"skipped MVSEC: no {folder / 'events.txt'}")
        return []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # rectified events just outside the sensor: dropped by the reader
        with open_recording(folder) as rec:
            ev = rec.read()
    spans = {"all": (0, len(ev)), "first 30000": (0, 30000)}
    third = len(ev) // 3
    for k in range(3):
        spans[f"third {k + 1}"] = (k * third, (k + 1) * third)
    out = []
    for name in names:
        a, b = spans[name]
        w = _subsampled(ev[a:b], max_events)
        out.append(Window("mvsec", name, w, w, None, None))
    return out


def _subsampled(events, max_events: int | None):
    if max_events is None or len(events) <= max_events:
        return events
    return events[:: int(np.ceil(len(events) / max_events))]


# --- one run --------------------------------------------------------------------------------------------
def scores(window: Window, nodes: np.ndarray, grid, displacement: np.ndarray) -> dict:
    """AEE / 3PE (with truth), FWL and the share of shrunk events of a flow (node values, px/s)."""
    from cmax_taichi.flow import DenseFlowProblem
    from cmax_taichi.metrics import event_mask, flow_error

    out: dict = {}
    if window.truth is not None:
        m = flow_error(displacement, window.truth, event_mask(window.undistorted), (3.0,))
        out["AEE"], out["3PE"] = float(m["AEE"]), float(m["3PE"])
    prob = DenseFlowProblem(window.undistorted, grid, objective="variance", references="first")
    out["FWL"] = float(prob.value(nodes))
    det = prob.event_quantities(nodes)["det"]
    out["shrunk"] = float(np.mean(np.abs(det) < 0.5))
    return out


def run_variant(window: Window, estimator) -> dict:
    estimator.camera = window.camera
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = estimator.estimate(window.events)
    seconds = time.perf_counter() - t0
    stalls = [
        str(w.message) for w in caught if "did not move" in str(w.message) or "ended at its" in str(w.message)
    ]
    row = scores(window, res.nodes, res.grid, res.flow(res.duration))
    row.update(
        J=float(res.value),
        seconds=seconds,
        levels=[
            {"cells": lv.grid.nx, "status": lv.status, "iterations": lv.iterations, "change_px": lv.change}
            for lv in res.levels
        ],
        stalled=len(res.stalled_levels),
        warned=len(stalls),
    )
    return row


def run_translation(window: Window) -> dict:
    """The best global translation of the window as a constant flow, scored like the variants."""
    import cmax_taichi as cm
    from cmax_taichi.flow import FlowGrid

    prob = cm.ContrastMaximization(window.undistorted, warp="translation2", objective="gradient_magnitude")
    result = cm.maximize(prob)
    v = np.asarray(result.theta, dtype=np.float64)  # px/s
    W, H = window.undistorted.sensor_size
    grid = FlowGrid(W, H, 1, 1)
    nodes = np.broadcast_to(v, grid.shape).copy()
    disp = grid.dense(nodes) * window.undistorted.duration
    row = scores(window, nodes, grid, disp)
    row.update(status=result.status, iterations=result.n_iterations, v=v.tolist())
    return row


# --- tables ----------------------------------------------------------------------------------------------
def _mean(values) -> float:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(vals)) if vals else float("nan")


def summary_table(rows: list[dict]) -> str:
    """One line per (variant, reference): mean AEE on the simulated scenes and on ECD, mean FWL on MVSEC
    (and the ECD FWL over the gyro's), the largest share of shrunk events on a real recording, the
    mean iterations per level (coarsest first), the levels that moved the flow of all levels run, and
    the levels that stalled."""
    by_key: dict = {}
    for r in rows:
        by_key.setdefault((r["variant"], r["references"], r["kink_width"]), []).append(r)
    lines = [
        "| variant | t_ref | sim AEE px | ECD AEE px | ECD FWL / gyro's | MVSEC FWL | shrunk % (max, real) "
        "| iterations per level | levels moved | stalled levels |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (variant, refs, width), rs in by_key.items():
        sim = [r["AEE"] for r in rs if r["dataset"] == "sim"]
        ecd = [r for r in rs if r["dataset"] == "ecd"]
        mv = [r for r in rs if r["dataset"] == "mvsec"]
        real = ecd + mv
        n_levels = max(len(r["levels"]) for r in rs) if rs and "levels" in rs[0] else 0
        its = [_mean([r["levels"][k]["iterations"] for r in rs]) for k in range(n_levels)]
        stalled = sum(r.get("stalled", 0) for r in rs)
        moved = sum(lv["change_px"] > 0 for r in rs for lv in r["levels"])
        label = variant if width is None or len(_widths(rows)) == 1 else f"{variant} (kink {width:g})"
        lines.append(
            f"| {label} | {refs} | {_fmt(_mean(sim))} | {_fmt(_mean([r['AEE'] for r in ecd]))} | "
            f"{_fmt(_mean([r['FWL'] / r['true_fwl'] for r in ecd]))} | "
            f"{_fmt(_mean([r['FWL'] for r in mv]))} | "
            f"{_fmt(100 * max([r['shrunk'] for r in real], default=float('nan')), 1)} | "
            f"{' / '.join(f'{v:.0f}' for v in its)} | {moved} of {sum(len(r['levels']) for r in rs)} "
            f"| {stalled} |"
        )
    return "\n".join(lines)


def window_table(rows: list[dict], dataset: str, metric: str) -> str:
    """``metric`` per window of ``dataset`` (columns) per (variant, reference) (rows)."""
    names = list(dict.fromkeys(r["window"] for r in rows if r["dataset"] == dataset))
    if not names:
        return ""
    head = f"| variant | t_ref | {' | '.join(names)} |"
    lines = [head, "|" + "---|" * (len(names) + 2)]
    keyed: dict = {}
    for r in rows:
        if r["dataset"] == dataset:
            keyed.setdefault((r["variant"], r["references"]), {})[r["window"]] = r
    for (variant, refs), per in keyed.items():
        cells = []
        for n in names:
            r = per.get(n)
            if r is None or metric not in r:
                cells.append("")
                continue
            mark = "" if not r.get("stalled") else " (stalled)"
            digits = 1 if metric == "shrunk" else 3 if metric == "FWL" else 2
            value = 100 * r[metric] if metric == "shrunk" else r[metric]
            cells.append(f"{value:.{digits}f}{mark}")
        lines.append(f"| {variant} | {refs} | {' | '.join(cells)} |")
    return "\n".join(lines)


def translation_table(rows: list[dict], variant: str, references: str) -> str:
    """Per window: what the optimizer did on each level of ``variant`` at ``references``, and its
    scores beside the best global translation's."""
    lines = [
        f"| window | {variant}, t_ref {references}: levels (status, iterations, largest node move) "
        "| AEE px (dense / translation) | FWL (dense / translation) | shrunk % |",
        "|---|---|---|---|---|",
    ]
    base = {(r["dataset"], r["window"]): r for r in rows if r["variant"] == "global translation"}
    for r in rows:
        if r["variant"] != variant or r["references"] != references:
            continue
        t = base[(r["dataset"], r["window"])]
        levels = ", ".join(
            f"{lv['status']} {lv['iterations']} it {lv['change_px']:.2g} px" for lv in r["levels"]
        )
        aee = f"{r['AEE']:.3f} / {t['AEE']:.3f}" if "AEE" in r else ""
        lines.append(
            f"| {r['dataset']} {r['window']} | {levels} | {aee} | {r['FWL']:.3f} / {t['FWL']:.3f} "
            f"| {100 * r['shrunk']:.1f} |"
        )
    return "\n".join(lines)


def _fmt(value: float, digits: int = 3) -> str:
    return "" if not np.isfinite(value) else f"{value:.{digits}f}"


def _widths(rows) -> set:
    return {r["kink_width"] for r in rows if r["kink_width"] is not None}


def _csv(rows: list[dict], path: Path) -> None:
    fields = ["dataset", "window", "variant", "references", "kink_width", "AEE", "3PE", "FWL", "shrunk", "J"]
    fields += ["seconds", "stalled", "levels"]
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        for r in rows:
            line = dict(r)
            if "levels" in r:
                line["levels"] = "; ".join(
                    f"{lv['cells']}x{lv['cells']} {lv['status']} {lv['iterations']} it "
                    f"{lv['change_px']:.3g} px"
                    for lv in r["levels"]
                )
            writer.writerow(line)


# --- main -------------------------------------------------------------------------------------------------
def render(rows: list[dict], command: str, seconds: float, load) -> str:
    """The markdown of a run: the summary table, the strong penalties at the first event beside the
    translation, and the per-window tables."""
    variant_rows = [r for r in rows if "levels" in r]
    text = [
        f"Command: {command}",
        f"{len(variant_rows)} runs in {seconds / 60:.1f} min; load average at the end {load[0]:.2f} "
        f"{load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} CPUs",
        "",
        summary_table(variant_rows),
        "",
    ]
    if any(r["variant"] == "div+def 10" and r["references"] == "first" for r in variant_rows):
        text += [
            "divergence 10 + deformation 10, t_ref first, beside the best global translation",
            "",
            translation_table(rows, "div+def 10", "first"),
            "",
        ]
    for dataset, metric in (("sim", "AEE"), ("ecd", "AEE"), ("ecd", "FWL"), ("mvsec", "FWL")):
        table = window_table(rows, dataset, metric)
        if table:
            text += [f"{dataset} {metric} per window", "", table, ""]
    for dataset in ("ecd", "mvsec"):
        table = window_table(rows, dataset, "shrunk")
        if table:
            text += [f"{dataset}: events shrunk below half their area, % per window", "", table, ""]
    return "\n".join(text)


def main(argv: list[str] | None = None) -> int:
    from cmax_taichi.flow import KINK_WIDTH

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a subset: two windows per kind, 7 variants")
    parser.add_argument("--out", type=Path, default=Path("bench-flow-ablation"))
    parser.add_argument(
        "--datasets", nargs="+", default=["sim", "ecd", "mvsec"], choices=["sim", "ecd", "mvsec"]
    )
    parser.add_argument("--variants", nargs="+", default=None, metavar="LABEL", help="labels of VARIANTS")
    parser.add_argument("--references", nargs="+", default=None, choices=REFERENCES)
    parser.add_argument("--kink-widths", nargs="+", type=float, default=[KINK_WIDTH], metavar="W")
    parser.add_argument("--max-events", type=int, default=None, help="subsample every window to at most N")
    parser.add_argument("--sim", nargs="+", default=None, choices=SIM_SCENES, help="simulated scenes")
    parser.add_argument("--ecd", nargs="+", default=None, choices=ECD_CUTS, help="ECD cuts")
    parser.add_argument("--mvsec", nargs="+", default=None, choices=MVSEC_WINDOWS)
    parser.add_argument(
        "--tables-from", type=Path, default=None, metavar="JSON", help="print the tables of a saved run"
    )
    args = parser.parse_args(argv)
    if args.tables_from is not None:
        saved = json.loads(args.tables_from.read_text())
        print(render(saved["rows"], saved.get("command", "?"), saved["seconds"], saved["load"]))
        return 0
    known = dict(VARIANTS)
    labels = args.variants or (list(QUICK_VARIANTS) if args.quick else [v[0] for v in VARIANTS])
    unknown = [v for v in labels if v not in known]
    if unknown:
        parser.error(f"unknown variant(s) {unknown}; valid: {', '.join(known)}")
    refs = args.references or (["first", "middle"] if args.quick else list(REFERENCES))
    sims = args.sim or (["room", "corridor"] if args.quick else list(SIM_SCENES))
    ecds = args.ecd or (["boxes_rotation", "poster_rotation"] if args.quick else list(ECD_CUTS))
    mvs = args.mvsec or (["first 30000", "third 1"] if args.quick else list(MVSEC_WINDOWS))
    args.out.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {os.cpu_count()} CPUs", flush=True)
    t_run = time.perf_counter()

    from cmax_taichi.flow import DenseFlowEstimator

    windows: list[Window] = []
    if "sim" in args.datasets:
        windows += sim_windows(sims, args.max_events)
    if "ecd" in args.datasets:
        windows += ecd_windows(ecds, args.max_events)
    if "mvsec" in args.datasets:
        windows += mvsec_windows(mvs, args.max_events)
    estimators = {
        (label, ref, width): DenseFlowEstimator(references=ref, regularizers=known[label], kink_width=width)
        for label in labels
        for ref in refs
        for width in args.kink_widths
    }
    rows: list[dict] = []
    for w in windows:
        base = {"dataset": w.dataset, "window": w.name, "n_events": len(w.events), "true_fwl": w.true_fwl}
        row = {**base, "variant": "global translation", "references": "first", "kink_width": None}
        row.update(run_translation(w))
        rows.append(row)
        for (label, ref, width), est in estimators.items():
            row = {**base, "variant": label, "references": ref, "kink_width": width}
            row.update(run_variant(w, est))
            rows.append(row)
            moved = " ".join(f"{lv['status'][:4]}/{lv['iterations']}" for lv in row["levels"])
            print(
                f"{w.dataset:5s} {w.name:16s} {label:22s} {ref:6s} kink {width:<6g} "
                f"AEE {row.get('AEE', float('nan')):7.3f}  FWL {row['FWL']:6.3f}  shrunk "
                f"{100 * row['shrunk']:5.1f}%  [{moved}]  {row['seconds']:.1f} s",
                flush=True,
            )
    elapsed = time.perf_counter() - t_run
    load = os.getloadavg()
    command = f"python -m benchmarks.flow_ablation {' '.join(argv if argv is not None else sys.argv[1:])}"
    text = render(rows, command, elapsed, load)
    (args.out / "flow_ablation.md").write_text(text)
    (args.out / "flow_ablation.json").write_text(
        json.dumps({"command": command, "rows": rows, "seconds": elapsed, "load": load}, indent=1)
    )
    _csv(rows, args.out / "flow_ablation.csv")
    print(text)
    print(f"wrote {args.out / 'flow_ablation.md'}, .json, .csv")
    return 0


if __name__ == "__main__":
    sys.exit(main())
