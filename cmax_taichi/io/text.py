"""Generic text events: one event per line, whitespace-separated columns (``t x y p`` by default, or
``t x y depth p`` as in the MVSEC cut of EventEMin), with an optional ``calib.txt`` beside the file
(line 1 ``fx fy cx cy [k1 k2 p1 p2 [k3]]``, optional line 2 ``W H``).

The text is parsed once, in 8 MiB chunks by NumPy's C ``loadtxt`` (about 90 MB/s here, the fastest of
``loadtxt``, ``fromstring`` and ``split``; the csv module is 10x slower), into the binary cache of
:mod:`._cache`, then memory-mapped: a second open of the same unchanged file costs milliseconds.
"""

from __future__ import annotations

import io
import math
import os
from pathlib import Path
from typing import BinaryIO

import numpy as np

from cmax_taichi.core import checks
from cmax_taichi.core.events import Camera
from cmax_taichi.io._cache import CachedTableReads
from cmax_taichi.io._files import check_regular, is_present
from cmax_taichi.io.base import Recording

#: the column layouts recognised by their count when ``columns=`` is not given
DEFAULT_COLUMNS = {4: ("t", "x", "y", "p"), 5: ("t", "x", "y", "depth", "p")}
#: file names looked for, in this order, when a folder is opened
EVENT_FILE_NAMES = ("events.txt", "events_chunk.txt")
_CHUNK = 8 << 20  # bytes parsed at once (bounded memory)


def read_text_file(path: Path) -> str:
    """The text of a small side file (calibration, timestamps, image list): ValueError naming the
    file when it is not UTF-8 text (a binary file), OSError naming it when it cannot be read."""
    check_regular(path)  # a FIFO or a device is refused, never read
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise OSError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(
            f"{path}: not a text file (byte 0x{raw[exc.start]:02x} at offset {exc.start} is not UTF-8)"
        ) from None


def find_events_file(path: Path) -> Path:
    """The events text file of ``path`` (the file itself, or the first of EVENT_FILE_NAMES in a folder)."""
    if path.is_dir():
        for name in EVENT_FILE_NAMES:
            if is_present(path / name):
                return path / name
        raise FileNotFoundError(f"{path}: no {' or '.join(EVENT_FILE_NAMES)} in this folder")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    return check_regular(path)


def _data_lines(raw: bytes) -> list[tuple[int, bytes]]:
    """(1-based line number, content) of the non-empty, non-comment lines of ``raw``."""
    out = []
    for k, line in enumerate(raw.split(b"\n"), start=1):
        content = line.split(b"#", 1)[0].strip()
        if content:
            out.append((k, content))
    return out


def count_columns(path: Path) -> int:
    """Number of columns of the first data line of a text events file."""
    with open(check_regular(path), "rb") as f:
        head = f.read(1 << 16)
    complete = head[: head.rfind(b"\n") + 1] if b"\n" in head else head
    # the first data line only: splitting all of the 64 KiB took 1.7 ms, read twice per opened file
    start = 0
    while start < len(complete):
        end = complete.find(b"\n", start)
        end = len(complete) if end < 0 else end
        content = complete[start:end].split(b"#", 1)[0].strip()
        if content:
            return len(content.split())
        start = end + 1
    raise ValueError(f"{path}: no event line in the first 64 KiB (empty file?)")


def resolve_columns(path: Path, columns) -> tuple[tuple[str, ...], int]:
    """The column names of ``path`` and their count (checked against the file's first line)."""
    n = count_columns(path)
    if columns is None:
        if n not in DEFAULT_COLUMNS:
            raise ValueError(
                f"{path}: {n} columns per line; the known layouts are "
                + ", ".join(" ".join(c) for c in DEFAULT_COLUMNS.values())
                + " (pass columns=('t', 'x', 'y', 'p', ...) naming each column)"
            )
        return DEFAULT_COLUMNS[n], n
    columns = tuple(str(c) for c in columns)
    missing = [c for c in ("t", "x", "y", "p") if c not in columns]
    if missing:
        raise ValueError(f"columns= must name t, x, y and p; {missing} missing from {columns}")
    if len(columns) != n:
        raise ValueError(f"{path}: lines have {n} columns but columns= names {len(columns)}: {columns}")
    return columns, n


