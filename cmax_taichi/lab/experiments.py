"""The paper's experiments (Shiba, Aoki, Gallego, Sensors 2022) as one reproducible command.

``cmax-taichi reproduce table1|table2|table3|sensitivity|complexity|all --out DIR [--quick]`` runs
:func:`reproduce`. Every experiment writes Markdown and CSV (and a PNG plot for the sensitivity and
complexity studies) into ``DIR``, with the paper's published numbers (``../shared/paper/SPEC.md``,
section 7) beside ours.

Protocol
--------
* **table1 / table2** stand in for the paper's MVSEC Tables 1 and 2 with the simulator presets
  ``indoor_flying`` and ``driving`` (:mod:`cmax_taichi.sim`): exact ground-truth flow, MVSEC's
  evaluation (ground-truth frames at 32 Hz, interval dt = 4 frames; the optimisation window is the
  last 30,000 events ending at the interval's end frame; AEE / NPE on the pixels with valid ground
  truth where an event of the interval occurred; FWL on all events of the interval). The estimate
  of a parametric warp is turned into a flow over the interval by :func:`cmax_taichi.metrics.flow_from_warp`.
  Rows: ground truth (the exact motion, ``mitrokhin4`` with the true parameters), the identity warp,
  and for ``zoom1`` and ``mitrokhin4``: no regularizer, whitening, divergence, deformation, both.
  Columns: AEE, 3PE, 10PE, 20PE, FWL for the variance and the gradient-magnitude objectives. Numbers
  are means over the evaluated intervals.
* **table3** reads the real ECD rotation cuts (``ecd_rotation/<name>``, ``events.txt``, ``calib.txt``,
  ``motion.txt`` through :func:`cmax_taichi.io.open_recording`), one window per cut (all its events),
  ``rotation3`` with the calibrated camera: RMS of the angular-velocity error (deg/s, the norm of the
  3-vector error) and FWL, for the gyro ground truth, no regularizer, divergence, deformation.
* **sensitivity**: AEE and FWL of ``zoom1`` and ``mitrokhin4`` (variance) on ``indoor_flying`` against
  the regularizer weight lambda on a log grid, for divergence, deformation and both.
* **complexity**: seconds per ``value_and_grad`` of ``mitrokhin4`` (variance) with no regularizer, each
  one and both, against the number of events.

Every problem uses the library defaults (t_ref = first event, blur 1 px, polarity ignored, objective
normalised by the identity warp) and :func:`cmax_taichi.maximize` (global grid search over its default
box, then Adam from the best candidates). The regularizer weight is ``lam``, by default
:data:`cmax_taichi.RECOMMENDED_LAMBDA`, which ``python -m cmax_taichi.lab.experiments_real``
selects on the real MVSEC cut before these simulated tables are made (the paper's weights are not
known).

The paper's numbers and the layout of its tables are in :mod:`cmax_taichi.lab.paper`; the Markdown,
CSV and plots are written by :mod:`cmax_taichi.lab.experiment_reports`.
"""

from __future__ import annotations

import math
import os
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from cmax_taichi import sim as sm
from cmax_taichi.core.events import Events
from cmax_taichi.io.outputs import json_text
from cmax_taichi.lab.experiment_reports import (
    COMPLEXITY_CONFIGS,
    complexity_outputs,
    flow_table_csv,
    flow_table_markdown,
    rotation_table_csv,
    rotation_table_markdown,
    sensitivity_outputs,
    write_rows_csv,
)
from cmax_taichi.lab.paper import (
    FLOW_WARPS,
    METRICS,
    OBJECTIVES,
    PAPER_TABLE1,
    PAPER_TABLE2,
    PAPER_TABLE3,
    ROTATION_CUTS,
    ROWS,
    WARP_LABEL,
)
from cmax_taichi.metrics import angular_velocity_error, event_mask, flow_error, flow_from_warp, fwl_problem
from cmax_taichi.models.regularizers import RECOMMENDED_LAMBDA
from cmax_taichi.pipeline.problem import ContrastMaximization
from cmax_taichi.solve.optimize import maximize
from cmax_taichi.solve.sequence import ProgressBar

__all__ = [
    "EXPERIMENTS",
    "PAPER_TABLE1",
    "PAPER_TABLE2",
    "PAPER_TABLE3",
    "Settings",
    "reproduce",
]

