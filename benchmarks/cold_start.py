"""The wait before the first result, from an empty kernel cache, as a new user meets it.

``python -m benchmarks.cold_start [--rounds 3] [--parts readme sensors warps] [--out DIR]``

Every case runs in fresh processes with Taichi's offline cache in an empty folder of its own
(``TI_OFFLINE_CACHE_FILE_PATH``), in the default compile mode (``auto``: quick kernels at once, the
optimized ones compiled by a background process; ``pipeline/tiers.py``). Between cases the benchmark
waits for the background compiles to end, and reports them apart (their seconds and peak memory, from
their records), so that no case runs beside another's compile.

* ``readme``: the ``cmax-taichi`` lines of the README's quick start (parsed as ``.ci/run`` parses them),
  each from an empty cache: seconds to its first result line (``first window ...`` for ``estimate``,
  ``segmented ...`` for ``segment``, ``first window ...`` for ``flow``) and to its end, and the peak
  memory of the command's process;
* ``sensors``: a simulated recording on 240x180, then (same cache, the first run's background compile
  done) the same options on 346x260 and 1280x720: seconds from the process start to the first
  evaluation, from building the problem to the first evaluation, and whether any kernel was built;
* ``warps``: every registered warp on 240x180 and then 346x260 in one process: seconds to the first
  evaluation of each (the second sensor compiles nothing).

Prints a Markdown table per part (medians over ``--rounds``, the load average before each case) and
writes it with the raw rows as JSON into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: the first line of a command's result, per command
FIRST_RESULT = {"estimate": "first window", "segment": "segmented", "flow": "first window"}

SENSOR_CHILD = r"""
import sys, time, json
t_start = float(sys.argv[1])
import numpy as np
import cmax_taichi as cm
from taichi.lang import kernel_impl
built = []
materialize = kernel_impl.Kernel.materialize
def counted(self, key=None, args=None, arg_features=None):
    if key not in self.compiled_kernels:
        built.append(self.func.__name__)
    return materialize(self, key=key, args=args, arg_features=arg_features)
kernel_impl.Kernel.materialize = counted
data = np.load(sys.argv[2])
W, H = (int(v) for v in data["size"])
events = cm.Events(data["x"], data["y"], data["t"], data["p"], (W, H))
camera = cm.Camera(fx=float(data["f"]), fy=float(data["f"]), cx=(W - 1) / 2, cy=(H - 1) / 2)
window = events[: min(len(events), 30000)]
t_build = time.time()
prob = cm.ContrastMaximization(window, sys.argv[3], camera=camera)
prob.value_and_grad(np.zeros(prob.model.n_params))
t_done = time.time()
print(json.dumps({"from_start": t_done - t_start, "from_problem": t_done - t_build, "kernels_built": built,
                  "tier": prob.kernels}))
"""

WARPS_CHILD = r"""
import sys, time, json
import numpy as np
import cmax_taichi as cm
rows = []
rng = np.random.default_rng(0)
for warp in cm.warp_names():
    for size in ((240, 180), (346, 260)):
        W, H = size
        n = 20000
        x0 = rng.uniform(0, W - 1, n // 20)
        x = np.clip(np.repeat(x0, 20) + rng.normal(0, 0.5, n), 0, W - 1)
        y, t = rng.uniform(0, H - 1, n), np.sort(rng.uniform(0, 0.02, n))
        events = cm.Events(x, y, t, rng.integers(0, 2, n), size)
        camera = cm.Camera(fx=200.0, fy=200.0, cx=(W - 1) / 2, cy=(H - 1) / 2)
        t0 = time.perf_counter()
        prob = cm.ContrastMaximization(events, warp, camera=camera)
        prob.value_and_grad(np.zeros(prob.model.n_params))
        seconds = time.perf_counter() - t0
        rows.append({"warp": warp, "sensor": f"{W}x{H}", "seconds": seconds, "tier": prob.kernels})
print(json.dumps(rows))
"""


def load() -> float:
    return os.getloadavg()[0]


def readme_commands() -> list[str]:
    """The ``cmax-taichi`` lines of the README's quick start (its first bash block), as ``.ci/run``
    reads them."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    block = section.split("```bash", 1)[1].split("```", 1)[0]
    return [line.strip() for line in block.splitlines() if line.strip().startswith("cmax-taichi ")]


def background_records(cache: Path) -> list[dict]:
    folder = cache / "cmax-taichi" / "ready"
    return [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))] if folder.is_dir() else []


