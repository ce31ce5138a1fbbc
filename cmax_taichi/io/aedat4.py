"""AEDAT 4.0 files (iniVation DV), through the optional package ``aedat``
(``pip install "cmax-taichi[aedat]"``, or ``pip install aedat``).

AEDAT4 packets are LZ4/ZSTD-compressed and have no event index, so the file is decoded once, packet
by packet (bounded memory), into the binary event cache of :mod:`._cache` and memory-mapped
afterwards, like the text formats. Timestamps are microseconds since the Unix epoch in the file and
seconds (float64, 0.24 us resolution at that magnitude) here. The sensor size comes from the event
stream's description. The IMU stream is available through :meth:`AEDAT4Recording.imu`; it is in the
IMU's own frame, so :meth:`~.base.Recording.angular_velocity` stays None.
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

PACKAGE = "aedat"


def _decoder(path: Path):
    try:
        import aedat
    except ImportError:
        raise ImportError(
            f"{path}: reading AEDAT4 files needs the optional package '{PACKAGE}': "
            f'pip install {PACKAGE}  (or pip install "cmax-taichi[aedat]")'
        ) from None
    try:
        return aedat.Decoder(str(path))
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # the Rust decoder raises plain exceptions, or panics, on bad files
        raise ValueError(f"{path}: not a readable AEDAT4 file ({exc})") from None


def _event_stream(decoder, path: Path) -> tuple[int, tuple[int, int]]:
    streams = [(sid, s) for sid, s in decoder.id_to_stream().items() if s.get("type") == "events"]
    if not streams:
        raise ValueError(f"{path}: no event stream in this AEDAT4 file")
    sid, stream = streams[0]
    return sid, (int(stream["width"]), int(stream["height"]))


def _decode(path: Path, out: BinaryIO, check_order: bool = True) -> dict:
    decoder = _decoder(path)
    sid, size = _event_stream(decoder, path)
    n, t_first, t_last = 0, math.nan, math.nan
    try:
        for packet in decoder:
            if packet.get("stream_id") != sid or "events" not in packet:
                continue
            ev = packet["events"]
            if len(ev) == 0:
                continue
            rows = np.empty((len(ev), 4), dtype=np.float64)
            rows[:, 0] = ev["t"] / 1e6
            rows[:, 1] = ev["x"]
            rows[:, 2] = ev["y"]
            rows[:, 3] = ev["on"]
            backwards = (not math.isnan(t_last) and rows[0, 0] < t_last) or np.any(np.diff(rows[:, 0]) < 0)
            if check_order and backwards:
                raise ValueError(
                    f"{path}: event timestamps go backwards (packet after {n} events; "
                    "open_recording(..., sort=True) sorts them)"
                )
            if n == 0:
                t_first = float(rows[0, 0])
            t_last = float(rows[-1, 0])
            out.write(rows.tobytes())
            n += len(rows)
    except (ValueError, KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # truncated or corrupt packets (the decoder may panic)
        raise ValueError(f"{path}: cannot decode the AEDAT4 file after {n} events ({exc})") from None
    return {"n": n, "t_start": t_first, "t_end": t_last, "sensor_size": list(size)}


class AEDAT4Recording(CachedTableReads, Recording):
    """An ``.aedat4`` file (or a folder holding exactly one).

    Parameters
    ----------
    path : path
        The file or its folder.
    sensor_size : (int, int), optional
        ``(W, H)`` px; default: the event stream's size.
    camera : Camera, optional
        AEDAT4 files carry no calibration.
    cache_dir, cache, sort
        As for the text formats (:class:`~.text.TextRecording`).
    """

    format = "aedat4"

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        sensor_size: tuple[int, int] | None = None,
        camera: Camera | None = None,
        cache_dir: str | os.PathLike | None = None,
        cache: bool = True,
        sort: bool = False,
    ) -> None:
        path = Path(path)
        if path.is_dir():
            found = sorted(path.glob("*.aedat4"))
            if len(found) != 1:
                raise ValueError(f"{path}: expected one .aedat4 file in this folder, found {len(found)}")
            path = found[0]
        check_regular(path)
        _decoder(path)  # fails early, before any cache look-up, without the package or on a bad file
        meta = self._load_table(
            path,
            "aedat4",
            {},
            lambda out: _decode(path, out, check_order=not sort),
            cache_dir=cache_dir,
            cache=cache,
            sort=sort,
        )
        self._init_decoded(path, meta, sensor_size, camera)

    def imu(self) -> np.ndarray | None:
        """The IMU samples ``(M, 7)``: ``t ax ay az gx gy gz`` (s, g, deg/s as the file stores them,
        in the IMU's frame); None when the file has no IMU stream. Decodes the file (not cached)."""
        decoder = _decoder(self.path)
        rows = []
        for packet in decoder:
            if "imus" in packet:
                s = packet["imus"]
                rows.append(
                    np.stack(
                        [s["t"] / 1e6]
                        + [s[f"accelerometer_{a}"] for a in "xyz"]
                        + [s[f"gyroscope_{a}"] for a in "xyz"],
                        axis=1,
                    ).astype(np.float64)
                )
        return np.concatenate(rows) if rows else None