EXPERIMENTS = ("table1", "table2", "table3", "sensitivity", "complexity")
N_EVENTS = 30_000  # the paper's MVSEC window


#: the most evaluation intervals of a preset (``Settings.windows``): refused above, before simulating
MAX_INTERVALS = 1000


@dataclass(frozen=True)
class Settings:
    """Sizes and budgets of the experiments.

    Attributes
    ----------
    windows : int
        Evaluation intervals per preset (tables 1, 2).
    sensitivity_windows : int
        Intervals of the sensitivity study.
    lambdas : tuple of float
        Weights of the sensitivity sweep.
    lam : float
        Regularizer weight of the tables (each regularizer; "Div. + Def." weights both by it).
    n_init_1dof, n_init_high : int
        Grid budget of the global search for 1-parameter and for multi-parameter warps.
    n_starts : int
        Local runs per optimisation.
    max_iter : int
        Adam iterations per local run.
    min_spacing : float
        Finest spacing of the zooming grid search, px of displacement over the window.
    complexity_sizes : tuple of int
        Event counts of the complexity study.
    complexity_repeats : int
        Timed evaluations per point (median reported).
    rotation_cuts : tuple of str
        ECD cuts of table 3.
    scale : float
        Size of the simulated presets relative to the DAVIS346 (px/s motions scale with it); the
        optimisation window holds ``30,000 * scale**2`` events.
    seed : int
        Simulator seed.
    """

    windows: int = 2
    sensitivity_windows: int = 1
    lambdas: tuple[float, ...] = (0.1, 0.3, 1.0, 3.0, 10.0, 100.0)
    lam: float = RECOMMENDED_LAMBDA
    n_init_1dof: int = 101
    n_init_high: int = 625
    n_starts: int = 2
    max_iter: int = 30
    min_spacing: float = 2.0
    complexity_sizes: tuple[int, ...] = (7_500, 30_000, 120_000, 240_000)
    complexity_repeats: int = 7
    rotation_cuts: tuple[str, ...] = ROTATION_CUTS
    scale: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("windows", "sensitivity_windows"):
            value = getattr(self, name)
            if not (isinstance(value, int) and 1 <= value <= MAX_INTERVALS):
                raise ValueError(
                    f"{name} must be a whole number from 1 to {MAX_INTERVALS:,}, got {value!r}: each "
                    "interval lengthens the simulated recording (held whole in memory) and runs every "
                    "objective's optimisations, so more would take days"
                )
        if not (isinstance(self.seed, int) and 0 <= self.seed < 2**32):
            raise ValueError(f"seed must be a whole number from 0 to 2**32 - 1, got {self.seed!r}")

    @property
    def n_events(self) -> int:
        """Events per optimisation window (the paper's 30,000 on a full-size sensor)."""
        return int(round(N_EVENTS * self.scale**2))

    @classmethod
    def quick(cls) -> Settings:
        """Small sizes for a smoke run (minutes, not tens of minutes)."""
        return cls(
            windows=1,
            sensitivity_windows=1,
            lambdas=(0.1, 1.0, 10.0),
            n_init_1dof=41,
            n_init_high=81,
            n_starts=1,
            max_iter=10,
            min_spacing=4.0,
            complexity_sizes=(15_000, 30_000),
            complexity_repeats=3,
            rotation_cuts=ROTATION_CUTS[:2],
            scale=0.5,
        )


# --- progress on stderr ------------------------------------------------------------------------------
class _Bar:
    """:class:`cmax_taichi.solve.sequence.ProgressBar` (stderr; a tqdm bar on a terminal, one line per
    10% elsewhere), or nothing when progress is off. One step is one estimate or timing run."""

    def __init__(self, total: int, label: str, enabled: bool) -> None:
        self.bar = ProgressBar(total, label, unit="run") if enabled else None

    def step(self, note: str = "") -> None:
        if self.bar is not None:
            self.bar.update(note)
            if self.bar.count >= (self.bar.total or 0):
                self.bar.close()


def _say(msg: str, enabled: bool) -> None:
    if enabled:
        print(msg, file=sys.stderr, flush=True)


# --- helpers -----------------------------------------------------------------------------------------
def _regs(names: tuple[str, ...], lam: float) -> dict[str, float]:
    return {name: float(lam) for name in names}


