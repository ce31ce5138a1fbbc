"""Median ``value_and_grad`` of a few benchmark rows through the library's benchmark implementation:
``python benchmarks/ab_rows.py [--small | --targets | --rotation | --rotation-small | --stored-terms]
[--value] [--repeats-scale S]``. Run it with each version's environment, alternating, to compare two
versions on one machine (docs/performance.md).

Row sets: by default six windows, small and large (100 calls each, 15 at 1M events); ``--small``: the
eight small rows that one pair of full runs showed slower after the row-order change (60 calls each);
``--targets``: rows of the benchmark grid (the full sweep's textured and uniform windows of ``cmax_taichi/lab/
bench_windows.py``, which this script loads from its own checkout, so that an older version runs the
same windows; the textured streams come from the shared cache, simulated once); ``--rotation``: the
rotation3 / translation2 pair at 300,000 edge events on 240x180 (20 calls each, three alternating rounds,
and their events-per-second ratio from the medians); ``--rotation-small``: rotation3 windows of 1,000 to
10,000 events with and without both regularizers (the serial schedule's sizes); ``--stored-terms``: those
windows on the serial schedule with rotation3's stored event terms against the same model without the
declaration, in alternating rounds (``pipeline/fused.py``'s ``stores_terms``). ``--value`` times the
value-only call (``value``, what the global searches call) instead of ``value_and_grad``. Each row prints
the wall median and the CPU time per call (all threads, ``getrusage``: on a shared machine the wall time
mostly measures the other processes).
"""

import functools
import importlib.util
import resource
import sys
import time
from pathlib import Path

import numpy as np

from cmax_taichi.core import backend
from cmax_taichi.lab import bench_impls


def _rows(table: str, kind: str = "edges") -> list[tuple[int, str, str, str, str]]:
    """``(events, sensor, warp, regularizers, window kind)`` per line "EVENTS SENSOR WARP REGS [KIND]"
    of ``table`` (``kind`` where a line names none)."""
    rows = []
    for line in table.strip().splitlines():
        n, sensor, warp, regs, *rest = line.split()
        rows.append((int(n), sensor, warp, regs, rest[0] if rest else kind))
    return rows


#: the default six windows, small and large, on the synthetic edges
DEFAULT_ROWS = _rows(
    """
    1000 346x260 translation2 none
    1000 1280x720 translation2 none
    1000 346x260 mitrokhin4 div+def
    1000 1280x720 mitrokhin4 div+def
    30000 346x260 mitrokhin4 div+def
    1000000 346x260 mitrokhin4 div+def
    """
)
#: the eight small rows that one pair of full runs showed slower after the row-order change
SMALL_ROWS = _rows(
    """
    1000 1280x720 rotation3 div+def
    1000 1280x720 translation2 none
    1000 240x180 translation2 div+def
    1000 346x260 rotation3 div+def
    1000 640x480 rotation3 none
    10000 240x180 mitrokhin4 none
    10000 240x180 translation2 none
    10000 346x260 rotation3 none
    """
)
#: the per-call targets and the 1M rows
TARGET_ROWS = _rows(
    """
    1000 240x180 translation2 none textured
    1000 240x180 translation2 none uniform
    5000 1280x720 translation2 none textured
    5000 1280x720 translation2 none uniform
    5000 1280x720 mitrokhin4 div+def textured
    300000 240x180 translation2 none edges
    300000 240x180 rotation3 none edges
    300000 240x180 translation2 none textured
    300000 240x180 rotation3 none textured
    1000000 346x260 mitrokhin4 div+def textured
    1000000 346x260 translation2 none edges
    """
)
#: the rotation3 / translation2 pair (events per second of rotation3 at least half translation2's)
ROTATION_ROWS = _rows(
    """
    300000 240x180 translation2 none edges
    300000 240x180 rotation3 none edges
    """
)
#: rotation3 windows on the serial schedule (a few thousand events), with and without regularizers
ROTATION_SMALL_ROWS = _rows(
    """
    1000 346x260 rotation3 none
    1000 346x260 rotation3 div+def
    1000 1280x720 rotation3 div+def
    5000 240x180 rotation3 none
    5000 240x180 rotation3 div+def
    10000 346x260 rotation3 none
    10000 346x260 rotation3 div+def
    """
)
STREAM_EVENTS = 1_000_000  # the full sweep's textured stream length (its prefixes are the windows)


