"""Arguments and checks that several sub-commands share.

Every list of names in a help text comes from where the names are defined: the warp, objective and
regularizer registries (``cm.warp_names()``, ``cm.objective_names()``, ``cm.regularizer_names()``, with
each warp's parameters and units), the readers (``cmax_taichi.io.FORMATS``), the backends
(``cmax_taichi.core.backend.ARCHS``) and the optimizer (``METHODS``, ``INITS``). A model registered at
run time shows up in the help without a change here: ``--plugin FILE.py`` (or a module name), on every
sub-command that reads the registries, is imported by :func:`load_plugins` before the parser (and its
help) is built.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import warnings
from collections.abc import Iterator

from cmax_taichi.core.backend import ARCHS, COMPILE_MODES
from cmax_taichi.io import FORMATS
from cmax_taichi.models.objectives import objective_names
from cmax_taichi.models.regularizers import regularizer_names
from cmax_taichi.models.warps import get_warp, warp_names

#: events per window of the count windows when --window is not given
DEFAULT_WINDOW_EVENTS = 30000

__all__ = [
    "PLUGIN_HELP",
    "T_REF_NAMES",
    "add_plugin_argument",
    "add_sensor_size_argument",
    "load_plugins",
    "names",
    "warp_listing",
    "add_recording_arguments",
    "add_t_ref_argument",
    "add_window_arguments",
    "check_windows",
    "why_no_window",
    "window_stride",
    "add_backend_arguments",
    "init_backend",
    "parse_regularizers",
    "parse_t_ref",
]

#: the named reference times of a window (a number of seconds is accepted too)
T_REF_NAMES = ("first", "middle", "last")

PLUGIN_HELP = (
    "a Python file (or module) that registers warps, objectives or regularizers, imported before anything "
    "else (repeatable; e.g. --plugin examples/user_extensions.py; docs/RECIPE_WARP.md)"
)


def add_plugin_argument(parser) -> None:
    """``--plugin FILE.py|MODULE`` (repeatable), on a parser or an argument group. :func:`load_plugins`
    imports them before the parser is built; this declaration documents them and accepts them."""
    parser.add_argument("--plugin", action="append", default=[], metavar="FILE.py|MODULE", help=PLUGIN_HELP)


SENSOR_SIZE_HELP = (
    "sensor size in px, for text files without one (default: the format's or the reader's guess)"
)


def add_sensor_size_argument(parser, help: str = SENSOR_SIZE_HELP) -> None:
    """``--sensor-size W H`` (px, integers; default None: the format's)."""
    parser.add_argument("--sensor-size", type=int, nargs=2, default=None, metavar=("W", "H"), help=help)


def load_plugins(argv: list[str]) -> list[str]:
    """Import every ``--plugin`` of the command line ``argv`` (wherever it stands), before the parser
    whose help lists the registries is built; returns them. CliError naming the plugin when one cannot
    be imported."""
    from cmax_taichi.cli import CliError
    from cmax_taichi.core.registry import PluginError, load_plugin

    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    pre.add_argument("--plugin", action="append", default=[])
    known, _ = pre.parse_known_args(argv)
    for plugin in known.plugin:
        try:
            load_plugin(plugin)
        except PluginError as exc:
            raise CliError(f"--plugin: {exc}") from None
    return known.plugin


def names(values) -> str:
    """``"a | b | c"``: the choices of an option, for its help text."""
    return " | ".join(values)


def warp_listing() -> str:
    """Every registered warp with its parameters and units, e.g. ``zoom1 (h_z [1/s])``; the warps that
    need a calibration say so."""
    parts = []
    for name in warp_names():
        model = get_warp(name)
        params = ", ".join(f"{p} [{u}]" for p, u in zip(model.params, model.units, strict=True))
        needs = "; needs a calibration" if model.needs_camera else ""
        parts.append(f"{name} ({params}{needs})")
    return ", ".join(parts)


def add_recording_arguments(
    parser: argparse.ArgumentParser,
    *,
    warp_default: str,
    warp_help: str,
    reg_help: str,
    sensor_size: bool = False,
    path_nargs: str | None = None,
    path_note: str = "",
    examples: dict | None = None,
) -> None:
    """The recording and model arguments of ``estimate`` and ``segment``: ``PATH``, ``--format``
    (``--sensor-size``), ``--warp``, ``--objective``, the repeatable ``--reg NAME=WEIGHT`` and
    ``--plugin``.

    Parameters
    ----------
    warp_default : str
        Default of ``--warp``.
    warp_help : str
        What ``--warp`` means for this command; the list of registered warps and the default follow it.
    reg_help : str
        What ``--reg`` means for this command; the registered regularizers follow it.
    sensor_size : bool
        Also declare ``--sensor-size W H`` (for text files without a size).
    path_nargs : str, optional
        ``nargs`` of ``PATH`` (e.g. ``"?"`` when ``--example`` can replace it, ``"*"`` for several).
    path_note : str
        Appended to the help of ``PATH``.
    examples : dict, optional
        Name -> example (``cmax_taichi.sim.examples``): declare ``--example NAME`` instead of ``PATH``.
        ``--warp`` then defaults to None, to be resolved as the example's model or ``warp_default``.
    """
    path_kwargs = {} if path_nargs is None else {"nargs": path_nargs, "default": None}
    parser.add_argument(
        "path",
        metavar="PATH",
        help="recording: an ECD folder or events.txt, MVSEC *_data.hdf5, DSEC events.h5, *.aedat4, "
        "Prophesee *.raw / *.dat, Event Stream *.es, a ROS1 *.bag or ROS2 bag folder" + path_note,
        **path_kwargs,
    )
    if examples is not None:
        parser.add_argument(
            "--example",
            default=None,
            metavar="NAME",
            help="instead of PATH, a recording simulated on the fly (fixed seed, exact truth), run and "
            "printed against the truth: " + "; ".join(f"{n}: {e.description}" for n, e in examples.items()),
        )
    parser.add_argument("--format", default=None, help=f"{names(FORMATS)} (default: detected)")
    if sensor_size:
        add_sensor_size_argument(parser)
    example_note = ", or the example's model" if examples is not None else ""
    parser.add_argument(
        "--warp",
        default=None if examples is not None else warp_default,
        help=f"{warp_help}; models: {warp_listing()} "
        f"(default {warp_default}{example_note}; 'cmax-taichi info' describes them)",
    )
    parser.add_argument(
        "--objective", default="variance", help=f"{names(objective_names())} (default variance)"
    )
    parser.add_argument(
        "--reg",
        action="append",
        default=[],
        metavar="NAME=WEIGHT",
        help=f"{reg_help} (repeatable; NAME: {names(regularizer_names())})",
    )
    add_plugin_argument(parser)


def add_window_arguments(parser):
    """The group "windows" of a pass over a recording: ``--window`` (events, default 30000),
    ``--duration``, ``--stride``, ``--max-windows`` and ``--keep-tail``; returns it for the command's own
    window options. :func:`check_windows` checks them."""
    win = parser.add_argument_group("windows")
    win.add_argument(
        "--window", type=int, default=None, metavar="N", help="events per window (default 30000)"
    )
    win.add_argument(
        "--duration", type=float, default=None, metavar="S", help="window length in seconds instead"
    )
    win.add_argument(
        "--stride", type=float, default=None, help="start-to-start step (events, or s with --duration)"
    )
    win.add_argument("--max-windows", type=int, default=None, metavar="K", help="stop after K windows")
    win.add_argument(
        "--keep-tail",
        action="store_true",
        help="also estimate the partial last window (count windows) when it holds at least half a window",
    )
    return win


def check_windows(args: argparse.Namespace) -> None:
    """The options of :func:`add_window_arguments`, before any data is read (CliError)."""
    from cmax_taichi.cli import CliError

    args.window_given = args.window is not None  # (adaptive windows refuse it: they choose their length)
    if args.window is None:
        args.window = DEFAULT_WINDOW_EVENTS
    if args.window < 2:
        raise CliError(f"--window must be at least 2 events, got {args.window}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise CliError(f"--duration must be a positive number of seconds, got {args.duration}")
    if args.stride is not None:
        if args.duration is not None:
            if not (math.isfinite(args.stride) and args.stride > 0):
                raise CliError(f"--stride must be a positive number of seconds, got {args.stride:g}")
        elif not (math.isfinite(args.stride) and args.stride >= 1 and args.stride == math.floor(args.stride)):
            raise CliError(
                f"--stride must be a whole number of events >= 1 (or seconds with --duration), "
                f"got {args.stride:g}"
            )
    if args.max_windows is not None and args.max_windows < 1:
        raise CliError(f"--max-windows must be at least 1, got {args.max_windows}")


def window_stride(args: argparse.Namespace):
    """``--stride`` as the windows take it: events (an int) for count windows, seconds with ``--duration``."""
    if args.stride is None:
        return None
    return args.stride if args.duration is not None else int(args.stride)


def why_no_window(args: argparse.Namespace, events: dict) -> str:
    """Why a pass estimated no window, from its event accounting (``SequenceResult.events``, or
    ``FlowPass.events``), in the terms of the options the user gave."""
    from cmax_taichi.core.windows import min_tail_events

    total = events.get("total", 0)
    if total == 0:
        return "the recording has no events"
    if getattr(args, "window_mode", None) == "adaptive":
        from cmax_taichi.cli import _live

        first = _live.window_rule(args)[0].first_events
        return (
            f"{total} events; no adaptive window was estimated (the first takes {first} events; --keep-tail "
            "estimates what there is as one window)"
        )
    if args.duration is None and total < args.window:
        least = min_tail_events(args.window)
        hint = (
            f"--keep-tail estimates a shorter window of {total} events"
            if total >= least
            else f"choose a smaller --window (--keep-tail needs at least {least} events)"
        )
        return f"{total} events, fewer than one window of --window {args.window}: {hint}"
    windows = events.get("windows", {})
    mode = f"--duration {args.duration:g} s" if args.duration is not None else f"--window {args.window}"
    reasons = ", ".join(f"{n} {status.replace('_', ' ')}" for status, n in windows.items() if n)
    return f"{total} events; no window of {mode} holds 2 events spanning a positive time ({reasons})"


def add_t_ref_argument(parser) -> None:
    """``--t-ref`` (default ``first``), on a parser or an argument group; read it with :func:`parse_t_ref`."""
    parser.add_argument(
        "--t-ref",
        default="first",
        help=f"reference time: {names(T_REF_NAMES)} (of each window) or seconds on the recording's clock "
        "(one window only, within its span give or take its duration) (default first)",
    )


COMPILE_HELP = (
    "how the kernels compile on first use: auto (quick kernels at once, the optimized ones compiled in "
    "the background and taken over when ready), full (wait for the optimized kernels: benchmarks), fast "
    "(quick kernels only) (default $CMAX_TAICHI_COMPILE or auto)"
)


def add_backend_arguments(parser, *, precision: bool = True, compile_mode: bool = True) -> None:
    """``--arch`` (and ``--precision``, ``--compile``) of the Taichi backend, on a parser or an argument
    group."""
    parser.add_argument("--arch", default=None, help=f"{names(ARCHS)} (default $CMAX_TAICHI_ARCH or cpu)")
    if precision:
        parser.add_argument(
            "--precision", default=None, choices=["f32", "f64"], help="default f64 on cpu, f32 on gpu"
        )
    if compile_mode:
        parser.add_argument("--compile", default=None, choices=COMPILE_MODES, help=COMPILE_HELP)


def init_backend(arch: str | None, precision: str | None, compile_mode: str | None = None):
    """:func:`cmax_taichi.core.backend.init_if_needed` (kept under this name for the commands)."""
    from cmax_taichi.core import backend

    return backend.init_if_needed(arch, precision, compile_mode)


def parse_regularizers(items: list[str], extra: tuple[str, ...] | list[str] = ()) -> dict[str, float]:
    """``["divergence=1", ...]`` -> ``{"divergence": 1.0}`` (CliError on bad syntax or names); ``extra``:
    more valid names (the dense flow's smoothness terms)."""
    from cmax_taichi.cli import CliError
    from cmax_taichi.pipeline.setup import MAX_REGULARIZER_WEIGHT

    valid = regularizer_names() + list(extra)
    out: dict[str, float] = {}
    for item in items:
        name, sep, weight = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise CliError(f"--reg expects NAME=WEIGHT (e.g. divergence=1), got {item!r}")
        if name not in valid:
            raise CliError(f"--reg: unknown regularizer {name!r}; valid: {', '.join(valid)}")
        try:
            value = float(weight)
        except ValueError:
            raise CliError(f"--reg {name}: weight must be a number, got {weight!r}") from None
        if not (math.isfinite(value) and value >= 0):
            raise CliError(f"--reg {name}: weight must be finite and >= 0, got {weight!r}")
        if value > MAX_REGULARIZER_WEIGHT:
            raise CliError(
                f"--reg {name}: weight {weight} is above {MAX_REGULARIZER_WEIGHT:g} (the data term would "
                "vanish in the rounding of the penalty)"
            )
        out[name] = value
    return out


def parse_t_ref(text: str) -> str | float:
    """``--t-ref``: one of :data:`T_REF_NAMES`, or seconds (CliError otherwise)."""
    from cmax_taichi.cli import CliError

    if text in T_REF_NAMES:
        return text
    try:
        return float(text)
    except ValueError:
        raise CliError(f"--t-ref must be first, middle, last or seconds, got {text!r}") from None


@contextlib.contextmanager
def held_drop_warnings() -> Iterator[list]:
    """Hold the warnings that count events not estimated (``EventsDroppedWarning``) until the pass is
    over; the other warnings show as they come. Yields the held ones: show them with
    :func:`show_warnings` when the pass estimated something, or drop them when the command ends in its
    one error line instead (which says why no window was estimated, with the counts)."""
    from cmax_taichi.core.checks import EventsDroppedWarning

    held: list[tuple] = []
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        if issubclass(category, EventsDroppedWarning):
            held.append((message, category, filename, lineno, file, line))
        else:
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        yield held
    finally:
        warnings.showwarning = shown


def show_warnings(held: list[tuple]) -> None:
    """Show the warnings :func:`held_drop_warnings` held."""
    for record in held:
        warnings.showwarning(*record)
