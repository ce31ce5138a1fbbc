"""Ground-truth flow over an arbitrary interval from per-frame flow maps, and lazy frame access to
the arrays of an ``.npz`` file (one frame in memory at a time).

The accumulation is the one of EV-FlowNet's ``estimate_corresponding_gt_flow`` (Zhu et al. RSS 2018),
which MVSEC evaluations use: frame ``i`` holds the displacement (px) of each pixel from ``ts[i]`` to
``ts[i+1]``.

* ``[t0, t1]`` shorter than the frame containing ``t0``: that frame's flow scaled by
  ``(t1 - t0) / (ts[i+1] - ts[i])`` (also when ``t1`` passes ``ts[i+1]``, as in EV-FlowNet);
* otherwise positions start at the pixel grid and are moved frame by frame by the flow sampled at
  their current (nearest-pixel, as ``cv2.remap(..., INTER_NEAREST)``) position: the partial first and
  last frames scaled by the share of them inside ``[t0, t1]``. The result is the total displacement.
  A pixel whose sampled flow has a component exactly zero (MVSEC's mark for no depth) or that leaves
  the image becomes invalid (EV-FlowNet zeroes that component instead).

Invalid pixels are NaN in both components.
"""

from __future__ import annotations

import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from cmax_taichi.io._files import NPZ_ERRORS, check_regular

Frame = Callable[[int], tuple[np.ndarray, np.ndarray]]


class GroundTruthRangeError(ValueError):
    """The interval asked for lies outside what the ground-truth flow covers (not an error of the
    file: a window there has no ground truth)."""


def _sample_nearest(fx: np.ndarray, fy: np.ndarray, xs: np.ndarray, ys: np.ndarray):
    """Flow at the nearest pixel of (xs, ys) (``np.rint``, as OpenCV rounds); NaN outside the image."""
    H, W = fx.shape
    xi = np.rint(xs).astype(np.int64)
    yi = np.rint(ys).astype(np.int64)
    inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
    vx = np.full(xs.shape, np.nan)
    vy = np.full(ys.shape, np.nan)
    vx[inside] = fx[yi[inside], xi[inside]]
    vy[inside] = fy[yi[inside], xi[inside]]
    return vx, vy


def accumulate_flow(
    frame: Frame, ts: np.ndarray, t0: float, t1: float, name: str, zero_is_invalid: bool = True
) -> np.ndarray:
    """Flow ``(2, H, W)`` px over ``[t0, t1]`` seconds (see the module docstring).

    Parameters
    ----------
    frame : callable
        ``frame(i) -> (flow_x, flow_y)``, each (H, W) px, the displacement from ``ts[i]`` to
        ``ts[i+1]``; NaN marks invalid pixels.
    ts : ndarray
        Frame boundaries, seconds, increasing; frames ``0 .. len(ts) - 2`` are used.
    t0, t1 : float
        The interval, seconds, inside ``[ts[0], ts[-1]]``.
    name : str
        What to name in errors (the ground-truth file).
    zero_is_invalid : bool
        Whether a zero flow component marks an invalid pixel (MVSEC: yes; DSEC has a validity
        channel instead).
    """
    t0, t1 = float(t0), float(t1)
    if not t1 > t0:
        raise ValueError(f"flow needs t1 > t0, got t0={t0}, t1={t1}")
    if len(ts) < 2 or t0 < ts[0] or t1 > ts[-1]:
        span = f"{ts[0]:.6f} .. {ts[-1]:.6f} s" if len(ts) else "nothing"
        raise GroundTruthRangeError(
            f"{name}: ground-truth flow covers {span}; asked for {t0:.6f} .. {t1:.6f} s"
        )
    i = min(int(np.searchsorted(ts, t0, side="right")) - 1, len(ts) - 2)
    gt_dt = ts[i + 1] - ts[i]
    dt = t1 - t0
    if gt_dt > dt:
        fx, fy = frame(i)
        out = np.stack([fx * (dt / gt_dt), fy * (dt / gt_dt)]).astype(np.float64)
        if zero_is_invalid:
            out[:, (fx == 0) & (fy == 0)] = np.nan
        out[:, ~(np.isfinite(out[0]) & np.isfinite(out[1]))] = np.nan
        return out
    fx, fy = frame(i)
    H, W = fx.shape
    y0, x0 = np.mgrid[0:H, 0:W].astype(np.float64)
    xs, ys = x0.copy(), y0.copy()
    valid = np.ones((H, W), dtype=bool)

    def step(fx, fy, scale):
        vx, vy = _sample_nearest(fx, fy, xs, ys)
        bad = ~(np.isfinite(vx) & np.isfinite(vy))
        if zero_is_invalid:
            bad |= (vx == 0) | (vy == 0)
        valid[bad] = False
        xs[...] += np.where(bad, 0.0, vx) * scale
        ys[...] += np.where(bad, 0.0, vy) * scale

    step(fx, fy, (ts[i + 1] - t0) / gt_dt)
    i += 1
    while i + 1 < len(ts) and ts[i + 1] < t1:
        step(*frame(i), 1.0)
        i += 1
    if i + 1 < len(ts):
        step(*frame(i), (t1 - ts[i]) / (ts[i + 1] - ts[i]))
    out = np.stack([xs - x0, ys - y0])
    out[:, ~valid] = np.nan
    return out


