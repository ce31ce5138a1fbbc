"""DSEC reader: ``events.h5`` (+ rectify map, calibration) and 16-bit flow PNGs written here in the
official layout; the PNG decoder against an encoder with every row filter and against Pillow."""

from __future__ import annotations

import struct
import sys
import zlib
from pathlib import Path

import h5py
import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi.io import detect_format, open_recording
from cmax_taichi.io._png import read_png
from cmax_taichi.io.dsec import read_flow_png

SIZE = (64, 48)  # (W, H): a small sensor keeps the tests fast (the reader takes sensor_size=)
T_OFFSET = 49_599_300_523  # us, a real DSEC magnitude


def write_png(path: Path, image: np.ndarray, filters=None, seed: int = 0) -> None:
    """A PNG of uint8/uint16 (H, W[, C]) samples, each row with the given filter type (0-4; random
    by default), zlib-compressed: an independent encoder for the decoder's tests."""
    image = np.asarray(image)
    H, W = image.shape[:2]
    C = 1 if image.ndim == 2 else image.shape[2]
    depth = 16 if image.dtype == np.uint16 else 8
    raw = image.astype(">u2" if depth == 16 else np.uint8).reshape(H, W * C).view(np.uint8).astype(np.int32)
    bpp = C * depth // 8
    if filters is None:
        filters = np.random.default_rng(seed).integers(0, 5, H)
    a = np.zeros_like(raw)
    a[:, bpp:] = raw[:, :-bpp]
    b = np.zeros_like(raw)
    b[1:] = raw[:-1]
    c = np.zeros_like(raw)
    c[1:, bpp:] = raw[:-1, :-bpp]
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    paeth = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))
    preds = [np.zeros_like(raw), a, b, (a + b) // 2, paeth]
    out = bytearray()
    for r in range(H):
        out.append(int(filters[r]))
        out += ((raw[r] - preds[filters[r]][r]) & 0xFF).astype(np.uint8).tobytes()
    color = {1: 0, 2: 4, 3: 2, 4: 6}[C]

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", W, H, depth, color, 0, 0, 0)
    data = zlib.compress(bytes(out))
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", data[:50])  # the image data may span several IDAT chunks
        + chunk(b"IDAT", data[50:])
        + chunk(b"IEND", b"")
    )


