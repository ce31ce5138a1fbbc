"""Checks of user-given arguments shared by the containers, the readers and the sequence driver, and
the planning of windows by time (bounded, so that a tiny window cannot step through billions of
empty windows).

Every check raises one error that names the argument and the value: TypeError for a value of the
wrong type (a string, None, a complex number, a bool where a count is meant), ValueError for a value
of the right type outside its domain (negative, non-finite, not a whole number).
"""

from __future__ import annotations

import math
import numbers
import warnings
from collections.abc import Callable, Iterator

import numpy as np

__all__ = [
    "MAX_TIME_WINDOWS",
    "MIN_EVENTS_PER_WINDOW",
    "MAX_ABS_WEIGHT",
    "EventsDroppedWarning",
    "OptimizerStallWarning",
    "sensor_size",
    "whole_number",
    "seconds",
    "vote_weights",
    "warn_dropped",
    "UndistortionTally",
    "time_windows",
]

#: the most windows :func:`time_windows` plans over one recording (``max_windows=`` overrides it)
MAX_TIME_WINDOWS = 10_000_000
#: a window by time must expect at least this many events on average (``duration / mean spacing``):
#: shorter windows are nearly all empty, which is a mistake of units rather than a request
MIN_EVENTS_PER_WINDOW = 1e-3
#: the largest per-event vote weight: the image of warped events sums weights and its variance their
#: squares, which must stay finite in float32 (3.4e38) for windows of millions of events; only the ratios
#: of the weights matter to a normalised objective, so larger weights are refused, not clipped
MAX_ABS_WEIGHT = 1e9


class EventsDroppedWarning(RuntimeWarning):
    """Events were dropped (outside the sensor, or lost by undistortion); the message gives the counts."""


class OptimizerStallWarning(RuntimeWarning):
    """An optimizer ended where it started without converging, and its fallback did not move it either
    (a level of the dense flow, a local run of :func:`cmax_taichi.maximize`); the message says which."""


class IdentityEstimateWarning(RuntimeWarning):
    """Windows of a sequence were estimated at the identity warp exactly: they may hold too little
    motion to be estimated (the message gives the count and what to change)."""


