"""Real-data results of the estimation pipeline on the shared recordings (``../shared/data``).

Run ``python -m cmax_taichi.lab.experiments_real [--data DIR]``; it prints the tables that
docs/results-real.md quotes. Five experiments:

1. MVSEC indoor_flying1, the first 30,000 events, ``zoom1`` and ``mitrokhin4``, both objectives, with
   no regularizer, the whitening baseline, and divergence, deformation and both at every weight of
   :data:`LAMBDA_GRID`: FWL and the share of the identity warp's event-covered pixels that stay
   covered. The smallest weight at which no regularized configuration collapses is selected (it is
   :data:`cmax_taichi.RECOMMENDED_LAMBDA`) and used by the next experiments. For
   ``zoom1`` the global search is checked against a dense grid of 2001 values of ``h_z`` over the
   search box.
2. ECD rotation cuts (4 windows, every event of each cut), ``rotation3`` with the camera of
   ``calib.txt``, variance: the estimate's FWL against the gyro's (``motion.txt``, a sample at the
   window middle), the angular-velocity error relative to ``|w_gt|``, and how much the divergence or
   the deformation regularizer (lambda = 1 and the selected weight) changes the estimate.
3. ECD slider_depth, ``translation2`` (undistorted with ``calib.txt``): the flow of the whole 50,000
   event chunk as one window, and per window of 10,000 events.
4. zoom1 on a dense grid of ``h_z T`` beyond the search box (the time-to-contact bound).
5. The whitening baseline with ``rotation3`` on poster_rotation: J with and without whitening along a
   ray of ever larger rotations (kernels and the float64 reference), and what the default search
   returns with whitening: the whitening's own collapse.

Every problem uses the library defaults (t_ref = first event, blur sigma = 1 px, polarity ignored,
normalised objective) and :func:`cmax_taichi.maximize` with its defaults (global grid search over
:func:`cmax_taichi.solve.optimize.search_bounds`, then Adam from the best 3 candidates).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

import cmax_taichi as cm
from cmax_taichi.lab.experiments import shared_data_root
from cmax_taichi.metrics import (
    COLLAPSE_SHARE,
    angular_velocity_error,
    covered_area_ratio,
    covered_share,
    fwl_problem,
)
from cmax_taichi.models.regularizers import RECOMMENDED_LAMBDA
from cmax_taichi.solve.optimize import METHODS, search_bounds

ROTATION_CUTS = ("shapes_rotation", "boxes_rotation", "dynamic_rotation", "poster_rotation")


def default_data_dir() -> Path:
    """``$CMAX_SHARED_DATA``, else ``../shared/data`` beside the checkout
    (:func:`cmax_taichi.lab.experiments.shared_data_root`)."""
    return shared_data_root()


def _fmt_vec(v) -> str:
    return "(" + ", ".join(f"{x:+.3f}" for x in np.asarray(v).reshape(-1)) + ")"


# --- 1. ECD rotation ------------------------------------------------------------------------------------
def rotation_window(folder: Path, method: str = "adam", lambdas=(1.0,), **options) -> dict:
    """One ECD rotation cut: estimates without and with each regularizer (at each weight of
    ``lambdas``), errors and FWLs."""
    from cmax_taichi import io

    with io.open_recording(folder) as rec:
        events = rec.read()
        camera = rec.camera
        w_gt = np.asarray(rec.angular_velocity(0.5 * (rec.t_start + rec.t_end)), dtype=np.float64)
    row: dict = {"name": folder.name, "w_gt": w_gt, "lambdas": tuple(float(lam) for lam in lambdas)}
    t0 = time.perf_counter()
    runs = [("none", {})] + [
        (f"{name}@{lam:g}", {name: float(lam)})
        for lam in row["lambdas"]
        for name in ("divergence", "deformation")
    ]
    for label, regs in runs:
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
    for label, _ in runs[1:]:
        row[f"change_{label}"] = float(np.linalg.norm(row[label] - est) / np.linalg.norm(est))
        row[f"error_{label}"] = float(angular_velocity_error(row[label], w_gt)["relative"][0])
    row["seconds"] = time.perf_counter() - t0
    return row


def rotation_header(lambdas) -> str:
    changes = [f"Div, lambda = {lam:g}: change / error" for lam in lambdas] + [
        f"Def, lambda = {lam:g}: change / error" for lam in lambdas
    ]
    cols = [
        "window",
        "events / T",
        "w_gt (rad/s)",
        "w_est, no reg. (rad/s)",
        "error / abs(w_gt)",
        "FWL est.",
        "FWL GT",
        *changes,
        "s",
    ]
    return "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols)


def rotation_line(r: dict) -> str:
    """One row; a regularized estimate's cell is ``|w_reg - w_est| / |w_est|`` (its change from the
    unregularized estimate) and ``|w_reg - w_gt| / |w_gt|`` (its error)."""
    changes = [
        f"{100 * r[f'change_{name}@{lam:g}']:.2f}% / {100 * r[f'error_{name}@{lam:g}']:.1f}%"
        for name in ("divergence", "deformation")
        for lam in r["lambdas"]
    ]
    return (
        f"| {r['name']} | {r['n_events']} / {1e3 * r['duration']:.1f} ms | {_fmt_vec(r['w_gt'])} | "
        f"{_fmt_vec(r['none'])} | {100 * r['error_rel']:.1f}% ({r['error_deg_s']:.1f} deg/s) | "
        f"{r['fwl_est']:.4f} | {r['fwl_gt']:.4f} | " + " | ".join(changes) + f" | {r['seconds']:.0f} |"
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
    from cmax_taichi import io
    from cmax_taichi.solve.sequence import process

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
#: weights tried on the MVSEC cut; the smallest at which no regularized configuration collapses is the
#: weight of the headline rows (and of ``cmax-taichi reproduce``: ``experiments.Settings.lam``)
LAMBDA_GRID = (1.0, 2.0, 5.0, 10.0, 20.0)
REGULARIZED = (
    ("divergence", ("divergence",)),
    ("deformation", ("deformation",)),
    ("div + def", ("divergence", "deformation")),
)


def _collapse_row(events, camera, warp, objective, label, lam, regs, whitening, method, options) -> dict:
    t0 = time.perf_counter()
    prob = cm.ContrastMaximization(
        events, warp=warp, objective=objective, camera=camera, regularizers=regs, whitening=whitening
    )
    res = cm.maximize(prob, method=method, **options)
    fprob = fwl_problem(prob.events, warp, camera=camera)
    row = {
        "warp": warp,
        "objective": objective,
        "label": label,
        "lambda": lam,
        "theta": res.theta,
        "params": res.param_names,
        "J": res.value,
        "fwl": fprob.value(res.theta),
        "covered": covered_share(fprob, res.theta),
        "area": covered_area_ratio(fprob, res.theta),
        "duration": prob.duration,
        "seconds": time.perf_counter() - t0,
    }
    if warp == "zoom1":  # the global search against a dense grid over the same box
        lo, hi = search_bounds(prob)
        grid = np.linspace(lo[0], hi[0], 2001)
        values = np.array([prob.value([h]) for h in grid])
        k = int(np.argmax(values))
        row["dense_best"] = (float(grid[k]), float(values[k]))
    return row


def collapse_rows(
    folder: Path,
    n_events: int = 30000,
    method: str = "adam",
    warps=("zoom1", "mitrokhin4"),
    lambdas=LAMBDA_GRID,
    **options,
) -> Iterator[dict]:
    """Per warp and objective: no regularizer, whitening, then each regularizer set at every weight
    of ``lambdas`` (each regularizer of a set weighted by lambda)."""
    from cmax_taichi import io

    with io.open_recording(folder) as rec:
        events = rec.read(0, n_events)
        camera = rec.camera
    for warp in warps:
        for objective in ("variance", "gradient_magnitude"):
            for label, whitening in (("none", False), ("whitening", True)):
                yield _collapse_row(
                    events, camera, warp, objective, label, 0.0, {}, whitening, method, options
                )
            for lam in lambdas:
                for label, names in REGULARIZED:
                    regs = {name: float(lam) for name in names}
                    yield _collapse_row(
                        events, camera, warp, objective, label, lam, regs, False, method, options
                    )


def _weighted_label(label: str, lam: float) -> str:
    """A configuration's name with its weight (unregularized rows, lambda 0, keep the bare name)."""
    return label if lam == 0 else f"{label}, lambda = {lam:g}"


