"""Prophesee RAW (EVT 2.0, 2.1, 3.0) and DAT files, and Event Stream (``.es``) files, through the
optional package ``faery`` (Rust decoders; ``pip install "cmax-taichi[formats]"`` or ``pip install faery``),
except EVT 2.1, which faery 0.7.1 cannot decode and :func:`evt21_packets` decodes here with NumPy.

========= ============================================ ==========================================
format    files                                        sensor size from
========= ============================================ ==========================================
``raw``   ``*.raw`` / ``*.evt``: EVT 2.0, 2.1 or 3.0    the ``% format``/``% geometry`` header
``dat``   ``*.dat`` whose first byte is ``%``: CD       the ``% Width``/``% Height`` header
          events, DAT version 1 or 2
``es``    ``*.es``: Event Stream 2.x, DVS or ATIS      the Event Stream header
========= ============================================ ==========================================

None of these formats has an event index, so the file is decoded once, packet by packet (bounded
memory), into the binary event cache of :mod:`._cache` and memory-mapped afterwards, like the text
and AEDAT4 formats. Timestamps are integer microseconds in the files and seconds (float64) here; the
RAW/DAT header's ``t0`` is added back by ``faery`` (times are the camera's clock, not zero-based).
Polarity 1 (ON) becomes +1 and 0 (OFF) -1. Event Stream files store ``y`` upwards; ``faery`` (and so
this reader) flips it to the usual top-left origin, and ATIS exposure events are dropped.

Damaged files: ``faery`` silently ignores a last, partial word, so the reader checks that the payload
after the header is a whole number of words (RAW: 2 / 4 / 8 bytes for EVT 3.0 / 2.0 / 2.1; DAT: the
event size in the header) and raises ValueError for a truncated file; bytes that decode to events
outside the sensor, or an unknown event type, raise ValueError naming the file. A file cut exactly at
a word boundary (or an ``.es`` file, whose events have no fixed size) cannot be told from a shorter
recording.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import BinaryIO

import numpy as np

from cmax_taichi.core.events import Camera
from cmax_taichi.io._cache import CachedTableReads
from cmax_taichi.io._files import check_regular
from cmax_taichi.io.base import Recording

PACKAGE = "faery"
EXTRA = "formats"
#: the encodings ``version=`` may name, per faery file type
VERSIONS = {"evt": ("evt2", "evt2.1", "evt3"), "dat": ("dat1", "dat2"), "es": ()}
#: bytes per word of each RAW encoding
_EVT_WORD_BYTES = {"evt2": 4, "evt2.1": 8, "evt3": 2}
_HEADER_LIMIT = 1 << 20  # a header longer than this is not a header


def _faery(path: Path, what: str):
    try:
        import faery
    except ImportError:
        raise ImportError(
            f"{path}: reading {what} files needs the optional package '{PACKAGE}': "
            f'pip install "cmax-taichi[{EXTRA}]"  (or pip install {PACKAGE})'
        ) from None
    return faery


def read_header(path: Path) -> tuple[list[str], int]:
    """The ``%`` header lines of a Prophesee RAW or DAT file (without ``% ``) and the header's length
    in bytes. The header is the run of lines starting with ``%`` at the start of the file (a RAW
    header may end with ``% end``)."""
    lines: list[str] = []
    offset = 0
    with open(path, "rb") as f:
        while offset < _HEADER_LIMIT:
            if f.read(1) != b"%":
                break
            f.seek(offset)
            line = f.readline(_HEADER_LIMIT)
            if not line.endswith(b"\n"):
                break  # no line end: the file stops inside the header
            offset += len(line)
            text = line[1:].decode("latin-1").strip()
            lines.append(text)
            if text == "end":
                break
    return lines, offset


def raw_version(lines: list[str]) -> str | None:
    """The EVT encoding named by a RAW header (``"evt2"``, ``"evt2.1"``, ``"evt3"``), or None."""
    for line in lines:
        key, _, value = line.partition(" ")
        value = value.strip().lower()
        if key == "evt":
            return {"2.0": "evt2", "2.1": "evt2.1", "3.0": "evt3"}.get(value)
        if key == "format":
            name = value.split(";", 1)[0].strip()
            return {"evt2": "evt2", "evt21": "evt2.1", "evt3": "evt3"}.get(name)
    return None


def check_whole_words(path: Path, file_type: str, version: str | None) -> None:
    """ValueError when the payload of a RAW or DAT file is not a whole number of words (a truncated
    file, whose last partial word ``faery`` would drop silently)."""
    size = path.stat().st_size
    lines, header = read_header(path)
    if file_type == "evt":
        encoding = raw_version(lines) or version or "evt3"  # faery's default when the header says nothing
        word, payload = _EVT_WORD_BYTES.get(encoding), size - header
        what = f"{encoding.upper()} words"
    elif file_type == "dat":
        with open(path, "rb") as f:
            f.seek(header)
            type_and_size = f.read(2)
        if len(type_and_size) < 2:
            if size > header:
                raise ValueError(f"{path}: truncated DAT file (it stops inside the event type and size)")
            return
        word, payload = type_and_size[1], size - header - 2
        what = f"{word}-byte events"
    else:
        return
    if word and payload % word:
        raise ValueError(
            f"{path}: truncated or damaged file: {payload} bytes after the header is not a whole number "
            f"of {what} ({payload % word} bytes left over)"
        )


def raw_geometry(lines: list[str]) -> tuple[int, int] | None:
    """``(W, H)`` from a RAW header's ``% format NAME;width=W;height=H`` or ``% geometry WxH`` line."""
    for line in lines:
        key, _, value = line.partition(" ")
        if key == "format":
            options = dict(item.partition("=")[::2] for item in value.split(";")[1:])
            if options.get("width", "").strip().isdigit() and options.get("height", "").strip().isdigit():
                return int(options["width"]), int(options["height"])
        if key == "geometry":
            w, _, h = value.strip().partition("x")
            if w.isdigit() and h.isdigit():
                return int(w), int(h)
    return None


