"""MVSEC (Zhu et al. RA-L 2018) ``*_data.hdf5`` files and the EV-FlowNet ``*_gt_flow_dist.npz``
ground truth.

* ``davis/left/events``: (N, 4) float64 rows ``x y t p`` (px, px, s, -1/+1), raw (distorted)
  coordinates of a DAVIS346 (346x260). Rows are read by hyperslab; a time is found by a binary
  search of single rows, then one block: nothing is loaded whole.
* ``davis/left/calibration`` (not part of the official files; accepted when present): ``fx fy cx cy
  [k1 k2 p1 p2 [k3]]``. MVSEC's own calibration (camchain yaml, equidistant distortion) is not read:
  pass ``camera=``.
* ``<name>_gt_flow_dist.npz`` beside ``<name>_data.hdf5`` (or ``gt_flow=``): ``timestamps`` (M,) s,
  ``x_flow_dist``, ``y_flow_dist`` (M, 260, 346) px: frame i is the displacement from
  ``timestamps[i]`` to ``timestamps[i+1]``. :meth:`MVSECRecording.flow` accumulates it over an
  interval as EV-FlowNet does (see :mod:`._flow`): scaled linearly within one frame, propagated
  frame by frame over several.
* ``davis/left/image_raw_ts``: the grey-scale frame times. MVSEC's flow is evaluated between frames
  ``i`` and ``i + dt`` (``dt = 1`` and ``dt = 4`` in the tables): :meth:`MVSECRecording.eval_windows`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cmax_taichi.core.events import Camera
from cmax_taichi.io import _hdf5
from cmax_taichi.io._files import NPZ_ERRORS, check_regular
from cmax_taichi.io._flow import NpzFrames, accumulate_flow
from cmax_taichi.io.base import Recording, event_span

SENSOR_SIZE = (346, 260)

#: The ground-truth flow frames of each sequence that evaluations use, as Python slices of the
#: ``*_gt_flow_dist.npz`` frames (start, stop; stop -1 drops the last frame, None keeps all): the ranges
#: of tub-rip/event_based_optical_flow ``src/data_loader/mvsec.py::omit_invalid_data`` (the frames where
#: the motion-capture / lidar ground truth is valid, after take-off and before landing).
MVSEC_VALID_GT_FRAMES: dict[str, tuple[int, int | None]] = {
    "indoor_flying1": (60, 1340),
    "indoor_flying2": (140, 1500),
    "indoor_flying3": (100, 1711),
    "indoor_flying4": (104, 380),
    "outdoor_day1": (0, 5020),
    "outdoor_day2": (30, -1),
}


def _find_data_file(path: Path) -> Path:
    if path.is_dir():
        found = sorted(path.glob("*_data.hdf5"))
        if len(found) != 1:
            raise ValueError(f"{path}: expected one *_data.hdf5 file in this folder, found {len(found)}")
        return check_regular(found[0])
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    return check_regular(path)


class MVSECRecording(Recording):
    """An MVSEC ``*_data.hdf5`` file (or a folder holding one).

    Parameters
    ----------
    path : path
        The ``*_data.hdf5`` file or its folder.
    camera : Camera, optional
        Intrinsics; default: ``davis/<side>/calibration`` when the file has it, else None.
    sensor_size : (int, int)
        ``(W, H)`` px, default 346x260.
    side : {"left", "right"}
        Which DAVIS.
    gt_flow : path, optional
        The ``*_gt_flow_dist.npz`` file; default: the one beside ``path`` named after it, if present.
    sort : bool
        Events out of order are refused (naming the first row) unless ``sort=True``: then they are
        decoded once into the event cache (``cache_dir=``), sorted by time, and read from there.
    cache_dir : path, optional
        Where ``sort=True`` keeps the sorted copy (default: the event cache, see :mod:`._cache`).
    """

    format = "mvsec"

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        camera: Camera | None = None,
        sensor_size: tuple[int, int] = SENSOR_SIZE,
        side: str = "left",
        gt_flow: str | os.PathLike | None = None,
        sort: bool = False,
        cache_dir: str | os.PathLike | None = None,
    ) -> None:
        self.data_file = _find_data_file(Path(path))
        self._file = _hdf5.open_h5(self.data_file)
        with _hdf5.closed_on_error(self._file):
            key = f"davis/{side}/events"
            self._key = key
            self._side = side
            self._ds = _hdf5.numeric_dataset(
                self._file, key, self.data_file, "not an MVSEC *_data.hdf5 file?"
            )
            if self._ds.ndim != 2 or self._ds.shape[1] != 4:
                raise ValueError(
                    f"{self.data_file}: '{key}' has shape {self._ds.shape}; expected (N, 4) x y t p"
                )
            n = self._ds.shape[0]
            span = event_span(n, lambda i: _hdf5.read(self._ds, (i, 2), self.data_file))
            calib_key = f"davis/{side}/calibration"
            if camera is None and calib_key in self._file:
                calib = _hdf5.numeric_dataset(self._file, calib_key, self.data_file, "calibration")
                values = np.ravel(_hdf5.read(calib, (), self.data_file))
                try:
                    camera = Camera.from_calib_line(values)
                except ValueError as exc:
                    raise ValueError(f"{self.data_file}: '{calib_key}': {exc}") from None
            super().__init__(
                self.data_file,
                sensor_size=sensor_size,
                camera=camera,
                undistorted=False,
                **span,
            )
        if gt_flow is None:
            guess = self.data_file.with_name(self.data_file.name.replace("_data.hdf5", "_gt_flow_dist.npz"))
            gt_flow = guess if guess != self.data_file and guess.is_file() else None
        elif not Path(gt_flow).is_file():
            raise FileNotFoundError(f"{gt_flow}: no such ground-truth flow file")
        self.gt_flow_file = Path(gt_flow) if gt_flow is not None else None
        self._gt = None
        if sort:
            with _hdf5.closed_on_error(self._file):
                self._sort_by_time(cache_dir)

    def _where(self, start: int, stop: int) -> str:
        return f"{self.data_file}: dataset '{self._key}', rows {start}..{stop}"

    def _where_time(self, row: int) -> str:
        return f"{self.data_file}: dataset '{self._key}', column 2 (t), row {row}"

    def _columns(self, start: int, stop: int):
        rows = np.asarray(_hdf5.read(self._ds, np.s_[start:stop], self.data_file), dtype=np.float64)
        return rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3]

    def _times(self, start: int, stop: int) -> np.ndarray:
        return np.asarray(_hdf5.read(self._ds, np.s_[start:stop, 2], self.data_file), dtype=np.float64)

    def _release(self) -> None:
        self._file.close()
        if self._gt is not None:
            self._gt[0].close()
            self._gt[1].close()

    def _flow_frames(self):
        if self._gt is None:
            path = self.gt_flow_file
            fx, fy = NpzFrames(path, "x_flow_dist"), NpzFrames(path, "y_flow_dist")
            try:
                with np.load(path, allow_pickle=False) as npz:
                    ts = np.asarray(npz["timestamps"], dtype=np.float64).ravel()
            except KeyError:
                raise KeyError(f"{path}: no array 'timestamps'") from None
            except (TypeError, *NPZ_ERRORS) as exc:  # a damaged file, object (pickled) or string arrays
                raise ValueError(f"{path}: 'timestamps' is not a numeric array ({exc})") from None
            if not np.all(np.isfinite(ts)):
                raise ValueError(f"{path}: 'timestamps' has non-finite values")
            W, H = self.sensor_size
            if fx.shape != fy.shape or fx.shape[1:] != (H, W) or len(ts) != fx.shape[0]:
                raise ValueError(
                    f"{path}: expected x_flow_dist, y_flow_dist of shape ({len(ts)}, {H}, {W}), "
                    f"got {fx.shape} and {fy.shape}"
                )
            if np.any(np.diff(ts) <= 0):
                raise ValueError(f"{path}: 'timestamps' must increase")
            self._gt = (fx, fy, ts)
        return self._gt

    @property
    def sequence(self) -> str:
        """The sequence name, from the file name (``indoor_flying1_data.hdf5`` -> ``indoor_flying1``)."""
        name = self.data_file.name
        return name[: -len("_data.hdf5")] if name.endswith("_data.hdf5") else self.data_file.stem

    def frame_times(self) -> np.ndarray | None:
        """The grey-scale frame timestamps ``davis/<side>/image_raw_ts`` (s), the instants between
        which MVSEC's flow is evaluated; None when the file has none."""
        key = f"davis/{self._side}/image_raw_ts"
        if key not in self._file:
            return None
        ds = _hdf5.numeric_dataset(self._file, key, self.data_file, "MVSEC frame timestamps")
        ts = np.ravel(_hdf5.finite(_hdf5.read(ds, (), self.data_file), self.data_file, key))
        if np.any(np.diff(ts) <= 0):
            raise ValueError(f"{self.data_file}: '{key}' must increase")
        return ts.astype(np.float64)

    def eval_windows(self, dt_frames: int = 1, valid_only: bool = True) -> list[tuple[float, float]]:
        """MVSEC's evaluation intervals: ``(ts[i], ts[i + dt_frames])`` over the grey-scale frame times
        (the published tables use ``dt_frames`` = 1 and 4), each inside the ground-truth flow.

        Parameters
        ----------
        dt_frames : int
            Frames per interval (>= 1).
        valid_only : bool
            Keep only the frames strictly between the first and last valid ground-truth frames of the
            sequence (:data:`MVSEC_VALID_GT_FRAMES`, when the file is named after a known sequence), as
            the evaluation code of tub-rip/event_based_optical_flow does; else the whole ground truth.

        Raises ValueError without frame timestamps (``davis/<side>/image_raw_ts``) or without the
        ground-truth file.
        """
        if isinstance(dt_frames, bool) or not isinstance(dt_frames, (int, np.integer)) or dt_frames < 1:
            raise ValueError(f"dt_frames must be a positive whole number of frames, got {dt_frames!r}")
        ts = self.frame_times()
        if ts is None:
            raise ValueError(f"{self.data_file}: no 'davis/{self._side}/image_raw_ts' (frame times)")
        if self.gt_flow_file is None:
            raise ValueError(f"{self.data_file}: no ground-truth flow file (*_gt_flow_dist.npz)")
        gt_ts = self._flow_frames()[2]
        if valid_only and self.sequence in MVSEC_VALID_GT_FRAMES:
            start, stop = MVSEC_VALID_GT_FRAMES[self.sequence]
            gt_ts = gt_ts[start:stop]
        if len(gt_ts) < 2:
            return []
        ts = ts[(ts > gt_ts[0]) & (ts < gt_ts[-1])]
        return [(float(ts[i]), float(ts[i + dt_frames])) for i in range(len(ts) - dt_frames)]

    def flow(self, t0: float, t1: float) -> np.ndarray | None:
        """Ground-truth flow ``(2, H, W)`` px over ``[t0, t1]`` s (NaN where invalid), accumulated from
        the gt_flow_dist frames as EV-FlowNet's ``estimate_corresponding_gt_flow``; None without the
        npz file. Frames are read one at a time."""
        if self.gt_flow_file is None:
            return None
        fx, fy, ts = self._flow_frames()
        # frame i is the displacement over [ts[i], ts[i+1]]: the last frame has no end time
        return accumulate_flow(lambda i: (fx[i], fy[i]), ts, t0, t1, str(self.gt_flow_file))
