"""DSEC (Gehrig et al. RA-L 2021) event files and optical-flow ground truth.

* ``events.h5``: ``events/x``, ``events/y`` (px), ``events/t`` (microseconds after ``t_offset``),
  ``events/p`` ({0, 1}), ``ms_to_idx`` (index of the first event of each millisecond) and
  ``t_offset`` (microseconds). Times are returned as ``(t + t_offset) / 1e6`` seconds, the clock of
  the flow timestamps. Time slicing reads ``ms_to_idx`` and one millisecond block of ``t``. Sensor
  640x480. Files compressed with blosc need ``pip install hdf5plugin`` (the error says so).
* ``rectify_map.h5`` beside ``events.h5`` (``rectify_map`` (480, 640, 2)): when present, coordinates
  are rectified through it (``rectify=True`` by default then) and ``undistorted`` is True, the frame
  of the flow ground truth. Events that rectify outside the sensor are dropped.
* ``calibration/cam_to_cam.yaml`` of the sequence (optional): the camera ``camRect0`` (rectified) or
  ``cam0`` (raw, with its distortion), read with a small parser of that file's layout.
* Flow: ``<sequence>/flow/forward/*.png`` and ``<sequence>/flow/forward_timestamps.txt`` (``from_us,
  to_us`` per line, one line per PNG in name order), or ``flow_dir=`` pointing at that ``flow``
  folder. 16-bit PNG: ``flow_x = (R - 2**15) / 128``, ``flow_y = (G - 2**15) / 128`` px over the
  line's interval, valid where ``B > 0`` (:func:`read_flow_png`; the writer of submissions is
  :func:`cmax_taichi.io.writers.write_dsec_flow_png`). :func:`read_flow_timestamps` reads those
  timestamps and the benchmark's test CSVs (``from_us, to_us, file_index``).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from cmax_taichi.core.events import Camera
from cmax_taichi.io import _hdf5
from cmax_taichi.io._files import check_regular, is_present
from cmax_taichi.io._flow import GroundTruthRangeError, accumulate_flow
from cmax_taichi.io._png import read_png
from cmax_taichi.io.base import Recording, event_span
from cmax_taichi.io.text import read_text_file

SENSOR_SIZE = (640, 480)
_MAX_US = 2**62  # microseconds; beyond, the int64 sums of times and offsets could overflow


def _find_events_file(path: Path) -> Path:
    if path.is_dir():
        for candidate in (path / "events.h5", path / "events" / "left" / "events.h5"):
            if is_present(candidate):
                return candidate
        raise FileNotFoundError(f"{path}: no events.h5 (nor events/left/events.h5) in this folder")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    return check_regular(path)


def _sequence_dirs(events_file: Path) -> list[Path]:
    """Folders that may hold the sequence's flow/ and calibration/: beside events.h5, and the
    sequence folder of the official ``<seq>/events/left/events.h5`` layout."""
    dirs = [events_file.parent]
    if len(events_file.parents) > 2 and events_file.parent.parent.name == "events":
        dirs.append(events_file.parents[2])
    return dirs


def read_flow_png(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A DSEC flow PNG as ``(flow (2, H, W) px with NaN where invalid, valid (H, W) bool)``.

    Raises ValueError when the file is not a 16-bit RGB(A) PNG."""
    path = Path(path)
    image = read_png(path)
    if image.dtype != np.uint16 or image.ndim != 3 or image.shape[2] < 3:
        kind = f"{image.dtype.itemsize * 8}-bit, {1 if image.ndim == 2 else image.shape[2]} channel(s)"
        raise ValueError(f"{path}: a DSEC flow PNG must be 16-bit RGB, got {kind}")
    valid = image[..., 2] > 0
    flow = (image[..., :2].astype(np.float64) - 2.0**15) / 128.0
    flow = np.moveaxis(flow, -1, 0)
    flow[:, ~valid] = np.nan
    return flow, valid


