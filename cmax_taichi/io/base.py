"""The :class:`Recording` base class: one open event file, read window by window.

A format subclass provides the row count, the time range and two hooks: ``_columns(start, stop)``
(the raw ``x, y, t, p`` arrays of a row range) and optionally ``_times(start, stop)`` and
``_search_time(t)``. Everything a user calls (reading by index or time, windows) lives here so that
all formats behave the same.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from cmax_taichi.core.events import Camera, Events, iter_count_windows, iter_time_windows

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

    A recording is a context manager: ``with open_recording(path) as rec: ...`` closes the files it
    holds open (HDF5). Reading never loads more than the rows asked for.
    """

    format: str = ""
    _closed: bool = False
    _warned_outside: bool = False

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
        W, H = (int(v) for v in sensor_size)
        if W <= 0 or H <= 0:
            raise ValueError(f"{self.path}: sensor_size must be positive (W, H), got {sensor_size!r}")
        self.sensor_size = (W, H)
        if camera is not None and not isinstance(camera, Camera):
            raise TypeError(f"camera must be cmax_taichi.Camera, got {type(camera).__name__}")
        self.camera = camera
        self.undistorted = bool(undistorted)
        self.n_events = int(n_events)
        self.t_start = float(t_start)
        self.t_end = float(t_end)

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

    def close(self) -> None:
        """Release open files and mappings (a closed recording cannot be read)."""
        if not self._closed:
            self._release()
            self._closed = True

    # --- reading ----------------------------------------------------------------------------
    def _events(self, x, y, t, p) -> Events:
        W, H = self.sensor_size
        inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
        if not np.all(inside):
            # undistorted coordinates may leave the sensor a little: drop them, and say so once per
            # recording rather than once per window
            if not self._warned_outside:
                warnings.warn(
                    f"{self.path}: dropping events outside the {W}x{H} sensor (e.g. {int(np.sum(~inside))} "
                    f"of {len(inside)} in this read); this warning is shown once per recording",
                    RuntimeWarning,
                    stacklevel=3,
                )
                self._warned_outside = True
            x, y, t, p = x[inside], y[inside], t[inside], p[inside]
        return Events(x, y, t, p, self.sensor_size, undistorted=self.undistorted)

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
        """
        if self._closed:
            raise ValueError(f"{self.path}: the recording is closed")
        start, stop, _ = slice(start, stop).indices(self.n_events)
        stop = max(start, stop)
        return self._events(*self._columns(start, stop))

    def read_time(self, t0: float, t1: float) -> Events:
        """Events with ``t0 <= t < t1``.

        Parameters
        ----------
        t0, t1 : float
            Interval bounds, seconds (the recording's clock: see ``t_start``, ``t_end``).
        """
        if self._closed:
            raise ValueError(f"{self.path}: the recording is closed")
        t0, t1 = float(t0), float(t1)
        if not (np.isfinite(t0) and np.isfinite(t1)):
            raise ValueError(f"read_time needs finite times, got t0={t0}, t1={t1}")
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
        """
        if duration is not None:
            span = (self.t_start, self.t_end) if self.n_events else None
            yield from iter_time_windows(self.read_time, span, duration, stride)
            return
        if n_events is None:
            raise ValueError("windows needs n_events or duration")
        yield from iter_count_windows(self.read, self.n_events, n_events, stride)

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
