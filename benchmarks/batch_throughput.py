"""Throughput of batch estimation (cmax_taichi.solve.batch) with 1 and 2 workers, per engine.

Each configuration estimates the same recordings into a fresh output folder (so nothing is resumed)
and reports the wall time of the whole batch (worker start-up and kernel compilation included), the
windows per second over the batch, and the median wall time of one window inside a worker.

    python benchmarks/batch_throughput.py ../shared/data/ecd_rotation/*_rotation \\
        --warp rotation3 --window 5000 --engines local ray --workers 1 2
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import tempfile

import numpy as np

from cmax_taichi.solve import batch


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("paths", nargs="+", help="recordings")
    parser.add_argument("--warp", default="translation2")
    parser.add_argument("--window", type=int, default=30000, help="events per window")
    parser.add_argument("--engines", nargs="+", default=["local"], choices=batch.ENGINES)
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    args = parser.parse_args()

    print(
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"load average {os.getloadavg()[0]:.1f} at the start"
    )
    print("| engine | workers | recordings | windows | wall s | windows/s | median s/window |")
    print("|---|---|---|---|---|---|---|")
    for engine in args.engines:
        for workers in args.workers:
            with tempfile.TemporaryDirectory() as out:
                result = batch.run(
                    args.paths,
                    out,
                    workers=workers,
                    engine=engine,
                    progress=False,
                    warp=args.warp,
                    n_events=args.window,
                )
                if result.failed:
                    raise SystemExit(f"failed: {[(r.name, r.error) for r in result.failed]}")
                seconds = [w.seconds for r in result.recordings for w in result.results(r.name).windows]
            n = len(seconds)
            print(
                f"| {engine} | {workers} | {len(result.recordings)} | {n} | {result.wall_seconds:.1f} | "
                f"{n / result.wall_seconds:.2f} | {np.median(seconds):.3f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
