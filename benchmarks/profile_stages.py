"""Where one fused value-and-gradient evaluation spends its time, stage by stage.

``python -m benchmarks.profile_stages [--events N] [--warp W] [--sensor WxH] [--regs none|div+def]
[--window edges|textured|uniform] [--loops parallel|serial|auto]``

Runs Taichi's kernel profiler over repeated ``value_and_grad`` calls of the fused pipeline
(``kernels/fused.py``, the variance objective) on a benchmark window and prints the median time of
each task of the kernel (:data:`STAGES`), on the thread pool's schedule by default; on the serial one
(``--loops serial``, what "auto" gives a small window) the whole kernel is one task. The wall-clock
median of the whole call is printed too (it includes launching the kernel and the thread-pool dispatch
of each task).
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from collections import defaultdict

import numpy as np

STAGES = {
    0: "serial: theta, clear reductions",
    1: "events: warp + splat",
    2: "rows: F0, slice sums, map reductions, blur x",
    3: "rows: y regions, the image's moments (the kept image), votes cleared",
    4: "serial: J",
    5: "rows: adjoint along x, map adjoints",
    6: "events: gradient gather",
    7: "serial: results",
}


def impl_schedule(impl) -> bool:
    """Whether the benchmark implementation's window runs its loops serially (``FusedPipeline.serial``)."""
    return bool(impl.vg.__self__._fused.serial)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.profile_stages", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--events", type=int, default=30_000)
    parser.add_argument("--warp", default="mitrokhin4")
    parser.add_argument("--sensor", default="346x260")
    parser.add_argument("--regs", default="div+def", choices=["none", "div+def"])
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument(
        "--window",
        default="edges",
        choices=["edges", "textured", "uniform"],
        help="the benchmark's synthetic edges, or the full sweep's textured / uniform windows",
    )
    parser.add_argument(
        "--loops",
        default="parallel",
        choices=["auto", "serial", "parallel"],
        help="FusedPipeline.loops (default parallel: one profiler task per stage; serial is one task)",
    )
    args = parser.parse_args(argv)

    import taichi as ti

    from cmax_taichi.core import backend
    from cmax_taichi.lab import bench_impls
    from cmax_taichi.pipeline.fused import FusedPipeline

    if args.sensor not in bench_impls.SENSORS:
        parser.error(f"--sensor must be one of {', '.join(bench_impls.SENSORS)}")
    if args.warp not in bench_impls.THETAS:
        parser.error(f"--warp must be one of {', '.join(bench_impls.THETAS)}")
    if args.events < 1 or args.repeats < 1:
        parser.error("--events and --repeats must be at least 1")
    backend.init(precision="f64", kernel_profiler=True)
    cfg = bench_impls.BenchConfig(args.events, args.sensor, args.warp, args.regs)
    if args.window == "edges":
        win = bench_impls.make_window(cfg.n, cfg.sensor, seed=cfg.n % 9973)
    else:
        from cmax_taichi.lab import bench_windows

        win = bench_windows.window(args.window, cfg.n, cfg.sensor, seed=cfg.n % 9973, stream_events=1_000_000)
    FusedPipeline.loops = args.loops
    impl = bench_impls.build_taichi(win, cfg)
    schedule = "serial" if impl_schedule(impl) else "parallel"
    theta = np.asarray(bench_impls.THETAS[args.warp], dtype=np.float64)
    impl.vg(theta)  # compile
    walls = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        impl.vg(theta)
        walls.append(time.perf_counter() - t0)
    ti.profiler.clear_kernel_profiler_info()
    for _ in range(args.repeats):
        impl.vg(theta)
    # Taichi 1.7 exposes the per-launch records only through its profiler object (no public getter)
    profiler = ti.profiler.kernel_profiler.get_default_kernel_profiler()
    profiler._update_records()
    per_task: dict[int, list[float]] = defaultdict(list)
    for rec in profiler._traced_records:
        m = re.match(r"run_c\d+_\d+_kernel_(\d+)_", rec.name)
        if m:
            per_task[int(m.group(1))].append(rec.kernel_time)
    print(
        f"{args.events} events ({args.window}), {args.sensor}, {args.warp}, {args.regs}, f64, "
        f"{args.repeats} calls, loops {schedule}"
    )
    print("| task | stage | median ms |\n|---:|---|---:|")
    total = 0.0
    for task in sorted(per_task):
        med = float(np.median(per_task[task]))
        total += med
        print(f"| {task} | {STAGES.get(task, '?')} | {med:.3f} |")
    print(f"| | sum of the tasks | {total:.3f} |")
    wall = 1e3 * float(np.median(walls))
    print(f"| | wall time of value_and_grad (median, profiler on) | {wall:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