def wait_for_background(cache: Path, timeout: float = 1800.0) -> float:
    """Wait until no background compile of ``cache`` runs; returns the seconds waited."""
    t0 = time.perf_counter()
    pending = cache / "cmax-taichi" / "pending"
    while time.perf_counter() - t0 < timeout:
        alive = False
        for path in pending.glob("*") if pending.is_dir() else ():
            try:
                os.kill(int(path.read_text().split()[0]), 0)
                alive = True
            except (OSError, ValueError, IndexError):
                continue
        if not alive:
            return time.perf_counter() - t0
        time.sleep(0.5)
    raise TimeoutError(f"background compiles of {cache} still running after {timeout:.0f} s")


def run_timed(argv: list[str], env: dict, cwd: Path, first_pattern: str | None) -> dict:
    """Run ``argv``; seconds to the first line containing ``first_pattern`` and to the end, peak RSS."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        argv, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    first = None
    lines = []
    for line in proc.stdout:
        lines.append(line.rstrip())
        if first is None and first_pattern and first_pattern in line:
            first = time.perf_counter() - t0
    _, status, usage = os.wait4(proc.pid, 0)
    total = time.perf_counter() - t0
    return {
        "first_result_s": first,
        "total_s": total,
        "peak_rss_mb": usage.ru_maxrss / 1024,
        "exit": os.waitstatus_to_exitcode(status),
        "tail": lines[-3:],
    }


def part_readme(rounds: int, work: Path) -> list[dict]:
    rows = []
    for line in readme_commands():
        argv = shlex.split(line)
        command = argv[1]
        for r in range(rounds):
            case = work / f"readme_{len(rows)}"
            cache = case / "ticache"
            (case / "run").mkdir(parents=True)
            env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=str(cache))
            env.pop("CMAX_TAICHI_COMPILE", None)
            before = load()
            row = run_timed(
                [sys.executable, "-m", "cmax_taichi.cli", *argv[1:]],
                env,
                case / "run",
                FIRST_RESULT.get(command),
            )
            row["background_wait_s"] = wait_for_background(cache)
            row.update(command=line, round=r, load=before, background=background_records(cache))
            rows.append(row)
            print(
                f"  {line}: first result {row['first_result_s']} s, total {row['total_s']:.1f} s, "
                f"peak {row['peak_rss_mb']:.0f} MB, load {before:.2f}",
                flush=True,
            )
    return rows


def simulated_recording(size: tuple[int, int], path: Path) -> Path:
    """A 40 ms textured-plane recording under a rotation, on ``size``, as an ``.npz`` of events."""
    import numpy as np

    from cmax_taichi.sim import default_camera, simulate, warp_scene

    camera = default_camera(size)
    scene = warp_scene("rotation3", (1.0, -1.5, 3.0), size, texture="minduka", camera=camera)
    rec = simulate(scene, 0.04, seed=0)
    ev = rec.events()
    np.savez(path, x=ev.x, y=ev.y, t=ev.t, p=ev.p, size=np.array(size), f=camera.fx)
    return path


def part_sensors(rounds: int, work: Path) -> list[dict]:
    rows = []
    files = {
        size: simulated_recording(size, work / f"rec_{size[0]}x{size[1]}.npz")
        for size in ((240, 180), (346, 260), (1280, 720))
    }
    for r in range(rounds):
        cache = work / f"sensors_{r}"
        env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=str(cache))
        env.pop("CMAX_TAICHI_COMPILE", None)
        for size, path in files.items():
            before = load()
            out = subprocess.run(
                [sys.executable, "-c", SENSOR_CHILD, repr(time.time()), str(path), "rotation3"],
                capture_output=True,
                text=True,
                env=env,
                cwd=work,
            )
            if out.returncode:
                raise RuntimeError(out.stderr[-2000:])
            row = json.loads(out.stdout.strip().splitlines()[-1])
            row["background_wait_s"] = wait_for_background(cache)
            row.update(sensor=f"{size[0]}x{size[1]}", round=r, load=before)
            rows.append(row)
            print(
                f"  {row['sensor']}: first evaluation {row['from_start']:.2f} s after the start, "
                f"{row['from_problem']:.2f} s after the problem; kernels built {row['kernels_built']}, "
                f"tier {row['tier']}; load {before:.2f}",
                flush=True,
            )
    return rows


def part_warps(rounds: int, work: Path) -> list[dict]:
    rows = []
    for r in range(rounds):
        cache = work / f"warps_{r}"
        env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=str(cache))
        env.pop("CMAX_TAICHI_COMPILE", None)
        before = load()
        out = subprocess.run([sys.executable, "-c", WARPS_CHILD], capture_output=True, text=True, env=env)
        if out.returncode:
            raise RuntimeError(out.stderr[-2000:])
        for row in json.loads(out.stdout.strip().splitlines()[-1]):
            row.update(round=r, load=before)
            rows.append(row)
        wait_for_background(cache)
    return rows


def median(values):
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else float("nan")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument(
        "--parts", nargs="+", default=["readme", "sensors", "warps"], choices=["readme", "sensors", "warps"]
    )
    parser.add_argument("--out", default=None, help="folder for cold_start.json and cold_start.md")
    args = parser.parse_args(argv)
    out = Path(args.out) if args.out else None
    results = {"load_before": load(), "rounds": args.rounds}
    md = []
    with tempfile.TemporaryDirectory(prefix="cmax-cold-") as tmp:
        work = Path(tmp)
        if "readme" in args.parts:
            print("README quick start, each from an empty cache:", flush=True)
            rows = results["readme"] = part_readme(args.rounds, work)
            md += [
                "| command | first result s | total s | peak MB | background compile s (peak MB) |",
                "|---|---:|---:|---:|---|",
            ]
            for line in readme_commands():
                mine = [r for r in rows if r["command"] == line]
                bg = [b for r in mine for b in r["background"]]
                bg_text = ", ".join(
                    f"{b['seconds']:.0f} ({b['peak_rss_mb']})" for b in bg[: len(bg) // max(len(mine), 1)]
                )
                md.append(
                    f"| `{line}` | {median(r['first_result_s'] for r in mine):.1f} | "
                    f"{median(r['total_s'] for r in mine):.1f} | "
                    f"{median(r['peak_rss_mb'] for r in mine):.0f} | "
                    f"{bg_text or '-'} |"
                )
        if "sensors" in args.parts:
            print("One configuration on three sensors, one after the other:", flush=True)
            rows = results["sensors"] = part_sensors(args.rounds, work)
            md += [
                "",
                "| sensor | first evaluation after the start s | after the problem s | kernels built "
                "| tier |",
                "|---|---:|---:|---|---|",
            ]
            for sensor in ("240x180", "346x260", "1280x720"):
                mine = [r for r in rows if r["sensor"] == sensor]
                built = sorted({k for r in mine for k in r["kernels_built"]})
                md.append(
                    f"| {sensor} | {median(r['from_start'] for r in mine):.2f} | "
                    f"{median(r['from_problem'] for r in mine):.2f} | {', '.join(built) or 'none'} | "
                    f"{', '.join(sorted({r['tier'] for r in mine}))} |"
                )
        if "warps" in args.parts:
            print("Every warp on 240x180, then 346x260, in one process:", flush=True)
            rows = results["warps"] = part_warps(args.rounds, work)
            md += [
                "",
                "| warp | 240x180 first evaluation s | 346x260 first evaluation s |",
                "|---|---:|---:|",
            ]
            for warp in dict.fromkeys(r["warp"] for r in rows):
                a = median(r["seconds"] for r in rows if r["warp"] == warp and r["sensor"] == "240x180")
                b = median(r["seconds"] for r in rows if r["warp"] == warp and r["sensor"] == "346x260")
                md.append(f"| {warp} | {a:.2f} | {b:.2f} |")
    text = "\n".join(md)
    print(text)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "cold_start.json").write_text(json.dumps(results, indent=1, default=str))
        (out / "cold_start.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