def collapse_outcome(r: dict) -> str:
    """ "no", or, when most covered pixels are emptied, "collapse" (gathered: FWL > 1) or "spread out"."""
    if r["covered"] >= COLLAPSE_SHARE:
        return "no"
    return "collapse" if r["fwl"] > 1.0 else "spread out"


def select_lambda(rows: list[dict]) -> float | None:
    """The smallest weight at which no regularized row collapses (None: none of the grid)."""
    for lam in sorted({r["lambda"] for r in rows if r["lambda"] > 0}):
        at = [r for r in rows if r["lambda"] == lam]
        if at and all(collapse_outcome(r) == "no" for r in at):
            return lam
    return None


def lambda_table(rows: list[dict]) -> str:
    """Outcome and FWL of every regularized configuration against lambda."""
    lambdas = sorted({r["lambda"] for r in rows if r["lambda"] > 0})
    lines = [
        "| warp | objective | regularizer | " + " | ".join(f"lambda = {lam:g}" for lam in lambdas) + " |",
        "|---|---|---|" + "---|" * len(lambdas),
    ]
    keys = []
    for r in rows:
        key = (r["warp"], r["objective"], r["label"])
        if r["lambda"] > 0 and key not in keys:
            keys.append(key)
    for key in keys:
        cells = []
        for lam in lambdas:
            match = [r for r in rows if (r["warp"], r["objective"], r["label"]) == key and r["lambda"] == lam]
            cells.append(f"{collapse_outcome(match[0])}, FWL {match[0]['fwl']:.2f}" if match else "-")
        lines.append(f"| {key[0]} | {key[1]} | {key[2]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


COLLAPSE_HEADER = (
    "| warp | objective | regularizer | estimate (per window: theta T) | J | FWL | covered share "
    "| covered area | collapse? | s |\n|---|---|---|---|---|---|---|---|---|---|"
)


def collapse_line(r: dict) -> str:
    T = r["duration"]
    est = ", ".join(f"{n} T = {v * T:+.3f}" for n, v in zip(r["params"], r["theta"], strict=True))
    label = _weighted_label(r["label"], r["lambda"])
    return (
        f"| {r['warp']} | {r['objective']} | {label} | {est} | {r['J']:.3f} | {r['fwl']:.3f} | "
        f"{100 * r['covered']:.1f}% | {r['area']:.2f} | {collapse_outcome(r)} | {r['seconds']:.0f} |"
    )


def beyond_box_rows(
    folder: Path, n_events: int = 30000, limit: float = 1.5, n: int = 1501, lam: float = 1.0
) -> Iterator[dict]:
    """zoom1 on a dense grid of ``h_z T`` in ``[-limit, limit]``: past ``h_z T = 1`` the window's last
    events pass through the centre (outside the default search box of :func:`cmax_taichi.maximize`)."""
    from cmax_taichi import io

    with io.open_recording(folder) as rec:
        events = rec.read(0, n_events)
        camera = rec.camera
    fprob = fwl_problem(events, "zoom1", camera=camera)
    configs = [("none", {}, False), ("whitening", {}, True)] + [
        (_weighted_label(label, lam), {name: float(lam) for name in names}, False)
        for label, names in REGULARIZED
    ]
    for objective in ("variance", "gradient_magnitude"):
        for label, regs, whitening in configs:
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
        label = _weighted_label(r["label"], r["lambda"])
        lines.append(
            f"| {r['objective']} | {label} | {r['theta'][0] * r['duration']:+.4f}, {r['J']:.4f} | "
            f"{h * r['duration']:+.4f}, {v:.4f} |"
        )
    return "\n".join(lines)


# --- 5. whitening and rotation3 ------------------------------------------------------------------------
#: the rotation that a global search once returned for rotation3 with whitening on poster_rotation (rad/s)
WHITENING_RAY = (78.0, -78.0, 130.0)
WHITENING_STEPS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0)


