"""Interleaved before/after timing of ``value_and_grad`` between two installed versions of the library.

``python benchmarks/ab_interleaved.py PYTHON_A PYTHON_B [--rows ROWS] [--rounds N] [--json OUT]``

Each version runs in a long-lived child process of its own Python (the environment of an editable
install of that version: the kernels are installed from its ``kernels/`` folder, so ``PYTHONPATH``
alone does not switch them), through the public API only, with ``compile_mode="full"`` (the optimized
kernels; a cold cache compiles them first, outside the timing). For each row both children build the
same window and warm up; then they time blocks of calls in turn, A then B, B then A, ... (load drifts
hit both alike), and the script prints the median wall and CPU (all threads) milliseconds per call of
each version and their ratio B / A.

Rows: ``WARP:REGS:EVENTS:WxH`` separated by commas (REGS ``none`` or ``both``: divergence and
deformation at weight 1), default the per-call grid of ``cmax-taichi bench`` on its windows' scale:
translation2, rotation3 without and mitrokhin4 with both regularizers, 1,000 / 30,000 / 1,000,000
events, on 240x180, 346x260 and 1280x720. The window: 5% of the events on short bright edges (20 events
each, 0.5 px apart), spread over the sensor and 20 ms.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile

CHILD = r"""
import json, resource, sys, time
import numpy as np
import cmax_taichi as cm

warp, regs, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
size = tuple(int(v) for v in sys.argv[4].split("x"))
cm.init(arch="cpu", precision="f64", compile_mode="full")
rng = np.random.default_rng(0)
W, H = size
x0 = rng.uniform(0, W - 1, max(n // 20, 1))
x = np.clip(np.repeat(x0, 20)[:n] + rng.normal(0, 0.5, n), 0, W - 1)
events = cm.Events(x, rng.uniform(0, H - 1, n), np.sort(rng.uniform(0, 0.02, n)), rng.integers(0, 2, n), size)
camera = cm.Camera(fx=200.0, fy=200.0, cx=W / 2, cy=H / 2)
both = {"divergence": 1.0, "deformation": 1.0}
prob = cm.ContrastMaximization(events, warp, regularizers=both if regs == "both" else {}, camera=camera)
theta = np.full(prob.model.n_params, 0.05) * (1.0 if warp == "rotation3" else 50.0)
for _ in range(20):
    prob.value_and_grad(theta)
reps = max(3, int(3e6 // max(n, 1000)))
print("ready", flush=True)
for _ in sys.stdin:
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    for _ in range(reps):
        prob.value_and_grad(theta)
    r1, t1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    cpu = (r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime) / reps * 1e3
    print(json.dumps({"wall": (t1 - t0) / reps * 1e3, "cpu": cpu}), flush=True)
"""

DEFAULT_ROWS = ",".join(
    f"{warp}:{regs}:{n}:{size}"
    for size in ("240x180", "346x260", "1280x720")
    for warp, regs in (("translation2", "none"), ("rotation3", "none"), ("mitrokhin4", "both"))
    for n in (1_000, 30_000, 1_000_000)
)


def _reply(child: subprocess.Popen, prefix: str) -> str:
    line = child.stdout.readline()
    while line and not line.startswith(prefix):
        line = child.stdout.readline()
    if not line:
        raise RuntimeError(f"a child ended early: {child.stderr.read()[-2000:]}")
    return line


def time_row(pythons: tuple[str, str], row: str, rounds: int) -> dict:
    """The medians of one row for both versions (``a`` and ``b``: wall and CPU ms per call)."""
    warp, regs, n, size = row.split(":")
    children = [
        subprocess.Popen(
            [py, "-c", CHILD, warp, regs, n, size],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=tempfile.gettempdir(),  # not a checkout: ``python -c`` imports from its working folder first
        )
        for py in pythons
    ]
    try:
        for child in children:
            _reply(child, "ready")
        samples: dict[int, list[dict]] = {0: [], 1: []}
        for r in range(rounds):
            for i in (0, 1) if r % 2 == 0 else (1, 0):
                children[i].stdin.write("go\n")
                children[i].stdin.flush()
                samples[i].append(json.loads(_reply(children[i], "{")))
    finally:
        for child in children:
            if child.stdin:
                child.stdin.close()
            child.wait(timeout=60)
    medians = {
        side: {key: statistics.median(s[key] for s in samples[i]) for key in ("wall", "cpu")}
        for i, side in enumerate("ab")
    }
    return {"row": row, **medians}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("python_a", help="the Python of version A (before)")
    parser.add_argument("python_b", help="the Python of version B (after)")
    parser.add_argument("--rows", default=DEFAULT_ROWS, help="WARP:REGS:EVENTS:WxH,... (default: the grid)")
    parser.add_argument("--rounds", type=int, default=9, help="timed blocks per version and row (default 9)")
    parser.add_argument("--json", default=None, help="write the rows here")
    args = parser.parse_args(argv)
    results = []
    for row in args.rows.split(","):
        res = time_row((args.python_a, args.python_b), row, args.rounds)
        results.append(res)
        a, b = res["a"], res["b"]
        print(
            f"{row:36s} A {a['wall']:9.3f} ms (CPU {a['cpu']:9.3f})  B {b['wall']:9.3f} ms "
            f"(CPU {b['cpu']:9.3f})  B/A wall {b['wall'] / a['wall']:.3f} CPU {b['cpu'] / a['cpu']:.3f}",
            flush=True,
        )
        if args.json:
            with open(args.json, "w") as fh:
                json.dump(results, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