def read_flow_timestamps(path: str | Path) -> np.ndarray:
    """A DSEC flow timestamps file: ``flow/forward_timestamps.txt`` of a training sequence
    (``from_timestamp_us, to_timestamp_us`` per line) or a ``<sequence>.csv`` of the benchmark's
    ``test_forward_optical_flow_timestamps`` (``from_timestamp_us, to_timestamp_us, file_index``).

    Returns
    -------
    ndarray
        (K, 2) or (K, 3) int64: microseconds (and the file index of the submission PNG). Lines
        starting with ``#`` are comments. Raises ValueError naming the file and the line for a line of
        another shape, a non-integer or ``to <= from``.
    """
    path = Path(path)
    rows: list[tuple[int, ...]] = []
    for k, line in enumerate(read_text_file(path).splitlines(), start=1):
        content = line.split("#", 1)[0].replace(",", " ").split()
        if not content:
            continue
        try:
            values = tuple(int(v) for v in content)
        except ValueError:
            raise ValueError(
                f"{path}, line {k}: expected integers (microseconds), got {line[:80]!r}"
            ) from None
        if len(values) not in (2, 3) or (rows and len(values) != len(rows[0])):
            raise ValueError(
                f"{path}, line {k}: expected 'from_us, to_us' or 'from_us, to_us, file_index' on every "
                f"line, got {len(values)} value(s)"
            )
        if values[1] <= values[0]:
            raise ValueError(f"{path}, line {k}: to_timestamp_us must exceed from_timestamp_us")
        rows.append(values)
    if not rows:
        raise ValueError(f"{path}: no timestamps")
    return np.array(rows, dtype=np.int64)


def _yaml_list(text: str, key: str) -> list[float]:
    m = re.search(rf"{key}:\s*\[([^\]]*)\]", text)
    return [float(v) for v in m.group(1).split(",")] if m else []


def _yaml_camera(path: Path, name: str) -> Camera | None:
    """``camera_matrix`` [fx, fy, cx, cy] and ``distortion_coeffs`` of block ``name`` in DSEC's
    ``cam_to_cam.yaml`` (None when the block is not there)."""
    lines = read_text_file(path).splitlines()
    for k, line in enumerate(lines):
        if line.strip() == f"{name}:":
            indent = len(line) - len(line.lstrip())
            block = []
            for nxt in lines[k + 1 :]:
                if nxt.strip() and len(nxt) - len(nxt.lstrip()) <= indent:
                    break
                block.append(nxt)
            text = "\n".join(block)
            try:
                K = _yaml_list(text, "camera_matrix")
                dist = _yaml_list(text, "distortion_coeffs")
            except ValueError as exc:
                raise ValueError(f"{path}: '{name}': not a number ({exc})") from None
            if len(K) != 4:
                raise ValueError(f"{path}: '{name}' has no camera_matrix [fx, fy, cx, cy]")
            if dist and "equidistant" in text:
                raise ValueError(f"{path}: '{name}' uses the equidistant model; pass camera= instead")
            if len(dist) > 5:
                raise ValueError(
                    f"{path}: '{name}' has {len(dist)} distortion coefficients; the radial-tangential "
                    "model takes at most 5 (k1, k2, p1, p2, k3): pass camera= instead"
                )
            try:
                return Camera(*K, dist=tuple(dist) or (0.0,) * 5)
            except ValueError as exc:
                raise ValueError(f"{path}: '{name}': {exc}") from None
    return None