def _optimize(prob: ContrastMaximization, settings: Settings) -> np.ndarray:
    n_init = settings.n_init_1dof if prob.model.n_params == 1 else settings.n_init_high
    res = maximize(
        prob,
        method="adam",
        init="grid",
        n_init=n_init,
        n_starts=settings.n_starts,
        max_iter=settings.max_iter,
        min_spacing=settings.min_spacing,
        seed=settings.seed,
    )
    return res.theta


def _window_before(events: Events, t_end: float, n: int) -> Events:
    """The last ``n`` events with ``t < t_end`` (fewer when the recording has fewer)."""
    i1 = int(np.searchsorted(events.t, t_end, side="left"))
    return events[max(0, i1 - n) : i1]


def _simulated_intervals(preset: str, settings: Settings, n_intervals: int, label: str, progress: bool):
    """Simulate ``preset`` for ``n_intervals`` evaluation intervals ``[t_k, t_k + dt]``, k = 1.. (dt = the
    preset's ``dt_frames`` ground-truth frames), so that ``settings.n_events`` events precede each
    interval's end.

    Returns
    -------
    (SimulatedRecording, float, iterator)
        The recording, dt (s), and per interval ``(t_a, t_b, interval events, optimisation window (the
        last n_events events before t_b), mask of pixels with an event of the interval, ground-truth flow
        from t_a to t_b (2, H, W) px)``.
    """
    p = sm.PRESETS[preset]
    dt_gt = p.dt_frames / p.frame_rate
    duration = (n_intervals + 1) * dt_gt + 1e-3
    W, H = (round(v * settings.scale) for v in p.sensor_size)
    _say(f"{label}: simulating {duration:.2f} s of {W}x{H} {preset} events", progress)
    t0 = time.monotonic()
    rec = sm.simulate_preset(
        preset, duration=duration, seed=settings.seed, progress=progress, scale=settings.scale
    )
    _say(f"{label}: {len(rec)} events in {time.monotonic() - t0:.1f} s", progress)
    all_events = rec.events()

    def intervals():
        for k in range(1, n_intervals + 1):
            ta, tb = k * dt_gt, (k + 1) * dt_gt
            interval = rec.events(ta, tb)
            window = _window_before(all_events, tb, settings.n_events)
            yield ta, tb, interval, window, event_mask(interval), rec.flow(ta, tb)

    return rec, dt_gt, intervals()


# --- tables 1 and 2 ----------------------------------------------------------------------------------
def flow_table(
    preset: str, settings: Settings, progress: bool = True, lam: float | None = None
) -> dict[tuple[str, str], dict[str, tuple]]:
    """Run the table 1 / table 2 protocol on a simulator preset.

    Returns
    -------
    dict
        ``(warp or "GT" / "Identity", row label) -> {objective: (AEE, 3PE, 10PE, 20PE, FWL)}``, means
        over the intervals; plus the key ``("_meta", "")`` with the per-interval details.
    """
    lam = settings.lam if lam is None else lam
    p = sm.PRESETS[preset]
    rec, dt_gt, intervals = _simulated_intervals(preset, settings, settings.windows, preset, progress)
    per_obj = len(FLOW_WARPS) * len(ROWS)
    bar = _Bar(settings.windows * len(OBJECTIVES) * per_obj, preset, progress)
    acc: dict[tuple[str, str], dict[str, list]] = {}
    meta = []

    def add(key, objective, values):
        acc.setdefault(key, {o: [] for o in OBJECTIVES})[objective].append(values)

    for w, (ta, tb, interval, window, mask, gt_flow) in enumerate(intervals):
        fprob = fwl_problem(interval, p.motion.warp)
        gt_theta = rec.theta_at(interval.t[0])
        gt_fwl = fprob.value(gt_theta)
        gt_window = rec.theta_at(window.t[0])  # the truth for the optimisation window (t_ref = first)
        ident = flow_error(np.zeros_like(gt_flow), gt_flow, mask)
        meta.append(
            {
                "interval": [ta, tb],
                "n_interval_events": len(interval),
                "window": [float(window.t[0]), float(window.t[-1])],
                "gt_theta": gt_theta.tolist(),
                "mean_gt_flow_px": float(np.mean(np.hypot(*gt_flow))),
                "gt_fwl": gt_fwl,
                "theta": {},
                "fwl": {},
                "J_estimate_truth": {},
            }
        )
        for objective in OBJECTIVES:
            add(("GT", ""), objective, (math.nan,) * 4 + (gt_fwl,))
            add(("Identity", ""), objective, tuple(ident[m] for m in METRICS[:4]) + (1.0,))
            for warp in FLOW_WARPS:
                fwl_w = fwl_problem(interval, warp)
                for label, names, whiten in ROWS:
                    prob = ContrastMaximization(
                        window, warp, objective=objective, regularizers=_regs(names, lam), whitening=whiten
                    )
                    theta = _optimize(prob, settings)
                    pred = flow_from_warp(warp, theta, rec.sensor_size, duration=prob.duration, dt=dt_gt)
                    err = flow_error(pred, gt_flow, mask)
                    fwl_est = fwl_w.value(theta)
                    add((warp, label), objective, tuple(err[m] for m in METRICS[:4]) + (fwl_est,))
                    key = f"{objective}/{warp}/{label}"
                    meta[-1]["theta"][key] = theta.tolist()
                    meta[-1]["fwl"][key] = fwl_est
                    truth = _truth_in(warp, p.motion.warp, gt_window)
                    if truth is not None:
                        # did the search find the global maximum, as far as the truth tells?
                        meta[-1]["J_estimate_truth"][key] = [prob.value(theta), prob.value(truth)]
                    bar.step(f"w{w + 1} {objective[:8]} {WARP_LABEL[warp]} {label}")
    out: dict = {
        key: {o: tuple(np.mean(np.array(v[o]), axis=0)) for o in OBJECTIVES} for key, v in acc.items()
    }
    out[("_meta", "")] = meta
    return out


