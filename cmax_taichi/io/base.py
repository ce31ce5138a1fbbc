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

#: rows read at once when a time is searched through ``_times`` (bounded memory)
_SEARCH_BLOCK = 4096


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
    usable after any of these errors.
    """

    format: str = ""
    _closed: bool = False
    _warned_outside: bool = False
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
        """Close what the format holds open."""

    def _where(self, start: int, stop: int) -> str:
        """Where rows ``start:stop`` live, for error messages (a format adds its dataset names)."""
        return f"{self.path}, events {start}..{stop}"

    def close(self) -> None:
        """Release open files and mappings (a closed recording cannot be read)."""
        if not self._closed:
            self._release()
            self._closed = True

    # --- reading ----------------------------------------------------------------------------
    def _events(self, start: int, stop: int) -> Events:
        x, y, t, p = self._columns(start, stop)
        W, H = self.sensor_size
        with np.errstate(invalid="ignore"):  # NaN coordinates are reported by Events below
            inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
        inside |= ~(np.isfinite(x) & np.isfinite(y))
        if not np.all(inside):
            # undistorted coordinates may leave the sensor a little: drop them, and say so once per
            # recording rather than once per window
            if not self._warned_outside:
                checks.warn_dropped(
                    int(np.sum(~inside)),
                    len(inside),
                    f"outside the {W}x{H} sensor in {self._where(start, stop)} (shown once per recording)",
                    stacklevel=3,
                )
                self._warned_outside = True
            x, y, t, p = x[inside], y[inside], t[inside], p[inside]
        try:
            return Events(x, y, t, p, self.sensor_size, undistorted=self.undistorted)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{self._where(start, stop)}: {exc}") from None

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
            A NaN or infinite bound; malformed rows as for :meth:`read`.
        """
        if self._closed:
            raise ValueError(f"{self.path}: the recording is closed")
        t0, t1 = checks.seconds("read_time t0", t0), checks.seconds("read_time t1", t1)
        i0 = self._search_time(t0)
        i1 = max(i0, self._search_time(t1)) if t1 > t0 else i0
        return self.read(i0, i1)

    def windows(
        self,
        n_events: int | None = 30000,
        duration: float | None = None,
        stride: int | float | None = None,
    ) -> Iterator[Events]:
        """Consecutive windows over the whole recording, read one at a time.

        Parameters
        ----------
        n_events : int, optional
            Events per window (the default 30,000 is the paper's MVSEC setting). Used when
            ``duration`` is None; the last, shorter window is dropped.
        duration : float, optional
            Window length, seconds; when given, windows are by time from ``t_start`` (``n_events``
            is then ignored) and empty windows are skipped.
        stride : int or float, optional
            Start-to-start step: events (count windows) or seconds (time windows). Default: the
            window size (no overlap).

        Yields
        ------
        Events

        Raises
        ------
        TypeError
            ``n_events`` or ``stride`` is not a number (None for ``n_events`` without ``duration``).
        ValueError
            Raised by this call, before any window is read: ``n_events < 2`` or a fraction; a count
            ``stride`` below 1 or a fraction (0.5 events); a ``duration`` or time ``stride`` that is
            not a positive finite number of seconds; a ``duration`` below 1/1000 of the mean event
            spacing (nearly every window empty: seconds expected), or more than
            ``max_time_windows`` windows by time. Runs of empty time windows are skipped without
            being stepped through.
        """
        if self._closed:
            raise ValueError(f"{self.path}: the recording is closed")
        if duration is not None:
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
            first = next(ranges, None)  # the checks run now, not at the caller's first iteration
            return self._read_ranges(first, ranges)
        if n_events is None:
            raise TypeError("windows needs n_events (events per window) or duration (seconds); both are None")
        n = checks.whole_number("n_events", n_events, 2)
        step = n if stride is None else checks.whole_number("stride (events)", stride, 1)
        return self._read_ranges(
            None, ((start, start + n) for start in range(0, self.n_events - n + 1, step))
        )

    def _read_ranges(self, first, ranges) -> Iterator[Events]:
        if first is not None:
            yield self.read(*first)
        for i0, i1 in ranges:
            yield self.read(i0, i1)

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