def _bad_line(path: Path, chunk: bytes, first_line: int, ncols: int) -> ValueError:
    """The error for the first malformed line of ``chunk`` (whose first line is ``first_line``)."""
    for k, content in _data_lines(chunk):
        fields = content.split()
        where = f"{path}, line {first_line + k - 1}"
        if len(fields) != ncols:
            hint = " (truncated line?)" if len(fields) < ncols else ""
            return ValueError(f"{where}: expected {ncols} numbers, got {len(fields)}{hint}: {content[:80]!r}")
        try:
            [float(v) for v in fields]
        except ValueError:
            return ValueError(f"{where}: not a number in {content[:80]!r}")
    return ValueError(f"{path}, lines {first_line}..: cannot parse the events")


def parse_text_events(path: Path, columns: tuple[str, ...], out: BinaryIO, check_order: bool = True) -> dict:
    """Parse the text events of ``path`` chunk by chunk; write ``t x y p`` rows (float64) to ``out``.

    Raises ValueError naming the file and the line for a malformed or truncated line, a non-finite
    value, a polarity outside {-1, 0, 1}, a polarity of the other convention than the lines before
    (-1 after 0 or 0 after -1: ``{0, 1}`` and ``{-1, +1}`` do not mix) or, with ``check_order``, a time
    that goes backwards (without it the caller sorts the rows: ``sort=True``).
    """
    ncols = len(columns)
    pick = [columns.index(c) for c in ("t", "x", "y", "p")]
    n = 0
    line_no = 1  # file line number of the first line of the current chunk
    t_first = t_last = math.nan
    lo = np.full(2, np.inf)
    hi = np.full(2, -np.inf)
    integer = True
    off_polarity = None  # the value marking OFF events so far (0 or -1), to refuse a mix
    rest = b""
    with open(path, "rb") as f:
        while True:
            block = f.read(_CHUNK)
            eof = not block
            data = rest + block
            if not eof:
                cut = data.rfind(b"\n") + 1
                if cut == 0:  # no full line yet: read on
                    rest = data
                    continue
                chunk, rest = data[:cut], data[cut:]
            else:
                chunk, rest = data, b""
            if chunk and not chunk.isspace():
                try:
                    arr = np.loadtxt(io.BytesIO(chunk), dtype=np.float64, comments="#", ndmin=2)
                except ValueError:
                    raise _bad_line(path, chunk, line_no, ncols) from None
                if arr.shape[1] != ncols:
                    raise _bad_line(path, chunk, line_no, ncols)
                rows = arr if pick == [0, 1, 2, 3] else np.ascontiguousarray(arr[:, pick])
                off_polarity = _check_rows(
                    path, chunk, line_no, rows, t_last if check_order else math.nan, off_polarity, check_order
                )
                if len(rows):
                    if n == 0:
                        t_first = float(rows[0, 0])
                    t_last = float(rows[-1, 0])
                    for k in (0, 1):  # 1-D reductions: much faster than axis=0 on a strided pair
                        column = rows[:, 1 + k]
                        lo[k] = min(lo[k], column.min())
                        hi[k] = max(hi[k], column.max())
                        integer = integer and bool(np.all(np.floor(column) == column))
                out.write(rows.data)
                n += len(rows)
            line_no += chunk.count(b"\n")
            if eof:
                break
    return {
        "n": n,
        "t_start": t_first,
        "t_end": t_last,
        "xy_min": lo.tolist() if n else None,
        "xy_max": hi.tolist() if n else None,
        "integer_coords": integer,
        "columns": list(columns),
    }


def _check_rows(
    path: Path,
    chunk: bytes,
    line_no: int,
    rows: np.ndarray,
    t_prev: float,
    off_polarity: float | None,
    check_order: bool = True,
) -> float | None:
    """ValueError naming the line of the first bad row; returns the OFF polarity value seen so far."""

    def where(i: int) -> str:
        k, content = _data_lines(chunk)[i]
        return f"{path}, line {line_no + k - 1} ({content[:80].decode(errors='replace')!r})"

    finite = np.isfinite(rows).all(axis=1)
    if not finite.all():
        raise ValueError(f"{where(int(np.argmin(finite)))}: non-finite value")
    pol_ok = np.isin(rows[:, 3], (-1.0, 0.0, 1.0))
    if not pol_ok.all():
        raise ValueError(f"{where(int(np.argmin(pol_ok)))}: polarity must be 0/1 or -1/+1")
    off = np.flatnonzero(rows[:, 3] <= 0)
    if len(off):
        first = float(rows[off[0], 3]) if off_polarity is None else off_polarity
        other = np.flatnonzero(rows[off, 3] != first)
        if len(other):
            raise ValueError(
                f"{where(int(off[other[0]]))}: polarity {rows[off[other[0]], 3]:+.0f} after earlier "
                f"{first:+.0f} polarities: use {{0, 1}} or {{-1, +1}}, not both"
            )
        off_polarity = first
    if not check_order:
        return off_polarity
    t = rows[:, 0]
    previous = np.concatenate([[-np.inf if math.isnan(t_prev) else t_prev], t[:-1]])
    back = np.flatnonzero(t < previous)
    if len(back):
        raise ValueError(
            f"{where(int(back[0]))}: time goes backwards (events must be sorted by time; "
            "open_recording(..., sort=True) sorts them)"
        )
    return off_polarity


