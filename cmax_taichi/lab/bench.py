"""Side-by-side benchmark: this library's Taichi kernels, a PyTorch autograd twin, the NumPy reference.

Run it as ``cmax-taichi bench [--quick] [--out DIR]`` or ``python -m benchmarks.run [--quick]``.

For every configuration (events N, sensor, warp, regularizers) it builds the same synthetic window for
every implementation, then

1. **checks agreement** on those identical inputs: the Taichi value and gradient against the PyTorch
   twin (both exact derivatives), the values against the float64 NumPy reference, and (for
   ``N <= FD_CHECK_MAX_EVENTS``) the gradients against central differences of the reference. An
   implementation that disagrees beyond the stated tolerance gets status ``DISAGREES`` and **no
   time** in the report;
2. **times** one ``value_and_grad`` (the reference: one value; its gradient by central differences
   would cost 2P values) after a warm-up, with the implementations interleaved round by round so that
   they share the machine's load; it reports the median over the repeats, events per second, the
   first call (compilation included) separately, the peak RSS growth and, for Taichi, the bytes held
   in its fields;
3. times one complete window solve (30,000 events): :func:`cmax_taichi.maximize` with a multi-start
   grid search and Adam iterations.

Outputs in ``--out``: ``results.csv`` (one row per implementation and configuration),
``results.md`` (machine, date, versions, tables), ``results.png`` (time and speed-up against N).
The generic Taichi kernel chain (the autodiff chain the fused kernels replaced) runs as a fourth
implementation, ``taichi-chain``, on the smaller windows: it is the "before" of the optimisation.
"""

from __future__ import annotations

import csv
import datetime as _dt
import gc
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from cmax_taichi.core import backend
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.pipeline.fused import FusedPipeline
from cmax_taichi.pipeline.problem import ContrastMaximization
from cmax_taichi.testing import reference

__all__ = [
    "BenchConfig",
    "Plan",
    "quick_plan",
    "full_plan",
    "gpu_plan",
    "run_benchmark",
    "make_window",
    "check_agreement",
]

#: the benchmark's parameter vector per warp (a moderate motion, a few px over the window)
THETAS = {
    "translation2": (120.0, -80.0),
    "rotation3": (0.6, -0.4, 1.5),
    "mitrokhin4": (120.0, -80.0, 4.0, 3.0),
}
SENSORS = {"240x180": (240, 180), "346x260": (346, 260), "640x480": (640, 480), "1280x720": (1280, 720)}
REGS = {"none": {}, "div+def": {"divergence": 1.0, "deformation": 1.0}}
DURATION = 0.05  # s, window length
FD_CHECK_MAX_EVENTS = 10_000  # central differences of the reference (2P evaluations) up to this N
FD_STEPS = (1e-7, 1e-8)  # relative steps: the second is tried when a pixel kink spoils the first
TOLERANCES = {  # relative to max(1, |J|) for values, to max |grad| for gradients
    "f64": {"value": 1e-9, "grad": 1e-6, "fd": 1e-4},
    "f32": {"value": 2e-3, "grad": 5e-2, "fd": 5e-2},
}


# ----------------------------------------------------------------------------------------------
# inputs
# ----------------------------------------------------------------------------------------------
def camera_for(sensor: tuple[int, int]) -> Camera:
    """A pinhole camera with a ~70 degree horizontal field of view, centred."""
    W, H = sensor
    f = 0.7 * W
    return Camera(fx=f, fy=f, cx=(W - 1) / 2.0, cy=(H - 1) / 2.0)