def _faery_decoder(path: Path, file_type: str, sensor_size, version: str | None, what: str):
    """faery's decoder of ``path``; ValueError naming the file when the header cannot be read."""
    faery = _faery(path, what)
    try:
        return faery.events_stream_from_file(
            path,
            # None: the size must come from the header (faery's own default would be 1280x720)
            dimensions_fallback=None if sensor_size is None else tuple(int(v) for v in sensor_size),
            version_fallback=version,
            file_type=file_type,
        )
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # the Rust decoders raise plain exceptions, or panic, on bad files
        hint = ""
        if sensor_size is None and file_type in ("evt", "dat"):
            hint = " (a header without the sensor size needs sensor_size=(W, H))"
        raise ValueError(f"{path}: not a readable {what} file ({exc}){hint}") from None


_EVT21_CHUNK_WORDS = 1 << 17  # 1 MiB of EVT 2.1 words decoded at once (bounded memory)
_EVENT_DTYPE = np.dtype([("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("on", "?")])


#: word types an EVT 2.1 type half may hold (CD OFF/ON, TIME_HIGH, trigger, vendor, continued)
_EVT21_TYPES = (0x0, 0x1, 0x8, 0xA, 0xE, 0xF)


def evt21_legacy_order(path: Path, header_length: int, header_says_legacy: bool) -> bool:
    """Whether an EVT 2.1 file has IMX636's word order (the type half first), judged from its first
    MiB: the type half holds only known word types and at least one TIME_HIGH, a validity mask does not.
    When both orders (or neither) fit, the header decides (``endianness=legacy``)."""
    with open(path, "rb") as f:
        f.seek(header_length)
        chunk = f.read(8 * _EVT21_CHUNK_WORDS)
    words = np.frombuffer(chunk[: len(chunk) - len(chunk) % 8], dtype="<u8")
    fits = []
    for half in (words >> np.uint64(60), (words >> np.uint64(28)) & np.uint64(0xF)):  # spec, legacy
        fits.append(bool(len(words)) and bool(np.isin(half, _EVT21_TYPES).all()) and bool(np.any(half == 8)))
    if fits[0] != fits[1]:
        return fits[1]
    return header_says_legacy


def evt21_packets(path: Path, header_length: int, sensor_size: tuple[int, int], legacy: bool):
    """Decode an EVT 2.1 payload chunk by chunk (faery 0.7 has no EVT 2.1 decoder); yields structured
    arrays ``t`` (us), ``x``, ``y``, ``on``, as faery's decoders do.

    Layout (Prophesee's EVT 2.1 specification): 64-bit little-endian words; the 32-bit half with the
    word type in its 4 top bits holds ``ts[5:0]`` (bits 22-27), ``x`` (11-21) and ``y`` (0-10) of a CD
    word, or ``ts[33:6]`` (bits 0-27) of a TIME_HIGH word (type 8); the other half is the validity
    mask of the 32 pixels ``x .. x + 31``. In the specification's layout the type half is the upper
    one; IMX636 sensors send it first (OpenEB's ``endianness=legacy``: the lower half), see
    :func:`evt21_legacy_order`. Types 0 / 1 are
    OFF / ON CD events; triggers and vendor words are skipped, as are CD words before the first
    TIME_HIGH. A decreasing TIME_HIGH is a 34-bit counter wrap; times never decrease (as faery's
    EVT 2.0 decoder: a time below the previous one is raised to it).
    """
    W, H = sensor_size
    t_high = -1  # time (us) of the TIME_HIGH in force; -1: none yet
    previous_high = -1  # its 28-bit value
    wraps = 0  # 34-bit counter loops so far
    t_last = 0
    bit = np.arange(32, dtype=np.uint32)
    with open(path, "rb") as f:
        f.seek(header_length)
        while True:
            chunk = f.read(8 * _EVT21_CHUNK_WORDS)
            if not chunk:
                return
            words = np.frombuffer(chunk[: len(chunk) - len(chunk) % 8], dtype="<u8")
            low = (words & np.uint64(0xFFFFFFFF)).astype(np.uint32)
            high = (words >> np.uint64(32)).astype(np.uint32)
            head, mask = (low, high) if legacy else (high, low)
            kind = head >> np.uint32(28)
            # the TIME_HIGH in force at each word: carry the last one across chunks, unwrap the 34-bit loop
            is_th = kind == 8
            th_value = (head[is_th] & np.uint32(0x0FFFFFFF)).astype(np.int64)
            before = np.concatenate([[previous_high], th_value[:-1]])
            loops = wraps + np.cumsum(th_value < before)
            th_time = (loops << 34) + (th_value << 6)
            word_high = np.concatenate([[t_high], th_time])[np.cumsum(is_th)]
            if len(th_value):
                previous_high, wraps, t_high = int(th_value[-1]), int(loops[-1]), int(th_time[-1])
            cd = (kind <= 1) & (word_high >= 0)
            if np.any(cd):
                h, m = head[cd], mask[cd]
                t_word = word_high[cd] + ((h >> np.uint32(22)) & np.uint32(0x3F)).astype(np.int64)
                t_word = np.maximum.accumulate(np.maximum(t_word, t_last))
                t_last = int(t_word[-1])
                word, k = np.nonzero((m[:, None] >> bit[None, :]) & np.uint32(1))
                x = ((h >> np.uint32(11)) & np.uint32(0x7FF)).astype(np.int64)[word] + k
                y = (h & np.uint32(0x7FF)).astype(np.int64)[word]
                if len(x) and (x.max() >= W or y.max() >= H):
                    raise ValueError(f"x up to {x.max()}, y up to {y.max()} outside the {W}x{H} sensor")
                events = np.empty(len(x), dtype=_EVENT_DTYPE)
                events["t"], events["x"], events["y"] = t_word[word], x, y
                events["on"] = (kind[cd] == 1)[word]
                yield events


class _Packets:
    """An iterable of event packets with the sensor size, like a faery decoder."""

    def __init__(self, packets, size: tuple[int, int]) -> None:
        self._packets, self._size = packets, size

    def __iter__(self):
        return iter(self._packets())

    def dimensions(self) -> tuple[int, int]:
        return self._size


def _decode(decoder, path: Path, what: str, out: BinaryIO, check_order: bool = True) -> dict:
    """Write the packets of ``decoder`` to ``out`` as ``t x y p`` rows (s, px, px, -1/+1)."""
    n, t_first, t_last = 0, math.nan, math.nan
    try:
        for packet in decoder:
            if len(packet) == 0:
                continue
            rows = np.empty((len(packet), 4), dtype=np.float64)
            rows[:, 0] = packet["t"] / 1e6
            rows[:, 1] = packet["x"]
            rows[:, 2] = packet["y"]
            rows[:, 3] = np.where(packet["on"], 1.0, -1.0)
            backwards = (not math.isnan(t_last) and rows[0, 0] < t_last) or np.any(np.diff(rows[:, 0]) < 0)
            if check_order and backwards:
                raise ValueError("event timestamps go backwards; open_recording(..., sort=True) sorts them")
            if n == 0:
                t_first = float(rows[0, 0])
            t_last = float(rows[-1, 0])
            out.write(rows.tobytes())
            n += len(rows)
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # corrupt words (coordinates outside the sensor, unknown types)
        raise ValueError(f"{path}: cannot decode the {what} file after {n} events ({exc})") from None
    return {"n": n, "t_start": t_first, "t_end": t_last, "sensor_size": list(decoder.dimensions())}


class FaeryRecording(CachedTableReads, Recording):
    """A Prophesee RAW or DAT file or an Event Stream file (see the module docstring); open one
    through :func:`~cmax_taichi.io.open_recording` or a subclass of one format.

    Parameters
    ----------
    path : path
        The file.
    sensor_size : (int, int), optional
        ``(W, H)`` px; default: the file header's. Needed only for RAW and DAT files whose header has
        no size (then it is also the size the decoder checks the coordinates against).
    camera : Camera, optional
        These formats carry no calibration.
    version : str, optional
        RAW: ``"evt2"``, ``"evt2.1"`` or ``"evt3"``; DAT: ``"dat1"`` or ``"dat2"``. Used only when
        the header does not name the encoding (default then ``evt3`` / ``dat2``, as in ``faery``).
    cache_dir, cache, sort
        As for the text formats (:class:`~.text.TextRecording`).

    Attributes
    ----------
    encoding : str
        What the file holds: ``"evt2"``, ``"evt2.1"``, ``"evt3"``, ``"dat1"``, ``"dat2"``, ``"es dvs"``
        or ``"es atis"``.
    """

    format = ""
    _faery_type = ""
    _what = ""

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        sensor_size: tuple[int, int] | None = None,
        camera: Camera | None = None,
        version: str | None = None,
        cache_dir: str | os.PathLike | None = None,
        cache: bool = True,
        sort: bool = False,
    ) -> None:
        path = check_regular(path)
        if path.stat().st_size == 0:
            raise ValueError(f"{path}: empty file (not a {self._what} file)")
        allowed = VERSIONS[self._faery_type]
        if version is not None and version not in allowed:
            valid = ", ".join(allowed) if allowed else "none (the header says it)"
            raise ValueError(f"version={version!r} is not a {self._what} encoding; valid: {valid}")
        # fails early, before any cache look-up, without the package or on an unreadable header
        decoder, self.encoding = self._decoder(path, sensor_size, version)
        check_whole_words(path, self._faery_type, version)
        meta = self._load_table(
            path,
            self.format,
            {"version": version, "sensor_size": None if sensor_size is None else list(sensor_size)},
            lambda out: _decode(decoder, path, self._what, out, check_order=not sort),
            cache_dir=cache_dir,
            cache=cache,
            sort=sort,
        )
        self._init_decoded(path, meta, sensor_size, camera)

    def _decoder(self, path: Path, sensor_size, version: str | None):
        """(an iterable of event packets with ``dimensions()``, the encoding name)."""
        decoder = _faery_decoder(path, self._faery_type, sensor_size, version, self._what)
        return decoder, f"es {decoder.event_type}"


class RawRecording(FaeryRecording):
    """A Prophesee RAW file (EVT 2.0, 2.1 or 3.0); see :class:`FaeryRecording`. EVT 2.0 and 3.0 go
    through ``faery``, EVT 2.1 through :func:`evt21_packets` (faery 0.7 cannot decode it)."""

    format = "raw"
    _faery_type = "evt"
    _what = "Prophesee RAW (EVT)"

    def _decoder(self, path: Path, sensor_size, version: str | None):
        lines, header_length = read_header(path)
        encoding = raw_version(lines) or version or "evt3"
        if encoding != "evt2.1":
            return _faery_decoder(path, "evt", sensor_size, encoding, self._what), encoding
        size = raw_geometry(lines) or (None if sensor_size is None else tuple(int(v) for v in sensor_size))
        if size is None:
            raise ValueError(f"{path}: the EVT 2.1 header has no sensor size (pass sensor_size=(W, H))")
        marked = any(line.startswith("format ") and "endianness=legacy" in line for line in lines)
        legacy = evt21_legacy_order(path, header_length, marked)
        return _Packets(lambda: evt21_packets(path, header_length, size, legacy), size), encoding


class DatRecording(FaeryRecording):
    """A Prophesee DAT file of CD events; see :class:`FaeryRecording`."""

    format = "dat"
    _faery_type = "dat"
    _what = "Prophesee DAT"

    def _decoder(self, path: Path, sensor_size, version: str | None):
        encoding = version or "dat2"
        for line in read_header(path)[0]:
            key, _, value = line.partition(" ")
            if key.lower() == "version" and value.strip() in ("1", "2"):
                encoding = f"dat{value.strip()}"
        return _faery_decoder(path, "dat", sensor_size, encoding, self._what), encoding


class EventStreamRecording(FaeryRecording):
    """An Event Stream (``.es``) file of DVS or ATIS events; see :class:`FaeryRecording`."""

    format = "es"
    _faery_type = "es"
    _what = "Event Stream"
