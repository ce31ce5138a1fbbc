"""Real-data results of the estimation pipeline on the shared recordings (``../shared/data``).

Run ``python -m cmax_taichi.experiments_real [--data DIR]``; it prints the tables that README.md
quotes. Three experiments:

1. ECD rotation cuts (4 windows, every event of each cut), ``rotation3`` with the camera of
   ``calib.txt``, variance: the estimate's FWL against the gyro's (``motion.txt``, a sample at the
   window middle), the angular-velocity error relative to ``|w_gt|``, and how much the divergence or
   the deformation regularizer (lambda = 1) changes the estimate.
2. ECD slider_depth, ``translation2`` (undistorted with ``calib.txt``): the flow of the whole 50,000
   event chunk as one window, and per window of 10,000 events.
3. MVSEC indoor_flying1, the first 30,000 events, ``zoom1`` and ``mitrokhin4``, both objectives, with
   no regularizer, the whitening baseline, divergence, deformation, and both (lambda = 1 each): FWL and
   the share of the identity warp's event-covered pixels that stay covered. For ``zoom1`` the global
   search is checked against a dense grid of 2001 values of ``h_z`` over the search box. Then zoom1
   with one regularizer at lambda = 2, 5, 10 (a sensitivity check as in the paper's Sec. 4.4).

Every problem uses the library defaults (t_ref = first event, blur sigma = 1 px, polarity ignored,
normalised objective) and :func:`cmax_taichi.maximize` with its defaults (global grid search over
:func:`cmax_taichi.optimize.search_bounds`, then Adam from the best 3 candidates).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

import cmax_taichi as cm

from .metrics import angular_velocity_error, covered_area_ratio, covered_share, fwl_problem
from .optimize import METHODS, search_bounds

ROTATION_CUTS = ("shapes_rotation", "boxes_rotation", "dynamic_rotation", "poster_rotation")
REGULARIZER_ROWS = (
    ("none", {}, False),
    ("whitening", {}, True),
    ("divergence", {"divergence": 1.0}, False),
    ("deformation", {"deformation": 1.0}, False),
    ("div + def", {"divergence": 1.0, "deformation": 1.0}, False),
)
#: less than this share of the identity warp's covered pixels stay covered: "collapse" when the IWE is
#: sharper than with no motion (FWL > 1), "spread out" when it is blurrier
COLLAPSE_SHARE = 0.5


def default_data_dir() -> Path:
    """``$CMAX_SHARED_DATA`` or ``../shared/data`` beside the checkout."""
    env = os.environ.get("CMAX_SHARED_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"


def _fmt_vec(v) -> str:
    return "(" + ", ".join(f"{x:+.3f}" for x in np.asarray(v).reshape(-1)) + ")"


# --- 1. ECD rotation ------------------------------------------------------------------------------------
def rotation_window(folder: Path, method: str = "adam", **options) -> dict:
    """One ECD rotation cut: estimates without and with each regularizer, errors and FWLs."""
    from . import io

    with io.open_recording(folder) as rec:
        events = rec.read()
        camera = rec.camera
        w_gt = np.asarray(rec.angular_velocity(0.5 * (rec.t_start + rec.t_end)), dtype=np.float64)
    row: dict = {"name": folder.name, "w_gt": w_gt}
    t0 = time.perf_counter()
    for label, regs in (
        ("none", {}),
        ("divergence", {"divergence": 1.0}),
        ("deformation", {"deformation": 1.0}),
    ):
        prob = cm.ContrastMaximization(events, warp="rotation3", camera=camera, regularizers=regs)
        res = cm.maximize(prob, method=method, **options)
        row[label] = res.theta
        if label == "none":
            fprob = fwl_problem(prob.events, "rotation3", camera=camera)
            row["fwl_est"] = fprob.value(res.theta)
            row["fwl_gt"] = fprob.value(w_gt)
            row["n_events"] = prob.n_events
            row["duration"] = prob.duration
    est = row["none"]
    err = angular_velocity_error(est, w_gt)
    row["error_rel"] = float(err["relative"][0])
    row["error_deg_s"] = float(err["error_deg_s"][0])
    for label in ("divergence", "deformation"):
        row[f"change_{label}"] = float(np.linalg.norm(row[label] - est) / np.linalg.norm(est))
    row["seconds"] = time.perf_counter() - t0
    return row


ROTATION_HEADER = (
    "| window | events / T | w_gt (rad/s) | w_est, no reg. (rad/s) | error / abs(w_gt) | FWL est. | FWL GT "
    "| change with Div | change with Def | s |\n|---|---|---|---|---|---|---|---|---|---|"
)


def rotation_line(r: dict) -> str:
    return (
        f"| {r['name']} | {r['n_events']} / {1e3 * r['duration']:.1f} ms | {_fmt_vec(r['w_gt'])} | "
        f"{_fmt_vec(r['none'])} | {100 * r['error_rel']:.1f}% ({r['error_deg_s']:.1f} deg/s) | "
        f"{r['fwl_est']:.4f} | {r['fwl_gt']:.4f} | {100 * r['change_divergence']:.2f}% | "
        f"{100 * r['change_deformation']:.2f}% | {r['seconds']:.0f} |"
    )


def rotation_footer(rows: list[dict]) -> str:
    err = angular_velocity_error(np.array([r["none"] for r in rows]), np.array([r["w_gt"] for r in rows]))
    return (
        f"RMS angular-velocity error over the {len(rows)} windows: {err['rms_deg_s']:.2f} deg/s "
        f"(per axis x, y, z: {', '.join(f'{v:.2f}' for v in err['rms_axes_deg_s'])} deg/s)."
    )


# --- 2. slider_depth ---------------------------------------------------------------------------------------
def slider_rows(folder: Path, method: str = "adam", window: int = 10000, **options) -> Iterator[dict]:
    """The whole chunk as one window, then windows of ``window`` events (warm-started)."""
    from . import io
    from .sequence import process

    with io.open_recording(folder) as rec:
        events = rec.read()
        camera = rec.camera
        t0 = time.perf_counter()
        prob = cm.ContrastMaximization(events, warp="translation2", camera=camera)
        res = cm.maximize(prob, method=method, **options)
        fprob = fwl_problem(prob.events, "translation2", camera=camera)
        yield {
            "label": f"whole chunk ({prob.n_events} events, {1e3 * prob.duration:.0f} ms)",
            "theta": res.theta,
            "fwl": fprob.value(res.theta),
            "seconds": time.perf_counter() - t0,
        }
        seq = process(rec, "translation2", n_events=window, method=method, progress=False)
    for w in seq.windows:
        yield {
            "label": f"window {w.index} ({w.n_events} events, {1e3 * (w.t_end - w.t_start):.0f} ms)",
            "theta": w.theta,
            "fwl": w.fwl,
            "seconds": w.seconds,
        }


SLIDER_TARGET = (-110.0, 0.0)
SLIDER_HEADER = "| window | v (px/s) | deviation from (-110, 0) px/s | FWL | s |\n|---|---|---|---|---|"


def slider_line(r: dict) -> str:
    tx, ty = SLIDER_TARGET
    dev = float(np.hypot(r["theta"][0] - tx, r["theta"][1] - ty) / np.hypot(tx, ty))
    return (
        f"| {r['label']} | ({r['theta'][0]:+.1f}, {r['theta'][1]:+.1f}) | {100 * dev:.1f}% "
        f"| {r['fwl']:.3f} | {r['seconds']:.0f} |"
    )


# --- 3. MVSEC collapse -------------------------------------------------------------------------------------
def collapse_rows(
    folder: Path, n_events: int = 30000, method: str = "adam", warps=("zoom1", "mitrokhin4"), **options
) -> Iterator[dict]:
    from . import io

    with io.open_recording(folder) as rec:
        events = rec.read(0, n_events)
        camera = rec.camera
    for warp in warps:
        for objective in ("variance", "gradient_magnitude"):
            for label, regs, whitening in REGULARIZER_ROWS:
                t0 = time.perf_counter()
                prob = cm.ContrastMaximization(
                    events,
                    warp=warp,
                    objective=objective,
                    camera=camera,
                    regularizers=regs,
                    whitening=whitening,
                )
                res = cm.maximize(prob, method=method, **options)
                fprob = fwl_problem(prob.events, warp, camera=camera)
                row = {
                    "warp": warp,
                    "objective": objective,
                    "label": label,
                    "theta": res.theta,
                    "params": res.param_names,
                    "J": res.value,
                    "fwl": fprob.value(res.theta),
                    "covered": covered_share(fprob, res.theta),
                    "area": covered_area_ratio(fprob, res.theta),
                    "duration": prob.duration,
                    "seconds": time.perf_counter() - t0,
                }
                if warp == "zoom1":
                    lo, hi = search_bounds(prob)
                    grid = np.linspace(lo[0], hi[0], 2001)
                    values = np.array([prob.value([h]) for h in grid])
                    k = int(np.argmax(values))
                    row["dense_best"] = (float(grid[k]), float(values[k]))
                yield row


COLLAPSE_HEADER = (
    "| warp | objective | regularizer | estimate (per window: theta T) | J | FWL | covered share "
    "| covered area | collapse? | s |\n|---|---|---|---|---|---|---|---|---|---|"
)


def collapse_line(r: dict) -> str:
    T = r["duration"]
    est = ", ".join(f"{n} T = {v * T:+.3f}" for n, v in zip(r["params"], r["theta"], strict=True))
    if r["covered"] >= COLLAPSE_SHARE:
        outcome = "no"
    else:  # most covered pixels emptied: gathered (sharper than no motion) or spread out (blurrier)
        outcome = "collapse" if r["fwl"] > 1.0 else "spread out"
    return (
        f"| {r['warp']} | {r['objective']} | {r['label']} | {est} | {r['J']:.3f} | {r['fwl']:.3f} | "
        f"{100 * r['covered']:.1f}% | {r['area']:.2f} | {outcome} | {r['seconds']:.0f} |"
    )


def sensitivity_rows(
    folder: Path, lambdas=(2.0, 5.0, 10.0), n_events: int = 30000, method: str = "adam", **options
) -> Iterator[dict]:
    """zoom1 with one regularizer at larger weights (the paper's sensitivity analysis, Sec. 4.4)."""
    from . import io

    with io.open_recording(folder) as rec:
        events = rec.read(0, n_events)
        camera = rec.camera
    fprob = fwl_problem(events, "zoom1", camera=camera)
    for objective in ("variance", "gradient_magnitude"):
        for reg in ("divergence", "deformation"):
            for lam in lambdas:
                t0 = time.perf_counter()
                prob = cm.ContrastMaximization(
                    events, warp="zoom1", objective=objective, camera=camera, regularizers={reg: lam}
                )
                res = cm.maximize(prob, method=method, **options)
                yield {
                    "warp": "zoom1",
                    "objective": objective,
                    "label": f"{reg}, lambda = {lam:g}",
                    "theta": res.theta,
                    "params": res.param_names,
                    "J": res.value,
                    "fwl": fprob.value(res.theta),
                    "covered": covered_share(fprob, res.theta),
                    "area": covered_area_ratio(fprob, res.theta),
                    "duration": prob.duration,
                    "seconds": time.perf_counter() - t0,
                }


def beyond_box_rows(folder: Path, n_events: int = 30000, limit: float = 1.5, n: int = 1501) -> Iterator[dict]:
    """zoom1 on a dense grid of ``h_z T`` in ``[-limit, limit]``: past ``h_z T = 1`` the window's last
    events pass through the centre (outside the default search box of :func:`cmax_taichi.maximize`)."""
    from . import io

    with io.open_recording(folder) as rec:
        events = rec.read(0, n_events)
        camera = rec.camera
    fprob = fwl_problem(events, "zoom1", camera=camera)
    for objective in ("variance", "gradient_magnitude"):
        for label, regs, whitening in REGULARIZER_ROWS:
            prob = cm.ContrastMaximization(
                events,
                warp="zoom1",
                objective=objective,
                camera=camera,
                regularizers=regs,
                whitening=whitening,
            )
            T = prob.duration
            grid = np.linspace(-limit, limit, n) / T
            values = np.array([prob.value([h]) for h in grid])
            k = int(np.argmax(values))
            inside = np.abs(grid * T) <= 1.0
            k_in = int(np.flatnonzero(inside)[np.argmax(values[inside])])
            yield {
                "objective": objective,
                "label": label,
                "best": (float(grid[k] * T), float(values[k]), fprob.value([grid[k]])),
                "best_inside": (float(grid[k_in] * T), float(values[k_in])),
            }


BEYOND_HEADER = (
    "| objective | regularizer | best h_z T in [-1, 1], J | best h_z T in [-1.5, 1.5], J | FWL there |\n"
    "|---|---|---|---|---|"
)


def beyond_line(r: dict) -> str:
    (h, v, f), (hi, vi) = r["best"], r["best_inside"]
    return f"| {r['objective']} | {r['label']} | {hi:+.3f}, {vi:.3f} | {h:+.3f}, {v:.3f} | {f:.3f} |"


def sensitivity4_rows(
    folder: Path, lambdas=(2.0, 5.0, 10.0), n_events: int = 30000, method: str = "adam", **options
) -> Iterator[dict]:
    """mitrokhin4 with both regularizers at larger weights."""
    from . import io

    with io.open_recording(folder) as rec:
        events = rec.read(0, n_events)
        camera = rec.camera
    fprob = fwl_problem(events, "mitrokhin4", camera=camera)
    for objective in ("variance", "gradient_magnitude"):
        for lam in lambdas:
            t0 = time.perf_counter()
            regs = {"divergence": lam, "deformation": lam}
            prob = cm.ContrastMaximization(
                events, warp="mitrokhin4", objective=objective, camera=camera, regularizers=regs
            )
            res = cm.maximize(prob, method=method, **options)
            yield {
                "warp": "mitrokhin4",
                "objective": objective,
                "label": f"div + def, lambda = {lam:g}",
                "theta": res.theta,
                "params": res.param_names,
                "J": res.value,
                "fwl": fprob.value(res.theta),
                "covered": covered_share(fprob, res.theta),
                "area": covered_area_ratio(fprob, res.theta),
                "duration": prob.duration,
                "seconds": time.perf_counter() - t0,
            }


def dense_grid_table(rows: list[dict]) -> str:
    lines = [
        "zoom1: the global search against a dense grid of 2001 values of h_z over the search box "
        "(h_z T in [-1, 1]):",
        "",
        "| objective | regularizer | maximize: h_z T, J | dense grid: h_z T, J |",
        "|---|---|---|---|",
    ]
    for r in rows:
        h, v = r["dense_best"]
        lines.append(
            f"| {r['objective']} | {r['label']} | {r['theta'][0] * r['duration']:+.4f}, {r['J']:.4f} | "
            f"{h * r['duration']:+.4f}, {v:.4f} |"
        )
    return "\n".join(lines)


def _emit(text: str = "") -> None:
    print(text, flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m cmax_taichi.experiments_real",
        description="Reproduce the real-data tables of README.md on ../shared/data.",
    )
    parser.add_argument("--data", type=Path, default=None, help="shared data folder (default ../shared/data)")
    parser.add_argument("--method", default="adam", choices=METHODS)
    parser.add_argument(
        "--arch", default=None, help="cpu | gpu | cuda | ... (default $CMAX_TAICHI_ARCH or cpu)"
    )
    parser.add_argument(
        "--only",
        default=None,
        choices=["rotation", "slider", "collapse", "beyond", "sensitivity4"],
        help="run one experiment only",
    )
    args = parser.parse_args(argv)
    data = args.data or default_data_dir()
    if not data.is_dir():
        print(f"experiments_real: error: data folder {data} not found (pass --data)", file=sys.stderr)
        return 2
    warnings.filterwarnings("ignore", message=".*dropping events outside.*")
    cm.init(arch=args.arch, precision="f64")
    info = cm.backend_info()
    _emit(f"cmax-taichi {cm.__version__}, backend {info.arch} {info.precision}, method {args.method}")
    t_all = time.perf_counter()
    if args.only in (None, "rotation"):
        _emit("\n### ECD rotation cuts: rotation3, variance, lambda = 1\n")
        _emit(ROTATION_HEADER)
        rows = []
        for name in ROTATION_CUTS:
            rows.append(rotation_window(data / "ecd_rotation" / name, method=args.method))
            _emit(rotation_line(rows[-1]))
        _emit("\n" + rotation_footer(rows))
    if args.only in (None, "slider"):
        _emit("\n### ECD slider_depth: translation2, variance\n")
        _emit(SLIDER_HEADER)
        for row in slider_rows(data / "ecd_slider_depth", method=args.method):
            _emit(slider_line(row))
    if args.only in (None, "collapse"):
        _emit("\n### MVSEC indoor_flying1, first 30,000 events: collapse-enabled warps, lambda = 1\n")
        _emit(COLLAPSE_HEADER)
        rows = []
        for row in collapse_rows(data / "mvsec_indoor_flying1", method=args.method):
            rows.append(row)
            _emit(collapse_line(row))
        _emit(
            f"\ncollapse: less than {100 * COLLAPSE_SHARE:.0f}% of the identity warp's covered pixels stay "
            "covered and FWL > 1 (events gathered); spread out: the same share lost with FWL <= 1."
        )
        _emit("\n" + dense_grid_table([r for r in rows if "dense_best" in r]))
        _emit("\n#### Sensitivity: zoom1 with one regularizer at larger lambda\n")
        _emit(COLLAPSE_HEADER)
        for row in sensitivity_rows(data / "mvsec_indoor_flying1", method=args.method):
            _emit(collapse_line(row))
    if args.only in (None, "sensitivity4"):
        _emit("\n#### Sensitivity: mitrokhin4 with both regularizers at larger lambda\n")
        _emit(COLLAPSE_HEADER)
        for row in sensitivity4_rows(data / "mvsec_indoor_flying1", method=args.method):
            _emit(collapse_line(row))
    if args.only in (None, "beyond"):
        _emit("\n#### zoom1 beyond the search box: dense grid of h_z T over [-1.5, 1.5] (1501 values)\n")
        _emit(BEYOND_HEADER)
        for row in beyond_box_rows(data / "mvsec_indoor_flying1"):
            _emit(beyond_line(row))
    _emit(f"\ntotal {time.perf_counter() - t_all:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
