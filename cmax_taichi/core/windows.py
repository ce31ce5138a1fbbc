"""Windows over a source's events as index spans, and the ledger that accounts for every event.

A pass of windows (:meth:`cmax_taichi.io.Recording.windows`, :func:`cmax_taichi.solve.sequence.process`)
is planned as :class:`Span` s, event index ranges ``[start, stop)`` of the source in time order, and
every event of the source ends in exactly one category of :data:`CATEGORIES`:

``estimated``
    in a window that was estimated (or, for ``Recording.windows``, given to the caller);
``outside_sensor``
    outside the sensor (undistorted coordinates a little off it, a rectification map's edge);
``undistortion``
    moved off the sensor by undistortion, or where the distortion model does not invert;
``partial_tail``
    in the last, shorter window of count windows, not estimated (``keep_tail=False``, or a tail below
    :func:`min_tail_events`);
``too_few_events``
    in a window of fewer than :data:`MIN_WINDOW_EVENTS` events (after the drops above);
``zero_duration``
    in a window whose events all share one timestamp;
``between_windows``
    in no window: a stride longer than the window leaves gaps;
``after_max_windows``
    after the last window that ``max_windows`` allowed.

A live stream (:func:`cmax_taichi.solve.online.run_live`) has four more, for events that never got a
place in a window (``EventLedger(stream=True)``, :meth:`EventLedger.drop`):

``late``
    earlier than an event that arrived before it (a late packet): dropped on arrival;
``malformed``
    a time or a coordinate that is not a finite number: dropped on arrival;
``behind``
    in a whole window skipped because the estimator had fallen behind the stream;
``after_stop``
    received, but not yet in a window when the run stopped (Ctrl-C, SIGTERM, a failed source).

So ``n_total == sum(counts.values())`` for any window size, stride, duration and gap (the property
``tests/test_input_properties.py`` checks). Overlapping windows (a stride below the window) count each
event once: it is ``estimated`` when any estimated window used it, else it takes the reason of the window
that came closest to using it (the order of :data:`CATEGORIES`, reversed). Drops by the sensor and by
undistortion depend on the event alone, so overlapping windows agree on them.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from cmax_taichi.core import checks
from cmax_taichi.core.checks import EventsDroppedWarning, whole_number
from cmax_taichi.core.events import Camera, Events

__all__ = [
    "CATEGORIES",
    "ESTIMATED",
    "ESTIMATED_STATUSES",
    "MIN_WINDOW_EVENTS",
    "BEHIND",
    "PARTIAL_TAIL",
    "SHORT_TAIL",
    "STATUSES",
    "STREAM_CATEGORIES",
    "TAIL_FRACTION",
    "TOO_FEW_EVENTS",
    "ZERO_DURATION",
    "EventLedger",
    "Span",
    "WindowPlan",
    "check_window_options",
    "count_spans",
    "estimable_windows",
    "min_tail_events",
    "plan_windows",
    "read_window",
    "time_spans",
    "window_status",
]

#: the fewest events a window needs to be estimated (after the drops)
MIN_WINDOW_EVENTS = 2
#: with ``keep_tail``, the partial tail of count windows is estimated when it holds at least this share of a
#: window (see :func:`min_tail_events`); a shorter tail is counted as ``partial_tail``
TAIL_FRACTION = 0.5

#: window statuses: estimated, and the reasons a window is not
ESTIMATED = "estimated"
SHORT_TAIL = "short_tail"  # the partial tail, estimated as a shorter window (keep_tail)
PARTIAL_TAIL = "partial_tail"
TOO_FEW_EVENTS = "too_few_events"
ZERO_DURATION = "zero_duration"
BEHIND = "behind"  # a live stream's window skipped because the estimator fell behind
ESTIMATED_STATUSES = (ESTIMATED, SHORT_TAIL)
STATUSES = (ESTIMATED, SHORT_TAIL, PARTIAL_TAIL, TOO_FEW_EVENTS, ZERO_DURATION)
#: the categories of a live stream's events that never got a place in a window (not event codes)
STREAM_CATEGORIES = ("late", "malformed", "behind", "after_stop")

#: where the events went; an event's code is its position here (higher codes win, see the module docstring)
CATEGORIES = (
    "between_windows",
    "partial_tail",
    "too_few_events",
    "zero_duration",
    "outside_sensor",
    "undistortion",
    "estimated",
)
_CODE = {name: code for code, name in enumerate(CATEGORIES)}
#: the category of the events of a window that is not estimated
_STATUS_CODE = {PARTIAL_TAIL: 1, TOO_FEW_EVENTS: 2, ZERO_DURATION: 3}
_AFTER = "after_max_windows"  # not an event code: only the remainder after a pass stopped by max_windows


@dataclass(frozen=True)
class Span:
    """One window of a pass: events ``start:stop`` of the source (time order).

    Attributes
    ----------
    index : int
        Window number (0-based, in the pass).
    start, stop : int
        Event index range.
    tail : bool
        The partial tail of count windows (fewer events than the others).
    keep : bool
        False for a partial tail that is counted, not estimated.
    """

    index: int
    start: int
    stop: int
    tail: bool = False
    keep: bool = True

    def __len__(self) -> int:
        return self.stop - self.start


def min_tail_events(n_events: int) -> int:
    """The fewest events a partial tail needs to be estimated with ``keep_tail``: ``ceil(TAIL_FRACTION *
    n_events)``, at least :data:`MIN_WINDOW_EVENTS` (15,000 for windows of 30,000 events)."""
    return max(MIN_WINDOW_EVENTS, math.ceil(TAIL_FRACTION * n_events))


def count_spans(n_total: int, n_events, stride=None, keep_tail: bool = False) -> Iterator[Span]:
    """The spans of windows of ``n_events`` events starting every ``stride`` events (default: no
    overlap) over ``n_total`` events, then the partial tail (the events from the next start to the
    end), marked ``keep`` when ``keep_tail`` and it holds at least :func:`min_tail_events`.

    ``n_events`` (>= 2) and ``stride`` (>= 1) are whole numbers, checked when this is called
    (TypeError / ValueError)."""
    n = whole_number("n_events", n_events, 2)
    step = n if stride is None else whole_number("stride (events)", stride, 1)
    return _count_spans(int(n_total), n, step, bool(keep_tail))


def _count_spans(n_total: int, n: int, step: int, keep_tail: bool) -> Iterator[Span]:
    index = start = 0
    while start + n <= n_total:
        yield Span(index, start, start + n)
        index += 1
        start += step
    if start < n_total:
        yield Span(index, start, n_total, tail=True, keep=keep_tail and n_total - start >= min_tail_events(n))


def time_spans(ranges: Iterator[tuple[int, int]]) -> Iterator[Span]:
    """The spans of the index ranges of :func:`~cmax_taichi.core.checks.time_windows`, numbered; the
    first range is taken now, so that the arguments are checked by this call."""
    first = next(ranges, None)
    return _numbered(first, ranges)


def _numbered(first, ranges) -> Iterator[Span]:
    if first is None:
        return
    yield Span(0, *first)
    for index, (i0, i1) in enumerate(ranges, start=1):
        yield Span(index, i0, i1)


def window_status(span: Span, n_used: int, duration: float) -> str:
    """The status of a window of ``n_used`` events spanning ``duration`` s (after the drops)."""
    if not span.keep:
        return PARTIAL_TAIL
    if n_used < MIN_WINDOW_EVENTS:
        return TOO_FEW_EVENTS
    if not duration > 0:
        return ZERO_DURATION
    return SHORT_TAIL if span.tail else ESTIMATED


def describe_events(events: dict, n_events: int | None = None, max_windows: int | None = None) -> str:
    """The counts of the events not estimated, by reason, with the remedies, for a message.

    Parameters
    ----------
    events : dict
        Counts per category as :meth:`EventLedger.as_dict` returns them (``SequenceResult.events``):
        a category or ``"windows"`` that is missing counts 0.
    n_events : int, optional
        Events per window of a pass of count windows: the partial tail's count then names
        ``keep_tail`` (``--keep-tail``) and whether it would keep it.
    max_windows : int, optional
        The limit that stopped the pass, named beside the events after its last window.

    Returns
    -------
    str
        ``"<count> <reason>, ..."``; empty when every event was estimated.
    """
    c = {name: events.get(name, 0) for name in (*CATEGORIES, _AFTER)}
    w = {**dict.fromkeys(STATUSES, 0), **events.get("windows", {})}
    parts = []
    if c["partial_tail"]:
        hint = ""
        if n_events is not None:
            least = min_tail_events(n_events)
            hint = (
                f" (keep_tail=True / --keep-tail keeps a tail of at least {least})"
                if c["partial_tail"] >= least
                else f" (shorter than the {least} that keep_tail=True / --keep-tail keeps)"
            )
        parts.append(f"{c['partial_tail']} in the partial last window{hint}")
    if c["outside_sensor"]:
        parts.append(f"{c['outside_sensor']} outside the sensor")
    if c["undistortion"]:
        parts.append(f"{c['undistortion']} lost in undistortion (the first such window's warning says why)")
    if c["too_few_events"]:
        parts.append(
            f"{c['too_few_events']} in {w[TOO_FEW_EVENTS]} window(s) of fewer than {MIN_WINDOW_EVENTS} events"
        )
    if c["zero_duration"]:
        parts.append(f"{c['zero_duration']} in {w[ZERO_DURATION]} window(s) whose events share one time")
    if c["between_windows"]:
        parts.append(f"{c['between_windows']} between windows (a stride longer than the window)")
    if c[_AFTER]:
        limit = f"={max_windows}" if max_windows is not None else ""
        parts.append(f"{c[_AFTER]} after the last window of max_windows{limit}")
    stream = {name: events.get(name, 0) for name in STREAM_CATEGORIES}
    if stream["late"]:
        parts.append(f"{stream['late']} late (earlier than an event received before them)")
    if stream["malformed"]:
        parts.append(f"{stream['malformed']} malformed (a time or coordinate not a finite number)")
    if stream["behind"]:
        skipped = w.get(BEHIND, 0)
        parts.append(f"{stream['behind']} in {skipped} window(s) skipped while the estimator was behind")
    if stream["after_stop"]:
        parts.append(f"{stream['after_stop']} received but not yet in a window when the run stopped")
    return ", ".join(parts)


class EventLedger:
    """Where every event of one pass of windows went (see the module docstring).

    Feed it the spans in order (``start`` and ``stop`` never decrease), each with the fate of its
    events; memory stays bounded by the events of the open windows.

    Parameters
    ----------
    n_total : int
        Events of the source (of a stream: those received so far that have a place in the pass,
        :meth:`extend`).
    stream : bool
        A live stream's ledger: with the categories of :data:`STREAM_CATEGORIES` and the ``behind``
        windows.
    """

    def __init__(self, n_total: int, stream: bool = False) -> None:
        self.n_total = int(n_total)
        self.counts = dict.fromkeys((*CATEGORIES, _AFTER, *(STREAM_CATEGORIES if stream else ())), 0)
        #: windows per status
        self.windows = dict.fromkeys((*STATUSES, *((BEHIND,) if stream else ())), 0)
        self._dropped = 0  # a stream's events counted by drop(), outside the index space
        self._base = 0  # events before it are final
        self._fate = np.zeros(0, dtype=np.int8)  # codes of the events base .. base + len
        self._finished = False

    def add(
        self,
        span: Span,
        status: str,
        inside: np.ndarray | None = None,
        kept: np.ndarray | None = None,
    ) -> None:
        """Account for one window.

        Parameters
        ----------
        span : Span
        status : str
            One of :data:`STATUSES`.
        inside : bool array, optional
            Per event of the span: on the sensor (default all).
        kept : bool array, optional
            Per event on the sensor (``inside.sum()`` values): kept by undistortion (default all).
        """
        if span.start < self._base:
            raise ValueError(f"window spans must come in order: {span} starts before event {self._base}")
        self.windows[status] += 1
        self._finalize(span.start)
        end = self._base + len(self._fate)
        if span.stop > end:
            self._fate = np.concatenate([self._fate, np.zeros(span.stop - end, dtype=np.int8)])
        code = _CODE["estimated"] if status in ESTIMATED_STATUSES else _STATUS_CODE[status]
        fate = np.full(len(span), code, dtype=np.int8)
        inside = np.ones(len(span), dtype=bool) if inside is None else np.asarray(inside, dtype=bool)
        if status in ESTIMATED_STATUSES and kept is not None:
            on_sensor = fate[inside]
            on_sensor[~np.asarray(kept, dtype=bool)] = _CODE["undistortion"]
            fate[inside] = on_sensor
        fate[~inside] = _CODE["outside_sensor"]
        segment = self._fate[span.start - self._base : span.stop - self._base]
        np.maximum(segment, fate, out=segment)

    def extend(self, n: int) -> None:
        """``n`` more events of a stream have a place in the pass (they come after every event so far)."""
        self.n_total += int(n)

    def drop(self, category: str, n: int, windows: int = 0) -> None:
        """Count ``n`` events of a stream that never got a place in the pass (``category`` one of
        :data:`STREAM_CATEGORIES`; ``windows``: whole ``behind`` windows they made)."""
        if category not in STREAM_CATEGORIES or category not in self.counts:
            raise ValueError(f"drop() counts a stream's {STREAM_CATEGORIES}, not {category!r}")
        self.counts[category] += int(n)
        self.n_total += int(n)
        self._dropped += int(n)
        if windows:
            self.windows[BEHIND] += int(windows)

    def _finalize(self, upto: int) -> None:
        """Count the events before ``upto``: no later window can hold them."""
        if upto <= self._base:
            return
        k = min(upto - self._base, len(self._fate))
        for code, count in enumerate(np.bincount(self._fate[:k], minlength=len(CATEGORIES))):
            self.counts[CATEGORIES[code]] += int(count)
        self.counts["between_windows"] += upto - self._base - k  # beyond every window so far
        self._fate = self._fate[k:]
        self._base = upto

    def finish(self, stopped_early: bool = False) -> dict[str, int]:
        """Close the pass: the events after the last window are ``between_windows``, or
        ``after_max_windows`` when ``max_windows`` stopped it (``stopped_early``). Returns :attr:`counts`."""
        if not self._finished:
            self._finalize(self._base + len(self._fate))
            rest = self.n_total - self._dropped - self._base
            if rest > 0:
                self.counts[_AFTER if stopped_early else "between_windows"] += rest
            self._base = self.n_total - self._dropped
            self._finished = True
        return self.counts

    @property
    def not_estimated(self) -> int:
        """Events not estimated (every category but ``estimated``), once :meth:`finish` ran."""
        return self.n_total - self.counts["estimated"]

    def as_dict(self) -> dict:
        """``{"total": N, "estimated": ..., <category>: count, ..., "windows": {status: count}}``."""
        return {"total": self.n_total, **self.counts, "windows": dict(self.windows)}

    def describe(self, n_events: int | None = None, max_windows: int | None = None) -> str:
        """The counts of the events not estimated, for a message (empty when every event was); see
        :func:`describe_events`."""
        return describe_events(self.as_dict(), n_events, max_windows)

    def warn(
        self,
        where: str,
        n_events: int | None = None,
        max_windows: int | None = None,
        verb: str = "not estimated",
        stacklevel: int = 2,
    ) -> None:
        """The one summary warning of a pass, an :class:`EventsDroppedWarning`
        ``"<where>: K of N event(s) <verb>: <counts by reason>"``; nothing when no event was left out.
        ``n_events`` (count windows) and ``max_windows`` make the message name the remedies."""
        import warnings

        detail = self.describe(n_events, max_windows)
        if detail:
            warnings.warn(
                f"{where}: {self.not_estimated} of {self.n_total} event(s) {verb}: {detail}",
                EventsDroppedWarning,
                stacklevel=stacklevel + 1,
            )


# --- a pass of windows over a source ---------------------------------------------------------------
@dataclass
class WindowPlan:
    """One pass of windows over a source: its spans, how to read one, and what to say about it.

    Attributes
    ----------
    spans : iterator of Span
    read : callable
        ``read(span) -> (events on the sensor, which rows of the span they are or None)``.
    n_total : int
        Events of the source.
    total : int or None
        Windows of the pass that may be estimated, if known (for a progress bar).
    camera : Camera or None
        The source's calibration.
    undistorted : bool
        Whether its coordinates are undistorted already.
    desc : dict
        ``source`` (a name for messages), and for a recording its ``format`` and ``fingerprint``.
    planner : object or None
        What plans each next span of motion-adaptive windows
        (:class:`cmax_taichi.solve.adaptive.AdaptivePlanner`); None for count and time windows.
    """

    spans: Iterator[Span]
    read: Callable[[Span], tuple[Events, np.ndarray | None]]
    n_total: int
    total: int | None
    camera: Camera | None
    undistorted: bool
    desc: dict
    planner: Any = None


def check_window_options(n_events, duration, stride, max_windows):
    """The window options of a pass, checked and normalised: ``(n_events, duration, stride,
    max_windows)`` (count windows: whole numbers ``n_events >= 2`` and ``stride >= 1``; time windows: a
    positive ``duration`` and ``stride`` in seconds; ``max_windows >= 1``). TypeError / ValueError."""
    if duration is None:
        n_events = whole_number("n_events", n_events, 2)
        stride = None if stride is None else whole_number("stride (events)", stride, 1)
    else:
        duration = checks.seconds("duration", duration, positive=True)
        stride = None if stride is None else checks.seconds("stride", stride, positive=True)
    if max_windows is not None:
        max_windows = whole_number("max_windows", max_windows, 1)
    return n_events, duration, stride, max_windows


def plan_windows(source, n_events: int, duration: float | None, stride, keep_tail: bool) -> WindowPlan:
    """The pass of windows over an :class:`~cmax_taichi.Events` or an open recording (what
    :func:`cmax_taichi.solve.sequence.process` and :func:`cmax_taichi.flow.iter_flow` both walk):
    arguments and timestamps checked now."""
    if isinstance(source, Events):
        n = len(source)
        if n > 1 and source.t[0] == source.t[-1]:
            raise ValueError(
                f"all {n} events have the same time t = {source.t[0]:.9f} s: no window spans a positive time"
            )
        if duration is not None:
            ranges = checks.time_windows(
                float(source.t[0]) if n else 0.0,
                float(source.t[-1]) if n else 0.0,
                n,
                duration,
                stride,
                lambda t: int(np.searchsorted(source.t, t, side="left")),
                lambda i: float(source.t[i]),
            )
            spans: Iterator[Span] = time_spans(ranges)
            total = None
            if n > 1:
                step = duration if stride is None else float(stride)
                total = int((source.t[-1] - source.t[0]) // step) + 1
        else:
            spans = count_spans(n, n_events, stride, keep_tail)
            total = estimable_windows(n, n_events, stride, keep_tail)
        return WindowPlan(
            spans, lambda span: (source[span.start : span.stop], None), n, total, None,
            source.undistorted, {"source": f"Events(n={n})"},
        )  # fmt: skip
    if hasattr(source, "window_spans"):  # an open Recording
        spans = source.window_spans(n_events=n_events, duration=duration, stride=stride, keep_tail=keep_tail)
        total = None
        if duration is None:
            total = estimable_windows(source.n_events, n_events, stride, keep_tail)
        desc = {"source": str(getattr(source, "path", source)), "format": getattr(source, "format", None)}
        fingerprint = getattr(source, "fingerprint", None)
        if callable(fingerprint):
            desc["fingerprint"] = fingerprint()
        return WindowPlan(
            spans, lambda span: source._span_events(span.start, span.stop), source.n_events, total,
            getattr(source, "camera", None), bool(getattr(source, "undistorted", False)), desc,
        )  # fmt: skip
    raise TypeError(f"source must be Events, a Recording or a path, got {type(source).__name__}")


def estimable_windows(n_total: int, n_events: int, stride: int | None, keep_tail: bool) -> int:
    """The windows of a count pass that may be estimated (for a progress bar): the full windows, and the
    partial tail when ``keep_tail`` keeps it."""
    step = n_events if stride is None else int(stride)
    full = 0 if n_total < n_events else (n_total - n_events) // step + 1
    tail = n_total - full * step
    return full + (1 if keep_tail and tail >= min_tail_events(n_events) else 0)


def read_window(span: Span, plan: WindowPlan, camera: Camera | None, lossy: checks.UndistortionTally):
    """Read a window and decide its fate: ``(events used, on-sensor mask or None, undistortion mask or
    None, status)``; undistorted here (once) when ``camera`` is given, so that the losses are counted."""
    events, inside = plan.read(span)  # the events on the sensor (inside: which rows)
    used, kept = events, None
    if camera is not None and span.keep and len(events):
        with warnings.catch_warnings():  # the tally's filter lives for this window only: no global state
            if lossy.windows:  # the first lossy window warned; the later ones are in the totals
                warnings.filterwarnings("ignore", message=lossy._MESSAGE, category=EventsDroppedWarning)
            used, kept = events.undistort(camera, return_mask=True)
            lossy.add(events, used)
    return used, inside, kept, window_status(span, len(used), used.duration)