def whitening_rows(
    folder: Path, ray=WHITENING_RAY, steps=WHITENING_STEPS, method: str = "adam", **options
) -> Iterator[dict]:
    """``rotation3`` with and without whitening on one ECD cut, J at ``s * ray`` for each ``s`` of
    ``steps`` (kernels and the float64 reference :mod:`cmax_taichi.testing.reference`), then what
    :func:`cmax_taichi.maximize` returns with whitening, against J at the gyro and at the unwhitened
    estimate. The values at the points do not depend on any search."""
    from cmax_taichi import io
    from cmax_taichi.testing import reference

    with io.open_recording(folder) as rec:
        events = rec.read()
        camera = rec.camera
        w_gt = np.asarray(rec.angular_velocity(0.5 * (rec.t_start + rec.t_end)), dtype=np.float64)
    white = cm.ContrastMaximization(events, warp="rotation3", camera=camera, whitening=True)
    plain = cm.ContrastMaximization(events, warp="rotation3", camera=camera)
    ev = white.events  # undistorted, as the problems see them
    geometry = reference.camera_geometry(camera)
    dt = ev.t - ev.t[0]
    for s in steps:
        theta = s * np.asarray(ray, dtype=np.float64)
        xw, yw, _, _ = reference.warp_events(
            "rotation3", ev.x, ev.y, dt, theta, duration=white.duration, **geometry
        )
        kept = np.isfinite(xw)
        spread = float(np.sqrt(np.max(np.linalg.eigvalsh(np.cov(xw[kept], yw[kept], bias=True)))))
        xs, ys = reference.whiten(xw, yw, ev.x, ev.y)
        votes = np.sort(
            reference.bilinear_votes(xs, ys, np.ones_like(xs), white.width, white.height), axis=None
        )
        ref = reference.evaluate_window(ev, theta, warp="rotation3", camera=camera, whitening=True)
        yield {
            "label": f"{s:g} x ray",
            "theta": theta,
            "angle": float(np.linalg.norm(theta) * white.duration),
            "behind": int(np.sum(~kept)),
            "spread": spread,
            "top10": float(np.sum(votes[-10:]) / len(xs)),
            "J_white": white.value(theta),
            "J_white_ref": float(ref["J"]),
            "J_plain": plain.value(theta),
        }
    t0 = time.perf_counter()
    found = cm.maximize(white, method=method, **options)
    seconds = time.perf_counter() - t0
    estimate = cm.maximize(plain, method=method, **options).theta
    for label, theta in (
        (f"maximize with whitening ({seconds:.0f} s)", found.theta),
        ("gyro (motion.txt)", w_gt),
        ("maximize without whitening", estimate),
    ):
        yield {
            "label": label,
            "theta": np.asarray(theta, dtype=np.float64),
            "angle": float(np.linalg.norm(theta) * white.duration),
            "behind": None,
            "spread": None,
            "top10": None,
            "J_white": white.value(theta),
            "J_white_ref": None,
            "J_plain": plain.value(theta),
        }