def write_dsec(root: Path, n: int = 30000, seed: int = 0, rectify: bool = True, compression="gzip"):
    """``<root>/<seq>/events/left/{events.h5, rectify_map.h5}``, calibration and forward flow."""
    rng = np.random.default_rng(seed)
    W, H = SIZE
    seq = root / "zurich_city_99_a"
    left = seq / "events" / "left"
    left.mkdir(parents=True)
    t = np.sort(rng.integers(0, 1_000_000, n)).astype(np.uint32)  # 1 s, microseconds
    x = rng.integers(0, W, n).astype(np.uint16)
    y = rng.integers(0, H, n).astype(np.uint16)
    p = rng.integers(0, 2, n).astype(np.uint8)
    ms_to_idx = np.searchsorted(t, np.arange(0, 1001) * 1000, side="left").astype(np.uint64)
    with h5py.File(left / "events.h5", "w") as f:
        for name, arr in (("x", x), ("y", y), ("t", t), ("p", p)):
            f.create_dataset(f"events/{name}", data=arr, chunks=(min(n, 4096),), compression=compression)
        f.create_dataset("ms_to_idx", data=ms_to_idx)
        f.create_dataset("t_offset", data=np.int64(T_OFFSET))
    rmap = None
    if rectify:
        gy, gx = np.mgrid[0:H, 0:W].astype(np.float32)
        rmap = np.stack([gx * 0.98 + 0.6, gy * 0.97 + 0.7], axis=-1)
        with h5py.File(left / "rectify_map.h5", "w") as f:
            f["rectify_map"] = rmap
    calib = seq / "calibration"
    calib.mkdir()
    (calib / "cam_to_cam.yaml").write_text(
        "intrinsics:\n"
        "  cam0:\n"
        "    camera_matrix: [555.5, 555.0, 31.5, 23.5]\n"
        "    distortion_coeffs: [-0.09, 0.19, 0.001, -0.0005]\n"
        "    model: pinhole\n"
        "  camRect0:\n"
        "    camera_matrix: [540.0, 540.0, 32.0, 24.0]\n"
        "    model: pinhole\n"
    )
    # forward flow every 100 ms from 0.1 s, back to back: valid on the left half
    flow_dir = seq / "flow" / "forward"
    flow_dir.mkdir(parents=True)
    stamps = ["# from_timestamp_us, to_timestamp_us"]
    truth = []
    for k in range(4):
        fxy = np.round(rng.normal(0, 8, (2, H, W)) * 128) / 128
        valid = np.zeros((H, W), dtype=bool)
        valid[:, : W // 2] = True
        fxy[:, 5, 5] = 0.0  # a valid zero flow
        image = np.zeros((H, W, 3), dtype=np.uint16)
        image[..., 0] = np.where(valid, fxy[0] * 128 + 2**15, 0)
        image[..., 1] = np.where(valid, fxy[1] * 128 + 2**15, 0)
        image[..., 2] = valid
        write_png(flow_dir / f"{2 * (k + 1):06d}.png", image, seed=k)
        a = T_OFFSET + 100_000 * (k + 1)
        stamps.append(f"{a}, {a + 100_000}")
        truth.append(np.where(valid, fxy, np.nan))
    (seq / "flow" / "forward_timestamps.txt").write_text("\n".join(stamps) + "\n")
    return seq, {"x": x, "y": y, "t": t, "p": p, "rmap": rmap, "flow": truth}


def seconds(t_us):
    return (t_us.astype(np.int64) + T_OFFSET) / 1e6


# --- PNG ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype, channels", [(np.uint16, 3), (np.uint16, 4), (np.uint16, 1), (np.uint8, 3)])
def test_png_decoder_every_filter(tmp_path, dtype, channels):
    rng = np.random.default_rng(3)
    top = np.iinfo(dtype).max
    shape = (37, 29) if channels == 1 else (37, 29, channels)
    smooth = (np.linspace(0, top, 29)[None, :] + np.linspace(0, top / 3, 37)[:, None]) % top
    image = rng.integers(0, top, shape, endpoint=True).astype(dtype)
    image[:20] = (smooth[:20] if channels == 1 else smooth[:20, :, None]).astype(dtype)
    for filters in (None, np.full(37, 3), np.full(37, 4), np.zeros(37, int)):
        write_png(tmp_path / "x.png", image, filters=filters)
        decoded = read_png(tmp_path / "x.png")
        assert decoded.dtype == dtype
        np.testing.assert_array_equal(decoded, image)


def test_png_decoder_against_pillow(tmp_path):
    Image = pytest.importorskip("PIL.Image")
    rng = np.random.default_rng(4)
    gy, gx = np.mgrid[0:60, 0:80]
    image = ((np.sin(gx / 9) + np.cos(gy / 7)) * 15000 + 32000).astype(np.uint16)
    image[10:20, 10:30] = rng.integers(0, 65535, (10, 20))
    Image.fromarray(image).save(tmp_path / "g16.png")  # Pillow picks its own row filters
    np.testing.assert_array_equal(read_png(tmp_path / "g16.png"), image)


def test_flow_png_values_and_errors(tmp_path):
    image = np.array([[[2**15 + 128, 2**15 - 64, 1], [7, 9, 0]]], dtype=np.uint16)
    write_png(tmp_path / "f.png", image)
    flow, valid = read_flow_png(tmp_path / "f.png")
    assert flow.shape == (2, 1, 2) and valid.tolist() == [[True, False]]
    assert flow[:, 0, 0].tolist() == [1.0, -0.5] and np.isnan(flow[:, 0, 1]).all()
    write_png(tmp_path / "8.png", image.astype(np.uint8))
    with pytest.raises(ValueError, match="8.png: a DSEC flow PNG must be 16-bit RGB, got 8-bit"):
        read_flow_png(tmp_path / "8.png")
    write_png(tmp_path / "g.png", image[..., 0])
    with pytest.raises(ValueError, match="must be 16-bit RGB, got 16-bit, 1 channel"):
        read_flow_png(tmp_path / "g.png")
    (tmp_path / "n.png").write_bytes(b"GIF89a")
    with pytest.raises(ValueError, match="n.png: not a PNG file"):
        read_png(tmp_path / "n.png")
    data = (tmp_path / "f.png").read_bytes()
    (tmp_path / "t.png").write_bytes(data[:-20])
    with pytest.raises(ValueError, match="t.png: truncated PNG"):
        read_png(tmp_path / "t.png")
    bad = bytearray(data)
    bad[40] ^= 0xFF
    (tmp_path / "c.png").write_bytes(bytes(bad))
    with pytest.raises(ValueError, match="c.png: corrupt PNG"):
        read_png(tmp_path / "c.png")


# --- events -------------------------------------------------------------------------------------
def test_events_exact_rectified(tmp_path):
    seq, d = write_dsec(tmp_path)
    assert detect_format(seq) == "dsec" and detect_format(seq / "events" / "left") == "dsec"
    assert detect_format(seq / "events" / "left" / "events.h5") == "dsec"
    with open_recording(seq, sensor_size=SIZE) as rec:
        assert rec.format == "dsec" and rec.undistorted and rec.n_events == len(d["t"])
        assert rec.camera == cm.Camera(540.0, 540.0, 32.0, 24.0)
        assert rec.t_start == seconds(d["t"][:1])[0] and rec.t_end == seconds(d["t"][-1:])[0]
        ev = rec.read(100, 5000)
        sl = slice(100, 5000)
        np.testing.assert_array_equal(ev.t, seconds(d["t"][sl]))
        np.testing.assert_array_equal(ev.x, d["rmap"][d["y"][sl], d["x"][sl], 0].astype(np.float64))
        np.testing.assert_array_equal(ev.y, d["rmap"][d["y"][sl], d["x"][sl], 1].astype(np.float64))
        np.testing.assert_array_equal(ev.p, np.where(d["p"][sl] > 0, 1, -1))


def test_time_slicing_with_ms_to_idx(tmp_path):
    seq, d = write_dsec(tmp_path, rectify=False)
    rec = open_recording(seq, sensor_size=SIZE)
    assert not rec.undistorted
    assert rec.camera == cm.Camera(555.5, 555.0, 31.5, 23.5, dist=(-0.09, 0.19, 0.001, -0.0005))
    np.testing.assert_array_equal(rec.read(0, 50).x, d["x"][:50])
    ts = seconds(d["t"])
    rng = np.random.default_rng(5)
    cases = [(ts[0], ts[-1]), (ts[0] - 1.0, ts[10]), (ts[-5], ts[-1] + 1.0), (ts[123], ts[123])]
    cases += [tuple(np.sort(rng.uniform(ts[0] - 0.01, ts[-1] + 0.01, 2))) for _ in range(30)]
    cases += [(ts[k], ts[k + 7]) for k in rng.integers(0, len(ts) - 8, 10)]  # exact event times
    for t0, t1 in cases:
        np.testing.assert_array_equal(rec.read_time(t0, t1).t, ts[(ts >= t0) & (ts < t1)])
    for t in [ts[0] - 5, ts[500], ts[-1], ts[-1] + 5]:
        assert rec._search_time(t) == int(np.searchsorted(ts, t))
    assert sum(len(w) for w in rec.windows(duration=0.05)) == len(ts)


def test_wrong_ms_to_idx_falls_back_to_a_binary_search(tmp_path):
    seq, d = write_dsec(tmp_path, rectify=False)
    with h5py.File(seq / "events" / "left" / "events.h5", "a") as f:
        f["ms_to_idx"][...] = np.roll(f["ms_to_idx"][...], 3)  # an index that disagrees with t
    rec = open_recording(seq, sensor_size=SIZE)
    ts = seconds(d["t"])
    for t0, t1 in [(ts[1000], ts[9000]), (ts[0], ts[5])]:
        np.testing.assert_array_equal(rec.read_time(t0, t1).t, ts[(ts >= t0) & (ts < t1)])


# --- flow ground truth --------------------------------------------------------------------------
def test_flow_ground_truth(tmp_path):
    seq, d = write_dsec(tmp_path)
    rec = open_recording(seq, sensor_size=SIZE)
    intervals, pngs = rec.flow_intervals()
    assert intervals.shape == (4, 2) and [q.name for q in pngs] == [
        "000002.png",
        "000004.png",
        "000006.png",
        "000008.png",
    ]
    for k in range(4):
        a, b = intervals[k]
        np.testing.assert_array_equal(rec.flow(a, b), d["flow"][k])
    a, b = intervals[1]
    # a part of one interval: scaled, NaN kept, a valid zero stays valid
    part = rec.flow(a + 0.02, a + 0.07)
    np.testing.assert_allclose(part, 0.5 * d["flow"][1], rtol=1e-9)  # 0.05 s at t ~ 5e4 s
    assert part[0, 5, 5] == 0.0
    # two back-to-back intervals: propagated through the second frame
    both = rec.flow(intervals[1, 0], intervals[2, 1])
    first = d["flow"][1]
    W, H = SIZE
    gy, gx = np.mgrid[0:H, 0:W]
    x1, y1 = np.rint(gx + first[0]), np.rint(gy + first[1])
    ok = np.isfinite(first[0]) & (x1 >= 0) & (x1 < W) & (y1 >= 0) & (y1 < H)
    second = np.full((2, H, W), np.nan)
    xi, yi = x1[ok].astype(int), y1[ok].astype(int)
    second[:, ok] = d["flow"][2][:, yi, xi]
    np.testing.assert_allclose(both, first + second, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="no ground-truth flow interval contains"):
        rec.flow(intervals[0, 0] - 1.0, intervals[0, 0])
    with pytest.raises(ValueError, match="do not cover"):
        rec.flow(intervals[3, 0], intervals[3, 1] + 0.5)


def test_flow_layout_errors(tmp_path):
    seq, _ = write_dsec(tmp_path, n=2000)
    (seq / "flow" / "forward" / "000008.png").unlink()
    with pytest.raises(ValueError, match="4 intervals but 3 PNG files"):
        open_recording(seq, sensor_size=SIZE).flow(0, 1)
    (seq / "flow" / "forward_timestamps.txt").write_text("1, 2\nthree, 4\n")
    with pytest.raises(ValueError, match="forward_timestamps.txt, line 2: expected 'from_us, to_us'"):
        open_recording(seq, sensor_size=SIZE).flow(0, 1)
    # no flow folder: no ground truth; another flow folder by option
    other = tmp_path / "elsewhere"
    (seq / "flow").rename(other)
    assert open_recording(seq, sensor_size=SIZE).flow(0, 1) is None
    assert open_recording(seq, sensor_size=SIZE, flow_dir=other)._flow_dir == other
    with pytest.raises(FileNotFoundError, match="no such flow folder"):
        open_recording(seq, sensor_size=SIZE, flow_dir=tmp_path / "missing")


def test_bad_events_files(tmp_path):
    with h5py.File(tmp_path / "events.h5", "w") as f:
        for c in "xyt":
            f[f"events/{c}"] = np.zeros(3, dtype=np.uint16)
    with pytest.raises(KeyError, match="events.h5: no dataset 'events/p'"):
        open_recording(tmp_path / "events.h5")
    with h5py.File(tmp_path / "events.h5", "a") as f:
        f["events/p"] = np.zeros(3, dtype=np.uint8)
    with pytest.raises(KeyError, match="no dataset 'ms_to_idx'"):
        open_recording(tmp_path)
    (tmp_path / "cut.h5").write_bytes(b"\x89HDF\r\n\x1a\n")
    with pytest.raises(OSError, match="cut.h5: not a readable HDF5 file"):
        open_recording(tmp_path / "cut.h5", format="dsec")
    seq, _ = write_dsec(tmp_path / "r", n=500)
    with pytest.raises(ValueError, match=r"'rectify_map' has shape \(48, 64, 2\); expected \(480, 640, 2\)"):
        open_recording(seq)  # the real 640x480 sensor does not match this small map


def test_missing_hdf5_filter_names_hdf5plugin(tmp_path, monkeypatch):
    seq, _ = write_dsec(tmp_path, n=500, rectify=False)
    real = h5py.h5z.filter_avail
    monkeypatch.setattr(h5py.h5z, "filter_avail", lambda code: code != h5py.h5z.FILTER_DEFLATE and real(code))
    monkeypatch.setitem(sys.modules, "hdf5plugin", None)  # "not installed"
    with pytest.raises(
        OSError, match=r"events/x' is compressed with the HDF5 filter 'deflate'.*pip install hdf5plugin"
    ):
        open_recording(seq, sensor_size=SIZE)