def make_window(n: int, sensor: tuple[int, int], seed: int = 0):
    """``n`` synthetic events (x, y, t, p) on 40 moving straight edges plus 10 % noise, time-sorted.

    Returns float64 arrays ``x, y`` (px), ``t`` (s, spanning exactly ``DURATION``) and ``p`` in {0, 1}.
    """
    rng = np.random.default_rng(seed)
    W, H = sensor
    n_edge = int(0.9 * n)
    k = 40
    centres = rng.uniform([0.1 * W, 0.1 * H], [0.9 * W, 0.9 * H], size=(k, 2))
    angles = rng.uniform(0, np.pi, k)
    length = 0.15 * min(W, H)
    which = rng.integers(0, k, n_edge)
    s = rng.uniform(-length, length, n_edge)
    t_edge = rng.uniform(0, DURATION, n_edge)
    vel = np.array([100.0, -60.0])  # px/s: the edges move, so the identity warp is blurred
    x = centres[which, 0] + s * np.cos(angles[which]) + vel[0] * t_edge + rng.normal(0, 0.5, n_edge)
    y = centres[which, 1] + s * np.sin(angles[which]) + vel[1] * t_edge + rng.normal(0, 0.5, n_edge)
    n_noise = n - n_edge
    x = np.concatenate([x, rng.uniform(0, W - 1, n_noise)])
    y = np.concatenate([y, rng.uniform(0, H - 1, n_noise)])
    t = np.concatenate([t_edge, rng.uniform(0, DURATION, n_noise)])
    x = np.clip(x, 0, W - 1)
    y = np.clip(y, 0, H - 1)
    order = np.argsort(t, kind="stable")
    x, y, t = x[order], y[order], t[order]
    t[0], t[-1] = 0.0, DURATION
    p = rng.integers(0, 2, n)
    return x, y, t, p


# ----------------------------------------------------------------------------------------------
# implementations
# ----------------------------------------------------------------------------------------------
@dataclass
class Impl:
    """One implementation bound to one window: ``vg(theta)`` and ``value(theta)`` callables."""

    name: str
    vg: Callable | None
    value: Callable
    setup_s: float
    field_bytes: int = 0


def build_taichi(win, cfg, *, fused: bool = True) -> Impl:
    x, y, t, p = win
    FusedPipeline.enabled = fused
    try:
        t0 = time.perf_counter()
        prob = ContrastMaximization(
            Events(x, y, t, p, cfg.sensor),
            warp=cfg.warp,
            regularizers=REGS[cfg.regs],
            camera=camera_for(cfg.sensor),
            blur_sigma=1.0,
        )
        prob.value_and_grad(THETAS[cfg.warp])  # compiles the gradient kernels too
        setup = time.perf_counter() - t0
    finally:
        FusedPipeline.enabled = True
    nbytes = prob._fused.nbytes() if prob._fused is not None else 0
    return Impl("taichi" if fused else "taichi-chain", prob.value_and_grad, prob.value, setup, nbytes)


def build_torch(win, cfg, precision: str) -> Impl:
    import torch

    from cmax_taichi.testing.torch_cmax import TorchCMax

    x, y, t, _ = win
    t0 = time.perf_counter()
    # the twin takes the same problem description as the reference
    dtype = torch.float64 if precision == "f64" else torch.float32
    twin = TorchCMax(x, y, t, **reference_kwargs(cfg), dtype=dtype)
    twin.value_and_grad(THETAS[cfg.warp])
    return Impl("torch", twin.value_and_grad, twin.value, time.perf_counter() - t0)


def reference_kwargs(cfg) -> dict:
    cam = camera_for(cfg.sensor)
    regs = REGS[cfg.regs]
    return dict(
        warp=cfg.warp,
        sensor_size=cfg.sensor,
        center=(cam.cx, cam.cy),
        focal=(cam.fx, cam.fy),
        blur_sigma=1.0,
        lambda_div=regs.get("divergence", 0.0),
        lambda_def=regs.get("deformation", 0.0),
    )


def build_numpy(win, cfg) -> Impl:
    kwargs = reference_kwargs(cfg)

    def value(theta):
        return reference.evaluate(*win, theta, **kwargs)["J"]

    t0 = time.perf_counter()
    value(THETAS[cfg.warp])
    return Impl("numpy", None, value, time.perf_counter() - t0)


def reference_fd_grad(win, cfg, theta, rel_step: float = 1e-7) -> np.ndarray:
    """Central differences of the reference J (2P evaluations).

    The bilinear IWE makes J piecewise smooth in theta: it has a kink wherever an event's warped
    position crosses a pixel boundary. A step of 1e-6 (relative) crossed such kinks at 1e4 events and
    missed the exact gradient by 3e-4 to 1.4e-3 (relative) while Taichi and PyTorch agreed to 1e-15;
    1e-7 agreed to 1e-8. In float64 the rounding error of a 1e-7 step is about 1e-9.
    """
    return reference.central_difference_grad(*win, theta, rel_step=rel_step, **reference_kwargs(cfg))


