"""Reproduce the paper's experiments (Shiba, Aoki, Gallego, Sensors 2022) on simulated MVSEC-like data
and the real ECD rotation cuts: Tables 1-3, the lambda sensitivity and the computational complexity.

Writes Markdown, CSV (and PNG plots) into --out and prints each table; progress goes to stderr.
See cmax_taichi/lab/experiments.py for the protocol. --out is never the data folder nor a folder that
holds it, files there that no cmax-taichi run wrote are never replaced, and the files appear in --out
when the whole run completes (an interrupted run leaves --out as it was).
"""

from __future__ import annotations

import argparse

from cmax_taichi.lab.experiments import EXPERIMENTS

NAME = "reproduce"
HELP = f"run the paper's experiments ({'|'.join(EXPERIMENTS)}|all)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("experiment", choices=[*EXPERIMENTS, "all"], help="which experiment")
    parser.add_argument("--out", required=True, help="output folder (created if needed)")
    parser.add_argument("--quick", action="store_true", help="small sizes: a smoke run of a few minutes")
    parser.add_argument(
        "--data",
        default=None,
        help="folder of the ECD rotation cuts for table3 (default: ../shared/data/ecd_rotation "
        "beside the checkout, or $CMAX_SHARED_DATA/ecd_rotation)",
    )
    parser.add_argument("--windows", type=int, default=None, help="evaluation intervals per preset")
    parser.add_argument(
        "--lam",
        type=float,
        default=None,
        help="regularizer weight of the tables (default: cmax_taichi.RECOMMENDED_LAMBDA)",
    )
    parser.add_argument("--seed", type=int, default=None, help="simulator seed (default 0)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars on stderr")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace
    from pathlib import Path

    from cmax_taichi.io.outputs import OutputFolder
    from cmax_taichi.lab.experiments import Settings, default_data_dir, reproduce

    settings = Settings.quick() if args.quick else Settings()
    changes = {}
    if args.windows is not None:  # checked by Settings (1 to MAX_INTERVALS)
        changes["windows"] = args.windows
        changes["sensitivity_windows"] = min(settings.sensitivity_windows, args.windows)
    if args.lam is not None:
        if not args.lam >= 0:
            raise ValueError(f"--lam must be >= 0, got {args.lam}")
        changes["lam"] = args.lam
    if args.seed is not None:
        changes["seed"] = args.seed
    settings = replace(settings, **changes)
    data_dir = Path(args.data) if args.data is not None else default_data_dir()
    names = EXPERIMENTS if args.experiment == "all" else (args.experiment,)
    patterns = [f"{name}.*" for name in names] + [f"run_{args.experiment}.json"]
    with OutputFolder(args.out, inputs=[data_dir], patterns=patterns, command="reproduce") as folder:
        staging = folder.staging
        written = reproduce(
            args.experiment,
            staging,
            quick=args.quick,
            data_dir=data_dir,
            settings=settings,
            progress=not args.no_progress,
        )
        folder.commit()  # every file moved into place whole, now that the run is complete
    for name, files in written.items():
        final = [folder.final(Path(f).relative_to(staging)) for f in files]
        print(f"{name}: " + ", ".join(str(f) for f in final))
    return 0
