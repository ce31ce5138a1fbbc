"""Run tub-rip/event_based_optical_flow's dense solver on one window of events (the authors' reference),
in the reference's own environment: ``benchmarks/reference_flow.py`` starts this file with
the reference checkout's Python (torch, optuna, ...). It imports only NumPy, PyTorch, PyYAML and the
reference, never cmax_taichi.

    REF/.venv/bin/python benchmarks/reference_flow_driver.py --reference REF \\
        --config REF/configs/mvsec_indoor_no_timeaware.yaml --events window.npz --threads 1 --out out.npz

``window.npz`` holds ``x, y`` (px, column and row), ``t`` (s), ``p`` (-1/+1) and ``height, width``. The
events are given to the solver as the reference's MVSEC loader gives them (``[row, column, t - t_0, p]``,
its "x" is the row) and its ``optimize`` runs as ``main.py`` runs it (the released configuration, the
profiler decorator included unless ``--no-profiler``). Written to ``out.npz``: ``flow`` (2, H, W) px/s
in (x, y) order (its ``motion_to_dense_flow``, the flow its ``calculate_flow_error`` scores),
``wall_s`` and ``cpu_s`` of ``optimize``, the number of parameters per pyramid level, and the count,
wall and CPU time of its loss evaluations (``objective_scipy``: one forward pass each), of the scipy
value-and-gradient calls and of the Hessian-vector products (Newton-CG).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
import types


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reference", required=True, help="the event_based_optical_flow checkout")
    parser.add_argument("--config", required=True, help="its YAML configuration")
    parser.add_argument("--events", required=True, help="npz: x, y, t, p, height, width")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (torch.set_num_threads)")
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of NumPy and torch (optuna's TPE is unseeded)"
    )
    parser.add_argument("--out", required=True, help="npz written with the flow and the timings")
    parser.add_argument("--log", default="warning", help="the reference's log level (info: its progress)")
    parser.add_argument(
        "--no-profiler",
        action="store_true",
        help="run optimize without the cProfile decorator the released code wraps it in",
    )
    args = parser.parse_args(argv)
    import logging

    logging.basicConfig(
        level=getattr(logging, args.log.upper()), stream=sys.stderr, format="%(asctime)s %(message)s"
    )

    import numpy as np
    import torch
    import yaml

    torch.set_num_threads(args.threads)
    torch.set_num_interop_threads(1)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    # torchvision 0.28's wheel on PyPI is a CUDA build whose C operators do not load beside torch's CPU
    # build; the reference uses only its Python transforms (gaussian_blur, resize), which need none
    sys.modules.setdefault(
        "torchvision._meta_registrations", types.ModuleType("torchvision._meta_registrations")
    )
    sys.path.insert(0, os.path.abspath(args.reference))
    from src import solver  # the reference

    with open(args.config) as fh:
        config = yaml.safe_load(fh)
    data = np.load(args.events)
    H, W = int(data["height"]), int(data["width"])
    size = (config["data"]["height"], config["data"]["width"])
    if size != (H, W):
        print(f"note: events of {W}x{H}, the configuration says {size[1]}x{size[0]}")
    t = np.asarray(data["t"], dtype=np.float64)
    events = np.stack([data["y"], data["x"], t - t.min(), data["p"]], axis=1).astype(np.float64)

    cls = solver.collections[config["solver"]["method"]]
    counters = {"objective": [0, 0.0, 0.0], "value_and_grad": [0, 0.0, 0.0], "hvp": [0, 0.0, 0.0]}

    def timed(owner, name, key):
        original = getattr(owner, name)

        def wrapper(*a, **k):
            t0, c0 = time.perf_counter(), _cpu_seconds()
            try:
                return original(*a, **k)
            finally:
                counters[key][0] += 1
                counters[key][1] += time.perf_counter() - t0
                counters[key][2] += _cpu_seconds() - c0

        setattr(owner, name, wrapper)

    from src.solver.scipy_autograd import torch_wrapper

    if args.no_profiler:
        cls.run_scipy_over_scale = cls.run_scipy_over_scale.__wrapped__
    timed(cls, "objective_scipy", "objective")
    timed(torch_wrapper.TorchWrapper, "get_value_and_grad", "value_and_grad")
    timed(torch_wrapper.TorchWrapper, "get_hvp", "hvp")

    work = tempfile.mkdtemp(prefix="reference_flow_")
    os.chdir(work)  # its profiler decorator writes optimize.prof into the working folder
    out_config = dict(config["output"], output_dir=work)
    solv = cls(
        (H, W),
        calibration_parameter={},
        solver_config=config["solver"],
        optimizer_config=config["optimizer"],
        output_config=out_config,
        visualize_module=None,
    )
    levels = {int(s): int(solv.scaled_n_patch[s]) * int(solv.motion_vector_size) for s in solv.scaled_n_patch}
    cpu0, wall0 = _cpu_seconds(), time.perf_counter()
    motion = solv.optimize(events)
    wall = time.perf_counter() - wall0
    cpu = _cpu_seconds() - cpu0
    finest = max(levels)
    solv.overload_patch_configuration(finest)
    flow = solv.motion_to_dense_flow(motion)  # the finest level's (2, H, W), (row, column) order, px/s
    flow = np.asarray(flow, dtype=np.float64)[::-1]
    result = {
        "wall_s": wall,
        "cpu_s": cpu,
        "threads": args.threads,
        "n_events": len(events),
        "params_per_level": levels,
        "params_finest": levels[finest],
        "params_total": sum(levels.values()),
        "profiler": not args.no_profiler,
        "counts": {k: v[0] for k, v in counters.items()},
        "seconds": {k: v[1] for k, v in counters.items()},
        "cpu_seconds": {k: v[2] for k, v in counters.items()},
        "torch": torch.__version__,
    }
    np.savez(args.out, flow=flow, report=json.dumps(result))
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
