"""Before/after timing of ``value_and_grad`` through the public API only, so that the same script runs
on an older version of the library: ``python benchmarks/ab_timing.py [OUT.json]``.

Run it once with the old version importable (e.g. ``PYTHONPATH=/path/to/old/checkout`` for a version
that runs from its source tree) and once with the new one, alternating a few times on a quiet machine,
and compare the medians. Windows: 40 moving straight edges plus 10% noise on 346x260, 50 ms; rows:
30,000 and 1,000,000 events, translation2 without and mitrokhin4 with both regularizers. Prints the
median milliseconds per call of each row and writes them to OUT.json when given.

``--million`` times instead every warp of the benchmark (translation2, rotation3, mitrokhin4) with and
without both regularizers at 1,000,000 events on the 240x180 and 346x260 sensors (the N = 1e6 rows of
``cmax-taichi bench`` on those sensors, on this script's windows).

Run the script file of the newest version with the Python of each version's environment (the kernels
are installed as ``cmax_taichi.kernels`` from the ``kernels/`` folder of an editable install, so
``PYTHONPATH`` alone does not switch them).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

import cmax_taichi as cm

SENSOR = (346, 260)
THETAS = {
    "translation2": (120.0, -80.0),
    "rotation3": (0.6, -0.4, 1.5),
    "mitrokhin4": (120.0, -80.0, 4.0, 3.0),
}
REGS = {"none": {}, "div+def": {"divergence": 1.0, "deformation": 1.0}}
#: (events, warp, regularizers, timed calls)
ROWS = [
    (30_000, "translation2", "none", 300),
    (30_000, "mitrokhin4", "div+def", 300),
    (1_000_000, "translation2", "none", 40),
    (1_000_000, "mitrokhin4", "div+def", 40),
]
#: --million: (events, warp, regularizers, timed calls, sensor)
MILLION_ROWS = [
    (1_000_000, warp, regs, 20, sensor)
    for sensor in ((240, 180), (346, 260))
    for warp in THETAS
    for regs in REGS
]


def window(n: int, seed: int = 0, duration: float = 0.05, sensor: tuple[int, int] = SENSOR):
    """``n`` events (x, y px; t s; p) of 40 straight edges moving at (120, -80) px/s plus 10% noise."""
    rng = np.random.default_rng(seed)
    W, H = sensor
    n_edge = int(0.9 * n)
    centres = rng.uniform([0.1 * W, 0.1 * H], [0.9 * W, 0.9 * H], size=(40, 2))
    angles = rng.uniform(0, np.pi, 40)
    half = 0.075 * min(W, H)
    which = rng.integers(0, 40, n_edge)
    s = rng.uniform(-half, half, n_edge)
    t_edge = rng.uniform(0, duration, n_edge)
    x = centres[which, 0] + s * np.cos(angles[which]) + 120 * t_edge
    y = centres[which, 1] + s * np.sin(angles[which]) - 80 * t_edge
    n_noise = n - n_edge
    x = np.clip(np.concatenate([x, rng.uniform(0, W - 1, n_noise)]), 0, W - 1)
    y = np.clip(np.concatenate([y, rng.uniform(0, H - 1, n_noise)]), 0, H - 1)
    t = np.concatenate([t_edge, rng.uniform(0, duration, n_noise)])
    order = np.argsort(t)
    return x[order], y[order], t[order], rng.integers(0, 2, n)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    cm.init(arch="cpu", precision="f64")
    million = "--million" in argv
    argv = [a for a in argv if a != "--million"]
    rows = MILLION_ROWS if million else [(*row, SENSOR) for row in ROWS]
    medians = {}
    for n, warp, regs, repeats, sensor in rows:
        W, H = sensor
        x, y, t, p = window(n, seed=n % 9973, sensor=sensor)
        events = cm.Events(x, y, t, p, sensor)
        kwargs = {}
        if warp == "rotation3":  # a centred pinhole camera with a ~70 degree field of view
            kwargs["camera"] = cm.Camera(fx=0.7 * W, fy=0.7 * W, cx=(W - 1) / 2.0, cy=(H - 1) / 2.0)
        prob = cm.ContrastMaximization(events, warp=warp, regularizers=REGS[regs], blur_sigma=1.0, **kwargs)
        theta = np.array(THETAS[warp])
        for _ in range(5):  # compile and warm up
            prob.value_and_grad(theta)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            prob.value_and_grad(theta)
            times.append(time.perf_counter() - t0)
        key = f"{n} {W}x{H} {warp} {regs}" if million else f"{n} {warp} {regs}"
        medians[key] = float(np.median(times)) * 1e3
        print(f"{key:48s} median {medians[key]:8.3f} ms  {n / medians[key] / 1e3:7.2f} Mev/s", flush=True)
    if argv:
        Path(argv[0]).write_text(json.dumps(medians, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
