"""The ``cmax-taichi`` command: a thin dispatcher over the sub-command modules of
``cmax_taichi/cli/``.

Each sub-command module defines ``NAME``, ``HELP`` and ``add_arguments(parser)`` / ``run(args) -> int``,
and is listed explicitly in ``COMMAND_MODULES``. Errors a user can cause (bad paths, unknown formats,
bad values) are raised as :class:`CliError` or ValueError / OSError / KeyError and printed as one line
with exit code 2, never a traceback. ``--plugin FILE.py`` anywhere on the line is imported first (the
user's warps, objectives and regularizers then appear in every help and choice).
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: explicit list of sub-command modules (cmax_taichi.cli.<name>)
COMMAND_MODULES = ("info", "estimate", "evaluate", "segment", "reproduce", "bench")


class CliError(Exception):
    """An error caused by the user's input: printed as one line, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cmax-taichi",
        description=(
            "Contrast Maximization for event cameras with the event-collapse regularizers "
            "(Shiba, Aoki, Gallego, Sensors 2022). Run 'cmax-taichi COMMAND --help' for a command."
        ),
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        module = importlib.import_module(f"cmax_taichi.cli.{name}")
        p = sub.add_parser(module.NAME, help=module.HELP, description=module.__doc__)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:  # the user's extensions first: the parser's help lists the registries
        from cmax_taichi.cli._common import load_plugins

        load_plugins(argv)
    except CliError as exc:
        print(f"cmax-taichi: error: {exc}", file=sys.stderr)
        return 2
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("cmax-taichi: interrupted", file=sys.stderr)
        return 130
    except (CliError, ValueError, TypeError, OSError, KeyError, MemoryError) as exc:
        message = str(exc) or type(exc).__name__
        if isinstance(exc, KeyError):
            message = f"missing key {message}"
        print(f"cmax-taichi {args.command}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
