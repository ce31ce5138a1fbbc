"""The event windows of the benchmark, of three kinds (``BenchConfig.window``):

* ``"textured"``: events where the edges are, as a camera records them: the first N events of the
  event simulator (:mod:`cmax_taichi.sim`) watching a textured plane ("minduka") that translates at
  (120, -80) px/s across the sensor (the camera of :func:`cmax_taichi.lab.bench_impls.camera_for`). One
  stream per sensor serves every N and warp (the timing depends on where the events fall, not on which
  motion made them); simulating a million events of a 1280x720 sensor takes minutes, so each stream is
  kept in the cache directory (``$CMAX_TAICHI_CACHE``, else ``~/.cache/cmax_taichi``, ``bench/``) and
  made again only when its key (sensor, length, seed, simulator settings, :data:`STREAM_VERSION`)
  changes;
* ``"uniform"``: positions and times uniformly spread over the sensor and :data:`DURATION`: every event
  touches its own pixels, the worst case for work that follows the touched pixels;
* ``"edges"``: the synthetic straight edges of :func:`cmax_taichi.lab.bench_impls.make_window` (the
  windows of the earlier benchmark sweeps, kept for the 1e7-event rows and the comparisons).

Each returns float64 arrays ``x, y`` (px), ``t`` (s, from 0) and ``p`` in {0, 1}, time-sorted.
"""

from __future__ import annotations

import hashlib
import json
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = [
    "DURATION",
    "STREAM_VERSION",
    "TEXTURED_MOTION",
    "WINDOW_KINDS",
    "textured_stream",
    "uniform_window",
    "window",
]

WINDOW_KINDS = ("textured", "uniform", "edges")
DURATION = 0.05  # s, the span of the uniform windows (the edges windows' too)
TEXTURED_MOTION = (120.0, -80.0)  # px/s, the plane's translation (the benchmark's translation2 theta)
TEXTURE = "minduka"
STREAM_VERSION = 1  # bump when the stream's recipe changes (cached streams are then made again)
_SIM_SETTINGS = {"contrast_threshold": 0.5, "log_eps": 0.02}  # the simulator settings of the examples

_STREAMS: dict = {}  # in-process copies of the streams used in this run


def _cache_dir() -> Path:
    from cmax_taichi.io._cache import cache_root

    return cache_root() / "bench"


def _stream_key(sensor: tuple[int, int], n_events: int, seed: int) -> str:
    recipe = {
        "sensor": list(sensor),
        "n": int(n_events),
        "seed": int(seed),
        "motion": list(TEXTURED_MOTION),
        "texture": TEXTURE,
        "sim": _SIM_SETTINGS,
        "version": STREAM_VERSION,
    }
    return hashlib.sha256(json.dumps(recipe, sort_keys=True).encode()).hexdigest()[:16]


def _simulate(sensor: tuple[int, int], n_events: int, seed: int, log: Callable[[str], None]):
    """At least ``n_events`` events of the textured plane (a short run measures the event rate first)."""
    from cmax_taichi.lab.bench_impls import camera_for
    from cmax_taichi.sim.scenes import warp_scene
    from cmax_taichi.sim.simulator import simulate

    scene = warp_scene("translation2", TEXTURED_MOTION, sensor, texture=TEXTURE, camera=camera_for(sensor))
    seconds = 0.02
    while True:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            rec = simulate(scene, seconds, seed=seed, **_SIM_SETTINGS)
        if len(rec.t) >= n_events:
            return rec
        # the event rate of the second half (the sensor starts at rest: few events at first)
        late = int(np.count_nonzero(np.asarray(rec.t) >= seconds / 2))
        rate = max(late, 1) / (seconds / 2)
        seconds = seconds + 1.1 * (n_events - len(rec.t)) / rate + 0.002
        log(f"simulating {seconds * 1e3:.0f} ms of the textured {sensor[0]}x{sensor[1]} scene "
            f"({rate / 1e6:.2f} Mev/s) for {n_events:,} events")  # fmt: skip


def textured_stream(
    sensor: tuple[int, int],
    n_events: int,
    seed: int = 0,
    *,
    log: Callable[[str], None] = print,
    cache: bool = True,
):
    """The first ``n_events`` events of the textured stream of ``sensor`` as ``(x, y, t, p)`` (see the
    module docstring), from the cache when it holds them."""
    sensor = (int(sensor[0]), int(sensor[1]))
    mem_key = (sensor, int(n_events), int(seed))
    if mem_key in _STREAMS:
        return _STREAMS[mem_key]
    name = f"textured_{sensor[0]}x{sensor[1]}_{n_events}_{_stream_key(sensor, n_events, seed)}.npz"
    path = _cache_dir() / name
    arrays = None
    if cache and path.exists():
        try:
            with np.load(path) as data:
                arrays = tuple(np.asarray(data[k], dtype=np.float64) for k in ("x", "y", "t", "p"))
        except (OSError, ValueError, KeyError):  # a damaged entry: make it again
            arrays = None
    if arrays is None:
        start = time.perf_counter()
        rec = _simulate(sensor, n_events, seed, log)
        order = np.argsort(rec.t, kind="stable")[:n_events]
        arrays = tuple(np.asarray(a, dtype=np.float64)[order] for a in (rec.x, rec.y, rec.t, rec.p))
        log(f"textured {sensor[0]}x{sensor[1]} stream: {n_events:,} events simulated in "
            f"{time.perf_counter() - start:.0f} s")  # fmt: skip
        if cache:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp.npz")
            np.savez(tmp, x=arrays[0], y=arrays[1], t=arrays[2], p=arrays[3])
            tmp.replace(path)
    x, y, t, p = arrays
    p = (p > 0).astype(np.float64)
    _STREAMS[mem_key] = (x, y, t - t[0], p)
    return _STREAMS[mem_key]


def uniform_window(n: int, sensor: tuple[int, int], seed: int = 0):
    """``n`` events uniformly spread over the sensor and ``DURATION``."""
    rng = np.random.default_rng(seed)
    W, H = sensor
    x = rng.uniform(0, W - 1, n)
    y = rng.uniform(0, H - 1, n)
    t = np.sort(rng.uniform(0, DURATION, n))
    t[0], t[-1] = 0.0, DURATION
    return x, y, t, rng.integers(0, 2, n).astype(np.float64)


def window(kind: str, n: int, sensor: tuple[int, int], seed: int = 0, *, stream_events: int | None = None,
           log: Callable[[str], None] = print):  # fmt: skip
    """``n`` events of a window of ``kind`` (:data:`WINDOW_KINDS`). Textured windows are the first ``n``
    events of the sensor's one stream of ``stream_events`` (default ``n``) events (``seed`` seeds the
    other kinds only: every N shares the stream)."""
    if kind == "textured":
        x, y, t, p = textured_stream(sensor, max(n, stream_events or n), 0, log=log)
        return x[:n], y[:n], t[:n], p[:n]
    if kind == "uniform":
        return uniform_window(n, sensor, seed)
    if kind == "edges":
        from cmax_taichi.lab.bench_impls import make_window

        return make_window(n, sensor, seed)
    raise ValueError(f"unknown window kind {kind!r}; valid: {', '.join(WINDOW_KINDS)}")
