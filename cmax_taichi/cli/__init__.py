"""The ``cmax-taichi`` command: a thin dispatcher over the sub-command modules of
``cmax_taichi/cli/``.

Each sub-command module defines ``NAME``, ``HELP`` and ``add_arguments(parser)`` / ``run(args) -> int``,
and is listed explicitly in ``COMMAND_MODULES``. A command line that names its sub-command imports that
module only (the others import what their options list: the lab's experiments, the benchmark, ...); the
full parser serves ``cmax-taichi``, ``--help`` and an unknown command. Errors a user can cause (bad
paths, unknown formats, bad values) are raised as :class:`CliError` or ValueError / OSError / KeyError
and printed as one line with exit code 2, never a traceback. Warnings (events not estimated, ...) are
printed as one line each, ``cmax-taichi COMMAND: warning: ...``. Ctrl-C ends a command with exit code
130 and SIGTERM with 143, both the same way (the outputs are left as they were: see
:mod:`cmax_taichi.io.outputs`). ``--plugin FILE.py`` anywhere on the line is imported first (the user's
warps, objectives and regularizers then appear in every help and choice).
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import importlib
import logging
import os
import signal
import sys
import threading
import warnings
from typing import NoReturn

#: explicit list of sub-command modules (cmax_taichi.cli.<name>)
COMMAND_MODULES = ("info", "estimate", "flow", "evaluate", "segment", "reproduce", "bench", "warmup")


class CliError(Exception):
    """An error caused by the user's input: printed as one line, exit code 2."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that it unwinds as Ctrl-C does (exit code 143)."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


class _StatusLines(logging.Handler):
    """The library's status messages (``cmax_taichi.compile``: which kernels compile, for how long) as
    lines ``cmax-taichi COMMAND: ...`` on stderr, above a progress bar if one is drawn."""

    def __init__(self, command: str) -> None:
        super().__init__(logging.INFO)
        self.command = command

    def emit(self, record: logging.LogRecord) -> None:
        line = f"cmax-taichi {self.command}: {record.getMessage()}"
        if "tqdm" in sys.modules:  # a bar may be on the line: tqdm clears and redraws it
            from tqdm import tqdm

            tqdm.write(line, file=sys.stderr)
        else:
            print(line, file=sys.stderr, flush=True)


@contextlib.contextmanager
def _command_signals_and_warnings(command: str):
    """For the length of a command: SIGTERM handled as SIGINT is, each warning as one line, and the
    library's status messages as lines of their own."""
    previous_term = None
    with contextlib.suppress(ValueError):  # not the main thread: leave the signals alone
        previous_term = signal.signal(signal.SIGTERM, _raise_terminated)
    previous_show = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = str(message).replace("\n", " ")
        print(f"cmax-taichi {command}: warning: {text}", file=file or sys.stderr)

    warnings.showwarning = show
    status = logging.getLogger("cmax_taichi.compile")
    handler, previous_level = _StatusLines(command), status.level
    status.addHandler(handler)
    status.setLevel(logging.INFO)
    try:
        yield
    finally:
        status.removeHandler(handler)
        status.setLevel(previous_level)
        warnings.showwarning = previous_show
        if previous_term is not None:
            signal.signal(signal.SIGTERM, previous_term)


def _version() -> str:
    """The installed package's version (without importing the library and Taichi)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("cmax-taichi")
    except PackageNotFoundError:
        return "(not installed)"


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The command's parser: every sub-command, or the one called ``only`` (a name of
    :data:`COMMAND_MODULES`)."""
    parser = argparse.ArgumentParser(
        prog="cmax-taichi",
        description=(
            "Contrast Maximization for event cameras with the event-collapse regularizers "
            "(Shiba, Aoki, Gallego, Sensors 2022). Run 'cmax-taichi COMMAND --help' for a command."
        ),
    )
    parser.add_argument("--version", action="version", version=f"cmax-taichi {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES if only is None else (only,):
        module = importlib.import_module(f"cmax_taichi.cli.{name}")
        p = sub.add_parser(module.NAME, help=module.HELP, description=module.__doc__)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def _plugins_after_the_command(args_list: list[str]) -> list[str]:
    """``cmax-taichi --plugin F.py estimate ...`` as ``cmax-taichi estimate --plugin F.py ...``: the
    option belongs to the sub-commands (already imported by :func:`load_plugins`)."""
    command = next((i for i, a in enumerate(args_list) if a in COMMAND_MODULES), None)
    if command is None:
        return args_list
    before, moved, i = [], [], 0
    while i < command:
        if args_list[i] == "--plugin" and i + 1 < command:
            moved += args_list[i : i + 2]
            i += 2
            continue
        (moved if args_list[i].startswith("--plugin=") else before).append(args_list[i])
        i += 1
    return before + [args_list[command]] + moved + args_list[command + 1 :]


def main(argv: list[str] | None = None) -> int:
    args_list = sys.argv[1:] if argv is None else list(argv)
    if any(a == "--plugin" or a.startswith("--plugin=") for a in args_list):
        try:  # the user's extensions first: the parser's help lists the registries
            from cmax_taichi.cli._common import load_plugins

            load_plugins(args_list)
        except CliError as exc:
            print(f"cmax-taichi: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:  # Ctrl-C while a plugin loads (it leaves nothing registered)
            print("cmax-taichi: interrupted", file=sys.stderr)
            return 130
        args_list = _plugins_after_the_command(args_list)
    named = args_list[0] if args_list and args_list[0] in COMMAND_MODULES else None
    parser = build_parser(named)
    args = parser.parse_args(args_list)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        with _command_signals_and_warnings(args.command):
            return int(args._run(args) or 0)
    except Terminated:
        print("cmax-taichi: terminated (SIGTERM)", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("cmax-taichi: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader of the output went away (| head): nothing to say to it
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except (CliError, ValueError, TypeError, OSError, KeyError, MemoryError, ImportError) as exc:
        # ImportError: an optional package a format needs (its message names the package and the install)
        message = str(exc) or type(exc).__name__
        if isinstance(exc, KeyError):
            message = f"missing key {message}"
        print(f"cmax-taichi {args.command}: error: {message}", file=sys.stderr)
        return 2


def console_main(argv: list[str] | None = None) -> NoReturn:
    """The ``cmax-taichi`` console script and ``python -m cmax_taichi.cli``: :func:`main`, then the
    process ends without the interpreter's teardown when nothing else runs in it.

    After the command, the outputs are committed and closed; what a normal exit still did was
    finalize Taichi's program (which writes the kernels compiled in this process to its offline
    cache) and run the ``atexit`` functions (multiprocessing's children, logging), both done here
    too, and then destroy every module and object, Taichi's C++ runtime and LLVM included: 0.3-0.8 s
    of each command's wall time on this project's 2-core machine. With another thread alive (a
    library's worker that a normal exit would join first), or under a profiler or tracer (``python -m
    cProfile``, a debugger: they write their results after the program returns), the exit is the
    normal one.
    """
    code = main(argv)
    if threading.active_count() > 1 or sys.getprofile() is not None or sys.gettrace() is not None:
        sys.exit(code)
    if "cmax_taichi.core.backend" in sys.modules:
        from cmax_taichi.core import backend

        backend.finish()  # the kernels compiled in this process into the offline cache
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed pipe or stream: nothing to flush
            stream.flush()
    os._exit(code)


if __name__ == "__main__":  # pragma: no cover
    console_main()
