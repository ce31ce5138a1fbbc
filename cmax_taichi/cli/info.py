"""Show the backend in use and the registered warps, objectives, regularizers and the dense flow's
smoothness terms."""

from __future__ import annotations

import argparse

from cmax_taichi.cli._common import add_backend_arguments, add_plugin_argument

NAME = "info"
HELP = "show the backend (arch, precision) and the registered models"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_backend_arguments(parser)
    add_plugin_argument(parser)


def run(args: argparse.Namespace) -> int:
    import cmax_taichi as cm
    from cmax_taichi.flow.smoothness import SMOOTHNESS, smoothness_names
    from cmax_taichi.pipeline import tiers

    info = cm.init(arch=args.arch, precision=args.precision, compile_mode=args.compile)
    print(f"cmax-taichi {cm.__version__}")
    print(f"backend: arch={info.arch} (requested {info.requested_arch}), precision={info.precision}")
    print(f"kernels: compile mode {info.compile_mode}; {tiers.cache_summary()}")
    print("warps:")
    for name in cm.warp_names():
        m = cm.get_warp(name)
        params = ", ".join(f"{p} [{u}]" for p, u in zip(m.params, m.units, strict=True))
        flag = " (collapse-enabled)" if m.collapse_enabled else ""
        print(f"  {name:14s} {params}{flag}: {m.description}")
    print("objectives:")
    for name in cm.objective_names():
        print(f"  {name:20s} {cm.OBJECTIVES.get(name).description}")
    print("regularizers:")
    for name in cm.regularizer_names():
        print(f"  {name:14s} {cm.REGULARIZERS.get(name).description}")
    print("smoothness terms of the dense flow (cmax-taichi flow --reg NAME=WEIGHT, beside the regularizers):")
    for name in smoothness_names():
        print(f"  {name:16s} {SMOOTHNESS.get(name).description}")
    return 0
