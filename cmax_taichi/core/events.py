"""Event containers: :class:`Events` (validated NumPy arrays) and :class:`Camera` (pinhole + distortion).

Nothing here touches Taichi: events are plain NumPy until a problem copies them into fields.
"""

from __future__ import annotations

import functools
import numbers
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from cmax_taichi.core.checks import EventsDroppedWarning, check_finite, real_array, time_windows, warn_dropped
from cmax_taichi.core.checks import sensor_size as _check_sensor_size

__all__ = ["Events", "Camera", "EventsDroppedWarning"]


def _as_1d(name: str, values, dtype) -> np.ndarray:
    arr = real_array(values, name, "a one-dimensional numeric array", "event coordinates")
    if arr.dtype.kind in "mM":  # timedelta64 / datetime64: the unit would be lost in the cast
        raise TypeError(f"{name} has dtype {arr.dtype}; convert it to seconds (float) first")
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.bool_)):
        raise TypeError(f"{name} must be a numeric array, got dtype {arr.dtype}")
    if arr.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {arr.shape}")
    arr = arr.astype(dtype, copy=True)
    check_finite(arr, name)
    return arr


class Events:
    """A time-sorted set of events of one sensor.

    The arrays are copied: nothing the caller passed is modified.

    Parameters
    ----------
    x, y : array_like
        Pixel coordinates (column, row), px. Integers or (undistorted) floats.
    t : array_like
        Timestamps, seconds. Sorted on input, or sorted here with a warning.
    p : array_like
        Polarities, all in {0, 1} or all in {-1, +1} (bools count as {0, 1}); stored as -1 / +1.
    sensor_size : (int, int)
        ``(W, H)``, px: positive whole numbers (``240.0`` is accepted, ``240.5`` is refused). Events
        outside ``[0, W-1] x [0, H-1]`` are dropped with an :class:`EventsDroppedWarning` giving the
        count (also in ``n_dropped``).
    undistorted : bool
        Whether ``x, y`` are already undistorted (a problem then skips the camera's undistortion).

    Raises
    ------
    TypeError
        An array that is not real numbers (strings, objects, complex values: the imaginary part is
        never dropped silently; datetime64 / timedelta64), or a sensor size that is not numbers.
    ValueError
        Arrays of different lengths or not one-dimensional; NaN or infinite values; polarities outside
        {-1, 0, 1}, or mixing the conventions (-1 and 0 together); a sensor size that is not a pair of
        positive whole numbers.

    Nothing else is raised for any input, and nothing is converted with a loss: every event is either
    kept as given or dropped with a warning that counts it.
    """

    __slots__ = ("x", "y", "t", "p", "sensor_size", "undistorted", "n_dropped")

    def __init__(
        self,
        x,
        y,
        t,
        p,
        sensor_size: tuple[int, int],
        *,
        undistorted: bool = False,
        _validated: bool = False,
    ) -> None:
        if _validated:
            self.x, self.y, self.t, self.p = x, y, t, p
            self.sensor_size = sensor_size
            self.undistorted = undistorted
            self.n_dropped = 0
            return
        W, H = _check_sensor_size(sensor_size)
        xs = _as_1d("x", x, np.float64)
        ys = _as_1d("y", y, np.float64)
        ts = _as_1d("t", t, np.float64)
        ps = _as_1d("p", p, np.float64)
        lengths = {len(xs), len(ys), len(ts), len(ps)}
        if len(lengths) != 1:
            raise ValueError(
                f"x, y, t, p must have the same length, got {len(xs)}, {len(ys)}, {len(ts)}, {len(ps)}"
            )
        values = set(np.unique(ps).tolist())
        if not values <= {-1.0, 0.0, 1.0}:
            odd = sorted(values - {-1.0, 0.0, 1.0})[:3]
            raise ValueError(f"p must hold polarities in {{0, 1}} or {{-1, +1}}, got values such as {odd}")
        if {-1.0, 0.0} <= values:
            # 0 would merge into -1 silently: refuse the ambiguous mix
            found = ", ".join(f"{v:g}" for v in sorted(values))
            raise ValueError(
                f"p mixes the polarity conventions (it holds {found}): use {{0, 1}} or {{-1, +1}}, not both"
            )
        ps = np.where(ps > 0, 1, -1).astype(np.int8)
        if len(ts) > 1 and np.any(np.diff(ts) < 0):
            warnings.warn("events were not sorted by time; sorting them", RuntimeWarning, stacklevel=2)
            order = np.argsort(ts, kind="stable")
            xs, ys, ts, ps = xs[order], ys[order], ts[order], ps[order]
        inside = (xs >= 0) & (xs <= W - 1) & (ys >= 0) & (ys <= H - 1)
        n_out = int(len(xs) - np.count_nonzero(inside))
        if n_out:
            warn_dropped(n_out, len(xs), f"outside the {W}x{H} sensor", stacklevel=2)
            xs, ys, ts, ps = xs[inside], ys[inside], ts[inside], ps[inside]
        self.x, self.y, self.t, self.p = xs, ys, ts, ps
        self.sensor_size = (W, H)
        self.undistorted = bool(undistorted)
        self.n_dropped = n_out

    # --- basic properties -------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.t)

    def __repr__(self) -> str:
        if len(self) == 0:
            return f"Events(n=0, sensor={self.sensor_size[0]}x{self.sensor_size[1]})"
        return (
            f"Events(n={len(self)}, t=[{self.t[0]:.6f}, {self.t[-1]:.6f}] s, "
            f"sensor={self.sensor_size[0]}x{self.sensor_size[1]})"
        )

    @property
    def width(self) -> int:
        return self.sensor_size[0]

    @property
    def height(self) -> int:
        return self.sensor_size[1]

    @property
    def duration(self) -> float:
        """``t[-1] - t[0]`` in seconds (0 for fewer than two events)."""
        return float(self.t[-1] - self.t[0]) if len(self) > 1 else 0.0

    def _subset(self, index) -> Events:
        return Events(
            self.x[index],
            self.y[index],
            self.t[index],
            self.p[index],
            self.sensor_size,
            undistorted=self.undistorted,
            _validated=True,
        )

    def __getitem__(self, index) -> Events:
        """Events by integer slice or boolean / integer index array (time order is kept)."""
        if isinstance(index, (int, np.integer)):
            index = slice(int(index), int(index) + 1 if int(index) != -1 else None)
        if not isinstance(index, slice):
            index = np.asarray(index)
            if index.dtype != bool:
                index = np.sort(index)
        return self._subset(index)

    # --- windows ----------------------------------------------------------------------------
    def time_slice(self, t_start: float, t_end: float) -> Events:
        """Events with ``t_start <= t < t_end`` (seconds)."""
        i0, i1 = np.searchsorted(self.t, [t_start, t_end], side="left")
        return self._subset(slice(int(i0), int(i1)))

    def windows_by_count(
        self, n_events: int, stride: int | None = None, keep_tail: bool = False
    ) -> Iterator[Events]:
        """Consecutive windows of ``n_events`` events, starting every ``stride`` events (default: no
        overlap). The last, shorter window (the partial tail) is yielded with ``keep_tail`` when it holds
        at least half a window; otherwise its events, and those a stride longer than the window skips,
        are counted in one :class:`EventsDroppedWarning` when the pass ends.

        Both are whole numbers (``n_events >= 2``, ``stride >= 1``), checked when this is called:
        TypeError for a non-number, ValueError for a fraction or a value too small."""
        from cmax_taichi.core.windows import count_spans

        return self._pass(count_spans(len(self), n_events, stride, keep_tail), n_events)

    def _pass(self, spans, n_events: int | None) -> Iterator[Events]:
        """The windows of ``spans``, then one warning with the events left out (see core/windows.py)."""
        from cmax_taichi.core.windows import ESTIMATED, PARTIAL_TAIL, EventLedger

        ledger = EventLedger(len(self))
        for span in spans:
            ledger.add(span, ESTIMATED if span.keep else PARTIAL_TAIL)
            if span.keep:
                yield self._subset(slice(span.start, span.stop))
        ledger.finish()
        ledger.warn(f"windows of {self!r}", n_events, verb="in no window", stacklevel=2)

    def windows_by_duration(
        self, duration: float, stride: float | None = None, max_windows: int | None = None
    ) -> Iterator[Events]:
        """Consecutive windows of ``duration`` seconds (start every ``stride`` s, default: no
        overlap), from the first event's time; empty windows are skipped (without stepping through
        them one by one). The events a stride longer than the window skips are counted in one
        :class:`EventsDroppedWarning` when the pass ends.

        The arguments are checked when this is called (see :func:`cmax_taichi.core.checks.time_windows`):
        ValueError for a non-positive or non-finite duration or stride, a duration below 1/1000 of the
        mean event spacing, or more than ``max_windows`` (default 10,000,000) windows."""
        ranges = time_windows(
            float(self.t[0]) if len(self) else 0.0,
            float(self.t[-1]) if len(self) else 0.0,
            len(self),
            duration,
            stride,
            lambda t: int(np.searchsorted(self.t, t, side="left")),
            lambda i: float(self.t[i]),
            max_windows,
        )
        from cmax_taichi.core.windows import time_spans

        return self._pass(time_spans(ranges), None)  # the checks run now, not at the first iteration

    def undistort(self, camera: Camera, return_mask: bool = False):
        """Return new events with undistorted coordinates.

        Events whose undistorted position leaves the sensor, or where the distortion model does not
        invert (a strong distortion folds the image), are dropped with an
        :class:`EventsDroppedWarning` giving both counts; the result's ``n_dropped`` holds the total.
        With ``return_mask``, also return the boolean mask of the kept events (to filter arrays that
        go with the events, such as weights).
        """
        if self.undistorted:
            return (self, np.ones(len(self), dtype=bool)) if return_mask else self
        W, H = self.sensor_size
        xu, yu = _undistort_pixels(camera, self.x, self.y, W, H)
        inverted = np.isfinite(xu) & np.isfinite(yu)
        with np.errstate(invalid="ignore"):
            inside = inverted & (xu >= 0) & (xu <= W - 1) & (yu >= 0) & (yu <= H - 1)
        n_out = int(len(inside) - np.count_nonzero(inside))
        if n_out:
            n_fold = int(len(inverted) - np.count_nonzero(inverted))
            warn_dropped(
                n_out,
                len(inside),
                f"in undistortion with dist (k1, k2, p1, p2, k3) = "
                f"({', '.join(f'{d:.3g}' for d in camera.dist)}): {n_out - n_fold} "
                f"outside the {W}x{H} sensor, {n_fold} where the distortion model does not invert",
                stacklevel=2,
            )
        result = Events(
            xu[inside],
            yu[inside],
            self.t[inside],
            self.p[inside],
            self.sensor_size,
            undistorted=True,
            _validated=True,
        )
        result.n_dropped = n_out
        return (result, inside) if return_mask else result