WHITENING_HEADER = (
    "| point | w (rad/s) | rotation over the window (rad) | events behind the camera | "
    "spread of the warped events (px) | whitened events in the 10 fullest pixels | "
    "J with whitening | J with whitening, float64 reference | J without whitening |\n"
    "|---|---|---|---|---|---|---|---|---|"
)


def whitening_line(r: dict) -> str:
    """One row; the spread is the square root of the largest eigenvalue of the warped events'
    covariance (what whitening divides by), the share is of all the window's events."""
    behind = "-" if r["behind"] is None else str(r["behind"])
    spread = "-" if r["spread"] is None else f"{r['spread']:.0f}"
    top10 = "-" if r["top10"] is None else f"{100 * r['top10']:.1f}%"
    ref = "-" if r["J_white_ref"] is None else f"{r['J_white_ref']:.4f}"
    w = "(" + ", ".join(f"{v:+.2f}" for v in r["theta"]) + ")"
    return (
        f"| {r['label']} | {w} | {r['angle']:.2f} | {behind} | {spread} | {top10} | {r['J_white']:.4f} | "
        f"{ref} | {r['J_plain']:.4f} |"
    )


def _emit(text: str = "") -> None:
    print(text, flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m cmax_taichi.lab.experiments_real",
        description="Reproduce the real-data tables of docs/results-real.md on ../shared/data.",
    )
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        help="shared data folder (default $CMAX_SHARED_DATA, else ../shared/data beside the checkout)",
    )
    parser.add_argument("--method", default="adam", choices=METHODS)
    parser.add_argument(
        "--arch", default=None, help="cpu | gpu | cuda | ... (default $CMAX_TAICHI_ARCH or cpu)"
    )
    parser.add_argument(
        "--only",
        default=None,
        choices=["collapse", "rotation", "slider", "beyond", "whitening"],
        help="run one experiment only",
    )
    parser.add_argument(
        "--lam",
        type=float,
        default=None,
        help="regularizer weight of the rotation and beyond-the-box tables when the collapse study "
        f"(which selects it) does not run (default {RECOMMENDED_LAMBDA:g})",
    )
    args = parser.parse_args(argv)
    data = args.data or default_data_dir()
    if not data.is_dir():
        print(
            f"experiments_real: error: data folder {data} not found (pass --data or set CMAX_SHARED_DATA)",
            file=sys.stderr,
        )
        return 2
    if args.lam is not None and not args.lam > 0:
        print(f"experiments_real: error: --lam must be > 0, got {args.lam}", file=sys.stderr)
        return 2
    warnings.filterwarnings("ignore", message=".*dropping events outside.*")
    cm.init(arch=args.arch, precision="f64")
    info = cm.backend_info()
    _emit(f"cmax-taichi {cm.__version__}, backend {info.arch} {info.precision}, method {args.method}")
    t_all = time.perf_counter()
    lam = args.lam if args.lam is not None else RECOMMENDED_LAMBDA
    if args.only in (None, "collapse"):
        grid = ", ".join(f"{g:g}" for g in LAMBDA_GRID)
        _emit(
            f"\n### MVSEC indoor_flying1, first 30,000 events: collapse-enabled warps, lambda in {{{grid}}}\n"
        )
        rows = []
        for row in collapse_rows(data / "mvsec_indoor_flying1", method=args.method):
            rows.append(row)
            print(collapse_line(row), file=sys.stderr, flush=True)  # progress
        selected = select_lambda(rows)
        if args.lam is None and selected is not None:
            lam = selected
        _emit("Outcome (collapse / no / spread out) and FWL against lambda:\n")
        _emit(lambda_table(rows))
        _emit(
            f"\ncollapse: less than {100 * COLLAPSE_SHARE:.0f}% of the identity warp's covered pixels stay "
            "covered and FWL > 1 (events gathered); spread out: the same share lost with FWL <= 1."
        )
        _emit(
            "\nSmallest lambda of the grid at which no regularized configuration collapses: "
            + (f"**{selected:g}**" if selected is not None else "none of the grid")
            + f" (RECOMMENDED_LAMBDA = {RECOMMENDED_LAMBDA:g})."
        )
        shown = [r for r in rows if r["lambda"] in (0.0, 1.0, lam)]
        _emit(f"\n#### No regularizer, whitening, and each regularizer at lambda = 1 and lambda = {lam:g}\n")
        _emit(COLLAPSE_HEADER)
        for row in shown:
            _emit(collapse_line(row))
        _emit("\n" + dense_grid_table([r for r in shown if "dense_best" in r]))
    if args.only in (None, "rotation"):
        lambdas = (1.0,) if lam == 1.0 else (1.0, lam)
        _emit("\n### ECD rotation cuts: rotation3, variance\n")
        _emit(rotation_header(lambdas))
        rows = []
        for name in ROTATION_CUTS:
            rows.append(rotation_window(data / "ecd_rotation" / name, method=args.method, lambdas=lambdas))
            _emit(rotation_line(rows[-1]))
        _emit("\n" + rotation_footer(rows))
    if args.only in (None, "slider"):
        _emit("\n### ECD slider_depth: translation2, variance\n")
        _emit(SLIDER_HEADER)
        for row in slider_rows(data / "ecd_slider_depth", method=args.method):
            _emit(slider_line(row))
    if args.only in (None, "beyond"):
        _emit(
            "\n#### zoom1 beyond the search box: dense grid of h_z T over [-1.5, 1.5] (1501 values), "
            f"lambda = {lam:g}\n"
        )
        _emit(BEYOND_HEADER)
        for row in beyond_box_rows(data / "mvsec_indoor_flying1", lam=lam):
            _emit(beyond_line(row))
    if args.only in (None, "whitening"):
        ray = ", ".join(f"{v:g}" for v in WHITENING_RAY)
        _emit(f"\n### Whitening and rotation3 on poster_rotation: J along s x ({ray}) rad/s\n")
        _emit(WHITENING_HEADER)
        for row in whitening_rows(data / "ecd_rotation" / "poster_rotation", method=args.method):
            _emit(whitening_line(row))
    _emit(f"\ntotal {time.perf_counter() - t_all:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
