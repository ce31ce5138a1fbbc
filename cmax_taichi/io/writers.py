"""Dense optical flow to files other tools read, and back.

* Middlebury ``.flo`` (Baker et al., "A Database and Evaluation Methodology for Optical Flow", IJCV
  2011; the format of Sintel, KITTI tools, flowiz, OpenCV's ``readOpticalFlow``): the float32 magic
  ``202021.25`` (the bytes ``PIEH``), int32 width, int32 height, then ``u v`` float32 pairs row by row,
  all little-endian. A pixel with a component larger than 1e9 in magnitude is unknown (NaN is written
  as 1e10, and such a pixel reads back as NaN in both components).
* NumPy ``.npz``: ``flow`` (2, H, W) float32 (x then y component, NaN where unknown) and the given
  metadata (e.g. ``t_start``, ``t_end``, ``unit``) as 0-d arrays.

Flow arrays are ``(2, H, W)`` (x then y component, px), the layout of
:meth:`~cmax_taichi.ContrastMaximization.dense_flow` and of the ground-truth readers.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = [
    "FLOW_FORMATS",
    "FLO_MAGIC",
    "read_flo",
    "read_flow",
    "read_flow_npz",
    "write_flo",
    "write_flow",
    "write_flow_npz",
]

#: the first float32 of a Middlebury .flo file ("PIEH" as bytes)
FLO_MAGIC = 202021.25
#: components larger than this in magnitude mark unknown flow (Middlebury's UNKNOWN_FLOW_THRESH)
FLO_UNKNOWN_THRESHOLD = 1e9
_FLO_UNKNOWN = 1e10
_FLO_MAX_SIDE = 1 << 16  # more is not a plausible image (and guards against reading garbage sizes)
#: the flow file formats of :func:`write_flow`, by suffix
FLOW_FORMATS = ("flo", "npz")


def _check_flow(flow) -> np.ndarray:
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[0] != 2 or flow.shape[1] < 1 or flow.shape[2] < 1:
        raise ValueError(f"flow must have shape (2, H, W) (x then y component), got {flow.shape}")
    if not np.issubdtype(flow.dtype, np.floating) and not np.issubdtype(flow.dtype, np.integer):
        raise TypeError(f"flow must be a real number array, got dtype {flow.dtype}")
    return flow


def write_flo(path: str | os.PathLike, flow) -> Path:
    """Write ``flow`` (2, H, W) px as a Middlebury ``.flo`` file; NaN becomes unknown (1e10).

    Returns the path. Values are stored as float32 (about 7 significant digits).
    """
    flow = _check_flow(flow)
    _, H, W = flow.shape
    uv = np.moveaxis(flow, 0, -1).astype("<f4")  # (H, W, 2): u v interleaved per pixel, row by row
    uv[~np.isfinite(uv)] = _FLO_UNKNOWN
    path = Path(path)
    with path.open("wb") as f:
        f.write(np.array([FLO_MAGIC], dtype="<f4").tobytes())
        f.write(np.array([W, H], dtype="<i4").tobytes())
        f.write(uv.tobytes())
    return path


def read_flo(path: str | os.PathLike) -> np.ndarray:
    """Read a Middlebury ``.flo`` file as (2, H, W) float32 px, NaN where the flow is unknown (both
    components of a pixel with either component above 1e9 in magnitude).

    Raises ValueError naming the file for a wrong magic number, an implausible size or a file whose
    length does not match its size (truncated).
    """
    path = Path(path)
    with path.open("rb") as f:
        head = f.read(12)
        if len(head) < 12:
            raise ValueError(f"{path}: not a .flo file (only {len(head)} bytes)")
        magic = float(np.frombuffer(head[:4], dtype="<f4")[0])
        if magic != FLO_MAGIC:
            raise ValueError(f"{path}: not a .flo file (magic {magic!r}, expected {FLO_MAGIC})")
        W, H = (int(v) for v in np.frombuffer(head[4:], dtype="<i4"))
        if not (0 < W <= _FLO_MAX_SIDE and 0 < H <= _FLO_MAX_SIDE):
            raise ValueError(f"{path}: implausible .flo size {W}x{H}")
        data = f.read()
    if len(data) != 8 * W * H:
        raise ValueError(
            f"{path}: {len(data)} bytes of flow for {W}x{H} pixels, expected {8 * W * H} (truncated?)"
        )
    uv = np.frombuffer(data, dtype="<f4").reshape(H, W, 2)
    flow = np.moveaxis(uv, -1, 0).astype(np.float32)
    flow[:, np.any(np.abs(flow) > FLO_UNKNOWN_THRESHOLD, axis=0)] = np.nan  # as Middlebury's unknown_flow()
    return flow


def write_flow_npz(path: str | os.PathLike, flow, **metadata) -> Path:
    """Write ``flow`` (2, H, W) as ``flow`` (float32) in an uncompressed ``.npz`` file, with each
    ``metadata`` item (numbers or strings, e.g. ``t_start=``, ``t_end=`` in s, ``unit="px"``) as a 0-d
    array. Returns the path (NumPy adds ``.npz`` when missing, so give it)."""
    flow = _check_flow(flow)
    if "flow" in metadata:
        raise ValueError("metadata cannot be named 'flow'")
    for key, value in metadata.items():
        if not isinstance(value, (int, float, str, bool, np.number)):
            raise TypeError(f"metadata {key!r} must be a number or a string, got {type(value).__name__}")
    path = Path(path)
    np.savez(path, flow=flow.astype(np.float32), **{k: np.asarray(v) for k, v in metadata.items()})
    return path


def read_flow_npz(path: str | os.PathLike) -> tuple[np.ndarray, dict]:
    """Read a file of :func:`write_flow_npz`: ``(flow (2, H, W) float32, metadata dict)``."""
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable .npz file ({exc})") from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise ValueError(f"{path}: a single .npy array, not an .npz archive")
    with data:
        if "flow" not in data.files:
            raise KeyError(f"{path}: no 'flow' array (arrays: {', '.join(data.files)})")
        try:
            flow = _check_flow(data["flow"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: {exc}") from None
        meta = {k: data[k].item() for k in data.files if k != "flow"}
    return flow, meta


def write_flow(path: str | os.PathLike, flow, **metadata) -> Path:
    """Write ``flow`` (2, H, W) by the suffix of ``path``: ``.flo`` (metadata is not stored) or
    ``.npz``."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix == "flo":
        return write_flo(path, flow)
    if suffix == "npz":
        return write_flow_npz(path, flow, **metadata)
    raise ValueError(f"{path}: unknown flow file type {suffix!r}; use one of {', '.join(FLOW_FORMATS)}")


def read_flow(path: str | os.PathLike) -> np.ndarray:
    """The (2, H, W) flow of a ``.flo`` or ``.npz`` file written by :func:`write_flow`."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix == "flo":
        return read_flo(path)
    if suffix == "npz":
        return read_flow_npz(path)[0]
    raise ValueError(f"{path}: unknown flow file type {suffix!r}; use one of {', '.join(FLOW_FORMATS)}")
