"""Compile the optimized kernels of a configuration beforehand, and show or clear the kernel cache.

The kernels a configuration (warp, objective, regularizers, blur footprint, polarity, weights) runs on
are compiled once per machine and kept in Taichi's offline cache. The quick kernels serve every sensor;
the optimized ones of a warp have the sensor compiled in (--sensor-size, one compile each), the dense
flow's serve every sensor. Without this command the first run of a configuration starts on the quick
kernels and compiles the optimized ones in the background (``--compile auto``, the default); after it,
runs start on the optimized ones.

examples:
  cmax-taichi warmup --warp rotation3            # on a 240x180 sensor (DAVIS240)
  cmax-taichi warmup --warp rotation3 --sensor-size 346 260 --sensor-size 640 480
  cmax-taichi warmup --warp mitrokhin4 --reg divergence=1 --reg deformation=1
  cmax-taichi warmup --flow                      # the dense flow's default configuration
  cmax-taichi warmup --examples                  # what the --example commands of the README run
  cmax-taichi warmup --list                      # the cache folder, its size, what it holds
  cmax-taichi warmup --clear                     # delete the cache (every compiled kernel)
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from cmax_taichi.cli import _common as common

NAME = "warmup"
HELP = "compile the optimized kernels of a configuration beforehand; show or clear the kernel cache"

#: the dense flow's default configuration (cmax-taichi flow's defaults: cmax_taichi/cli/flow.py)
FLOW_DEFAULTS = {"objective": "gradient_magnitude", "references": 1}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    what = parser.add_argument_group("what to compile (one configuration per --warp, or --flow)")
    what.add_argument(
        "--warp",
        action="append",
        default=[],
        metavar="NAME",
        help=f"a warp model (repeatable): {common.warp_listing()}",
    )
    what.add_argument("--flow", action="store_true", help="the dense flow (cmax-taichi flow)")
    what.add_argument(
        "--references", type=int, default=1, help="the dense flow's reference times (1; 3 for multi)"
    )
    what.add_argument(
        "--objective", default=None, help="objective (default variance; gradient_magnitude with --flow)"
    )
    what.add_argument(
        "--reg",
        action="append",
        default=[],
        metavar="NAME=WEIGHT",
        help="an event-collapse regularizer (repeatable; its weight does not matter here)",
    )
    what.add_argument(
        "--sensor-size",
        type=int,
        nargs=2,
        action="append",
        default=None,
        metavar=("W", "H"),
        help="the sensor of the --warp configurations (repeatable; default 240 180)",
    )
    what.add_argument("--blur", type=float, default=1.0, help="Gaussian blur sigma, px (default 1)")
    what.add_argument("--polarity", default="ignore", help="ignore | signed | split (default ignore)")
    what.add_argument("--weights", action="store_true", help="problems with per-event vote weights")
    what.add_argument(
        "--examples", action="store_true", help="every configuration the README's --example commands run"
    )
    cache = parser.add_argument_group("the cache")
    cache.add_argument("--list", action="store_true", help="the cache folder, its size and what it holds")
    cache.add_argument(
        "--clear", action="store_true", help="delete the cache folder (every compiled kernel)"
    )
    common.add_backend_arguments(parser, compile_mode=False)
    common.add_plugin_argument(parser)


def _example_configs(tiers) -> list:
    """The configurations of ``estimate --example`` (each example's warp, without and, where the warp can
    collapse, with both regularizers) and of ``flow --example``."""
    import cmax_taichi as cm
    from cmax_taichi.sim.examples import EXAMPLES

    configs = []
    for example in EXAMPLES.values():
        size = example.sensor_size
        configs.append(tiers.config_for(warp=example.warp, sensor_size=size))
        if cm.get_warp(example.warp).collapse_enabled:
            both = ("divergence", "deformation")
            configs.append(tiers.config_for(warp=example.warp, regularizers=both, sensor_size=size))
    configs.append(tiers.config_for(warp=None, **FLOW_DEFAULTS, regularizers=_flow_regularizers()))
    return configs


def _flow_regularizers() -> tuple:
    """The event-collapse regularizers of the dense flow's defaults, in their order."""
    from cmax_taichi.flow.problem import split_regularizers
    from cmax_taichi.flow.solver import DEFAULT_REGULARIZERS

    maps, _ = split_regularizers(DEFAULT_REGULARIZERS)
    return tuple(maps)


def _clear_cache(records: Path) -> None:
    """Delete the compiled kernels (Taichi's own cleaner: its cache files only) and cmax-taichi's records
    of them, ``records``; whatever else the cache folder holds (it may be any folder the user named in
    TI_OFFLINE_CACHE_FILE_PATH) is left in place and said."""
    from taichi._lib import core as ti_core

    folder = records.parent
    n_files = ti_core.clean_offline_cache_files(str(folder.resolve())) if folder.is_dir() else 0
    if records.is_dir():
        shutil.rmtree(records)
    others = sorted(folder.iterdir()) if folder.is_dir() else []
    kept = f"; kept {len(others)} other item(s) there (not kernels), e.g. {others[0].name}" if others else ""
    if folder.is_dir() and not others:
        folder.rmdir()
    print(f"cleared the kernel cache {folder} ({n_files} compiled kernel file(s)){kept}")


def run(args: argparse.Namespace) -> int:
    from cmax_taichi.cli import CliError
    from cmax_taichi.pipeline import tiers

    common.init_backend(args.arch, args.precision)
    if args.clear:
        _clear_cache(tiers.cache_folder())
        return 0
    if args.list:
        print(tiers.cache_summary())
        for config, record in tiers.ready_records():
            seconds, finished = record.get("seconds", "?"), record.get("finished", "")
            print(f"  {config.describe()}: {seconds} s to compile ({finished})")
        return 0
    regs = tuple(common.parse_regularizers(args.reg))
    configs = _example_configs(tiers) if args.examples else []
    if args.flow:
        objective = args.objective or FLOW_DEFAULTS["objective"]
        configs.append(
            tiers.config_for(
                warp=None, objective=objective, regularizers=regs or _flow_regularizers(),
                blur_sigma=args.blur, polarity=args.polarity, weighted=args.weights,
                references=args.references,
            )  # fmt: skip
        )
    for warp in args.warp:
        for size in args.sensor_size or [(240, 180)]:
            configs.append(
                tiers.config_for(
                    warp=warp, objective=args.objective or "variance", regularizers=regs,
                    blur_sigma=args.blur, polarity=args.polarity, weighted=args.weights, sensor_size=size,
                )  # fmt: skip
            )
    if not configs:
        raise CliError("nothing to compile: name --warp NAME, --flow or --examples (or --list, --clear)")
    failed = 0
    for record in tiers.compile_configs(configs):
        config = record["config"]
        if record["status"] == "ready":
            print(f"{config.describe()}: already compiled")
        elif record["status"] == "compiled":
            print(f"{config.describe()}: compiled in {record['seconds']:.1f} s")
        else:
            failed += 1
            print(f"{config.describe()}: failed ({record.get('reason', 'see above')})")
    print(tiers.cache_summary())
    return 1 if failed else 0