def _truth_in(warp: str, true_warp: str, theta: np.ndarray) -> np.ndarray | None:
    """The true parameters in the estimated model: the same model, or the zoom part of the 4-DOF one."""
    if warp == true_warp:
        return np.asarray(theta)
    if warp == "zoom1" and true_warp == "mitrokhin4":
        return np.asarray(theta[2:3])
    return None


# --- table 3 -----------------------------------------------------------------------------------------
def rotation_table(
    data_dir: Path, settings: Settings, progress: bool = True, lam: float | None = None
) -> dict:
    """Table 3 on the ECD rotation cuts: ``{(row, cut): (RMS deg/s, FWL)}`` plus ``("_meta", cut)``."""
    from cmax_taichi import io

    lam = settings.lam if lam is None else lam
    cuts = [c for c in settings.rotation_cuts if (Path(data_dir) / c).is_dir()]
    if not cuts:
        raise FileNotFoundError(
            f"{data_dir}: no ECD rotation cut ({', '.join(settings.rotation_cuts)}); pass --data "
            "the folder that holds them (../shared/data/ecd_rotation beside the checkout)"
        )
    rows = (("No regularizer", ()), ("Divergence", ("divergence",)), ("Deformation", ("deformation",)))
    bar = _Bar(len(cuts) * len(rows), "table3", progress)
    out: dict = {}
    for cut in cuts:
        with io.open_recording(Path(data_dir) / cut) as rec:
            events = rec.read()
            camera = rec.camera
            w_gt = np.asarray(rec.angular_velocity(0.5 * (rec.t_start + rec.t_end)), dtype=np.float64)
        fprob = None
        for label, names in rows:
            prob = ContrastMaximization(events, "rotation3", camera=camera, regularizers=_regs(names, lam))
            if fprob is None:
                # FWL on the same (undistorted) events, with the gyro ground truth as its own row
                fprob = fwl_problem(prob.events, "rotation3", camera=camera)
                out[("GT", cut)] = (math.nan, fprob.value(w_gt))
            theta = _optimize(prob, settings)
            rms = angular_velocity_error(theta, w_gt)["rms_deg_s"]
            out[(label, cut)] = (rms, fprob.value(theta))
            out.setdefault(("_meta", cut), {"w_gt": w_gt.tolist(), "n_events": len(events)})[label] = (
                theta.tolist()
            )
            bar.step(f"{cut} {label}")
    return out