def read_calib(path: Path) -> tuple[Camera | None, tuple[int, int] | None]:
    """``calib.txt``: line 1 ``fx fy cx cy [k1 k2 p1 p2 [k3]]``, optional line 2 ``W H``."""
    if not is_present(path):
        return None, None
    text = read_text_file(path)
    lines = [ln.split() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
    if not lines:
        raise ValueError(f"{path}: empty calibration file")
    try:
        camera = Camera.from_calib_line(lines[0])
    except ValueError as exc:
        raise ValueError(f"{path}, line 1: {exc}") from None
    size = None
    if len(lines) > 1:
        try:
            size = checks.sensor_size([float(v) for v in lines[1]])
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"{path}, line 2: expected the sensor size 'W H' (positive whole numbers), got "
                f"{' '.join(lines[1])!r} ({exc})"
            ) from None
    return camera, size


class TextRecording(CachedTableReads, Recording):
    """Text events, any column layout (see :func:`open_recording` for the options).

    Parameters
    ----------
    path : path
        The events file, or a folder holding ``events.txt`` (or ``events_chunk.txt``).
    columns : sequence of str, optional
        Names of the columns, which must include ``t`` (s), ``x``, ``y`` (px), ``p``; other names are
        ignored. Default: by the column count, ``t x y p`` or ``t x y depth p``.
    sensor_size : (int, int), optional
        ``(W, H)`` px. Default: line 2 of ``calib.txt``, else the format's default (ECD: 240x180),
        else the smallest sensor holding every event.
    camera : Camera, optional
        Default: line 1 of ``calib.txt`` beside the events, if present.
    undistorted : bool, optional
        Default: True when the coordinates are not all integers (undistorted floats).
    cache_dir : path, optional
        Where the binary cache goes (default ``$CMAX_TAICHI_CACHE`` or ``~/.cache/cmax_taichi``).
    cache : bool
        False: decode into a temporary file that is dropped with the recording.
    sort : bool
        Sort the events by time when they are out of order (stable), instead of refusing the file;
        the sorted table is what the cache keeps. ``rows_out_of_order`` says how many rows were.
    """

    format = "text"
    default_sensor_size: tuple[int, int] | None = None

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        columns=None,
        sensor_size: tuple[int, int] | None = None,
        camera: Camera | None = None,
        undistorted: bool | None = None,
        cache_dir: str | os.PathLike | None = None,
        cache: bool = True,
        sort: bool = False,
    ) -> None:
        path = Path(path)
        self.events_file = find_events_file(path)
        self.folder = path if path.is_dir() else path.parent
        names, _ = resolve_columns(self.events_file, columns)
        self._meta = self._load_table(
            self.events_file,
            "text",
            {"columns": names},
            lambda out: parse_text_events(self.events_file, names, out, check_order=not sort),
            cache_dir=cache_dir,
            cache=cache,
            sort=sort,
        )
        calib_camera, calib_size = read_calib(self.folder / "calib.txt")
        meta = self._meta
        integer = bool(meta["integer_coords"])
        if sensor_size is None:
            sensor_size = calib_size or self.default_sensor_size
        if sensor_size is None:
            if not meta["n"]:
                raise ValueError(f"{self.events_file}: no events and no sensor size (pass sensor_size=)")
            sensor_size = (int(math.ceil(meta["xy_max"][0])) + 1, int(math.ceil(meta["xy_max"][1])) + 1)
        sensor_size = checks.sensor_size(sensor_size, where=str(self.events_file))
        if integer and meta["n"]:
            (x0, y0), (x1, y1) = meta["xy_min"], meta["xy_max"]
            W, H = sensor_size
            if x0 < 0 or y0 < 0 or x1 > W - 1 or y1 > H - 1:
                raise ValueError(
                    f"{self.events_file}: events span x {x0:.0f}..{x1:.0f}, y {y0:.0f}..{y1:.0f}, "
                    f"outside the {W}x{H} sensor (pass sensor_size=(W, H))"
                )
        super().__init__(
            path,
            sensor_size=sensor_size,
            camera=camera if camera is not None else calib_camera,
            undistorted=(not integer) if undistorted is None else undistorted,
            **self.table_span(meta),
        )
        self.columns = tuple(names)
