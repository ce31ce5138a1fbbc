"""Dense optical flow to files other tools read, and back.

* Middlebury ``.flo`` (Baker et al., "A Database and Evaluation Methodology for Optical Flow", IJCV
  2011; the format of Sintel, KITTI tools, flowiz, OpenCV's ``readOpticalFlow``): the float32 magic
  ``202021.25`` (the bytes ``PIEH``), int32 width, int32 height, then ``u v`` float32 pairs row by row,
  all little-endian. A pixel with a component larger than 1e9 in magnitude is unknown (NaN is written
  as 1e10, and such a pixel reads back as NaN in both components).
* NumPy ``.npz``: ``flow`` (2, H, W) float32 (x then y component, NaN where unknown) and the given
  metadata (e.g. ``t_start``, ``t_end``, ``unit``) as 0-d arrays.
* The DSEC optical-flow benchmark's 16-bit PNG (https://dsec.ifi.uzh.ch/optical-flow-submission-format/
  and ``scripts/check_optical_flow_submission.py`` of uzh-rpg/DSEC): RGB uint16, ``R = x * 128 +
  2**15``, ``G = y * 128 + 2**15`` (px, 1/128 px steps, so -256 .. +256 px), ``B`` = 1 where valid and
  0 elsewhere (the benchmark's check wants the third channel <= 1; it scores every pixel of a
  submission and reads the ground truth's validity from that channel). The files of a submission are
  ``<sequence>/<file_index:06d>.png`` (:func:`dsec_submission_path`).

Flow arrays are ``(2, H, W)`` (x then y component, px), the layout of
:meth:`~cmax_taichi.ContrastMaximization.dense_flow` and of the ground-truth readers.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cmax_taichi.io._files import NPZ_ERRORS, check_regular

__all__ = [
    "DSEC_FLOW_LIMIT",
    "FLOW_FORMATS",
    "FLO_MAGIC",
    "FlowWindow",
    "dsec_submission_path",
    "read_flow_windows",
    "timestamps_unit",
    "write_dsec_flow_png",
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
#: the flow file formats of :func:`write_flow`, by suffix (png: DSEC's 16-bit flow PNG)
FLOW_FORMATS = ("flo", "npz", "png")
#: the largest flow component a DSEC PNG holds, px: (2**16 - 1 - 2**15) / 128
DSEC_FLOW_LIMIT = (2**16 - 1 - 2**15) / 128.0


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
    path = check_regular(path)  # a FIFO or a device is refused, never read
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
    if "t_start" in metadata or "t_end" in metadata:  # the interval evaluate scores the file over
        a, b = float(metadata.get("t_start", math.nan)), float(metadata.get("t_end", math.nan))
        if not (math.isfinite(a) and math.isfinite(b) and b > a):
            raise ValueError(f"{path}: the interval needs finite t_start < t_end (s), got {a} .. {b}")
    path = Path(path)
    np.savez(path, flow=flow.astype(np.float32), **{k: np.asarray(v) for k, v in metadata.items()})
    return path


def read_flow_npz(path: str | os.PathLike) -> tuple[np.ndarray, dict]:
    """Read a file of :func:`write_flow_npz`: ``(flow (2, H, W) float32, metadata dict)``."""
    path = check_regular(path)  # a FIFO or a device is refused, never read
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError(f"{path}: a single .npy array, not an .npz archive")
        with data:
            if "flow" not in data.files:
                raise KeyError(f"{path}: no 'flow' array (arrays: {', '.join(data.files)})")
            flow, meta = data["flow"], {k: data[k].item() for k in data.files if k != "flow"}
    except (KeyError, TypeError):
        raise
    except NPZ_ERRORS as exc:  # truncated, a bad CRC, not an archive
        message = str(exc) if str(exc).startswith(str(path)) else f"{path}: not a readable .npz file ({exc})"
        raise ValueError(message) from None
    try:
        flow = _check_flow(flow)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {exc}") from None
    return flow, meta


def write_dsec_flow_png(path: str | os.PathLike, flow, valid=None, *, clip: bool = False) -> Path:
    """Write ``flow`` (2, H, W), px, as a DSEC 16-bit flow PNG (module docstring).

    Parameters
    ----------
    path : path
        The ``.png`` file.
    flow : array_like
        (2, H, W) displacement, px (DSEC: from the reference time to the target time, about 100 ms).
    valid : array_like of bool, optional
        (H, W) the pixels with a flow; default: where both components are finite. Invalid pixels are
        written as zero flow with ``B = 0`` (a submission is scored on every pixel, so they count as
        zero flow there).
    clip : bool
        A component beyond +-256 px (:data:`DSEC_FLOW_LIMIT`) does not fit: False raises ValueError
        naming how many; True clips them (with a RuntimeWarning that counts them).

    Returns the path. Values are rounded to the nearest 1/128 px.
    """
    flow = _check_flow(flow).astype(np.float64)
    finite = np.all(np.isfinite(flow), axis=0)
    if valid is None:
        valid = finite
    else:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != flow.shape[1:]:
            raise ValueError(f"valid has shape {valid.shape}, the flow {flow.shape[1:]}")
        if np.any(valid & ~finite):
            raise ValueError(
                f"{int(np.count_nonzero(valid & ~finite))} pixel(s) marked valid have a non-finite flow"
            )
    flow = np.where(valid, flow, 0.0)
    over = np.any(np.abs(flow) > DSEC_FLOW_LIMIT, axis=0)
    if np.any(over):
        n_over = int(np.count_nonzero(over))
        if not clip:
            raise ValueError(
                f"{path}: {n_over} pixel(s) have a flow component beyond +-{DSEC_FLOW_LIMIT:g} px, more than "
                "a DSEC PNG holds (pass clip=True to clip them)"
            )
        import warnings

        warnings.warn(
            f"{path}: {n_over} pixel(s) clipped to +-{DSEC_FLOW_LIMIT:g} px", RuntimeWarning, stacklevel=2
        )
    coded = np.clip(np.rint(flow * 128.0 + 2.0**15), 0, 2**16 - 1).astype(np.uint16)
    image = np.stack([coded[0], coded[1], valid.astype(np.uint16)], axis=-1)
    from cmax_taichi.io._png import write_png

    return write_png(path, image)


def dsec_submission_path(out_dir: str | os.PathLike, sequence: str, file_index: int) -> Path:
    """``<out_dir>/<sequence>/<file_index:06d>.png``, the name the DSEC benchmark expects (the index
    from its ``test_forward_optical_flow_timestamps`` CSV,
    :func:`cmax_taichi.io.dsec.read_flow_timestamps`)."""
    if not isinstance(file_index, (int, np.integer)) or file_index < 0:
        raise ValueError(f"file_index must be a non-negative integer, got {file_index!r}")
    return Path(out_dir) / str(sequence) / f"{int(file_index):06d}.png"


def write_flow(path: str | os.PathLike, flow, **metadata) -> Path:
    """Write ``flow`` (2, H, W) by the suffix of ``path``: ``.flo`` (metadata is not stored),
    ``.npz`` or ``.png`` (DSEC's 16-bit PNG, metadata not stored; :func:`write_dsec_flow_png`)."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix == "flo":
        return write_flo(path, flow)
    if suffix == "npz":
        return write_flow_npz(path, flow, **metadata)
    if suffix == "png":
        return write_dsec_flow_png(path, flow)
    raise ValueError(f"{path}: unknown flow file type {suffix!r}; use one of {', '.join(FLOW_FORMATS)}")


def read_flow(path: str | os.PathLike) -> np.ndarray:
    """The (2, H, W) flow of a ``.flo``, ``.npz`` or DSEC ``.png`` file (NaN where unknown/invalid)."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix == "flo":
        return read_flo(path)
    if suffix == "npz":
        return read_flow_npz(path)[0]
    if suffix == "png":
        from cmax_taichi.io.dsec import read_flow_png

        return read_flow_png(path)[0]
    raise ValueError(f"{path}: unknown flow file type {suffix!r}; use one of {', '.join(FLOW_FORMATS)}")


@dataclass(frozen=True)
class FlowWindow:
    """One flow file and the interval its flow covers.

    Attributes
    ----------
    path : Path
    t_start, t_end : float
        The interval, s.
    unit : str
        ``"px"`` (displacement over the interval) or ``"px/s"``.
    fingerprint : str or None
        The fingerprint of the recording the flow was estimated on (:meth:`Recording.fingerprint`), when
        the file carries it (``.npz`` files of ``cmax-taichi flow``).
    """

    path: Path
    t_start: float
    t_end: float
    unit: str = "px"
    fingerprint: str | None = None

    def displacement(self) -> np.ndarray:
        """The flow of the file as the displacement (2, H, W) px over ``[t_start, t_end]``."""
        flow = read_flow(self.path).astype(np.float64)
        return flow * (self.t_end - self.t_start) if self.unit == "px/s" else flow


def _read_times(path: Path) -> tuple[np.ndarray, np.ndarray | None, str]:
    """``(intervals (K, 2) s, file indices or None, the unit read: "s" or "us")`` of a timestamps file:
    ``t_start t_end`` per line in seconds, or integers in microseconds (DSEC's ``from_us, to_us[,
    file_index]``)."""
    from cmax_taichi.io.text import read_text_file

    rows, integer = [], True
    for k, line in enumerate(read_text_file(path).splitlines(), start=1):
        content = line.split("#", 1)[0].replace(",", " ").split()
        if not content:
            continue
        try:
            values = [float(v) for v in content]
        except ValueError:
            raise ValueError(f"{path}, line {k}: expected numbers, got {line[:80]!r}") from None
        if len(values) not in (2, 3) or not all(np.isfinite(values)) or values[1] <= values[0]:
            raise ValueError(
                f"{path}, line {k}: expected 't_start t_end' (t_end > t_start), got {line[:80]!r}"
            )
        integer &= all(v.lstrip("+-").isdigit() for v in content)
        rows.append(values)
    if not rows or len({len(r) for r in rows}) != 1:
        raise ValueError(f"{path}: expected the same 2 or 3 columns on every line (and at least one line)")
    table = np.array(rows)
    scale = 1e-6 if integer else 1.0  # whole numbers are microseconds (DSEC), else seconds
    indices = table[:, 2].astype(np.int64) if table.shape[1] == 3 else None
    return table[:, :2] * scale, indices, "us" if integer else "s"


def timestamps_unit(path: str | os.PathLike) -> str:
    """How :func:`read_flow_windows` reads the timestamps file ``path``: ``"us"`` (whole numbers,
    DSEC's microseconds) or ``"s"``."""
    return _read_times(Path(path))[2]


def read_flow_windows(
    source: str | os.PathLike, timestamps: str | os.PathLike | None = None
) -> list[FlowWindow]:
    """The flow files of ``source`` (a folder or one file) with the interval of each.

    ``.npz`` files of :func:`write_flow_npz` carry their interval (``t_start``, ``t_end`` in s, ``unit``
    ``"px"`` or ``"px/s"``; what ``cmax-taichi estimate --flow-out`` writes). ``.flo`` and DSEC ``.png``
    files need ``timestamps``: a text file with ``t_start t_end`` (s) per line, one line per file in
    name order, or DSEC's ``from_us, to_us[, file_index]`` integers (microseconds; with a file index the
    files are matched by their name, ``<file_index:06d>.png``).

    Raises ValueError for a folder without flow files, files without an interval, a count of lines
    that does not match the files, or a missing indexed file.
    """
    source = Path(source)
    if source.is_dir():
        files = sorted(
            f for f in source.iterdir() if f.suffix.lower().lstrip(".") in FLOW_FORMATS and f.is_file()
        )
        if not files:
            raise ValueError(f"{source}: no flow files ({', '.join('*.' + f for f in FLOW_FORMATS)})")
    elif source.is_file():
        files = [source]
    else:
        raise FileNotFoundError(f"{source}: no such flow file or folder")
    if timestamps is not None:
        intervals, indices, _ = _read_times(Path(timestamps))
        if indices is not None:
            by_name = {f.stem: f for f in files}
            missing = [f"{i:06d}" for i in indices if f"{i:06d}" not in by_name]
            if missing:
                raise ValueError(
                    f"{timestamps}: no flow file {missing[0]}.png (and {len(missing) - 1} more) in {source}"
                )
            files = [by_name[f"{i:06d}"] for i in indices]
        elif len(intervals) != len(files):
            raise ValueError(
                f"{timestamps}: {len(intervals)} intervals for {len(files)} flow files in {source}"
            )
        return [FlowWindow(f, float(a), float(b)) for f, (a, b) in zip(files, intervals, strict=True)]
    windows = []
    for f in files:
        if f.suffix.lower() != ".npz":
            raise ValueError(f"{f}: a .{f.suffix.lstrip('.')} file has no interval: pass its timestamps file")
        _, meta = read_flow_npz(f)
        try:
            t0, t1 = float(meta["t_start"]), float(meta["t_end"])
        except (KeyError, TypeError, ValueError):
            raise ValueError(
                f"{f}: no numeric 't_start' and 't_end' (s) in the file: pass a timestamps file"
            ) from None
        unit = str(meta.get("unit", "px"))
        if unit not in ("px", "px/s"):
            raise ValueError(f"{f}: unit {unit!r}; expected 'px' (displacement) or 'px/s'")
        if not (np.isfinite(t0) and np.isfinite(t1) and t1 > t0):
            raise ValueError(f"{f}: t_end ({t1}) must exceed t_start ({t0})")
        fingerprint = meta.get("fingerprint")
        windows.append(FlowWindow(f, t0, t1, unit, None if fingerprint is None else str(fingerprint)))
    return windows