# ----------------------------------------------------------------------------------------------
# agreement
# ----------------------------------------------------------------------------------------------
def _rel(a, b, scale) -> float:
    return float(np.max(np.abs(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64))) / scale)


def check_agreement(impls: dict[str, Impl], win, cfg, precision: str) -> dict[str, str]:
    """Status of every implementation: "ok", or "DISAGREES: ..." naming what and by how much.

    Values are held against the NumPy reference where it runs (else against PyTorch), gradients
    against each other (Taichi, the chain, PyTorch) and, up to ``FD_CHECK_MAX_EVENTS`` events, against
    central differences of the reference (:func:`reference_fd_grad`). Tolerances: :data:`TOLERANCES`.
    """
    tol = TOLERANCES[precision]
    theta = np.asarray(THETAS[cfg.warp], dtype=np.float64)
    values, grads = {}, {}
    for name, impl in impls.items():
        if impl.vg is not None:
            values[name], grads[name] = impl.vg(theta)
        else:
            values[name] = impl.value(theta)
    status = {name: "ok" for name in impls}
    # values: against the reference when it runs, else against torch, else taichi
    anchor = "numpy" if "numpy" in values else ("torch" if "torch" in values else "taichi")
    # a float32 implementation is checked against the float64 reference with the f32 tolerance
    v_ref = values[anchor]
    for name, v in values.items():
        err = abs(v - v_ref) / max(1.0, abs(v_ref))
        if not (math.isfinite(v) and err <= tol["value"]):
            status[name] = f"DISAGREES: J = {v:.12g} vs {anchor} {v_ref:.12g} (rel {err:.1e})"
    # gradients: the exact derivatives against each other (PyTorch's autograd is the anchor), then
    # against central differences of the reference (a second, smaller step when a kink spoils the first)
    exact = grads.get("torch", grads.get("taichi"))
    anchor_name = "torch" if "torch" in grads else "taichi"
    if exact is not None:
        scale = max(float(np.max(np.abs(exact))), 1e-300)
        for name, g in grads.items():
            err = _rel(g, exact, scale)
            if not (np.all(np.isfinite(g)) and err <= tol["grad"]) and status[name] == "ok":
                status[name] = f"DISAGREES: gradient vs {anchor_name} (rel {err:.1e})"
    if cfg.n <= FD_CHECK_MAX_EVENTS and grads:
        fds: dict[float, np.ndarray] = {}  # computed on first use, shared by the implementations
        for name, g in grads.items():
            if status[name] != "ok":
                continue
            errs = []
            for step in FD_STEPS:
                if step not in fds:
                    fds[step] = reference_fd_grad(win, cfg, theta, rel_step=step)
                scale = max(float(np.max(np.abs(fds[step]))), 1e-300)
                errs.append(_rel(g, fds[step], scale))
                if np.all(np.isfinite(g)) and errs[-1] <= tol["fd"]:
                    break
            else:
                status[name] = (
                    f"DISAGREES: gradient vs finite differences of the reference (rel {min(errs):.1e})"
                )
    return status


