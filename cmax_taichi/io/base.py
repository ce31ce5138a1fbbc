"""The :class:`Recording` base class: one open event file, read window by window.

A format subclass provides the row count, the time range and two hooks: ``_columns(start, stop)``
(the raw ``x, y, t, p`` arrays of a row range) and optionally ``_times(start, stop)`` and
``_search_time(t)``. Everything a user calls (reading by index or time, windows) lives here so that
all formats behave the same.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from cmax_taichi.core import checks
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.core.windows import ESTIMATED, PARTIAL_TAIL, EventLedger, Span, count_spans, time_spans

#: rows read at once when a time is searched through ``_times`` (bounded memory)
_SEARCH_BLOCK = 4096
#: rows read at once by :meth:`Recording.check_times` (8 MiB of float64 times)
_TIME_BLOCK = 1 << 20


def event_span(n_events: int, time_of: Callable[[int], float]) -> dict:
    """``n_events``, ``t_start`` and ``t_end`` as keyword arguments of :class:`Recording`: ``time_of(i)`` is
    the time (s) of event ``i``, read for the first and the last event only; NaN times without events."""
    n = int(n_events)
    return {
        "n_events": n,
        "t_start": float(time_of(0)) if n else math.nan,
        "t_end": float(time_of(n - 1)) if n else math.nan,
    }


class Recording:
    """An open event recording; read it by event index, by time or as windows.

    Attributes
    ----------
    path : pathlib.Path
        The file or folder that was opened.
    format : str
        ``"ecd"``, ``"text"``, ``"mvsec"``, ``"dsec"``, ``"aedat4"``, ``"raw"``, ``"dat"`` or ``"es"``.
    sensor_size : (int, int)
        ``(W, H)``, px.
    camera : Camera or None
        Intrinsics (and distortion) when the format or the caller gives them.
    undistorted : bool
        Whether the event coordinates are already undistorted (then ``camera``'s distortion is not
        applied again by a problem).
    n_events : int
        Number of events.
    t_start, t_end : float
        Time of the first and the last event, seconds.

    max_time_windows : int
        The most windows :meth:`windows` plans by time (default
        :data:`cmax_taichi.core.checks.MAX_TIME_WINDOWS`, 10,000,000); set it on the instance to allow more.

    A recording is a context manager: ``with open_recording(path) as rec: ...`` closes the files it
    holds open (HDF5). Reading never loads more than the rows asked for.

    Every reading method checks its arguments first (TypeError for a non-number, ValueError for a
    value out of range) and reports a malformed row (NaN, a polarity outside the conventions) as a
    ValueError naming the file, the dataset where there is one, and the rows; the recording stays
    usable after any of these errors. Before the first search by time or pass of windows, the
    timestamps are checked once (:meth:`check_times`).
    """

    format: str = ""
    _closed: bool = False
    #: whether every timestamp is known to be finite and in order (the decoders of the cached formats
    #: check it while decoding; the HDF5 formats by :meth:`check_times`)
    _times_checked: bool = False
    max_time_windows: int = checks.MAX_TIME_WINDOWS

    def __init__(
        self,
        path: Path,
        sensor_size: tuple[int, int],
        camera: Camera | None,
        undistorted: bool,
        n_events: int,
        t_start: float,
        t_end: float,
    ) -> None:
        self.path = Path(path)
        self.sensor_size = checks.sensor_size(sensor_size, where=str(self.path))
        if camera is not None and not isinstance(camera, Camera):
            raise TypeError(f"camera must be cmax_taichi.Camera, got {type(camera).__name__}")
        self.camera = camera
        self.undistorted = bool(undistorted)
        self.n_events = int(n_events)
        self.t_start = float(t_start)
        self.t_end = float(t_end)
        if self.n_events and not (np.isfinite(self.t_start) and np.isfinite(self.t_end)):
            raise ValueError(
                f"{self._where(0, self.n_events)}: the first or last time is not finite "
                f"(t = {self.t_start} .. {self.t_end})"
            )

    # --- hooks of a format ------------------------------------------------------------------
    def _columns(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``x, y, t, p`` of rows ``start:stop`` (0 <= start <= stop <= n_events); t in seconds."""
        raise NotImplementedError

    def _times(self, start: int, stop: int) -> np.ndarray:
        """Timestamps (s) of rows ``start:stop``, exactly as ``_columns`` returns them."""
        return self._columns(start, stop)[2]

    def _search_time(self, t: float) -> int:
        """Index of the first event with time >= ``t`` (``n_events`` if none): a binary search on
        single rows down to one block, then one block read."""
        lo, hi = 0, self.n_events  # the answer lies in [lo, hi]
        while hi - lo > _SEARCH_BLOCK:
            mid = (lo + hi) // 2
            if self._times(mid, mid + 1)[0] < t:
                lo = mid + 1
            else:
                hi = mid
        return lo + int(np.searchsorted(self._times(lo, hi), t, side="left"))

    def _release(self) -> None:
        """Close what the format holds open (a format that overrides this calls it too)."""

    def _where(self, start: int, stop: int) -> str:
        """Where rows ``start:stop`` live, for error messages (a format adds its dataset names)."""
        return f"{self.path}, events {start}..{stop}"

    def _where_time(self, row: int) -> str:
        """Where the timestamp of row ``row`` lives (a format adds its dataset and column)."""
        return f"{self.path}, event {row} (t)"

    def close(self) -> None:
        """Release open files and mappings (a closed recording cannot be read)."""
        if not self._closed:
            self._release()
            self._closed = True

    # --- reading ----------------------------------------------------------------------------
    def _span_events(self, start: int, stop: int) -> tuple[Events, np.ndarray]:
        """Rows ``start:stop`` as Events without the events outside the sensor, and the mask of the
        rows kept (no warning: the caller counts the drops)."""
        x, y, t, p = self._columns(start, stop)
        W, H = self.sensor_size
        with np.errstate(invalid="ignore"):  # NaN coordinates are reported by Events below
            inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
        inside |= ~(np.isfinite(x) & np.isfinite(y))
        if not np.all(inside):
            # undistorted coordinates may leave the sensor a little: those events are dropped
            x, y, t, p = x[inside], y[inside], t[inside], p[inside]
        if len(t) > 1 and np.any(np.diff(t) < 0):  # never sorted silently (Events would sort them)
            bad = int(np.flatnonzero(np.diff(t) < 0)[0]) + 1
            row = start + int(np.flatnonzero(inside)[bad])
            raise ValueError(
                f"{self._where_time(row)}: time {t[bad]:.9f} s is earlier than the event before "
                f"({t[bad - 1]:.9f} s): events must be sorted by time "
                "(open_recording(..., sort=True) sorts them)"
            )
        try:
            return Events(x, y, t, p, self.sensor_size, undistorted=self.undistorted), inside
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{self._where(start, stop)}: {exc}") from None

    def _events(self, start: int, stop: int) -> Events:
        events, inside = self._span_events(start, stop)
        if len(events) < len(inside):
            W, H = self.sensor_size
            where = f"outside the {W}x{H} sensor in {self._where(start, stop)}"
            checks.warn_dropped(len(inside) - len(events), len(inside), where, stacklevel=4)
        return events

    def _sort_by_time(self, cache_dir=None) -> None:
        """``sort=True`` of a reader whose file is read in place (HDF5): when :meth:`check_times` finds
        the events out of order, decode them once into the event cache, sorted by time (stable), and
        read from there; ``rows_out_of_order`` counts the rows that were earlier than the row before.
        Non-finite times are still refused."""
        from cmax_taichi.io._cache import cached_table

        self.rows_out_of_order = 0
        try:
            self.check_times()
            return
        except ValueError as exc:
            if "must be sorted by time" not in str(exc):
                raise
        source = self._source_file()
        options = {"reader": type(self).__name__, "sensor_size": list(self.sensor_size)}
        table, meta = cached_table(
            source, f"{self.format}-sorted", options, self._dump_rows, cache_dir=cache_dir, sort=True
        )
        self.rows_out_of_order = int(meta.get("rows_out_of_order", 0))
        self.t_start, self.t_end = float(meta["t_start"]), float(meta["t_end"])
        # read from the sorted table from now on (instance attributes shadow the format's hooks)
        self._columns = lambda a, b: (table[a:b, 1], table[a:b, 2], table[a:b, 0], table[a:b, 3])
        self._times = lambda a, b: np.asarray(table[a:b, 0])
        self._search_time = lambda t: int(np.searchsorted(table[:, 0], t, side="left"))
        self._sorted_table = table
        self._times_checked = True

    def _source_file(self) -> Path:
        """The file that holds the events (a folder's events file, MVSEC's data file, or the path)."""
        return Path(getattr(self, "events_file", None) or getattr(self, "data_file", None) or self.path)

    def fingerprint(self) -> str | None:
        """What identifies this recording's events wherever its file is: ``"<size>-<content>"``, the
        file's size in bytes and the SHA-256 of its content sampled in blocks (at most 1 MiB read; the
        event cache's key). Results and flow files carry it, and ``cmax-taichi evaluate`` checks
        ``--data`` against it. None for a source that is not a file."""
        from cmax_taichi.io._cache import content_fingerprint

        source = self._source_file()
        try:
            size = source.stat().st_size
            return f"{size}-{content_fingerprint(source, size)}" if source.is_file() else None
        except OSError:
            return None

    def _dump_rows(self, out) -> dict:
        """Every row as ``t x y p`` float64 to the binary stream ``out`` (blocks: bounded memory)."""
        for start in range(0, self.n_events, _TIME_BLOCK):
            x, y, t, p = self._columns(start, min(start + _TIME_BLOCK, self.n_events))
            if not np.all(np.isfinite(t)):
                bad = start + int(np.flatnonzero(~np.isfinite(t))[0])
                raise ValueError(f"{self._where_time(bad)}: time {t[bad - start]} is not finite")
            out.write(np.column_stack([t, x, y, p]).astype(np.float64).tobytes())
        return {"n": self.n_events}

    def check_times(self) -> None:
        """Check every timestamp once (in blocks of a million rows, bounded memory): ValueError naming
        the file, the dataset and column where there are some, and the first row whose time is not
        finite or earlier than the row before. Searches by time and passes of windows rely on the order,
        so :meth:`read_time` and :meth:`windows` call this first; later calls return at once.
        ``open_recording(path, sort=True)`` sorts a file whose events are out of order instead."""
        if self._times_checked:
            return
        if self._closed:
            raise ValueError(f"{self.path}: the recording is closed")
        previous = -math.inf
        for start in range(0, self.n_events, _TIME_BLOCK):
            stop = min(start + _TIME_BLOCK, self.n_events)
            t = np.asarray(self._times(start, stop), dtype=np.float64)
            bad = np.flatnonzero(~np.isfinite(t))
            if len(bad):
                i = int(bad[0])
                raise ValueError(
                    f"{self._where_time(start + i)}: time {t[i]} is not finite "
                    f"({len(bad)} non-finite time(s) in rows {start}..{stop})"
                )
            before = np.concatenate([[previous], t[:-1]])
            back = np.flatnonzero(t < before)
            if len(back):
                i = int(back[0])
                raise ValueError(
                    f"{self._where_time(start + i)}: time {t[i]:.9f} s is earlier than row {start + i - 1} "
                    f"({before[i]:.9f} s): events must be sorted by time "
                    "(open_recording(..., sort=True) sorts them)"
                )
            if len(t):
                previous = float(t[-1])
        self._times_checked = True

    def read(self, start: int = 0, stop: int | None = None) -> Events:
        """Events ``start:stop`` by index, with Python slice semantics (negative counts from the end).

        Parameters
        ----------
        start, stop : int
            Event indices; ``stop=None`` reads to the end. Only these rows are read from disk.

        Returns
        -------
        Events
            Coordinates in px, times in seconds, polarities -1 / +1.

        Raises
        ------
        TypeError
            An index that is not an integer (``0.5``, a string).
        ValueError
            A closed recording, or malformed rows (NaN, polarities mixing the conventions): the
            message names the file, the dataset where there is one, and the rows.
        """
        if self._closed:
            raise ValueError(f"{self.path}: the recording is closed")
        start, stop = _index("start", start), None if stop is None else _index("stop", stop)
        start, stop, _ = slice(start, stop).indices(self.n_events)
        stop = max(start, stop)
        return self._events(start, stop)

    def read_time(self, t0: float, t1: float) -> Events:
        """Events with ``t0 <= t < t1``.

        Parameters
        ----------
        t0, t1 : float
            Interval bounds, seconds (the recording's clock: see ``t_start``, ``t_end``); an empty
            interval (``t1 <= t0``) gives no events.

        Raises
        ------
        TypeError
            A bound that is not a number.
        ValueError
            A NaN or infinite bound; malformed rows as for :meth:`read`; timestamps out of order or
            not finite anywhere in the recording (:meth:`check_times`).
        """
        if self._closed:
            raise ValueError(f"{self.path}: the recording is closed")
        t0, t1 = checks.seconds("read_time t0", t0), checks.seconds("read_time t1", t1)
        self.check_times()  # a binary search is only right on sorted times
        i0 = self._search_time(t0)
        i1 = max(i0, self._search_time(t1)) if t1 > t0 else i0
        return self.read(i0, i1)

    def window_spans(
        self,
        n_events: int | None = 30000,
        duration: float | None = None,
        stride: int | float | None = None,
        keep_tail: bool = False,
    ) -> Iterator[Span]:
        """The windows of :meth:`windows` as event index spans (:class:`~cmax_taichi.core.windows.Span`),
        planned now: the arguments and the timestamps (:meth:`check_times`) are checked by this call.

        A count pass ends with the partial tail (the events after the last full window), marked
        ``keep`` when ``keep_tail`` and it holds at least
        :func:`~cmax_taichi.core.windows.min_tail_events`; time windows that hold no event are left out.
        """
        if self._closed:
            raise ValueError(f"{self.path}: the recording is closed")
        if duration is not None:
            duration = checks.seconds("duration", duration, positive=True)
            stride = None if stride is None else checks.seconds("stride", stride, positive=True)
            self.check_times()
            self._check_span()
            ranges = checks.time_windows(
                self.t_start,
                self.t_end,
                self.n_events,
                duration,
                stride,
                self._search_time,
                lambda i: float(self._times(i, i + 1)[0]),
                self.max_time_windows,
            )
            return time_spans(ranges)  # the remaining checks run now, not at the caller's first iteration
        if n_events is None:
            raise TypeError("windows needs n_events (events per window) or duration (seconds); both are None")
        spans = count_spans(self.n_events, n_events, stride, keep_tail)  # checks the arguments
        self.check_times()
        self._check_span()
        return spans

    def _check_span(self) -> None:
        """ValueError when two or more events all share one time (no window could span a positive time)."""
        if self.n_events > 1 and self.t_start == self.t_end:
            raise ValueError(
                f"{self._where(0, self.n_events)}: all {self.n_events} events have the same time "
                f"t = {self.t_start:.9f} s: no window spans a positive time"
            )

    def windows(
        self,
        n_events: int | None = 30000,
        duration: float | None = None,
        stride: int | float | None = None,
        keep_tail: bool = False,
    ) -> Iterator[Events]:
        """Consecutive windows over the whole recording, read one at a time.

        Parameters
        ----------
        n_events : int, optional
            Events per window (the default 30,000 is the paper's MVSEC setting). Used when
            ``duration`` is None.
        duration : float, optional
            Window length, seconds; when given, windows are by time from ``t_start`` (``n_events``
            is then ignored) and empty windows are skipped.
        stride : int or float, optional
            Start-to-start step: events (count windows) or seconds (time windows). Default: the
            window size (no overlap).
        keep_tail : bool
            Count windows: also yield the partial tail, the events after the last full window, when it
            holds at least half a window (:func:`~cmax_taichi.core.windows.min_tail_events`). Default: the
            tail is not yielded, and counted.

        Yields
        ------
        Events

        Events in no yielded window (the partial tail, the gaps of a stride longer than the window) and
        events outside the sensor are counted, and one :class:`~cmax_taichi.core.checks.EventsDroppedWarning`
        gives the totals when the pass ends.

        Raises
        ------
        TypeError
            ``n_events`` or ``stride`` is not a number (None for ``n_events`` without ``duration``).
        ValueError
            Raised by this call, before any window is read: ``n_events < 2`` or a fraction; a count
            ``stride`` below 1 or a fraction (0.5 events); a ``duration`` or time ``stride`` that is
            not a positive finite number of seconds; a ``duration`` below 1/1000 of the mean event
            spacing (nearly every window empty: seconds expected), or more than
            ``max_time_windows`` windows by time; timestamps out of order or not finite
            (:meth:`check_times`, naming the file, the dataset and the first bad row), or all equal.
            Runs of empty time windows are skipped without being stepped through.
        """
        spans = self.window_spans(n_events, duration, stride, keep_tail)
        return self._read_spans(spans, n_events if duration is None else None)

    def _read_spans(self, spans: Iterator[Span], n_events: int | None) -> Iterator[Events]:
        ledger = EventLedger(self.n_events)
        for span in spans:
            if not span.keep:  # a partial tail not asked for: counted, not read
                ledger.add(span, PARTIAL_TAIL)
                continue
            events, inside = self._span_events(span.start, span.stop)
            ledger.add(span, ESTIMATED, inside)
            yield events
        ledger.finish()
        ledger.warn(f"windows of {self.path}", n_events, verb="in no window", stacklevel=2)

    # --- ground truth (None when the recording has none) ------------------------------------
    def angular_velocity(self, t) -> np.ndarray | None:
        """Angular velocity of the camera, rad/s, camera frame, interpolated at ``t`` (seconds):
        shape (3,) for a scalar ``t``, (len(t), 3) for an array; None without ground truth."""
        return None

    def poses(self) -> np.ndarray | None:
        """Camera poses ``(M, 8)``: ``t px py pz qx qy qz qw`` (s, m, unit quaternion); None without."""
        return None

    def flow(self, t0: float, t1: float) -> np.ndarray | None:
        """Ground-truth optical flow ``(2, H, W)`` (x, y displacement in px) over ``[t0, t1]``
        seconds, NaN where invalid; None when the recording has no flow ground truth."""
        return None

    # --- context manager and display ----------------------------------------------------------
    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __len__(self) -> int:
        return self.n_events

    def __repr__(self) -> str:
        W, H = self.sensor_size
        return (
            f"{type(self).__name__}({str(self.path)!r}, format={self.format!r}, n_events={self.n_events}, "
            f"t=[{self.t_start:.6f}, {self.t_end:.6f}] s, sensor={W}x{H}, "
            f"camera={'yes' if self.camera else 'no'}, undistorted={self.undistorted})"
        )


def _index(name: str, value) -> int:
    try:
        return operator.index(value)
    except TypeError:
        raise TypeError(
            f"{name} must be an integer event index, got {value!r} ({type(value).__name__})"
        ) from None


def interpolate_rows(t_query, t_table: np.ndarray, values: np.ndarray, name: str) -> np.ndarray:
    """Linear interpolation of each column of ``values`` (M, k) at ``t_query`` (s); times outside
    the table raise ValueError (extrapolating ground truth would hide a wrong window)."""
    tq = np.asarray(t_query, dtype=np.float64)
    scalar = tq.ndim == 0
    tq = np.atleast_1d(tq)
    if len(t_table) == 0:
        raise ValueError(f"{name} has no samples")
    lo, hi = t_table[0], t_table[-1]
    if np.any(tq < lo) or np.any(tq > hi):
        raise ValueError(
            f"{name} covers t = {lo:.6f} .. {hi:.6f} s; asked for {tq.min():.6f} .. {tq.max():.6f} s"
        )
    out = np.stack([np.interp(tq, t_table, values[:, k]) for k in range(values.shape[1])], axis=-1)
    return out[0] if scalar else out
