"""What one parallel task of a Taichi CPU kernel costs besides its work: the thread pool's dispatch.

``python benchmarks/dispatch_cost.py [--threads N] [--blocks B]``

Times four kernels over a 64-element field (no real work): one parallel loop, ten parallel loops, the
same ten loops serialized (``ti.loop_config(serialize=True)``: they run on the launching thread) and ten
parallel loops with ``block_dim=64`` (one task each). Prints the median over ``B`` blocks of 100 calls
(microseconds per call). On the CPU, Taichi 1.7.4's ``ThreadPool::run`` wakes its workers for every
parallel task and the launching thread sleeps until they finish, so a kernel's fixed cost grows with
its number of parallel tasks (the fused kernel has six): the difference between the second and third
rows, divided by ten, is the dispatch of one task on this machine.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=0, help="cpu_max_num_threads (0: Taichi's default)")
    parser.add_argument("--blocks", type=int, default=30, help="blocks of 100 calls per kernel")
    args = parser.parse_args(argv)

    import taichi as ti

    options = {"cpu_max_num_threads": args.threads} if args.threads > 0 else {}
    ti.init(arch=ti.cpu, log_level=ti.ERROR, offline_cache=False, **options)
    x = ti.field(ti.f64, shape=64)

    @ti.kernel
    def one_parallel_loop():
        for i in range(64):
            x[i] += 1.0

    @ti.kernel
    def ten_parallel_loops():
        for _ in ti.static(range(10)):
            for i in range(64):
                x[i] += 1.0

    @ti.kernel
    def ten_serial_loops():
        for _ in ti.static(range(10)):
            ti.loop_config(serialize=True)
            for i in range(64):
                x[i] += 1.0

    @ti.kernel
    def ten_loops_one_block_each():
        for _ in ti.static(range(10)):
            ti.loop_config(block_dim=64)
            for i in range(64):
                x[i] += 1.0

    threads = args.threads or "default"
    print(f"Taichi CPU, cpu_max_num_threads={threads}: us per call (median of {args.blocks} x 100 calls)")
    for kernel in (one_parallel_loop, ten_parallel_loops, ten_serial_loops, ten_loops_one_block_each):
        kernel()  # compiled
        blocks = []
        for _ in range(args.blocks):
            start = time.perf_counter()
            for _ in range(100):
                kernel()
            blocks.append((time.perf_counter() - start) / 100 * 1e6)
        print(f"  {kernel.__name__:28s} {statistics.median(blocks):8.1f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
