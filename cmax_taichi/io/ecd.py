"""The Event-Camera Dataset (ECD, Mueggler et al. IJRR 2017) text layout: a folder with

* ``events.txt`` (or ``events_chunk.txt``): ``t x y p`` per line (s, integer px, {0, 1}), raw
  (distorted) coordinates of a DAVIS240C (240x180);
* ``calib.txt``: ``fx fy cx cy k1 k2 p1 p2 k3``;
* optional ``groundtruth.txt`` (``t px py pz qx qy qz qw``), ``imu.txt`` (``t ax ay az gx gy gz``,
  m/s^2 and rad/s), ``images.txt`` (``t path``);
* in the project's shared rotation cuts: ``motion.txt`` (``wx wy wz`` rad/s, the gyro sample at the
  window middle) and ``flow.npy`` ((1, 2, H, W) flow in px over the whole window).

Events go through the binary cache of the text reader; the small ground-truth files are read on
first use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cmax_taichi.core import checks
from cmax_taichi.io._files import is_present
from cmax_taichi.io.base import interpolate_rows
from cmax_taichi.io.text import TextRecording, read_text_file


def _load_table(path: Path, ncols: int) -> np.ndarray:
    """A small numeric text table with exactly ``ncols`` columns (ValueError naming the file)."""
    try:
        table = np.loadtxt(path, dtype=np.float64, comments="#", ndmin=2)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    if table.size and table.shape[1] != ncols:
        raise ValueError(f"{path}: expected {ncols} columns, got {table.shape[1]}")
    if not np.all(np.isfinite(table)):
        raise ValueError(f"{path}: non-finite value")
    return table.reshape(-1, ncols)


class ECDRecording(TextRecording):
    """An ECD folder (see the module docstring); options as :class:`~.text.TextRecording`, with the
    DAVIS240C's 240x180 as the default sensor size."""

    format = "ecd"
    default_sensor_size = (240, 180)

    def __init__(self, path, **options) -> None:
        options.setdefault("columns", ("t", "x", "y", "p"))
        super().__init__(path, **options)
        self._gt: dict[str, np.ndarray | None] = {}

    def _file(self, name: str, ncols: int) -> np.ndarray | None:
        if name not in self._gt:
            path = self.folder / name
            self._gt[name] = _load_table(path, ncols) if is_present(path) else None
        return self._gt[name]

    def angular_velocity(self, t) -> np.ndarray | None:
        """Angular velocity, rad/s, at ``t`` (s): the gyro of ``imu.txt`` interpolated linearly (the
        DAVIS IMU, whose axes ECD uses as the camera frame), else the constant of ``motion.txt`` (one
        gyro sample at the window middle, returned for every ``t``); None when neither exists."""
        imu = self._file("imu.txt", 7)
        if imu is not None:
            return interpolate_rows(t, imu[:, 0], imu[:, 4:7], str(self.folder / "imu.txt"))
        motion = self._file("motion.txt", 3)
        if motion is None:
            return None
        if len(motion) != 1:
            raise ValueError(f"{self.folder / 'motion.txt'}: expected one line 'wx wy wz', got {len(motion)}")
        tq = np.asarray(t, dtype=np.float64)
        return np.broadcast_to(motion[0], tq.shape + (3,)).copy()

    def poses(self) -> np.ndarray | None:
        """``groundtruth.txt`` as an (M, 8) array ``t px py pz qx qy qz qw`` (s, m, quaternion)."""
        gt = self._file("groundtruth.txt", 8)
        return None if gt is None else gt.copy()

    def images(self) -> list[tuple[float, Path]] | None:
        """``images.txt`` as ``(t, path)`` pairs (s, absolute path); None when absent."""
        path = self.folder / "images.txt"
        if not is_present(path):
            return None
        out = []
        for k, line in enumerate(read_text_file(path).splitlines(), start=1):
            fields = line.split("#", 1)[0].split()
            if not fields:
                continue
            try:
                out.append((float(fields[0]), self.folder / fields[1]))
            except (ValueError, IndexError):
                raise ValueError(f"{path}, line {k}: expected 't path', got {line[:80]!r}") from None
        return out

    def flow(self, t0: float, t1: float) -> np.ndarray | None:
        """``flow.npy`` of the shared rotation cuts, (2, H, W) px. That file holds the instantaneous
        rotational flow of ``motion.txt`` times the window's duration ``t_end - t_start``; the flow
        over ``[t0, t1]`` is scaled by ``(t1 - t0) / (t_end - t_start)``. None without ``flow.npy``."""
        path = self.folder / "flow.npy"
        if not is_present(path):
            return None
        try:
            # never unpickle: a pickled .npy runs code of whoever wrote it
            flow = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise ValueError(
                f"{path}: not a plain numeric .npy array ({exc}); pickled object arrays are refused"
            ) from None
        if not isinstance(flow, np.ndarray) or flow.dtype.kind not in "iuf":
            kind = flow.dtype if isinstance(flow, np.ndarray) else type(flow).__name__
            raise ValueError(f"{path}: expected a float array of flow in px, got {kind}")
        W, H = self.sensor_size
        if flow.shape not in ((1, 2, H, W), (2, H, W)):
            raise ValueError(f"{path}: expected shape (1, 2, {H}, {W}), got {flow.shape}")
        span = self.t_end - self.t_start
        if not span > 0:
            raise ValueError(f"{self.events_file}: the window has no duration to scale flow.npy by")
        t0 = checks.seconds("flow t0", t0)
        t1 = checks.seconds("flow t1", t1)
        return flow.reshape(2, H, W).astype(np.float64) * ((t1 - t0) / span)
