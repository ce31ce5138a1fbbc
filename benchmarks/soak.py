"""Soak test of long recordings: thousands of windows through ``sequence.process``, memory sampled.

``python -m benchmarks.soak [--windows 2000] [--events 30000] [--varying] [--out DIR]``

A synthetic stream (straight edges translating at a constant velocity, generated window by window, so
the stream itself holds no memory) is estimated window after window by
:func:`cmax_taichi.solve.sequence.process` with the warm start, exactly as ``cmax-taichi estimate``
runs a recording. The resident set size (RSS) of the process is read from ``/proc/self/statm`` after
every window. Writes ``soak.csv`` (window, events, seconds, RSS MB, estimate) and ``soak.png`` (RSS over
windows) into ``--out`` and prints the RSS growth between window 100 (after the kernels compiled and
the pools filled) and the last window, the median seconds per window and the real-time factor.
``--varying`` draws every window's size uniformly in [0.5, 1.5] x ``--events``.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path

import numpy as np

SENSOR = (346, 260)
VELOCITY = (120.0, -80.0)  # px/s
RATE = 1.0e6  # events/s of the synthetic stream


def rss_mb() -> float:
    """Resident set size of this process, MB (Linux)."""
    with open("/proc/self/statm") as fh:
        resident_pages = int(fh.read().split()[1])
    return resident_pages * os.sysconf("SC_PAGE_SIZE") / 1e6


class SyntheticStream:
    """A recording-like source of fresh windows of moving edges (the protocol of an open Recording
    that :func:`~cmax_taichi.solve.sequence.process` reads: ``window_spans`` and ``_span_events``).

    ``sizes`` gives the number of events of each window; a window's events are generated when it is
    read, from its own seed, at :data:`RATE` events per second, so that the stream's clock advances like
    a camera's and nothing but the current window is held.
    """

    format = "synthetic"
    camera = None
    undistorted = False
    sensor_size = SENSOR

    def __init__(self, sizes: np.ndarray, seed: int = 0) -> None:
        self.sizes = np.asarray(sizes, dtype=np.int64)
        self.n_events = int(self.sizes.sum())
        self.path = f"synthetic stream of {len(self.sizes)} windows"
        self._seed = seed
        self._starts = np.concatenate([[0], np.cumsum(self.sizes)])
        rng = np.random.default_rng(seed)
        W, H = SENSOR
        k = 60
        self._centres = rng.uniform([0.1 * W, 0.1 * H], [0.9 * W, 0.9 * H], size=(k, 2))
        self._angles = rng.uniform(0, np.pi, k)

    def window_spans(self, n_events=None, duration=None, stride=None, keep_tail=False):
        """The stream's own windows (``sizes``) as index spans; the arguments are ignored."""
        from cmax_taichi.core.windows import Span

        for i, (start, stop) in enumerate(zip(self._starts[:-1], self._starts[1:], strict=True)):
            yield Span(i, int(start), int(stop))

    def _span_events(self, start: int, stop: int):
        import cmax_taichi as cm

        i = int(np.searchsorted(self._starts, start, side="right")) - 1
        if self._starts[i] != start or self._starts[i + 1] != stop:
            raise ValueError(f"events {start}:{stop} are not one window of the synthetic stream")
        n = stop - start
        rng = np.random.default_rng((self._seed, i))
        W, H = SENSOR
        t_start = start / RATE
        which = rng.integers(0, len(self._angles), n)
        s = rng.uniform(-20, 20, n)
        t = t_start + np.sort(rng.uniform(0, n / RATE, n))
        x = self._centres[which, 0] + s * np.cos(self._angles[which]) + VELOCITY[0] * (t - t_start)
        y = self._centres[which, 1] + s * np.sin(self._angles[which]) + VELOCITY[1] * (t - t_start)
        x = np.clip(x + rng.normal(0, 0.3, n), 0, W - 1)
        y = np.clip(y + rng.normal(0, 0.3, n), 0, H - 1)
        return cm.Events(x, y, t, rng.integers(0, 2, n), SENSOR), np.ones(n, dtype=bool)


def run(n_windows: int, n_events: int, varying: bool, warp: str, out: Path, seed: int = 0) -> dict:
    """Run the soak and write soak.csv / soak.png; returns the summary."""
    import cmax_taichi as cm
    from cmax_taichi.solve.sequence import process

    cm.init(arch="cpu", precision="f64")
    rng = np.random.default_rng(seed)
    sizes = (
        rng.integers(n_events // 2, 3 * n_events // 2 + 1, n_windows)
        if varying
        else np.full(n_windows, n_events)
    )
    stream = SyntheticStream(sizes, seed=seed)
    rows = []
    t_last = [time.perf_counter()]

    def on_window(row, prob, res):
        now = time.perf_counter()
        rows.append(
            {
                "window": row.index,
                "events": row.n_events,
                "data_s": row.t_end - row.t_start,
                "seconds": now - t_last[0],
                "rss_mb": rss_mb(),
                "theta": " ".join(f"{v:.3f}" for v in res.theta),
            }
        )
        t_last[0] = now

    rss0 = rss_mb()
    t0 = time.perf_counter()
    process(stream, warp, n_events=n_events, progress=False, on_window=on_window, compute_fwl=False)
    wall = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)
    with (out / "soak.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    rss = np.array([r["rss_mb"] for r in rows])
    secs = np.array([r["seconds"] for r in rows])
    data = np.array([r["data_s"] for r in rows])
    ref = min(100, len(rows) - 1)
    summary = {
        "windows": len(rows),
        "events_per_window": n_events,
        "varying": varying,
        "warp": warp,
        "rss_start_mb": rss0,
        "rss_at_ref_mb": float(rss[ref]),
        "rss_end_mb": float(rss[-1]),
        "growth_mb": float(rss[-1] - rss[ref]),
        "ref_window": ref,
        "median_window_s": float(np.median(secs[1:])) if len(secs) > 1 else float(secs[0]),
        "first_window_s": float(secs[0]),
        "real_time_factor": float(data[1:].sum() / secs[1:].sum()) if len(secs) > 1 else float("nan"),
        "wall_s": wall,
    }
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.5), constrained_layout=True)
    ax.plot(np.arange(len(rss)), rss, lw=1)
    ax.axvline(ref, color="0.6", ls=":", lw=1)
    ax.set_xlabel("window")
    ax.set_ylabel("RSS [MB]")
    kind = "varying" if varying else "equal"
    ax.set_title(
        f"{len(rows)} windows of {n_events} events ({kind} sizes), {warp}: "
        f"RSS +{summary['growth_mb']:.1f} MB after window {ref}",
        fontsize=9,
    )
    fig.savefig(out / "soak.png", dpi=90)
    plt.close(fig)
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.soak", description=__doc__.split("\n\n")[0])
    parser.add_argument("--windows", type=int, default=2000, help="windows (default 2000)")
    parser.add_argument("--events", type=int, default=30000, help="events per window (default 30000)")
    parser.add_argument("--varying", action="store_true", help="window sizes in [0.5, 1.5] x --events")
    parser.add_argument("--warp", default="translation2", help="warp model (default translation2)")
    parser.add_argument("--out", default="soak-results", help="output folder (default soak-results)")
    args = parser.parse_args(argv)
    if args.windows < 2 or args.events < 100:
        parser.error("--windows must be at least 2 and --events at least 100")
    summary = run(args.windows, args.events, args.varying, args.warp, Path(args.out))
    for key, value in summary.items():
        print(f"{key}: {value:.4g}" if isinstance(value, float) else f"{key}: {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
