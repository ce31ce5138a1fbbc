"""What it costs a streaming problem to take the next window: ``python benchmarks/window_setup.py
[--events N ...] [--seconds S]``.

On a simulated stream (lab/realtime.py's textured plane, 240x180, translation2; ``--seconds`` of data),
for each window size: the median of ``ContrastMaximization.set_events`` over every window of the stream
(three passes; it checks the window, packs and hands over its events, and evaluates the identity for
G0), and of its parts: the checks and derived values (``ProblemSetup``), the packing
(``FusedPipeline.load_window``), one ``value`` of the window (the kernel that G0 needs); then one
``sequence.process`` of the whole stream (warm start, FWL on): the median seconds of a warm window, its
median evaluations, and the events per second of the warm windows. Runs on any version with the fused
pipeline (the parts are timed through its internals).
"""

import argparse
import statistics
import sys
import time

import numpy as np

import cmax_taichi as cm
from cmax_taichi.lab.realtime import simulated_stream
from cmax_taichi.solve import sequence


def _median_us(fn, items, passes: int = 3) -> float:
    times = []
    for _ in range(passes):
        for item in items:
            t0 = time.perf_counter()
            fn(item)
            times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e6


def measure(events, camera, n: int) -> str:
    """The line of one window size (see the module docstring)."""
    windows = list(events.windows_by_count(n))
    prob = cm.ContrastMaximization(windows[0], warp="translation2", camera=camera)
    rest = windows[1:]
    set_us = _median_us(prob.set_events, rest)
    setups = [prob._setup_for(w, None) for w in rest]
    setup_us = _median_us(lambda w: prob._setup_for(w, None), rest)
    fused = prob._fused

    def load(setup):
        prob.setup, prob.events, prob.n_events = setup, setup.events, setup.n_events
        prob.t_ref = setup.t_ref
        fused.load_window(prob, setup.vote_weights)

    load_us = _median_us(load, setups)
    prob.set_events(windows[-1])
    theta = np.full(2, 1e-3)
    value_us = _median_us(lambda _: prob.value(theta), range(50), passes=1)
    t0 = time.perf_counter()
    result = sequence.process(events, "translation2", n_events=n, camera=camera, progress=False)
    wall = time.perf_counter() - t0
    warm = result.windows[1:]
    data = sum(w.t_end - w.t_start for w in warm)
    seconds = sum(w.seconds for w in warm)
    return (
        f"{n:6d}-event windows ({len(windows)}): set_events {set_us:8.1f} us = set-up {setup_us:6.1f} + "
        f"packing {load_us:6.1f} + G0 value ~{value_us:7.1f} (+ rest); sequence.process {wall:.2f} s: "
        f"warm window median {statistics.median(w.seconds for w in warm) * 1e3:.2f} ms, "
        f"{statistics.median(w.evaluations for w in warm):.0f} evaluations, "
        f"{sum(w.n_events for w in warm) / seconds / 1e6:.3f} Mev/s, "
        f"real-time factor {data / seconds:.2f}"
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--events", type=int, nargs="+", default=[1000, 2000, 5000])
    parser.add_argument("--seconds", type=float, default=0.3)
    args = parser.parse_args(argv)
    cm.init(precision="f64")
    events, camera = simulated_stream(args.seconds)
    print(f"simulated stream: {len(events):,} events over {args.seconds} s, 240x180, translation2")
    for n in args.events:
        print(measure(events, camera, n), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