#: largest sensor (pixels) whose per-pixel undistortion table is kept (2 float64 per pixel: 64 MiB)
UNDISTORTION_TABLE_MAX_PIXELS = 1 << 22


@functools.lru_cache(maxsize=4)
def _undistortion_table(camera: Camera, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted ``(x, y)`` of every pixel centre, shape (height, width) each (NaN where the model
    does not invert): :meth:`Camera.undistort_points` on the pixel grid, computed once per camera and
    sensor."""
    ys, xs = np.mgrid[0:height, 0:width]
    xu, yu = camera.undistort_points(xs.ravel(), ys.ravel())
    xu, yu = xu.reshape(height, width), yu.reshape(height, width)
    xu.flags.writeable = yu.flags.writeable = False
    return xu, yu


def _undistort_pixels(camera: Camera, x: np.ndarray, y: np.ndarray, width: int, height: int):
    """``camera.undistort_points(x, y)``; events on whole pixels (as sensors record them) read a cached
    per-pixel table instead (the same values: the same elementwise computation), which makes the
    undistortion of a window a lookup."""
    if width * height <= UNDISTORTION_TABLE_MAX_PIXELS and len(x) and camera.has_distortion:
        xi, yi = x.astype(np.int64), y.astype(np.int64)
        whole = np.array_equal(xi, x) and np.array_equal(yi, y)
        if whole and xi.min() >= 0 and yi.min() >= 0 and xi.max() < width and yi.max() < height:
            table_x, table_y = _undistortion_table(camera, int(width), int(height))
            return table_x[yi, xi], table_y[yi, xi]
    return camera.undistort_points(x, y)


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics with the radial-tangential distortion of OpenCV / the ECD ``calib.txt``.

    Parameters
    ----------
    fx, fy : float
        Focal lengths, px.
    cx, cy : float
        Principal point, px.
    dist : tuple of float
        ``(k1, k2, p1, p2, k3)``; all zero means no distortion. Fewer than five values are padded
        with zeros (``(k1, k2, p1, p2)`` is OpenCV's four-coefficient model).

    Raises
    ------
    TypeError
        A parameter that is not a real number (a string such as ``"200"``, None, a bool, a complex),
        or ``dist`` that is not a sequence of real numbers.
    ValueError
        A non-finite value, a focal length ``<= 0``, or more than five distortion coefficients.

    Undistortion (:meth:`undistort_points`) returns NaN where the model does not invert;
    :meth:`Events.undistort` drops those events with a warning that counts them.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not _is_real(value):
                raise TypeError(
                    f"Camera {name} must be a real number (px), got {value!r} ({type(value).__name__})"
                )
            object.__setattr__(self, name, float(value))
        values = [self.fx, self.fy, self.cx, self.cy]
        if not all(np.isfinite(v) for v in values):
            raise ValueError(f"camera intrinsics must be finite, got {values}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        try:
            raw = list(self.dist)
        except TypeError:  # not iterable (a single number)
            raw = None
        if raw is None or isinstance(self.dist, (str, bytes)) or not all(_is_real(d) for d in raw):
            raise TypeError(
                f"Camera dist must be a sequence of real numbers (k1, k2, p1, p2, k3), got {self.dist!r}"
            )
        dist = tuple(float(d) for d in raw)
        if len(dist) < 5:
            dist = dist + (0.0,) * (5 - len(dist))
        if len(dist) != 5 or not all(np.isfinite(d) for d in dist):
            raise ValueError(f"dist must be (k1, k2, p1, p2, k3) finite values, got {self.dist}")
        object.__setattr__(self, "dist", dist)

    @property
    def has_distortion(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the conventional name of the intrinsic matrix
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def distort_normalized(self, xn, yn) -> tuple[np.ndarray, np.ndarray]:
        """Apply the distortion model to normalised coordinates (unitless)."""
        k1, k2, p1, p2, k3 = self.dist
        r2 = xn * xn + yn * yn
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        return xd, yd

    def undistort_points(self, x, y, iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
        """Undistort pixel coordinates (px in, px out, same intrinsics).

        Fixed-point iteration as in OpenCV's ``undistortPoints``; returns NaN where it diverges.
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        xd = (x - self.cx) / self.fx
        yd = (y - self.cy) / self.fy
        if not self.has_distortion:
            return x.copy(), y.copy()
        k1, k2, p1, p2, k3 = self.dist
        xn, yn = xd.copy(), yd.copy()
        with np.errstate(all="ignore"):
            for _ in range(iterations):
                r2 = xn * xn + yn * yn
                radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
                dx = 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
                dy = p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
                xn = (xd - dx) / radial
                yn = (yd - dy) / radial
            # keep only points that the distortion model maps back to where they came from
            xr, yr = self.distort_normalized(xn, yn)
            ok = np.isfinite(xn) & np.isfinite(yn) & (np.hypot(xr - xd, yr - yd) < 1e-6)
        xu = np.where(ok, xn * self.fx + self.cx, np.nan)
        yu = np.where(ok, yn * self.fy + self.cy, np.nan)
        return xu, yu

    @classmethod
    def from_calib_line(cls, values) -> Camera:
        """From ``fx fy cx cy [k1 k2 p1 p2 k3]`` (the ECD ``calib.txt`` layout)."""
        values = [float(v) for v in values]
        if len(values) not in (4, 8, 9):
            raise ValueError(f"calibration needs fx fy cx cy [k1 k2 p1 p2 [k3]], got {len(values)} numbers")
        return cls(*values[:4], dist=tuple(values[4:]) or (0.0,) * 5)
