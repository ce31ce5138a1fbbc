"""A minimal PNG decoder (zlib + NumPy) that returns exact 8- or 16-bit sample values, and an encoder
(:func:`write_png`, for the DSEC flow files of :mod:`cmax_taichi.io.writers`).

Why not matplotlib: it reads PNGs through Pillow, which has no 16-bit RGB mode and truncates DSEC's
16-bit flow images to 8 bits. Non-interlaced grayscale, gray+alpha, RGB and RGBA images of bit depth 8
or 16 are supported. Row filters are undone along anti-diagonals (a pixel depends only on its left,
upper and upper-left neighbours), so the Python loop runs H + W times, not H * W.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from cmax_taichi.io._files import check_regular

SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}  # colour type -> samples per pixel


def _unfilter(raw: np.ndarray, H: int, W: int, bpp: int, path: Path) -> np.ndarray:
    """Undo the per-row filters of the (H, 1 + W * bpp) bytes ``raw``; returns (H, W, bpp) uint8."""
    types = raw[:, 0]
    if np.any(types > 4):
        raise ValueError(f"{path}: corrupt PNG (row filter type {int(types.max())})")
    filt = raw[:, 1:].reshape(H, W, bpp).astype(np.int32)
    if np.all(types == 0):
        return filt.astype(np.uint8)
    # padded reconstruction: row 0 and column 0 are the zero neighbours of the image's edges
    rec = np.zeros((H + 1, W + 1, bpp), dtype=np.int32)
    for d in range(H + W - 1):
        r = np.arange(max(0, d - W + 1), min(H - 1, d) + 1)
        c = d - r
        a = rec[r + 1, c]  # left
        b = rec[r, c + 1]  # up
        cc = rec[r, c]  # up-left
        kind = types[r][:, None]
        p = a + b - cc
        pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - cc)
        paeth = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, cc))
        pred = np.select([kind == 1, kind == 2, kind == 3, kind == 4], [a, b, (a + b) >> 1, paeth], 0)
        rec[r + 1, c + 1] = (filt[r, c] + pred) & 0xFF
    return rec[1:, 1:].astype(np.uint8)


def read_png(path: str | Path) -> np.ndarray:
    """Decode a PNG file exactly.

    Returns
    -------
    ndarray
        (H, W) or (H, W, C) array, uint8 or uint16 (big-endian samples converted to native order).

    Raises
    ------
    ValueError
        Not a PNG, truncated or corrupt data, or an unsupported kind (interlaced, palette, < 8 bits).
    """
    path = check_regular(path)  # a FIFO or a device is refused, never read
    data = path.read_bytes()
    if not data.startswith(SIGNATURE):
        raise ValueError(f"{path}: not a PNG file")
    pos, header, idat = len(SIGNATURE), None, []
    while True:
        if pos + 8 > len(data):
            raise ValueError(f"{path}: truncated PNG (no IEND chunk)")
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        body = data[pos + 8 : pos + 8 + length]
        crc = data[pos + 8 + length : pos + 12 + length]
        if len(body) != length or len(crc) != 4:
            raise ValueError(f"{path}: truncated PNG (chunk {kind!r} cut short)")
        if zlib.crc32(kind + body) != struct.unpack(">I", crc)[0]:
            raise ValueError(f"{path}: corrupt PNG (bad CRC in chunk {kind!r})")
        pos += 12 + length
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
    if header is None:
        raise ValueError(f"{path}: corrupt PNG (no IHDR chunk)")
    W, H, depth, color, _compression, _filter, interlace = header
    if color not in _CHANNELS or depth not in (8, 16):
        raise ValueError(
            f"{path}: unsupported PNG kind (bit depth {depth}, colour type {color}); "
            "8- or 16-bit gray, gray+alpha, RGB or RGBA only"
        )
    if interlace:
        raise ValueError(f"{path}: interlaced PNGs are not supported")
    channels = _CHANNELS[color]
    bpp = channels * depth // 8
    try:
        raw = zlib.decompress(b"".join(idat))
    except zlib.error as exc:
        raise ValueError(f"{path}: corrupt PNG image data ({exc})") from None
    if len(raw) != H * (1 + W * bpp):
        raise ValueError(
            f"{path}: corrupt PNG (image data has {len(raw)} bytes, expected {H * (1 + W * bpp)})"
        )
    rows = _unfilter(np.frombuffer(raw, dtype=np.uint8).reshape(H, 1 + W * bpp), H, W, bpp, path)
    image = rows.reshape(H, W * bpp)
    if depth == 16:
        image = image.view(">u2").astype(np.uint16)
    image = image.reshape(H, W, channels)
    return image[..., 0] if channels == 1 else image


def write_png(path: str | Path, image: np.ndarray, level: int = 6) -> Path:
    """Encode ``image`` as a PNG file: (H, W) gray or (H, W, C) with C = 2, 3, 4 (gray+alpha, RGB,
    RGBA), uint8 or uint16 (16-bit samples are written big-endian, as the format wants). Each row is
    filtered with "up" (type 2), which suits smooth images such as flow fields. Returns the path."""
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"a PNG holds uint8 or uint16 samples, got {image.dtype}")
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[2] not in (1, 2, 3, 4) or min(image.shape[:2]) < 1:
        raise ValueError(f"a PNG image is (H, W) or (H, W, 1..4), got shape {image.shape}")
    H, W, C = image.shape
    depth = 16 if image.dtype == np.uint16 else 8
    color = {1: 0, 2: 4, 3: 2, 4: 6}[C]
    rows = image.astype(">u2" if depth == 16 else np.uint8).reshape(H, W * C).view(np.uint8)
    up = rows.copy()
    up[1:] = rows[1:] - rows[:-1]  # uint8 arithmetic wraps modulo 256, as the filter is defined
    raw = np.concatenate([np.full((H, 1), 2, dtype=np.uint8), up], axis=1)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", W, H, depth, color, 0, 0, 0)
    path = Path(path)
    path.write_bytes(
        SIGNATURE
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw.tobytes(), level))
        + chunk(b"IEND", b"")
    )
    return path