# --- sensitivity -------------------------------------------------------------------------------------
def sensitivity(settings: Settings, progress: bool = True) -> list[dict]:
    """AEE and FWL against lambda (``indoor_flying``, variance): one dict per (warp, regularizer,
    lambda), means over the intervals; lambda 0 is the unregularized estimate."""
    s = replace(settings, windows=settings.sensitivity_windows)
    p = sm.PRESETS["indoor_flying"]
    rec, dt_gt, intervals = _simulated_intervals("indoor_flying", s, s.windows, "sensitivity", progress)
    combos = [("none", (), 0.0)] + [(label, names, lam) for label, names, _ in ROWS[2:] for lam in s.lambdas]
    bar = _Bar(s.windows * len(FLOW_WARPS) * len(combos), "sensitivity", progress)
    acc: dict[tuple, list] = {}
    for w, (_, _, interval, window, mask, gt_flow) in enumerate(intervals):
        ident = flow_error(np.zeros_like(gt_flow), gt_flow, mask)["AEE"]
        gt_fwl = fwl_problem(interval, p.motion.warp).value(rec.theta_at(interval.t[0]))
        acc.setdefault(("identity",), []).append((ident, 1.0))
        acc.setdefault(("gt",), []).append((0.0, gt_fwl))
        for warp in FLOW_WARPS:
            fprob = fwl_problem(interval, warp)
            for label, names, lam in combos:
                prob = ContrastMaximization(
                    window, warp, objective="variance", regularizers=_regs(names, lam)
                )
                theta = _optimize(prob, s)
                pred = flow_from_warp(warp, theta, rec.sensor_size, duration=prob.duration, dt=dt_gt)
                aee = flow_error(pred, gt_flow, mask)["AEE"]
                acc.setdefault((warp, label, lam), []).append((aee, fprob.value(theta)))
                bar.step(f"w{w + 1} {WARP_LABEL[warp]} {label} lambda={lam:g}")
    rows = []
    ident = np.mean(acc[("identity",)], axis=0)
    gt = np.mean(acc[("gt",)], axis=0)
    for key, values in acc.items():
        if len(key) != 3:
            continue
        warp, label, lam = key
        aee, fw = np.mean(values, axis=0)
        rows.append(
            {
                "warp": warp,
                "regularizer": label,
                "lambda": lam,
                "AEE": float(aee),
                "FWL": float(fw),
                "identity_AEE": float(ident[0]),
                "gt_FWL": float(gt[1]),
            }
        )
    return rows


def complexity(settings: Settings, progress: bool = True) -> list[dict]:
    """Median seconds per ``value_and_grad`` (mitrokhin4, variance) against the number of events."""
    from cmax_taichi.core import backend

    n_max = max(settings.complexity_sizes)
    p = sm.PRESETS["indoor_flying"]
    # enough simulated time for the largest window (about 30k events per 0.125 s)
    duration = min(4.0, 0.125 * (n_max / 25_000.0) + 0.05)
    _say(f"complexity: simulating {duration:.2f} s of indoor_flying", progress)
    rec = sm.simulate_preset("indoor_flying", duration=duration, seed=settings.seed, progress=progress)
    events = rec.events()
    if len(events) < n_max:
        raise RuntimeError(f"complexity: {len(events)} simulated events, fewer than {n_max}")
    info = backend.info()
    bar = _Bar(len(settings.complexity_sizes) * len(COMPLEXITY_CONFIGS), "complexity", progress)
    rows = []
    theta = np.asarray(p.motion.theta)
    for n in settings.complexity_sizes:
        window = events[:n]
        for label, names in COMPLEXITY_CONFIGS:
            prob = ContrastMaximization(
                window, "mitrokhin4", objective="variance", regularizers=_regs(names, 1.0)
            )
            seconds = prob.timed_value_and_grad(theta, repeats=settings.complexity_repeats)
            rows.append(
                {
                    "n_events": n,
                    "config": label,
                    "seconds": seconds,
                    "arch": info.arch,
                    "precision": info.precision,
                }
            )
            bar.step(f"N={n} {label}")
    return rows