class NpzFrames:
    """Frames ``array[i]`` of an array stored in an ``.npz`` file, read one at a time.

    Uncompressed members (``np.savez``) are memory-mapped; compressed ones (``np.savez_compressed``)
    are read by seeking in the decompressed stream. Either way only one frame is in memory.
    """

    def __init__(self, path: Path, key: str) -> None:
        self.path = check_regular(path)  # a FIFO or a device is refused, never read
        self.key = key
        try:
            with zipfile.ZipFile(self.path) as zf:
                info = zf.getinfo(f"{key}.npy")
                with zf.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    if version == (1, 0):
                        shape, fortran, dtype = np.lib.format.read_array_header_1_0(member)
                    elif version == (2, 0):
                        shape, fortran, dtype = np.lib.format.read_array_header_2_0(member)
                    else:
                        raise ValueError(f"unsupported .npy format version {version}")
                    self._data_offset = member.tell()
                    if info.compress_type == zipfile.ZIP_STORED:
                        while member.read(1 << 24):  # the member's CRC-32, checked once at its end
                            pass
        except KeyError:
            raise KeyError(f"{self.path}: no array '{key}'") from None
        except NPZ_ERRORS as exc:
            raise ValueError(f"{self.path}: not a readable .npz file ({exc})") from None
        if fortran:
            raise ValueError(f"{self.path}: array '{key}' is stored in Fortran order; expected C order")
        self.shape, self.dtype = tuple(shape), np.dtype(dtype)
        if self.dtype.kind not in "iuf" or len(self.shape) < 1:
            # object arrays would need unpickling, which is never done
            raise ValueError(f"{self.path}: array '{key}' holds {self.dtype} values; expected numbers")
        self._frame_bytes = int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize
        self._map = None
        self._zip = self._member = None
        if info.compress_type == zipfile.ZIP_STORED:
            with open(self.path, "rb") as f:
                f.seek(info.header_offset)
                local = f.read(30)
                name_len = int.from_bytes(local[26:28], "little")
                extra_len = int.from_bytes(local[28:30], "little")
            offset = info.header_offset + 30 + name_len + extra_len + self._data_offset
            try:
                self._map = np.memmap(self.path, dtype=self.dtype, mode="r", offset=offset, shape=self.shape)
            except NPZ_ERRORS as exc:  # shorter than its header says
                raise ValueError(f"{self.path}: not a readable .npz file ({exc})") from None

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, i: int) -> np.ndarray:
        if not 0 <= i < len(self):
            raise IndexError(f"{self.path}: frame {i} of '{self.key}' out of range (0..{len(self) - 1})")
        if self._map is not None:
            return np.array(self._map[i])
        try:
            if self._member is None:
                # kept open: a forward seek decompresses only the gap (frames are asked for in time order)
                self._zip = zipfile.ZipFile(self.path)
                self._member = self._zip.open(f"{self.key}.npy")
            self._member.seek(self._data_offset + i * self._frame_bytes)
            raw = self._member.read(self._frame_bytes)
        except NPZ_ERRORS as exc:
            raise ValueError(f"{self.path}: '{self.key}' is not readable at frame {i} ({exc})") from None
        if len(raw) != self._frame_bytes:
            raise ValueError(f"{self.path}: array '{self.key}' is truncated at frame {i}")
        return np.frombuffer(raw, dtype=self.dtype).reshape(self.shape[1:]).copy()

    def close(self) -> None:
        """Release the open file (the memory map goes with the object)."""
        if self._member is not None:
            self._member.close()
            self._zip.close()
            self._member = self._zip = None