class DSECRecording(Recording):
    """A DSEC ``events.h5`` (or a sequence folder holding ``events.h5`` or ``events/left/events.h5``).

    Parameters
    ----------
    path : path
        The file or its folder.
    camera : Camera, optional
        Default: from ``cam_to_cam.yaml`` when found (see the module docstring), else None.
    sensor_size : (int, int)
        ``(W, H)`` px, default 640x480.
    rectify : bool, optional
        Map coordinates through ``rectify_map.h5``; default: when that file is beside ``events.h5``.
    flow_dir : path, optional
        The folder with ``forward/`` PNGs and ``forward_timestamps.txt``; default: ``flow/`` of the
        sequence, if present.
    flow_direction : {"forward", "backward"}
        Which flow of ``flow_dir`` to use.
    sort, cache_dir
        As for :class:`~.mvsec.MVSECRecording`: events out of order are refused unless ``sort=True``.
    """

    format = "dsec"

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        camera: Camera | None = None,
        sensor_size: tuple[int, int] = SENSOR_SIZE,
        rectify: bool | None = None,
        flow_dir: str | os.PathLike | None = None,
        flow_direction: str = "forward",
        sort: bool = False,
        cache_dir: str | os.PathLike | None = None,
    ) -> None:
        self.events_file = _find_events_file(Path(path))
        ef = self.events_file
        self._file = _hdf5.open_h5(ef)
        with _hdf5.closed_on_error(self._file):
            self._x, self._y, self._t, self._p = (
                _hdf5.numeric_dataset(self._file, f"events/{c}", ef, "not a DSEC events.h5 file?")
                for c in "xytp"
            )
            n = self._t.shape[0]
            if any(ds.shape != (n,) for ds in (self._x, self._y, self._p)):
                raise ValueError(f"{ef}: events/x, y, t, p must have the same length")
            self._ms_to_idx = _hdf5.numeric_dataset(self._file, "ms_to_idx", ef, "not a DSEC events.h5 file?")
            offset = _hdf5.numeric_dataset(self._file, "t_offset", ef, "not a DSEC events.h5 file?")
            offset_value = np.ravel(_hdf5.finite(_hdf5.read(offset, (), ef), ef, "t_offset"))
            if (
                offset_value.size != 1
                or offset_value[0] != np.floor(offset_value[0])
                or abs(offset_value[0]) >= _MAX_US
            ):
                raise ValueError(
                    f"{ef}: dataset 't_offset' must hold one whole number of microseconds below 2**62, "
                    f"got {offset_value.tolist()}"
                )
            self.t_offset_us = int(offset_value[0])
            span = event_span(n, lambda i: self._seconds(_hdf5.read(self._t, np.s_[i : i + 1], ef))[0])
            self._rectify_map = None
            map_file = ef.with_name("rectify_map.h5")
            if rectify is None:
                rectify = is_present(map_file)
            if rectify:
                if not is_present(map_file):
                    raise FileNotFoundError(f"{map_file}: rectify=True but there is no rectify_map.h5")
                with _hdf5.open_h5(map_file) as mf:
                    rmap = _hdf5.read(
                        _hdf5.dataset(mf, "rectify_map", map_file, "DSEC rectify map"), (), map_file
                    )
                W, H = sensor_size
                if rmap.shape != (H, W, 2):
                    raise ValueError(
                        f"{map_file}: 'rectify_map' has shape {rmap.shape}; expected ({H}, {W}, 2)"
                    )
                self._rectify_map = np.asarray(rmap, dtype=np.float64)
            if camera is None:
                for d in _sequence_dirs(ef):
                    for yaml in (d / "calibration" / "cam_to_cam.yaml", d / "cam_to_cam.yaml"):
                        if camera is None and is_present(yaml):
                            camera = _yaml_camera(yaml, "camRect0" if rectify else "cam0")
            super().__init__(
                ef,
                sensor_size=sensor_size,
                camera=camera,
                undistorted=bool(rectify),
                **span,
            )
        self._flow_dir = self._locate_flow(flow_dir)
        self.flow_direction = flow_direction
        self._flow_index = None
        if sort:
            with _hdf5.closed_on_error(self._file):
                self._sort_by_time(cache_dir)

    # --- events -----------------------------------------------------------------------------
    def _seconds(self, t_us, where: str = "") -> np.ndarray:
        t_us = _hdf5.finite(t_us, self.events_file, "events/t", where)
        if t_us.size:
            # the same range for float and integer times: beyond it, int64 arithmetic would wrap around
            # and the time index (ms_to_idx) arithmetic would overflow
            largest = max(abs(int(t_us.min())), abs(int(t_us.max()))) + abs(self.t_offset_us)
            if largest >= _MAX_US:  # int64 arithmetic would wrap around without a word
                rows = f", {where}" if where else ""
                raise ValueError(
                    f"{self.events_file}: dataset 'events/t'{rows}: times of {largest} us with t_offset "
                    "are out of range (2**62 us)"
                )
        if t_us.dtype.kind == "f":  # keep fractions of a microsecond (the format stores integers)
            return (t_us.astype(np.float64) + self.t_offset_us) / 1e6
        return (t_us.astype(np.int64) + self.t_offset_us) / 1e6

    def _where(self, start: int, stop: int) -> str:
        return f"{self.events_file}: datasets 'events/x, y, t, p', rows {start}..{stop}"

    def _where_time(self, row: int) -> str:
        return f"{self.events_file}: dataset 'events/t', row {row}"

    def _columns(self, start: int, stop: int):
        ef = self.events_file
        sl = np.s_[start:stop]
        x = np.asarray(_hdf5.read(self._x, sl, ef), dtype=np.float64)
        y = np.asarray(_hdf5.read(self._y, sl, ef), dtype=np.float64)
        t = self._seconds(_hdf5.read(self._t, sl, ef), f"rows {start}..{stop}")
        p = np.asarray(_hdf5.read(self._p, sl, ef), dtype=np.float64)
        if self._rectify_map is not None:
            W, H = self.sensor_size
            rows = f"rows {start}..{stop}"
            x, y = _hdf5.finite(x, ef, "events/x", rows), _hdf5.finite(y, ef, "events/y", rows)
            if len(x) and (x.max() > W - 1 or y.max() > H - 1 or x.min() < 0 or y.min() < 0):
                raise ValueError(
                    f"{ef}: events ({rows}) outside 0 <= x <= {W - 1}, 0 <= y <= {H - 1}, the rectify map"
                )
            xi, yi = x.astype(np.int64), y.astype(np.int64)
            x, y = self._rectify_map[yi, xi, 0], self._rectify_map[yi, xi, 1]
        return x, y, t, p

    def _times(self, start: int, stop: int) -> np.ndarray:
        return self._seconds(
            _hdf5.read(self._t, np.s_[start:stop], self.events_file), f"rows {start}..{stop}"
        )

    def _search_time(self, t: float) -> int:
        """``ms_to_idx`` brackets the answer within +-1 ms; one block of ``t`` is then searched.
        Falls back to the generic binary search if the index disagrees with the timestamps."""
        n = self.n_events
        m = self._ms_to_idx.shape[0]
        if n == 0 or m == 0:
            return super()._search_time(t)
        ms = math.floor((t * 1e6 - self.t_offset_us) / 1000.0)
        k0, k1 = ms - 1, ms + 2
        ef = self.events_file
        lo = 0 if k0 < 0 else (n if k0 >= m else int(_hdf5.read(self._ms_to_idx, k0, ef)))
        hi = n if k1 >= m else (0 if k1 < 0 else int(_hdf5.read(self._ms_to_idx, k1, ef)))
        lo, hi = min(max(lo, 0), n), min(max(hi, 0), n)
        if lo > hi:
            return super()._search_time(t)
        block = self._times(max(lo - 1, 0), min(hi + 1, n))
        start = max(lo - 1, 0)
        # the bracket is right when the event before it is earlier than t and the one after is not
        before_ok = lo == 0 or block[0] < t
        after_ok = hi == n or block[-1] >= t
        if not (before_ok and after_ok):
            return super()._search_time(t)
        return start + int(np.searchsorted(block, t, side="left"))

    def _release(self) -> None:
        self._file.close()

    # --- flow ground truth ------------------------------------------------------------------
    def _locate_flow(self, flow_dir) -> Path | None:
        if flow_dir is not None:
            flow_dir = Path(flow_dir)
            if not flow_dir.is_dir():
                raise FileNotFoundError(f"{flow_dir}: no such flow folder")
            return flow_dir
        for d in _sequence_dirs(self.events_file):
            if (d / "flow").is_dir():
                return d / "flow"
        return None

    def flow_intervals(self) -> tuple[np.ndarray, list[Path]] | None:
        """The ground-truth intervals ``(K, 2)`` (from, to) in seconds and their PNG files; None
        without flow ground truth."""
        if self._flow_dir is None:
            return None
        if self._flow_index is None:
            direction = self.flow_direction
            stamps = self._flow_dir / f"{direction}_timestamps.txt"
            pngs = sorted((self._flow_dir / direction).glob("*.png"))
            if not stamps.is_file():
                raise FileNotFoundError(f"{stamps}: no flow timestamps file")
            rows = []
            for k, line in enumerate(read_text_file(stamps).splitlines(), start=1):
                content = line.split("#", 1)[0].replace(",", " ").split()
                if not content:
                    continue
                try:
                    a, b = (int(v) for v in content)
                except ValueError:
                    raise ValueError(
                        f"{stamps}, line {k}: expected 'from_us, to_us', got {line[:80]!r}"
                    ) from None
                rows.append((a, b))
            if len(rows) != len(pngs):
                raise ValueError(
                    f"{stamps}: {len(rows)} intervals but {len(pngs)} PNG files in "
                    f"{self._flow_dir / direction}"
                )
            intervals = np.array(rows, dtype=np.int64).reshape(-1, 2) / 1e6
            if np.any(intervals[:, 1] <= intervals[:, 0]):
                raise ValueError(f"{stamps}: every interval needs to_us > from_us")
            self._flow_index = (intervals, pngs)
        return self._flow_index

    def flow(self, t0: float, t1: float) -> np.ndarray | None:
        """Ground-truth flow ``(2, H, W)`` px over ``[t0, t1]`` s, NaN where invalid.

        An interval equal (to 1 us) to a ground-truth interval returns that PNG's flow; a shorter one
        inside it is that flow scaled linearly by the share of time; one spanning consecutive
        contiguous intervals is accumulated by propagation as for MVSEC (:mod:`._flow`). None without
        flow ground truth."""
        index = self.flow_intervals()
        if index is None:
            return None
        intervals, pngs = index
        t0, t1 = float(t0), float(t1)
        tol = 1e-6
        exact = np.flatnonzero((np.abs(intervals[:, 0] - t0) <= tol) & (np.abs(intervals[:, 1] - t1) <= tol))
        if len(exact):
            return read_flow_png(pngs[int(exact[0])])[0]
        i = int(np.searchsorted(intervals[:, 0], t0 + tol, side="right")) - 1
        if i < 0:
            raise GroundTruthRangeError(
                f"{self._flow_dir}: no ground-truth flow interval contains t0 = {t0:.6f} s"
            )
        # frames i, i+1, ... must be back to back up to t1 for the accumulation
        j = i
        while intervals[j, 1] < t1 - tol:
            if j + 1 >= len(intervals) or abs(intervals[j + 1, 0] - intervals[j, 1]) > tol:
                raise GroundTruthRangeError(
                    f"{self._flow_dir}: the ground-truth flow intervals do not cover {t0:.6f} .. {t1:.6f} s"
                )
            j += 1
        ts = np.concatenate([intervals[i : j + 1, 0], [intervals[j, 1]]])
        t1 = min(t1, ts[-1])  # within the 1 us tolerance

        def frame(k: int):
            flow = read_flow_png(pngs[i + k])[0]
            return flow[0], flow[1]

        # a zero flow is valid in DSEC (the PNG's third channel marks validity, NaN here)
        return accumulate_flow(frame, ts, t0, t1, str(self._flow_dir), zero_is_invalid=False)