def _is_real_number(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def flag(name: str, value) -> bool:
    """``value`` as a bool, refusing anything but True and False (a string such as ``"no"`` would read
    as True): TypeError naming ``name``."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def whole_number(name: str, value, minimum: int = 0) -> int:
    """``value`` as an int, refusing what is not a whole number ``>= minimum``.

    Accepts ints and integral floats (``3.0``). Raises TypeError for a non-number (None, a string, a
    bool, a complex) and ValueError for a fraction, a non-finite value or a value below ``minimum``.
    """
    if not _is_real_number(value):
        raise TypeError(f"{name} must be a whole number, got {value!r} ({type(value).__name__})")
    if not math.isfinite(value):
        raise ValueError(f"{name} must be a finite whole number, got {value!r}")
    if value != math.floor(value):
        raise ValueError(f"{name} must be a whole number, got {value!r}")
    number = int(value)
    if number < minimum:
        raise ValueError(f"{name} must be at least {minimum}, got {number}")
    return number


def seconds(name: str, value, positive: bool = False) -> float:
    """``value`` as a finite float (seconds); with ``positive``, also ``> 0``.

    Raises TypeError for a non-number and ValueError for NaN, an infinity or (``positive``) a value
    ``<= 0``."""
    if not _is_real_number(value):
        raise TypeError(f"{name} must be a number of seconds, got {value!r} ({type(value).__name__})")
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"{name} must be a finite number of seconds, got {number}")
    if positive and not number > 0:
        raise ValueError(f"{name} must be a positive number of seconds, got {number}")
    return number


def real_array(values, name: str, readable_as: str, real_what: str) -> np.ndarray:
    """``np.asarray(values)``, checked to hold no complex value.

    ValueError when ``values`` cannot be read as an array (ragged nested lists and the like: "``name``
    cannot be read as ``readable_as``"); TypeError for complex values, whose imaginary part a cast
    would drop without a word ("``real_what`` must be real")."""
    try:
        arr = np.asarray(values)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} cannot be read as {readable_as} ({exc})") from None
    if np.iscomplexobj(arr):
        raise TypeError(f"{name} has complex values (dtype {arr.dtype}); {real_what} must be real")
    return arr


def check_finite(arr: np.ndarray, name: str) -> None:
    """ValueError naming how many values of ``arr`` are NaN or infinite."""
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise ValueError(f"{name} has {bad} non-finite value(s) (NaN or inf)")


def vote_weights(values, n_events: int, name: str = "weights") -> np.ndarray:
    """Per-event vote weights as a float64 array of ``n_events`` values.

    Raises TypeError for values that are not real numbers (strings, even numeric ones, objects,
    complex values: the imaginary part is never dropped silently, datetimes), ValueError for another
    count, a NaN or an infinity, or a magnitude above :data:`MAX_ABS_WEIGHT`."""
    arr = real_array(values, name, "a numeric array", "vote weights")
    if arr.dtype.kind not in "biuf":
        raise TypeError(f"{name} must be real numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64).reshape(-1)
    if arr.size != n_events:
        raise ValueError(f"{name} has {arr.size} values for {n_events} events")
    check_finite(arr, name)
    largest = float(np.max(np.abs(arr))) if arr.size else 0.0
    if largest > MAX_ABS_WEIGHT:
        raise ValueError(
            f"{name} up to {largest:g} in magnitude would overflow the image of warped events (at most "
            f"{MAX_ABS_WEIGHT:g}); rescale them: only their ratios matter to a normalised objective"
        )
    return arr


def sensor_size(value, where: str = "") -> tuple[int, int]:
    """``(W, H)`` as two positive ints, px.

    Integral floats (``240.0``) are accepted; a fraction (``240.5``) is refused rather than truncated.
    Raises ValueError for anything but a pair, a non-finite, fractional or non-positive size, and
    TypeError for a size that is not a number. ``where`` (e.g. a file name) prefixes the message.
    """
    prefix = f"{where}: " if where else ""
    try:
        pair = tuple(value)
    except TypeError:
        pair = None
    if pair is None or len(pair) != 2 or isinstance(value, (str, bytes)):
        raise ValueError(
            f"{prefix}sensor_size must be a pair (W, H) of positive integers (px), got {value!r}"
        )
    out = []
    for label, v in zip("WH", pair, strict=True):
        if not _is_real_number(v):
            raise TypeError(
                f"{prefix}sensor_size {label} must be an integer number of pixels, "
                f"got {v!r} ({type(v).__name__})"
            )
        if not math.isfinite(v):
            raise ValueError(f"{prefix}sensor_size {label} must be finite, got {v!r}")
        if v != math.floor(v):
            raise ValueError(f"{prefix}sensor_size {label} = {v!r} is not a whole number of pixels")
        out.append(int(v))
    W, H = out
    if W <= 0 or H <= 0:
        raise ValueError(f"{prefix}sensor_size must be positive, got (W, H) = ({W}, {H})")
    return W, H


def warn_dropped(n_dropped: int, n_total: int, why: str, stacklevel: int = 2) -> None:
    """The one warning for dropped events: ``dropped N of M event(s) <why>`` as an
    :class:`EventsDroppedWarning` (a RuntimeWarning). Nothing when ``n_dropped`` is 0."""
    if n_dropped:
        warnings.warn(
            f"dropped {n_dropped} of {n_total} event(s) {why}",
            EventsDroppedWarning,
            stacklevel=stacklevel + 1,
        )


class UndistortionTally:
    """Events lost by undistortion over the windows: the first lossy window warns with its own counts
    (from :meth:`~cmax_taichi.Events.undistort`), later ones are held back (a real calibration drops
    a share of every window) and :meth:`report` gives the totals once.

    Use it inside ``warnings.catch_warnings()``: :meth:`add` installs the filter that holds the later
    warnings back, and leaving the block removes it."""

    _MESSAGE = r"dropped \d+ of \d+ event\(s\) in undistortion"

    def __init__(self) -> None:
        self.windows = self.dropped = self.events = 0

    def add(self, window, used) -> None:
        """Count ``window`` (the events read) and what undistortion dropped from it (``used``, the
        undistorted events, or ``window`` itself when nothing was undistorted)."""
        self.events += len(window)
        if used is not window and used.n_dropped:
            self.windows += 1
            self.dropped += used.n_dropped
            warnings.filterwarnings("ignore", message=self._MESSAGE, category=EventsDroppedWarning)

    def report(self) -> None:
        """The warning with the totals, when more than one window lost events."""
        if self.windows > 1:
            warn_dropped(
                self.dropped,
                self.events,
                f"in undistortion over {self.windows} windows (the first window's warning has the details)",
                stacklevel=3,
            )


def time_windows(
    t_first: float,
    t_last: float,
    n_events: int,
    duration,
    stride,
    search: Callable[[float], int],
    time_at: Callable[[int], float],
    max_windows: int | None = None,
) -> Iterator[tuple[int, int]]:
    """Index ranges ``(i0, i1)`` of the non-empty windows ``[t_first + k * stride, + duration)``.

    Validates ``duration`` and ``stride`` (seconds, default stride = duration) before yielding
    anything: ValueError when a window would expect fewer than :data:`MIN_EVENTS_PER_WINDOW` events
    (``duration`` far below the mean event spacing) or when there would be more than ``max_windows``
    (default :data:`MAX_TIME_WINDOWS`) windows. Runs of empty windows are jumped over with one search,
    so the cost grows with the non-empty windows only.

    Parameters
    ----------
    t_first, t_last : float
        Time of the first and the last event, s.
    n_events : int
        Number of events.
    duration, stride : float
        Window length and start-to-start step, s.
    search : callable
        ``search(t)``: index of the first event with time ``>= t`` (``n_events`` if none).
    time_at : callable
        ``time_at(i)``: time of event ``i``, s.
    max_windows : int, optional
        The bound on the window count.
    """
    duration = seconds("duration", duration, positive=True)
    step = duration if stride is None else seconds("stride", stride, positive=True)
    limit = MAX_TIME_WINDOWS if max_windows is None else whole_number("max_windows", max_windows, 1)
    if n_events == 0:
        return
    span = float(t_last - t_first)
    if n_events > 1 and span > 0:
        spacing = span / (n_events - 1)
        if duration / spacing < MIN_EVENTS_PER_WINDOW:
            raise ValueError(
                f"duration = {duration:g} s is below {MIN_EVENTS_PER_WINDOW:g} x the mean event spacing "
                f"({spacing:.3g} s over {n_events} events): nearly every window would be empty "
                f"(seconds expected; at least {spacing * MIN_EVENTS_PER_WINDOW:.3g} s)"
            )
    ratio = span / step  # infinite for a stride of a few denormals: more windows than any limit
    count = math.floor(ratio) + 1 if math.isfinite(ratio) else math.inf
    if count > limit:
        raise ValueError(
            f"windows of {duration:g} s starting every {step:g} s over the events' {span:.6g} s would be "
            f"{count:.4g} windows, more than the limit of {limit} "
            f"(cmax_taichi.core.checks.MAX_TIME_WINDOWS); choose a stride of at least "
            f"{span / (limit - 1) if limit > 1 else span:.3g} s"
        )
    k = 0
    while k <= count:  # (one more than the count: span / step may round below a whole number)
        start = t_first + k * step
        if start > t_last:
            return
        i0 = search(start)
        if i0 >= n_events:
            return
        i1 = search(start + duration)
        if i1 > i0:
            yield i0, i1
            k += 1
            continue
        # empty: jump to the last window start that still ends at or before the next event (at most
        # one more empty probe, so rounding never skips a window that holds it)
        t_next = float(time_at(i0))
        k = max(k + 1, math.floor((t_next - duration - t_first) / step))
