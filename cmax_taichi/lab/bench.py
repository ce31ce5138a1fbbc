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
   they share the machine's load (a call under 100 ms in a burst of consecutive calls per round: the
   median is over the calls that follow a call of the same implementation, as an optimizer's
   evaluations do, and each burst's first call, in the caches the other implementations left, is
   reported beside it); it reports the median over the repeats, events per second, the
   first call (compilation included) separately, the peak RSS growth and, for Taichi, the bytes held
   in its fields;
3. times one complete window solve (30,000 events): :func:`cmax_taichi.maximize` with a multi-start
   grid search and Adam iterations.

Outputs in ``--out``: ``results.csv`` (one row per implementation and configuration),
``results.md`` (machine, date, versions, tables), ``results.png`` (time and speed-up against N).
The generic Taichi kernel chain (the autodiff chain the fused kernels replaced) runs as a fourth
implementation, ``taichi-chain``, on the smaller windows: it is the "before" of the optimisation.

This module holds the plans, the timing and the run; :mod:`cmax_taichi.lab.bench_impls` the
implementations and their agreement check; :mod:`cmax_taichi.lab.bench_report` the report.
"""

from __future__ import annotations

import argparse
import csv
import gc
import os
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cmax_taichi.core import backend
from cmax_taichi.core.events import Events
from cmax_taichi.io.outputs import OutputFolder
from cmax_taichi.lab import bench_windows
from cmax_taichi.lab.bench_impls import (
    REGS,
    SENSORS,
    THETAS,
    BenchConfig,
    Impl,
    build_numpy,
    build_taichi,
    build_torch,
    camera_for,
    check_agreement,
    make_window,
)
from cmax_taichi.lab.bench_report import machine_info, markdown_report, write_csv, write_plot
from cmax_taichi.pipeline.problem import ContrastMaximization

#: what a run of the kernel plan writes into its output folder
BENCH_OUTPUTS = ("results.csv", "results.md", "results.png", "segmentation.csv")

__all__ = [
    "BenchConfig",
    "Plan",
    "Row",
    "quick_plan",
    "full_plan",
    "run_config",
    "gpu_plan",
    "run_benchmark",
    "make_window",
    "check_agreement",
    "add_arguments",
    "run_from_args",
    "main",
]


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
class Row:
    """One implementation on one configuration (times in ms, memory in MB)."""

    impl: str
    n: int
    sensor: str
    warp: str
    regs: str
    precision: str
    status: str
    window: str = "edges"  # the kind of event window (lab/bench_windows.py)
    measured: str = ""  # "value_and_grad" or "value"
    median_ms: float = float("nan")
    min_ms: float = float("nan")
    #: median of each burst's first call, made right after the other implementations' calls (their
    #: caches): :func:`_time_round_robin`
    first_of_burst_ms: float = float("nan")
    repeats: int = 0
    events_per_s: float = float("nan")
    value_ms: float = float("nan")
    first_call_s: float = float("nan")
    peak_rss_mb: float = float("nan")
    field_mb: float = float("nan")
    vs_torch: float = float("nan")  # torch median / this median (same measured quantity)


#: each implementation's first call of a round runs in the caches that the other implementations' calls
#: left (a 1280x720 call of 5,000 events took 2.0 ms there against 0.71 ms call after call, docs/
#: performance.md), which is not what an optimizer's consecutive evaluations see: so a call shorter than
#: :data:`BURST_LONGEST` s is timed in bursts of consecutive calls per round, as many as last about
#: :data:`BURST_SECONDS` s, at least 2 and at most :data:`BURST_MAX_CALLS`
BURST_SECONDS = 0.01
BURST_MAX_CALLS = 8
BURST_LONGEST = 0.1


def _burst_sizes(fns: dict[str, Callable], theta) -> dict[str, int]:
    """Calls per burst of each function (see :data:`BURST_SECONDS`), from the time of a call that follows
    another of the same function; 1 for a call of :data:`BURST_LONGEST` s or more (its caches matter
    little against its own work)."""
    sizes = {}
    for name, fn in fns.items():
        fn(theta)  # the first in the others' caches: the second times a call
        t0 = time.perf_counter()
        fn(theta)
        dt = time.perf_counter() - t0
        calls = min(BURST_MAX_CALLS, max(2, int(BURST_SECONDS / max(dt, 1e-9))))
        sizes[name] = 1 if dt >= BURST_LONGEST else calls
    return sizes


def _time_round_robin(
    fns: dict[str, Callable], theta, *, min_repeats: int, max_repeats: int, budget_s: float
) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """Interleaved timings: each round calls every function in a burst of consecutive calls
    (:func:`_burst_sizes`). Stops after ``max_repeats`` rounds, or after ``min_repeats`` when the rounds
    so far took ``budget_s``.

    Returns
    -------
    warm : dict of list of float
        Per function, the times (s) of the calls that followed a call of the same function (every call
        of a burst but the first; all calls for a burst of one).
    first : dict of list of float
        Per function, the time (s) of each burst's first call: the call made right after the other
        functions' bursts (after its own last burst when it is alone).
    """
    sizes = _burst_sizes(fns, theta)
    warm: dict[str, list[float]] = {k: [] for k in fns}
    first: dict[str, list[float]] = {k: [] for k in fns}
    spent = 0.0
    for r in range(max_repeats):
        for name, fn in fns.items():
            for call in range(sizes[name]):
                t0 = time.perf_counter()
                fn(theta)
                dt = time.perf_counter() - t0
                spent += dt
                if call == 0:
                    first[name].append(dt)
                if call > 0 or sizes[name] == 1:
                    warm[name].append(dt)
        if r + 1 >= min_repeats and spent >= budget_s:
            break
    return warm, first


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
    mitrokhin4 with both regularizers, mitrokhin4 with both at 1e6 (Taichi and PyTorch), on the synthetic
    edges; the generic chain at the headline configuration (3e4, mitrokhin4, both); rotation3 at 5e3
    events on a textured and a uniform 240x180 window (the full sweep's kinds; the textured stream of
    5,000 events takes a few seconds to simulate once)."""
    cfgs = []
    for n in (1_000, 30_000):
        for warp, regs in (("translation2", "none"), ("mitrokhin4", "div+def")):
            impls = ("taichi", "torch", "numpy")
            if n == 30_000 and warp == "mitrokhin4":
                impls += ("taichi-chain",)
            cfgs.append(BenchConfig(n, "346x260", warp, regs, precision, impls))
    cfgs.append(BenchConfig(1_000_000, "346x260", "mitrokhin4", "div+def", precision, ("taichi", "torch")))
    for window in ("textured", "uniform"):
        impls = ("taichi", "numpy")
        cfgs.append(BenchConfig(5_000, "240x180", "rotation3", "none", precision, impls, window))
    notes = [
        "NumPy reference: value only (its gradient by central differences would cost 2P values).",
        "taichi-chain = the generic kernel chain differentiated by Taichi autodiff (before the fused "
        "kernels).",
    ]
    return Plan(cfgs, min_repeats=3, max_repeats=10, budget_s=0.4, label="quick", notes=notes)


