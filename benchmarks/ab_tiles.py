"""``value_and_grad`` on small windows of textured scenes and of uniformly spread events, for comparing
two versions of the library on one machine (benchmarks/NOTES.md, "Image work that follows the events").

``python benchmarks/ab_tiles.py windows PATH.npz``
    simulates the windows once (the simulator's textured scenes, as a camera records them: events
    where the edges are) and stores them, so that every version times the same events;
``python benchmarks/ab_tiles.py time PATH.npz [--rows SUBSTRING ...] [--repeats N] [--json OUT]``
    times ``value_and_grad`` of every stored window (medians of ``N`` calls after three warm-up calls,
    wall time and CPU time of the process, both threads: ``getrusage``), one line per row;
``python benchmarks/ab_tiles.py million [--rows SUBSTRING ...] [--repeats N] [--json OUT]``
    the same for the benchmark's synthetic 1,000,000-event windows (``lab/bench_impls.make_window``)
    on the four sensors, three warps (mitrokhin4 with both regularizers).

Run ``time`` with each version's own environment (``.venv/bin/python`` of its checkout: the editable
install maps ``cmax_taichi.kernels`` to the checkout it was installed from), alternating.
Only public API is used, so the script runs against older versions of the library too.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time

import numpy as np

SENSORS = {"240x180": (240, 180), "346x260": (346, 260), "640x480": (640, 480), "1280x720": (1280, 720)}
#: the scene's motion per warp, scaled with the sensor width (px/s parameters) where it has units of px
MOTIONS = {
    "translation2": lambda W: (0.5 * W, -0.3 * W),
    "rotation3": lambda W: (0.8, -1.2, 2.0),
    "mitrokhin4": lambda W: (0.4 * W, -0.25 * W, 2.0, 0.0),
}
#: where ``value_and_grad`` is evaluated: near the scene's motion, not on it
OFFSETS = {"translation2": (0.0, 0.0), "rotation3": (0.0, 0.0, 0.0), "mitrokhin4": (0.0, 0.0, 0.0, 0.5)}
CASES = [  # (warp, regularizers)
    ("translation2", "none"),
    ("rotation3", "none"),
    ("mitrokhin4", "div+def"),
]
REGS = {"none": {}, "div+def": {"divergence": 1.0, "deformation": 1.0}}


def _windows(path: str) -> int:
    import cmax_taichi as cm
    from cmax_taichi.sim import simulate, warp_scene

    cm.init(precision="f64")
    out = {}
    for name, (W, H) in SENSORS.items():
        for warp, _ in CASES:
            scene = warp_scene(warp, MOTIONS[warp](W), (W, H), texture="minduka")
            rec = simulate(scene, 0.02, contrast_threshold=0.5, log_eps=0.02, seed=1)
            cam = rec.camera
            for n in (1000, 5000):
                k = len(rec.t) // 2  # a window from the middle of the recording
                sl = slice(k, k + n)
                key = f"{n}_{name}_{warp}_textured"
                out[key + "_x"] = rec.x[sl]
                out[key + "_y"] = rec.y[sl]
                out[key + "_t"] = rec.t[sl]
                out[key + "_p"] = rec.p[sl]
                out[key + "_cam"] = np.array([cam.fx, cam.fy, cam.cx, cam.cy])
                rng = np.random.default_rng(n + W)
                key = f"{n}_{name}_{warp}_uniform"
                out[key + "_x"] = rng.uniform(0, W - 1, n)
                out[key + "_y"] = rng.uniform(0, H - 1, n)
                out[key + "_t"] = np.sort(rng.uniform(0, rec.t[sl][-1] - rec.t[sl][0], n))
                out[key + "_p"] = rng.choice([-1, 1], n).astype(np.int8)
                out[key + "_cam"] = np.array([cam.fx, cam.fy, cam.cx, cam.cy])
                print(f"{key}: span {1e3 * (rec.t[sl][-1] - rec.t[sl][0]):.3f} ms", flush=True)
    np.savez_compressed(path, **out)
    return 0


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _timed(value_and_grad, theta: np.ndarray, repeats: int) -> dict:
    """Medians of ``repeats`` calls ``value_and_grad(theta)`` after three warm-up calls: wall and process
    CPU time, ms, and the 1-minute load average after them."""
    for _ in range(3):
        value_and_grad(theta)
    wall, cpu = [], []
    for _ in range(repeats):
        c0, t0 = _cpu(), time.perf_counter()
        value_and_grad(theta)
        wall.append(time.perf_counter() - t0)
        cpu.append(_cpu() - c0)
    return dict(
        wall_ms=float(np.median(wall)) * 1e3,
        cpu_ms=float(np.median(cpu)) * 1e3,
        load=os.getloadavg()[0],
    )


def _write_json(results: list[dict], json_out: str | None) -> None:
    if json_out:
        with open(json_out, "w") as fh:
            json.dump(results, fh, indent=1)


def _time(path: str, rows: list[str], repeats: int, json_out: str | None) -> int:
    import cmax_taichi as cm

    cm.init(precision="f64")
    data = np.load(path)
    keys = sorted({k.rsplit("_", 1)[0] for k in data.files}, key=lambda k: (int(k.split("_")[0]), k))
    results = []
    for key in keys:
        n, sensor, warp, kind = key.split("_")
        if rows and not any(r in key for r in rows):
            continue
        W, H = SENSORS[sensor]
        fx, fy, cx, cy = data[key + "_cam"]
        events = cm.Events(data[key + "_x"], data[key + "_y"], data[key + "_t"], data[key + "_p"], (W, H))
        for regs in ("none", "div+def") if warp == "mitrokhin4" else ("none",):
            if warp == "mitrokhin4" and regs == "none":
                continue
            prob = cm.ContrastMaximization(
                events,
                warp=warp,
                regularizers=REGS[regs],
                camera=cm.Camera(fx=fx, fy=fy, cx=cx, cy=cy),
                blur_sigma=1.0,
            )
            theta = 0.8 * np.asarray(MOTIONS[warp](W), dtype=np.float64) + np.asarray(OFFSETS[warp])
            row = dict(key=key, regs=regs, **_timed(prob.value_and_grad, theta, repeats))
            results.append(row)
            print(
                f"{n:>5} {sensor:9s} {warp:13s} {regs:8s} {kind:9s} wall {row['wall_ms']:7.3f} ms"
                f"  cpu {row['cpu_ms']:7.3f} ms  load {row['load']:.1f}",
                flush=True,
            )
    _write_json(results, json_out)
    return 0


def _time_rows(rows_of, rows: list[str], repeats: int, json_out: str | None) -> int:
    results = []
    for label, prob_vg, theta in rows_of(rows):
        row = dict(key=label, **_timed(prob_vg, theta, repeats))
        results.append(row)
        print(
            f"{label:45s} wall {row['wall_ms']:8.3f} ms  cpu {row['cpu_ms']:8.3f} ms  load {row['load']:.1f}",
            flush=True,
        )
    _write_json(results, json_out)
    return 0


def _million(rows: list[str], repeats: int, json_out: str | None) -> int:
    import cmax_taichi as cm
    from cmax_taichi.lab import bench_impls

    cm.init(precision="f64")

    def rows_of(selected):
        for sensor in SENSORS:
            for warp, regs in CASES:
                label = f"1000000_{sensor}_{warp}_{regs}"
                if selected and not any(r in label for r in selected):
                    continue
                cfg = bench_impls.BenchConfig(1_000_000, sensor, warp, regs)
                win = bench_impls.make_window(cfg.n, cfg.sensor, seed=cfg.n % 9973)
                impl = bench_impls.build_taichi(win, cfg)
                yield label, impl.vg, np.asarray(bench_impls.THETAS[warp], dtype=np.float64)

    return _time_rows(rows_of, rows, repeats, json_out)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="python benchmarks/ab_tiles.py", description=__doc__.split("\n\n")[0]
    )
    sub = parser.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("windows")
    w.add_argument("path")
    t = sub.add_parser("time")
    t.add_argument("path")
    t.add_argument("--rows", nargs="*", default=[])
    t.add_argument("--repeats", type=int, default=50)
    t.add_argument("--json")
    m = sub.add_parser("million")
    m.add_argument("--rows", nargs="*", default=[])
    m.add_argument("--repeats", type=int, default=15)
    m.add_argument("--json")
    args = parser.parse_args(argv)
    if args.cmd == "windows":
        return _windows(args.path)
    if args.cmd == "million":
        return _million(args.rows, args.repeats, args.json)
    return _time(args.path, args.rows, args.repeats, args.json)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