# --- driver ------------------------------------------------------------------------------------------
def shared_data_root() -> Path:
    """The shared recordings: ``$CMAX_SHARED_DATA``, else ``shared/data`` beside the checkout.

    "Beside the checkout" is ``../shared/data`` seen from the checkout's root (this file is
    ``<checkout>/cmax_taichi/lab/experiments.py``), the folder that ``tests/conftest.py`` reads too.
    """
    env = os.environ.get("CMAX_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "shared" / "data"


def default_data_dir() -> Path:
    """The ECD rotation cuts of table 3: ``ecd_rotation`` in :func:`shared_data_root`."""
    return shared_data_root() / "ecd_rotation"


def reproduce(
    what: str,
    out_dir,
    *,
    quick: bool = False,
    data_dir=None,
    settings: Settings | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> dict[str, list[Path]]:
    """Run one experiment (or ``"all"``) and write its outputs into ``out_dir``.

    Parameters
    ----------
    what : {"table1", "table2", "table3", "sensitivity", "complexity", "all"}
    out_dir : path
        Created if needed.
    quick : bool
        :meth:`Settings.quick` sizes (ignored when ``settings`` is given).
    data_dir : path, optional
        Folder of the ECD rotation cuts (table 3); default :func:`default_data_dir`.
    settings : Settings, optional
    progress : bool
        Progress bars on stderr.
    log : callable, optional
        Receives each Markdown table as it is written (default: print to stdout).

    Returns
    -------
    dict
        Experiment name -> the files written.
    """
    names = EXPERIMENTS if what == "all" else (what,)
    for name in names:
        if name not in EXPERIMENTS:
            raise ValueError(f"unknown experiment {what!r}; valid: {', '.join(EXPERIMENTS)}, all")
    settings = settings or (Settings.quick() if quick else Settings())
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data_dir = Path(data_dir) if data_dir is not None else default_data_dir()
    log = log or (lambda text: print(text, flush=True))
    written: dict[str, list[Path]] = {}
    timings: dict[str, float] = {}
    for name in names:
        t0 = time.monotonic()
        files: list[Path] = []
        if name in ("table1", "table2"):
            preset = "indoor_flying" if name == "table1" else "driving"
            paper = PAPER_TABLE1 if name == "table1" else PAPER_TABLE2
            result = flow_table(preset, settings, progress)
            title = (
                f"Table {name[-1]}: simulated {preset} (stands in for MVSEC "
                f"{'indoor_flying1' if name == 'table1' else 'outdoor_day1'}), "
                f"{settings.windows} interval(s) of dt = 4 frames, lambda = {settings.lam:g}"
            )
            if settings.scale != 1.0:
                title += f"; sensor scaled by {settings.scale:g} (quick run, not the tables)"
            md = flow_table_markdown(result, paper, title)
            flow_table_csv(result, paper, out / f"{name}.csv", name)
            (out / f"{name}.json").write_text(json_text(result[("_meta", "")]))
            files += [out / f"{name}.md", out / f"{name}.csv", out / f"{name}.json"]
        elif name == "table3":
            if not data_dir.is_dir() and what == "all":
                _say(
                    f"table3: skipped, no ECD rotation data at {data_dir} "
                    "(pass --data or set CMAX_SHARED_DATA)",
                    True,
                )
                continue
            result = rotation_table(data_dir, settings, progress)
            md = rotation_table_markdown(result)
            rotation_table_csv(result, out / "table3.csv")
            meta = {cut: v for (row, cut), v in result.items() if row == "_meta"}
            (out / "table3.json").write_text(json_text(meta))
            files += [out / "table3.md", out / "table3.csv", out / "table3.json"]
        elif name == "sensitivity":
            rows = sensitivity(settings, progress)
            md, png = sensitivity_outputs(rows, out)
            write_rows_csv(rows, out / "sensitivity.csv")
            files += [out / "sensitivity.md", out / "sensitivity.csv", png]
        else:
            rows = complexity(settings, progress)
            md, png = complexity_outputs(rows, out)
            write_rows_csv(rows, out / "complexity.csv")
            files += [out / "complexity.md", out / "complexity.csv", png]
        timings[name] = time.monotonic() - t0
        md += f"\n({name}: {timings[name]:.0f} s)\n"
        (out / f"{name}.md").write_text(md)
        log(md)
        written[name] = files
    run = {
        "what": what,
        "quick": quick,
        "settings": asdict(settings),
        "seconds": timings,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
    }
    (out / f"run_{what}.json").write_text(json_text(run))
    return written