@functools.lru_cache(maxsize=1)
def _windows_module():
    """``cmax_taichi/lab/bench_windows.py`` of this script's checkout (an older version has none)."""
    path = Path(__file__).resolve().parents[1] / "cmax_taichi" / "lab" / "bench_windows.py"
    spec = importlib.util.spec_from_file_location("ab_bench_windows", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def time_row(
    n: int, sensor: str, warp: str, regs: str, repeats: int, kind: str = "edges", *, value_only: bool = False
):
    """``(wall median ms, CPU ms per call)`` of one ``value_and_grad`` (``value_only``: one ``value``)
    after three warm-up calls."""
    cfg = bench_impls.BenchConfig(n, sensor, warp, regs)
    if kind == "edges":
        win = bench_impls.make_window(cfg.n, cfg.sensor, seed=cfg.n % 9973)
    else:
        win = _windows_module().window(kind, n, cfg.sensor, seed=n % 9973, stream_events=STREAM_EVENTS)
    impl = bench_impls.build_taichi(win, cfg)
    theta = np.asarray(bench_impls.THETAS[warp], dtype=np.float64)
    call = impl.value if value_only else impl.vg
    return _timed(lambda: call(theta), repeats)


def _timed(call, repeats: int, warmup: int = 3) -> tuple[float, float]:
    """``(wall median ms, CPU ms per call)`` of ``repeats`` calls of ``call()`` after ``warmup`` calls."""
    for _ in range(warmup):
        call()
    times = []
    c0 = _cpu_seconds()
    for _ in range(repeats):
        t = time.perf_counter()
        call()
        times.append(time.perf_counter() - t)
    cpu = (_cpu_seconds() - c0) / repeats
    return float(np.median(times)) * 1e3, cpu * 1e3


def median_ms(n: int, sensor: str, warp: str, regs: str, repeats: int) -> float:
    """Median wall time of one ``value_and_grad`` (ms) on the synthetic edges (the earlier interface)."""
    return time_row(n, sensor, warp, regs, repeats)[0]


def _rotation_ratio(repeats: int, rounds: int = 3, *, value_only: bool = False) -> int:
    """The rotation rows in alternating rounds; rotation3's events per second over translation2's, from
    the medians over the rounds of the wall and of the CPU time per call."""
    walls: dict[str, list[float]] = {}
    cpus: dict[str, list[float]] = {}
    for r in range(rounds):
        for n, sensor, warp, regs, kind in ROTATION_ROWS:
            wall, cpu = time_row(n, sensor, warp, regs, repeats, kind, value_only=value_only)
            walls.setdefault(warp, []).append(wall)
            cpus.setdefault(warp, []).append(cpu)
            line = f"round {r} {n:8d} {sensor:9s} {kind:9s} {warp:13s} {wall:8.3f} ms  cpu {cpu:8.3f} ms"
            print(line, flush=True)
    t_wall, r_wall = (float(np.median(walls[w])) for w in ("translation2", "rotation3"))
    t_cpu, r_cpu = (float(np.median(cpus[w])) for w in ("translation2", "rotation3"))
    print(f"rotation3 / translation2 events per second: wall {t_wall / r_wall:.2f}, cpu {t_cpu / r_cpu:.2f}")
    return 0


def _stored_terms(repeats: int, rounds: int = 3) -> int:
    """The serial schedule with rotation3's stored event terms against the same model without the
    declaration (``store_event_terms=False``: the warp evaluated again in the gather), on the
    :data:`ROTATION_SMALL_ROWS` windows, alternating, ``rounds`` rounds; the medians and their ratio."""
    from cmax_taichi.kernels.warps import rotation3

    import cmax_taichi as cm
    from cmax_taichi.pipeline.fused import FusedPipeline

    FusedPipeline.loops = "serial"
    unstored = cm.WarpModel.from_module(rotation3, store_event_terms=False)
    models = {"stored": cm.get_warp("rotation3"), "unstored": unstored}
    theta = np.asarray(bench_impls.THETAS["rotation3"], dtype=np.float64)
    for n, sensor, _, regs, _ in ROTATION_SMALL_ROWS:
        cfg = bench_impls.BenchConfig(n, sensor, "rotation3", regs)
        x, y, t, p = bench_impls.make_window(cfg.n, cfg.sensor, seed=cfg.n % 9973)
        events = cm.Events(x, y, t, p, cfg.sensor)
        medians: dict[str, list[float]] = {}
        for _ in range(rounds):
            for name, model in models.items():
                prob = cm.ContrastMaximization(
                    events, warp=model, camera=bench_impls.camera_for(cfg.sensor),
                    regularizers=bench_impls.REGS[regs] or None,
                )  # fmt: skip
                wall, _ = _timed(lambda prob=prob: prob.value_and_grad(theta), repeats)
                medians.setdefault(name, []).append(wall)
        stored, unstored = (float(np.median(medians[k])) for k in ("stored", "unstored"))
        print(
            f"{n:8d} {sensor:9s} rotation3 {regs:8s} serial: unstored {unstored:.3f} ms, stored "
            f"{stored:.3f} ms, ratio {stored / unstored:.3f}",
            flush=True,
        )
    return 0


def main(argv: list[str]) -> int:
    backend.init(precision="f64")
    scale = 1.0
    if "--repeats-scale" in argv:
        scale = float(argv[argv.index("--repeats-scale") + 1])
    value_only = "--value" in argv
    if "--rotation" in argv:
        return _rotation_ratio(max(5, int(scale * 20)), value_only=value_only)
    if "--stored-terms" in argv:
        return _stored_terms(max(5, int(scale * 80)))
    if "--targets" in argv:
        rows = TARGET_ROWS
        repeats = [max(5, int(scale * (15 if n >= 300_000 else 100))) for n, *_ in rows]
    elif "--small" in argv:
        rows = SMALL_ROWS
        repeats = [max(5, int(scale * 60))] * len(rows)
    elif "--rotation-small" in argv:
        rows = ROTATION_SMALL_ROWS
        repeats = [max(5, int(scale * 60))] * len(rows)
    else:
        rows = DEFAULT_ROWS
        repeats = [max(5, int(scale * (15 if n >= 1_000_000 else 100))) for n, *_ in rows]
    for (n, sensor, warp, regs, kind), reps in zip(rows, repeats, strict=True):
        wall, cpu = time_row(n, sensor, warp, regs, reps, kind, value_only=value_only)
        line = f"{n:8d} {sensor:9s} {kind:9s} {warp:13s} {regs:8s} {wall:8.3f} ms  cpu {cpu:8.3f} ms"
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