# ----------------------------------------------------------------------------------------------
# timing and memory
# ----------------------------------------------------------------------------------------------
def _rss_bytes(field_name: str = "VmRSS") -> int:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field_name + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def _reset_peak() -> bool:
    """Reset the kernel's peak-RSS counter (VmHWM) of this process; False where not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def measure_peak(fn: Callable[[], object]) -> int:
    """Peak RSS growth (bytes) while ``fn()`` runs: VmHWM after minus VmRSS before (-1: unknown)."""
    gc.collect()
    if not _reset_peak():
        return -1
    before = _rss_bytes("VmRSS")
    fn()
    return max(0, _rss_bytes("VmHWM") - before)


@dataclass
class BenchConfig:
    """One row group of the sweep."""

    n: int
    sensor_name: str
    warp: str
    regs: str
    precision: str = "f64"
    impls: tuple[str, ...] = ("taichi", "torch", "numpy")

    @property
    def sensor(self) -> tuple[int, int]:
        """``(W, H)`` of a named sensor, or of a ``"WxH"`` name."""
        if self.sensor_name in SENSORS:
            return SENSORS[self.sensor_name]
        w, h = self.sensor_name.lower().split("x")
        return int(w), int(h)


@dataclass
class Row:
    """One implementation on one configuration (times in ms, memory in MB)."""

    impl: str
    n: int
    sensor: str
    warp: str
    regs: str
    precision: str
    status: str
    measured: str = ""  # "value_and_grad" or "value"
    median_ms: float = float("nan")
    min_ms: float = float("nan")
    repeats: int = 0
    events_per_s: float = float("nan")
    value_ms: float = float("nan")
    first_call_s: float = float("nan")
    peak_rss_mb: float = float("nan")
    field_mb: float = float("nan")
    vs_torch: float = float("nan")  # torch median / this median (same measured quantity)


def _time_round_robin(
    fns: dict[str, Callable], theta, *, min_repeats: int, max_repeats: int, budget_s: float
):
    """Interleaved timings: each round calls every function once. Stops after ``max_repeats`` rounds, or
    after ``min_repeats`` when the rounds so far took ``budget_s``."""
    times: dict[str, list[float]] = {k: [] for k in fns}
    spent = 0.0
    for r in range(max_repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn(theta)
            dt = time.perf_counter() - t0
            times[name].append(dt)
            spent += dt
        if r + 1 >= min_repeats and spent >= budget_s:
            break
    return times


@dataclass
class Plan:
    """What one run measures."""

    configs: list[BenchConfig]
    min_repeats: int = 3
    max_repeats: int = 15
    budget_s: float = 1.5
    solve: bool = True
    segment: bool = False
    label: str = "full"
    notes: list[str] = field(default_factory=list)


def quick_plan(precision: str = "f64") -> Plan:
    """About two minutes (most of it compiling): 346x260, N = 1e3 and 3e4, translation2 without and
    mitrokhin4 with both regularizers, mitrokhin4 with both at 1e6 (Taichi and PyTorch); the generic
    chain at the headline configuration (3e4, mitrokhin4, both)."""
    cfgs = []
    for n in (1_000, 30_000):
        for warp, regs in (("translation2", "none"), ("mitrokhin4", "div+def")):
            impls = ("taichi", "torch", "numpy")
            if n == 30_000 and warp == "mitrokhin4":
                impls += ("taichi-chain",)
            cfgs.append(BenchConfig(n, "346x260", warp, regs, precision, impls))
    cfgs.append(BenchConfig(1_000_000, "346x260", "mitrokhin4", "div+def", precision, ("taichi", "torch")))
    notes = [
        "NumPy reference: value only (its gradient by central differences would cost 2P values).",
        "taichi-chain = the generic kernel chain differentiated by Taichi autodiff (before the fused "
        "kernels).",
    ]
    return Plan(cfgs, min_repeats=3, max_repeats=10, budget_s=0.4, label="quick", notes=notes)


def full_plan(precision: str = "f64") -> Plan:
    """The sweep of issue 5: N = 1e3 .. 1e7, four sensors, three warps, with / without regularizers.

    Limits, to stay within about 20 minutes on a 2-core machine (said in the report): N = 3e4 (the
    headline size) on 346x260 only; N = 1e7 on 346x260 with translation2 and mitrokhin4 only; the
    NumPy reference (value only) up to 1e5 events; the generic Taichi chain (the "before") on 346x260
    with translation2 and mitrokhin4 at N = 3e4 and 1e6.
    """
    cfgs = []
    for n in (1_000, 10_000, 30_000, 100_000, 1_000_000, 10_000_000):
        for sensor in SENSORS:
            if n in (30_000, 10_000_000) and sensor != "346x260":
                continue
            for warp in THETAS:
                if n == 10_000_000 and warp == "rotation3":
                    continue
                for regs in REGS:
                    impls = ["taichi", "torch"]
                    if n <= 100_000:
                        impls.append("numpy")
                    if sensor == "346x260" and warp != "rotation3" and n in (30_000, 1_000_000):
                        impls.append("taichi-chain")
                    cfgs.append(BenchConfig(n, sensor, warp, regs, precision, tuple(impls)))
    notes = [
        "NumPy reference: value only (its gradient by central differences would cost 2P values), N <= 1e5.",
        "N = 3e4 and N = 1e7: sensor 346x260 only; N = 1e7 without rotation3 (time budget of the run).",
        "taichi-chain = the generic kernel chain differentiated by Taichi autodiff (the state before the "
        "fused kernels), measured in the same run: 346x260, translation2 and mitrokhin4, N = 3e4 and 1e6.",
    ]
    return Plan(cfgs, min_repeats=3, max_repeats=15, budget_s=1.5, segment=True, label="full", notes=notes)


def gpu_plan(precision: str = "f32", max_events: int = 10_000_000) -> Plan:
    """The GPU throughput sweep of ``benchmarks/gpu_check.sh``: N = 1e3 .. 1e7 (at most ``max_events``)
    on 346x260 and 1280x720, three warps with and without both regularizers; the NumPy reference (the
    value anchor of the agreement check) up to 1e5 events, PyTorch (on the CPU) and the generic chain on
    346x260 up to 1e6 events; the window solve and the segmentation timing as in the full plan."""
    cfgs = []
    for n in (1_000, 10_000, 100_000, 1_000_000, 10_000_000):
        if n > max_events:
            continue
        for sensor in ("346x260", "1280x720"):
            for warp in THETAS:
                for regs in REGS:
                    impls = ["taichi"]
                    if sensor == "346x260" and n <= 1_000_000:
                        impls += ["taichi-chain", "torch"]
                    if n <= 100_000:
                        impls.append("numpy")
                    cfgs.append(BenchConfig(n, sensor, warp, regs, precision, tuple(impls)))
    notes = [
        "GPU sweep: Taichi on the backend named above; PyTorch and NumPy run on the CPU (their times are "
        "a CPU baseline, not a GPU comparison). NumPy reference: value only, N <= 1e5.",
        "taichi-chain = the generic kernel chain differentiated by Taichi autodiff: 346x260, N <= 1e6.",
    ]
    return Plan(cfgs, min_repeats=3, max_repeats=15, budget_s=1.0, segment=True, label="gpu", notes=notes)


def _torch_available() -> bool:
    try:
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


def run_config(cfg: BenchConfig, plan: Plan, log: Callable[[str], None]) -> list[Row]:
    """Check and time every implementation of one configuration."""
    win = make_window(cfg.n, cfg.sensor, seed=cfg.n % 9973)
    impls: dict[str, Impl] = {}
    rows: dict[str, Row] = {}
    base = dict(n=cfg.n, sensor=cfg.sensor_name, warp=cfg.warp, regs=cfg.regs, precision=cfg.precision)
    peak: dict[str, float] = {}
    for name in cfg.impls:
        if name == "torch" and not _torch_available():
            rows[name] = Row(name, status="skipped: torch is not installed", **base)
            continue
        holder: dict[str, Impl] = {}

        def build(name=name, holder=holder):
            if name in ("taichi", "taichi-chain"):
                holder["impl"] = build_taichi(win, cfg, fused=name == "taichi")
            elif name == "torch":
                holder["impl"] = build_torch(win, cfg, cfg.precision)
            else:
                holder["impl"] = build_numpy(win, cfg)

        try:
            peak[name] = measure_peak(build) / 1e6
        except Exception as exc:  # an implementation that fails to run is reported, not fatal
            rows[name] = Row(name, status=f"error: {type(exc).__name__}: {exc}", **base)
            continue
        impls[name] = holder["impl"]
    status = check_agreement(impls, win, cfg, cfg.precision) if impls else {}
    ok = {k: v for k, v in impls.items() if status[k] == "ok"}
    theta = np.asarray(THETAS[cfg.warp], dtype=np.float64)
    vg_fns = {k: v.vg for k, v in ok.items() if v.vg is not None}
    value_fns = {k: v.value for k, v in ok.items()}
    for fn in list(vg_fns.values()) + list(value_fns.values()):
        fn(theta)  # warm-up
    t_vg = _time_round_robin(
        vg_fns, theta, min_repeats=plan.min_repeats, max_repeats=plan.max_repeats, budget_s=plan.budget_s
    )
    t_val = _time_round_robin(
        value_fns,
        theta,
        min_repeats=plan.min_repeats,
        max_repeats=plan.max_repeats,
        budget_s=plan.budget_s / 2,
    )
    for name, impl in impls.items():
        row = Row(name, status=status[name], **base)
        row.first_call_s = impl.setup_s
        row.peak_rss_mb = peak.get(name, float("nan"))
        row.field_mb = impl.field_bytes / 1e6 if impl.field_bytes else float("nan")
        if status[name] == "ok":
            if name in t_vg:
                ts = t_vg[name]
                row.measured = "value_and_grad"
            else:
                ts = t_val[name]
                row.measured = "value"
            row.median_ms = statistics.median(ts) * 1e3
            row.min_ms = min(ts) * 1e3
            row.repeats = len(ts)
            row.events_per_s = cfg.n / (row.median_ms / 1e3)
            if name in t_val:
                row.value_ms = statistics.median(t_val[name]) * 1e3
        rows[name] = row
    torch_row = rows.get("torch")
    for row in rows.values():
        if torch_row is not None and torch_row.measured == row.measured and row.median_ms > 0:
            row.vs_torch = torch_row.median_ms / row.median_ms
    out = [rows[k] for k in cfg.impls if k in rows]
    for row in out:
        if row.status == "ok":
            log(
                f"  {row.impl:13s} {row.measured:15s} {row.median_ms:10.3f} ms  "
                f"{row.events_per_s / 1e6:8.2f} Mev/s  x{row.vs_torch:6.1f} vs torch  "
                f"first {row.first_call_s:6.2f} s"
            )
        else:
            log(f"  {row.impl:13s} {row.status}")
    del impls, ok, vg_fns, value_fns
    gc.collect()
    return out


# ----------------------------------------------------------------------------------------------
# window solve
# ----------------------------------------------------------------------------------------------
SOLVE = dict(n=30_000, sensor="346x260", warp="mitrokhin4", regs="div+def")
SOLVE_ARGS = dict(method="adam", init="random", n_init=64, n_starts=2, max_iter=25, gtol=0.0, xtol=1e-9)


def time_window_solve(repeats: int, log: Callable[[str], None]) -> dict:
    """Median wall time of :func:`cmax_taichi.maximize` on a 30,000-event window (after a warm-up)."""
    from cmax_taichi.solve import optimize

    cfg = BenchConfig(SOLVE["n"], SOLVE["sensor"], SOLVE["warp"], SOLVE["regs"])
    x, y, t, p = make_window(cfg.n, cfg.sensor, seed=7)
    prob = ContrastMaximization(
        Events(x, y, t, p, cfg.sensor),
        warp=cfg.warp,
        regularizers=REGS[cfg.regs],
        camera=camera_for(cfg.sensor),
    )
    result = optimize.maximize(prob, **SOLVE_ARGS)  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = optimize.maximize(prob, **SOLVE_ARGS)
        times.append(time.perf_counter() - t0)
    iters = len(result.history.value) - 1
    out = {
        "events": cfg.n,
        "sensor": cfg.sensor_name,
        "warp": cfg.warp,
        "regularizers": cfg.regs,
        "call": "maximize(prob, " + ", ".join(f"{k}={v!r}" for k, v in SOLVE_ARGS.items()) + ")",
        "median_ms": statistics.median(times) * 1e3,
        "min_ms": min(times) * 1e3,
        "repeats": repeats,
        "n_evaluations": result.n_evaluations,
        "n_iterations_winning_run": result.n_iterations,
        "history_iterates": iters,
        "theta": [float(v) for v in result.theta],
    }
    log(
        f"window solve: {out['median_ms']:.1f} ms median of {repeats} ({result.n_evaluations} evaluations, "
        f"winning run {result.n_iterations} iterations)"
    )
    return out


# ----------------------------------------------------------------------------------------------
# reporting
# ----------------------------------------------------------------------------------------------
def machine_info() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    versions = {"python": platform.python_version(), "numpy": np.__version__}
    try:
        import taichi as ti

        versions["taichi"] = ".".join(str(v) for v in ti.__version__)
    except Exception:  # pragma: no cover - taichi is a dependency
        versions["taichi"] = "?"
    try:
        import torch

        versions["torch"] = torch.__version__
        torch_threads = torch.get_num_threads()
    except ImportError:
        versions["torch"] = "not installed"
        torch_threads = 0
    try:
        load = os.getloadavg()
    except OSError:
        load = (float("nan"),) * 3
    from cmax_taichi import __version__

    versions["cmax-taichi"] = __version__
    info = backend.info()
    return {
        "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "load_average_1min": round(load[0], 2),
        "arch": info.arch,
        "precision": info.precision,
        "torch_threads": torch_threads,
        "versions": versions,
    }


def _fmt(v, digits=3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}g}" if abs(v) < 1000 else f"{v:.0f}"
    return str(v)


def segmentation_markdown(seg: list[dict]) -> list[str]:
    """The segmentation timing table (``segment_eval.timing`` rows) with its caption."""
    from cmax_taichi.lab.segment_eval import timing_table

    return [
        "",
        "Motion segmentation (`cmax_taichi.segment`, mitrokhin4 with both regularizers, lambda = 1, "
        "simulated 3-object windows; medians of 5 complete segmentations after one that compiles; CPU = "
        "process time of all threads; value_and_grad of all clusters: median of 20):",
        "",
        *timing_table(seg),
    ]


def markdown_report(
    rows: list[Row],
    machine: dict,
    plan: Plan,
    solve: dict | None,
    wall_s: float,
    seg: list[dict] | None = None,
) -> str:
    """The Markdown report (also the README's Performance table)."""
    v = machine["versions"]
    lines = [
        f"Benchmark `{plan.label}` run on {machine['date']}: {machine['cpu']}, {machine['cores']} cores "
        f"(load average {machine['load_average_1min']} at the start), Taichi {v['taichi']} "
        f"({machine['arch']}, {machine['precision']}), PyTorch {v['torch']} "
        f"({machine['torch_threads']} threads), NumPy {v['numpy']}, Python {v['python']}, "
        f"cmax-taichi {v['cmax-taichi']}; {wall_s / 60:.1f} min in all.",
        "",
        "Times are medians over interleaved repeats after a warm-up, of one `value_and_grad` (NumPy: one "
        "value); Mev/s = million events per second; `x torch` = PyTorch's median / this median. "
        "Every implementation was first checked against the others on the same inputs "
        "(value to 1e-9 relative in f64, gradient to 1e-6 against PyTorch and to 1e-4 against central "
        "differences of the reference up to 1e4 events); a `DISAGREES` row has no time.",
        "",
        "| N | sensor | warp | regularizers | impl | measured | median ms | Mev/s | x torch "
        "| first call s | peak RSS MB | fields MB |",
        "|---:|---|---|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        if r.status != "ok":
            lines.append(f"| {r.n} | {r.sensor} | {r.warp} | {r.regs} | {r.impl} | {r.status} | | | | | | |")
            continue
        lines.append(
            f"| {r.n} | {r.sensor} | {r.warp} | {r.regs} | {r.impl} | {r.measured} | {_fmt(r.median_ms)} | "
            f"{_fmt(r.events_per_s / 1e6)} | {_fmt(r.vs_torch)} | {_fmt(r.first_call_s)} | "
            f"{_fmt(r.peak_rss_mb)} | {_fmt(r.field_mb)} |"
        )
    if solve:
        lines += [
            "",
            f"Window solve ({solve['events']} events, {solve['sensor']}, {solve['warp']}, "
            f"{solve['regularizers']}): "
            f"`{solve['call']}` takes **{solve['median_ms']:.1f} ms** (median of {solve['repeats']}, min "
            f"{solve['min_ms']:.1f} ms): {solve['n_evaluations']} evaluations, the winning run "
            f"{solve['n_iterations_winning_run']} Adam iterations.",
        ]
    if seg:
        lines += segmentation_markdown(seg)
    if plan.notes:
        lines += [""] + [f"* {n}" for n in plan.notes]
    return "\n".join(lines) + "\n"


def write_csv(rows: list[Row], path: Path) -> None:
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(asdict(rows[0]).keys()))
        writer.writeheader()
        for r in rows:
            writer.writerow(asdict(r))


def write_plot(rows: list[Row], path: Path) -> bool:
    """Time per evaluation and speed-up over PyTorch against N (sensor 346x260); False without rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r.status == "ok"]
    if not ok:
        return False
    sensor = "346x260" if any(r.sensor == "346x260" for r in ok) else ok[0].sensor
    sel = [r for r in ok if r.sensor == sensor]
    combos = sorted({(r.warp, r.regs) for r in sel})
    fig, axes = plt.subplots(2, len(combos), figsize=(3.2 * len(combos), 6.0), squeeze=False)
    colors = {"taichi": "C0", "taichi-chain": "C2", "torch": "C1", "numpy": "C3"}
    for j, (warp, regs) in enumerate(combos):
        ax, ax2 = axes[0, j], axes[1, j]
        for impl in colors:
            pts = sorted(
                (r.n, r.median_ms, r.vs_torch)
                for r in sel
                if r.impl == impl and (r.warp, r.regs) == (warp, regs)
            )
            if not pts:
                continue
            ns, ms, sp = zip(*pts, strict=True)
            ax.loglog(ns, ms, "o-", color=colors[impl], label=impl, ms=3)
            if impl != "torch":
                ax2.semilogx(ns, sp, "o-", color=colors[impl], label=impl, ms=3)
        ax.set_title(f"{warp}, {regs}", fontsize=9)
        ax.set_xlabel("events N")
        ax2.set_xlabel("events N")
        ax2.axhline(1.0, color="k", lw=0.5)
        if j == 0:
            ax.set_ylabel(f"ms per evaluation ({sensor})")
            ax2.set_ylabel("speed-up over PyTorch")
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def run_benchmark(
    plan: Plan,
    out_dir: str | Path,
    *,
    log: Callable[[str], None] = print,
    arch: str | None = None,
) -> dict:
    """Run ``plan`` on ``arch`` (default: ``CMAX_TAICHI_ARCH``, else the CPU); write results.csv,
    results.md and results.png into ``out_dir``.

    Returns
    -------
    dict
        ``rows`` (list of :class:`Row`), ``machine``, ``solve`` (or None), ``segmentation`` (rows of
        :func:`cmax_taichi.lab.segment_eval.timing`, or None), ``markdown`` and the paths.
    """
    # PyTorch's OpenMP threads busy-wait between operations; on a shared (oversubscribed) machine a
    # waiting thread then holds a core another needs, and small calls took seconds here: wait passively
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    precision = plan.configs[0].precision if plan.configs else "f64"
    backend.init(arch=arch, precision=precision)
    machine = machine_info()
    log(f"cmax-taichi bench ({plan.label}): {machine['cpu']}, {machine['cores']} cores, {machine['date']}")
    rows: list[Row] = []
    for i, cfg in enumerate(plan.configs):
        log(
            f"[{i + 1}/{len(plan.configs)}] N={cfg.n} {cfg.sensor_name} {cfg.warp} {cfg.regs} "
            f"({cfg.precision})"
        )
        rows.extend(run_config(cfg, plan, log))
    solve = time_window_solve(5 if plan.label == "full" else 3, log) if plan.solve else None
    seg = None
    if plan.segment:
        from cmax_taichi.lab.segment_eval import timing

        log("segmentation: K = 3 at 7,500-60,000 events, K = 1-4 at 30,000 events")
        seg = timing()
    wall = time.perf_counter() - t_start
    md = markdown_report(rows, machine, plan, solve, wall, seg)
    paths = {"csv": out / "results.csv", "md": out / "results.md", "png": out / "results.png"}
    if rows:
        write_csv(rows, paths["csv"])
    if seg:
        paths["segmentation"] = out / "segmentation.csv"
        with open(paths["segmentation"], "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(seg[0].keys()))
            writer.writeheader()
            writer.writerows(seg)
    paths["md"].write_text(md)
    if not write_plot(rows, paths["png"]):
        paths.pop("png")
    log(f"wrote {', '.join(str(p) for p in paths.values())} in {wall:.0f} s")
    return {
        "rows": rows,
        "machine": machine,
        "solve": solve,
        "segmentation": seg,
        "markdown": md,
        "paths": paths,
        "seconds": wall,
    }


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.run`` entry point (same options as ``cmax-taichi bench``)."""
    import argparse

    from cmax_taichi.cli import bench as cmd

    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__.split("\n\n")[0])
    cmd.add_arguments(parser)
    return cmd.run(parser.parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