#: the benchmark grid: events per window, and the three configurations of each (N, sensor)
GRID_EVENTS = (1_000, 5_000, 30_000, 300_000, 1_000_000)
GRID_CONFIGS = (("translation2", "none"), ("rotation3", "none"), ("mitrokhin4", "div+def"))


def full_plan(precision: str = "f64") -> Plan:
    """The full sweep: N = 1e3, 5e3, 3e4, 3e5, 1e6 events on the four sensors for translation2,
    rotation3 (no regularizer) and mitrokhin4 with both regularizers, on textured windows (the event
    simulator's, lab/bench_windows.py) with PyTorch and the NumPy reference beside (NumPy up to 1e5
    events), and the same on uniformly spread events (Taichi and, up to 3e4 events, the reference);
    then, on the synthetic edges of the earlier sweeps, N = 1e7 on 346x260 (translation2, mitrokhin4
    with both) and the generic Taichi chain (the "before" of the fused kernels) at 3e4 and 1e6.

    About 15 minutes on this 2-core machine, plus a few minutes once to simulate the textured streams
    (cached, see lab/bench_windows.py).
    """
    cfgs = []
    stream = max(GRID_EVENTS)
    for n in GRID_EVENTS:
        for sensor in SENSORS:
            for warp, regs in GRID_CONFIGS:
                impls = ("taichi", "torch") + (("numpy",) if n <= 100_000 else ())
                textured = dict(window="textured", stream_events=stream)
                cfgs.append(BenchConfig(n, sensor, warp, regs, precision, impls, **textured))
                impls = ("taichi",) + (("numpy",) if n <= 30_000 else ())
                cfgs.append(BenchConfig(n, sensor, warp, regs, precision, impls, window="uniform"))
    for warp, regs in (("translation2", "none"), ("mitrokhin4", "div+def")):
        cfgs.append(BenchConfig(10_000_000, "346x260", warp, regs, precision, ("taichi", "torch")))
        for n in (30_000, 1_000_000):
            cfgs.append(BenchConfig(n, "346x260", warp, regs, precision, ("taichi", "taichi-chain")))
    notes = [
        "Windows (column `window`, lab/bench_windows.py): `textured` = the first N events of the event "
        "simulator watching a textured plane translate at (120, -80) px/s (events where the edges are, as "
        "a camera records them; one stream per sensor); `uniform` = events uniformly spread over the sensor "
        "and 50 ms (the worst case for work that follows the touched pixels); `edges` = 40 synthetic "
        "straight edges plus 10% noise (the windows of the earlier sweeps).",
        "NumPy reference: value only (its gradient by central differences would cost 2P values), N <= 1e5 "
        "(textured), N <= 3e4 (uniform).",
        "N = 1e7 on 346x260 only, translation2 and mitrokhin4 with both regularizers (time budget).",
        "taichi-chain = the generic kernel chain differentiated by Taichi autodiff (the state before the "
        "fused kernels), measured in the same run: 346x260, N = 3e4 and 1e6.",
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
    win = bench_windows.window(
        cfg.window, cfg.n, cfg.sensor, seed=cfg.n % 9973, stream_events=cfg.stream_events, log=log
    )
    impls: dict[str, Impl] = {}
    rows: dict[str, Row] = {}
    base = dict(n=cfg.n, sensor=cfg.sensor_name, warp=cfg.warp, regs=cfg.regs, precision=cfg.precision)
    base["window"] = cfg.window
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
    t_vg, first_vg = _time_round_robin(
        vg_fns, theta, min_repeats=plan.min_repeats, max_repeats=plan.max_repeats, budget_s=plan.budget_s
    )
    t_val, first_val = _time_round_robin(
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
                ts, firsts = t_vg[name], first_vg[name]
                row.measured = "value_and_grad"
            else:
                ts, firsts = t_val[name], first_val[name]
                row.measured = "value"
            row.median_ms = statistics.median(ts) * 1e3
            row.first_of_burst_ms = statistics.median(firsts) * 1e3
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
def run_benchmark(
    plan: Plan,
    out_dir: str | Path,
    *,
    log: Callable[[str], None] = print,
    arch: str | None = None,
) -> dict:
    """Run ``plan`` on ``arch`` (default: ``CMAX_TAICHI_ARCH``, else the CPU); write results.csv,
    results.md and results.png into ``out_dir`` (:class:`~cmax_taichi.io.outputs.OutputFolder`: files of
    another run or command, or a user's, are refused before any work; all in place when complete).

    Returns
    -------
    dict
        ``rows`` (list of :class:`Row`), ``machine``, ``solve`` (or None), ``segmentation`` (rows of
        :func:`cmax_taichi.lab.segment_eval.timing`, or None), ``markdown`` and the paths.
    """
    # PyTorch's OpenMP threads busy-wait between operations; on a shared (oversubscribed) machine a
    # waiting thread then holds a core another needs, and small calls took seconds here: wait passively
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    folder = OutputFolder(out_dir, patterns=BENCH_OUTPUTS, command="bench")
    folder.check()  # files this run may not replace (another run's, a user's): before minutes of work
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
    names = dict(zip(("csv", "md", "png", "segmentation"), BENCH_OUTPUTS, strict=True))
    with folder:
        if rows:
            write_csv(rows, folder.path(names["csv"]))
        if seg:
            with open(folder.path(names["segmentation"]), "w", newline="") as fh:
                writer = csv.DictWriter(fh, fieldnames=list(seg[0].keys()))
                writer.writeheader()
                writer.writerows(seg)
        folder.path(names["md"]).write_text(md)
        write_plot(rows, folder.path(names["png"]))
        written = {p.name for p in folder.commit()}
    paths = {key: folder.final(name) for key, name in names.items() if name in written}
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


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``cmax-taichi bench`` and ``python -m benchmarks.run``."""
    parser.add_argument("--quick", action="store_true", help="a sub-two-minute subset (CI)")
    parser.add_argument("--out", default="bench-results", help="output folder (default: bench-results)")
    parser.add_argument(
        "--precision",
        default=None,
        choices=["f64", "f32"],
        help="Taichi and PyTorch precision (default: f64 on the CPU, f32 on a GPU arch)",
    )
    parser.add_argument(
        "--arch",
        default=None,
        choices=list(backend.ARCHS),
        help="Taichi backend (default: CMAX_TAICHI_ARCH, else cpu); a GPU arch that is not available is an "
        "error here, not a fallback to the CPU",
    )
    parser.add_argument(
        "--gpu-sweep",
        action="store_true",
        help="the GPU throughput sweep (N = 1e3 .. 1e7, two sensors, three warps) instead of the CPU plan",
    )
    parser.add_argument(
        "--max-events",
        type=int,
        default=None,
        help="largest N of --gpu-sweep (default 1e7; smaller for a software-Vulkan check)",
    )
    parser.add_argument(
        "--realtime",
        action="store_true",
        help="instead of the kernel plan: the real-time factor of whole recordings (sequence estimation "
        "over the shared recordings in --data and a long simulated stream; realtime.md / realtime.csv)",
    )
    parser.add_argument(
        "--data",
        default=None,
        help="folder of the shared recordings for --realtime (default ../shared/data, where it is)",
    )
    parser.add_argument(
        "--sim-seconds",
        type=float,
        default=2.0,
        help="length of the simulated stream of --realtime, s (default 2)",
    )
    parser.add_argument("--no-solve", action="store_true", help="skip the window-solve timing")
    parser.add_argument(
        "--no-segment", action="store_true", help="skip the motion-segmentation timing (full run only)"
    )


def start_backend(arch: str | None, precision: str) -> str:
    """Start the requested arch; a GPU arch that Taichi cannot start (it falls back to the CPU) is a
    ValueError, so that no CPU timing is reported as a GPU one. Returns the arch name."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the fallback warning: said below instead
        info = backend.init(arch=arch, precision=precision)
    if info.requested_arch != "cpu" and info.arch == "cpu":
        raise ValueError(
            f"arch {info.requested_arch!r} is not available on this machine (Taichi fell back to the CPU); "
            "no benchmark was run"
        )
    return info.requested_arch


def run_from_args(args: argparse.Namespace) -> int:
    """Run the plan the options of :func:`add_arguments` describe and print the report; exit code 1
    when an implementation disagrees with the others. Bad options raise ValueError."""
    if args.max_events is not None and not args.gpu_sweep:  # the other plans' sizes are fixed
        raise ValueError("--max-events applies to --gpu-sweep only")
    if args.max_events is not None and args.max_events < 1:
        raise ValueError(f"--max-events must be at least 1, got {args.max_events}")
    requested = (args.arch or os.environ.get(backend.ARCH_ENV) or "cpu").strip().lower()
    precision = args.precision or ("f64" if requested == "cpu" else "f32")
    if requested in ("vulkan", "metal") and precision == "f64":
        raise ValueError(f"arch {requested!r} has no f64 support; use --precision f32")
    arch = start_backend(requested, precision)
    if getattr(args, "realtime", False):
        from cmax_taichi.lab.realtime import markdown, run_realtime

        rows = run_realtime(args.data, args.out, sim_seconds=args.sim_seconds)
        print()
        print(markdown(rows))
        return 0
    if args.gpu_sweep:
        plan = gpu_plan(precision, max_events=args.max_events or 10_000_000)
        if not plan.configs:
            raise ValueError(
                f"--max-events {args.max_events} leaves no configuration (the smallest N is 1000)"
            )
    elif args.quick:
        plan = quick_plan(precision)
    else:
        plan = full_plan(precision)
    if args.no_solve:
        plan.solve = False
    if args.no_segment:
        plan.segment = False
    result = run_benchmark(plan, args.out, arch=arch)
    print()
    print(result["markdown"])
    bad = [r for r in result["rows"] if r.status.startswith("DISAGREES")]
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.run`` entry point (the options of ``cmax-taichi bench``)."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
