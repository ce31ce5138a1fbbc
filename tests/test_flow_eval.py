"""Dense-flow evaluation: the DSEC submission PNG (bytes, round trip, range), DSEC timestamps files,
MVSEC's evaluation windows (dt = 1 / 4 frames), AEE / NPE / %Out / AE by hand, and 'cmax-taichi
evaluate' scoring flow files against MVSEC, DSEC and simulator ground truth written here in the real
formats."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import h5py
import numpy as np
import pytest

from cmax_taichi import metrics
from cmax_taichi.cli import main
from cmax_taichi.io import open_recording
from cmax_taichi.io._png import read_png, write_png
from cmax_taichi.io.dsec import read_flow_png, read_flow_timestamps
from cmax_taichi.io.writers import (
    DSEC_FLOW_LIMIT,
    dsec_submission_path,
    read_flow,
    read_flow_windows,
    write_dsec_flow_png,
    write_flow,
    write_flow_npz,
)


# --- DSEC PNG -------------------------------------------------------------------------------------
def test_dsec_png_bytes_follow_the_benchmark_layout(tmp_path):
    """16-bit RGB; R, G = flow * 128 + 2**15 (rounded), B = 1 where valid, 0 elsewhere; decoded with
    DSEC's own formula ((v - 2**15) / 128) the flow comes back to 1/256 px."""
    rng = np.random.default_rng(0)
    flow = rng.uniform(-250, 250, (2, 48, 64))
    flow[:, 3, 4] = np.nan
    flow[0, 7, 9] = 0.0
    path = write_dsec_flow_png(tmp_path / "000820.png", flow)
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height, depth, color = struct.unpack(">IIBB", data[16:26])
    assert (width, height, depth, color) == (64, 48, 16, 2)
    image = read_png(path)
    assert image.dtype == np.uint16 and image.shape == (48, 64, 3)
    valid = np.isfinite(flow[0])
    np.testing.assert_array_equal(image[..., 2], valid.astype(np.uint16))
    assert image[3, 4, 0] == 2**15 and image[3, 4, 1] == 2**15  # invalid: zero flow
    expected = np.rint(np.nan_to_num(flow) * 128 + 2**15)
    np.testing.assert_array_equal(image[..., 0], expected[0])
    np.testing.assert_array_equal(image[..., 1], expected[1])
    official = (image[..., :2].astype(np.float64) - 2**15) / 128  # check_optical_flow_submission.py
    np.testing.assert_allclose(np.moveaxis(official, -1, 0)[:, valid], flow[:, valid], atol=1 / 256 + 1e-12)
    back, ok = read_flow_png(path)
    np.testing.assert_array_equal(ok, valid)
    assert np.isnan(back[:, 3, 4]).all() and back[0, 7, 9] == 0.0
    # the same through the dispatching reader and writer
    write_flow(tmp_path / "b.png", flow)
    np.testing.assert_array_equal(np.isnan(read_flow(tmp_path / "b.png")), np.isnan(back))


def test_png_encoder_round_trips_every_kind(tmp_path):
    rng = np.random.default_rng(1)
    for dtype, shape in (
        (np.uint16, (5, 7, 3)),
        (np.uint8, (4, 3)),
        (np.uint16, (6, 2, 4)),
        (np.uint8, (3, 3, 2)),
    ):
        info = np.iinfo(dtype)
        image = rng.integers(0, info.max + 1, shape).astype(dtype)
        path = write_png(tmp_path / "x.png", image)
        np.testing.assert_array_equal(read_png(path), image)
        # an independent check of the stream: the chunks, zlib, and the "up" filter undone by hand
        data, pos, idat = path.read_bytes(), 8, b""
        while pos < len(data):
            length, kind = struct.unpack(">I4s", data[pos : pos + 8])
            body = data[pos + 8 : pos + 8 + length]
            assert struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])[0] == zlib.crc32(
                kind + body
            )
            idat += body if kind == b"IDAT" else b""
            pos += 12 + length
        H = shape[0]
        raw = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(H, -1)
        assert np.all(raw[:, 0] == 2)
        rows = np.cumsum(raw[:, 1:].astype(np.int64), axis=0) % 256  # undo "up"
        wide = image.astype(">u2" if dtype == np.uint16 else np.uint8).reshape(H, -1).view(np.uint8)
        np.testing.assert_array_equal(rows, wide)


def test_dsec_png_range_and_bad_input(tmp_path):
    flow = np.zeros((2, 4, 5))
    flow[0, 1, 1] = 300.0
    with pytest.raises(ValueError, match="1 pixel"):
        write_dsec_flow_png(tmp_path / "a.png", flow)
    with pytest.warns(RuntimeWarning, match="clipped"):
        write_dsec_flow_png(tmp_path / "a.png", flow, clip=True)
    assert read_flow_png(tmp_path / "a.png")[0][0, 1, 1] == pytest.approx(DSEC_FLOW_LIMIT)
    nan = np.zeros((2, 4, 5))
    nan[:, 0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        write_dsec_flow_png(tmp_path / "b.png", nan, valid=np.ones((4, 5), bool))
    with pytest.raises(ValueError, match="shape"):
        write_dsec_flow_png(tmp_path / "b.png", np.zeros((4, 5, 2)))
    assert dsec_submission_path("sub", "thun_01_a", 820) == Path("sub/thun_01_a/000820.png")
    with pytest.raises(ValueError, match="file_index"):
        dsec_submission_path("sub", "thun_01_a", -1)


def test_dsec_timestamps_files(tmp_path):
    train = tmp_path / "forward_timestamps.txt"
    train.write_text(
        "# from_timestamp_us, to_timestamp_us\n49599300523, 49599400523\n49599400523, 49599500523\n"
    )
    np.testing.assert_array_equal(
        read_flow_timestamps(train), [[49599300523, 49599400523], [49599400523, 49599500523]]
    )
    test = tmp_path / "thun_01_a.csv"
    test.write_text("# from_timestamp_us, to_timestamp_us, file_index\n100, 200, 820\n600, 700, 830\n")
    assert read_flow_timestamps(test).tolist() == [[100, 200, 820], [600, 700, 830]]
    for text, message in (
        ("1, 2\n3, 4, 5\n", "line 2"),
        ("5, 4\n", "must exceed"),
        ("1.5, 2\n", "integers"),
        ("", "no time"),
    ):
        (tmp_path / "bad.txt").write_text(text)
        with pytest.raises(ValueError, match=message):
            read_flow_timestamps(tmp_path / "bad.txt")


# --- metrics ---------------------------------------------------------------------------------------
def test_outlier_rate_angular_error_and_zero_flow_by_hand():
    gt = np.zeros((2, 1, 4))
    pred = np.zeros((2, 1, 4))
    gt[:, 0, 0], pred[:, 0, 0] = (
        (100.0, 1.0),
        (104.0, 1.0),
    )  # EPE 4 > 3 px but < 5% of |gt| = 5: not an outlier
    gt[:, 0, 1], pred[:, 0, 1] = (10.0, 1.0), (14.0, 1.0)  # EPE 4 > 3 px and > 5%: outlier
    gt[:, 0, 2], pred[:, 0, 2] = (2.0, 1.0), (2.0, 1.0)  # exact
    gt[:, 0, 3], pred[:, 0, 3] = (0.0, 3.0), (0.0, 3.0)  # a zero component: invalid for MVSEC, valid for DSEC
    out = metrics.flow_error(pred, gt)
    assert out["n_pixels"] == 3
    assert out["AEE"] == pytest.approx(8 / 3)
    assert out["3PE"] == pytest.approx(200 / 3)
    assert out["outlier"] == pytest.approx(100 / 3)

    def angle(u, v, ug, vg):
        a, b = np.array([u, v, 1.0]), np.array([ug, vg, 1.0])
        return np.degrees(np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))

    assert out["AE_deg"] == pytest.approx((angle(104, 1, 100, 1) + angle(14, 1, 10, 1) + 0.0) / 3)
    dsec = metrics.flow_error(pred, gt, zero_is_invalid=False)
    assert dsec["n_pixels"] == 4 and dsec["AEE"] == pytest.approx(2.0)
    # a NaN prediction is not scored, and counted
    pred[:, 0, 2] = np.nan
    out = metrics.flow_error(pred, gt)
    assert out["n_pixels"] == 2 and out["n_missing"] == 1


# --- MVSEC -----------------------------------------------------------------------------------------
def _write_mvsec(folder: Path, name: str, size=(16, 12), n_gt: int = 1400, seed: int = 0):
    """``<name>_data.hdf5`` (events, image_raw_ts) and ``<name>_gt_flow_dist.npz``: constant flow of
    (0.3, 0.2) px per GT frame (20 Hz), 10 events per frame on random pixels, frames at 31 Hz."""
    rng = np.random.default_rng(seed)
    W, H = size
    t0 = 1500000000.0
    gt_ts = t0 + np.arange(n_gt) / 20.0
    n = 10 * n_gt
    t = np.sort(rng.uniform(gt_ts[0], gt_ts[-1], n))
    rows = np.column_stack([rng.integers(0, W, n), rng.integers(0, H, n), t, rng.choice([-1.0, 1.0], n)])
    image_ts = t0 + 0.013 + np.arange(int((n_gt - 1) / 20 * 31)) / 31.0
    with h5py.File(folder / f"{name}_data.hdf5", "w") as f:
        f.create_dataset("davis/left/events", data=rows)
        f.create_dataset("davis/left/image_raw_ts", data=image_ts)
    fx = np.full((n_gt, H, W), 0.3)
    fy = np.full((n_gt, H, W), 0.2)
    fx[:, -1, :] = fy[:, -1, :] = 0.0  # the last row has no depth
    np.savez(folder / f"{name}_gt_flow_dist.npz", timestamps=gt_ts, x_flow_dist=fx, y_flow_dist=fy)
    return folder / f"{name}_data.hdf5", image_ts, gt_ts


def test_mvsec_eval_windows_dt1_dt4_and_the_valid_frames(tmp_path):
    path, image_ts, gt_ts = _write_mvsec(tmp_path, "indoor_flying1")
    with open_recording(path, sensor_size=(16, 12)) as rec:
        assert rec.sequence == "indoor_flying1"
        np.testing.assert_array_equal(rec.frame_times(), image_ts)
        inside = image_ts[(image_ts > gt_ts[60]) & (image_ts < gt_ts[1339])]
        w1 = rec.eval_windows(1)
        w4 = rec.eval_windows(4)
        assert w1[0] == (inside[0], inside[1]) and w4[0] == (inside[0], inside[4])
        assert len(w1) == len(inside) - 1 and len(w4) == len(inside) - 4
        everything = rec.eval_windows(1, valid_only=False)
        assert everything[0][0] == image_ts[image_ts > gt_ts[0]][0]
        # the ground truth of a dt = 4 window (over 2-3 GT frames): 0.3 px/frame x 20 Hz x (4 / 31 s);
        # points that reach the last row (no depth) or leave the image are invalid
        t0, t1 = w4[10]
        gt = rec.flow(t0, t1)
        # (1.5e9 s timestamps: t1 - t0 is known to about 1e-7 s)
        np.testing.assert_allclose(gt[0, :-3, :-3], 6.0 * (t1 - t0), atol=1e-5)
        np.testing.assert_allclose(gt[1, :-3, :-3], 4.0 * (t1 - t0), atol=1e-5)
        assert np.isnan(gt[:, -1]).all() and np.isnan(gt[:, :, -1]).all()
        with pytest.raises(ValueError, match="dt_frames"):
            rec.eval_windows(0)
    # no frame times
    with h5py.File(path, "a") as f:
        del f["davis/left/image_raw_ts"]
    with open_recording(path, sensor_size=(16, 12)) as rec, pytest.raises(ValueError, match="image_raw_ts"):
        rec.eval_windows(1)


def test_evaluate_scores_flow_files_against_mvsec(tmp_path, capsys):
    data = tmp_path / "data"
    data.mkdir()
    path, _, _ = _write_mvsec(data, "indoor_flying1")
    flows = tmp_path / "flows"
    flows.mkdir()
    with open_recording(path, sensor_size=(16, 12)) as rec:
        windows = rec.eval_windows(4)[:3]
        truths = [rec.flow(a, b) for a, b in windows]
    for k, ((a, b), gt) in enumerate(zip(windows, truths, strict=True)):
        pred = np.nan_to_num(gt) + np.array([3.0, 4.0])[:, None, None] * (k == 1)
        write_flow_npz(flows / f"flow_{k:04d}.npz", pred, t_start=a, t_end=b, unit="px")
    # px/s files are scaled by the interval
    a, b = windows[2]
    write_flow_npz(
        flows / "flow_0003.npz", np.nan_to_num(truths[2]) / (b - a), t_start=a, t_end=b, unit="px/s"
    )
    out = tmp_path / "out"
    size = ["--sensor-size", "16", "12"]
    assert main(["evaluate", str(flows), "--data", str(path), *size, "--out", str(out), "--npe", "3"]) == 0
    report = json.loads((out / "metrics.json").read_text())
    rows = report["windows"]
    assert [r["file"] for r in rows] == [f"flow_{k:04d}.npz" for k in range(4)]
    assert rows[0]["AEE"] == pytest.approx(0.0, abs=1e-5) and rows[3]["AEE"] == pytest.approx(0.0, abs=1e-4)
    assert rows[1]["AEE"] == pytest.approx(5.0, abs=1e-5) and rows[1]["3PE"] == 100.0
    assert rows[1]["outlier"] == 100.0  # 5 px error on a 0.8 px flow
    # the pixels scored: events of the window, the pixels without ground truth left out
    assert 0 < rows[0]["n_pixels"] <= 15 * 11
    assert report["summary"]["mean_AEE"] == pytest.approx(1.25, abs=1e-4)
    text = capsys.readouterr().out
    assert "mean AEE 1.250 px" in text and "%Out" in text
    # .flo files need their intervals
    write_flow(flows / "x.flo", truths[0])
    assert main(["evaluate", str(flows), "--data", str(path), *size]) == 2
    err = capsys.readouterr().err
    assert "x.flo" in err and "timestamps" in err


# --- DSEC ------------------------------------------------------------------------------------------
def test_evaluate_scores_a_dsec_submission(tmp_path):
    """A DSEC sequence (events.h5, ground-truth PNGs + forward_timestamps.txt) and a submission folder
    of PNGs named by the test CSV's file indices."""
    rng = np.random.default_rng(2)
    W, H = 640, 480  # DSEC's sensor, which the reader takes by default
    seq = tmp_path / "zurich_city_99_a"
    (seq / "events" / "left").mkdir(parents=True)
    (seq / "flow" / "forward").mkdir(parents=True)
    n = 6000
    t = np.sort(rng.integers(0, 400_000, n)).astype(np.uint32)
    with h5py.File(seq / "events" / "left" / "events.h5", "w") as f:
        f["events/x"] = rng.integers(0, W, n).astype(np.uint16)
        f["events/y"] = rng.integers(0, H, n).astype(np.uint16)
        f["events/t"] = t
        f["events/p"] = rng.integers(0, 2, n).astype(np.uint8)
        f["ms_to_idx"] = np.searchsorted(t, np.arange(0, 401) * 1000).astype(np.uint64)
        f["t_offset"] = np.int64(1_000_000)
    stamps, csv, truths = (
        ["# from_timestamp_us, to_timestamp_us"],
        ["# from_timestamp_us, to_timestamp_us, file_index"],
        [],
    )
    for k in range(3):
        gt = np.round(rng.normal(0, 6, (2, H, W)) * 128) / 128
        gt[0, :, 3] = 0.0  # zero x-flow: valid in DSEC
        gt[:, :2, :] = np.nan  # no ground truth on the first rows
        truths.append(gt)
        write_dsec_flow_png(seq / "flow" / "forward" / f"{2 * k:06d}.png", gt)
        a = 1_000_000 + 100_000 * k
        stamps.append(f"{a}, {a + 100_000}")
        csv.append(f"{a}, {a + 100_000}, {10 * k}")
    (seq / "flow" / "forward_timestamps.txt").write_text("\n".join(stamps) + "\n")
    (tmp_path / "stamps.csv").write_text("\n".join(csv) + "\n")
    sub = tmp_path / "submission"
    (sub / seq.name).mkdir(parents=True)
    for k, gt in enumerate(truths):
        pred = np.nan_to_num(gt, nan=1.0)
        if k == 2:
            pred = pred + 1.0  # EPE sqrt(2)
        write_dsec_flow_png(dsec_submission_path(sub, seq.name, 10 * k), pred)
    out = tmp_path / "out"
    argv = ["evaluate", str(sub / seq.name), "--data", str(seq), "--timestamps", str(tmp_path / "stamps.csv")]
    assert main([*argv, "--out", str(out)]) == 0
    rows = json.loads((out / "metrics.json").read_text())["windows"]
    assert [r["file"] for r in rows] == ["000000.png", "000010.png", "000020.png"]
    assert rows[0]["AEE"] == 0.0 and rows[2]["AEE"] == pytest.approx(np.sqrt(2))
    with open_recording(seq) as rec:
        mask = metrics.event_mask(rec.read_time(1.0, float(np.nextafter(1.1, 2.0))))
    assert rows[0]["n_pixels"] == np.count_nonzero(mask[2:])  # the zero x-flow column counts


# --- simulator -------------------------------------------------------------------------------------
def test_evaluate_scores_flow_against_the_simulator(tmp_path):
    from cmax_taichi import sim as sm

    rec = sm.simulate_depth("object", duration=0.1, scale=0.25)
    h5, _ = rec.write(tmp_path / "sim", "object", frame_rate=40.0)
    flows = tmp_path / "flows"
    flows.mkdir()
    t0, t1 = 0.025, 0.075
    truth = rec.flow(t0, t1)
    write_flow_npz(flows / "flow_0000.npz", truth, t_start=t0, t_end=t1)
    write_flow_npz(flows / "flow_0001.npz", np.zeros_like(truth), t_start=t0, t_end=t1)
    out = tmp_path / "out"
    W, H = rec.sensor_size
    assert (
        main(["evaluate", str(flows), "--data", str(h5), "--sensor-size", str(W), str(H), "--out", str(out)])
        == 0
    )
    rows = json.loads((out / "metrics.json").read_text())["windows"]
    # the files' frames are accumulated over 2 frames of 25 ms: exact up to float32 and nearest-pixel
    # sampling of the second frame (EV-FlowNet's propagation)
    assert rows[0]["AEE"] < 0.1
    with open_recording(h5, format="mvsec", sensor_size=rec.sensor_size) as mv:
        err = metrics.score_flow(mv, np.zeros_like(truth), t0, t1)
        # the simulator's files carry MVSEC's frame times: dt = 1 and dt = 2 frame windows
        frames = mv.frame_times()
        np.testing.assert_allclose(frames, np.arange(len(frames)) / 40.0)
        assert mv.eval_windows(1)[0] == (frames[1], frames[2]) and mv.eval_windows(2)[0] == (
            frames[1],
            frames[3],
        )
    assert rows[1]["AEE"] == pytest.approx(err["AEE"]) and err["AEE"] > 1.0
    assert err["n_events"] == len(rec.events(t0, float(np.nextafter(t1, np.inf))))


def test_read_flow_windows_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_flow_windows(tmp_path / "none")
    with pytest.raises(ValueError, match="no flow files"):
        read_flow_windows(tmp_path)
    write_flow(tmp_path / "a.flo", np.zeros((2, 3, 4)))
    (tmp_path / "t.txt").write_text("0.0 0.1\n0.1 0.2\n")
    with pytest.raises(ValueError, match="2 intervals for 1"):
        read_flow_windows(tmp_path, tmp_path / "t.txt")
    (tmp_path / "t.txt").write_text("0.0 0.1\n")
    (w,) = read_flow_windows(tmp_path, tmp_path / "t.txt")
    assert (w.t_start, w.t_end, w.unit) == (0.0, 0.1, "px")
    (tmp_path / "t.txt").write_text("100 200 7\n")
    with pytest.raises(ValueError, match="000007"):
        read_flow_windows(tmp_path, tmp_path / "t.txt")
    write_flow_npz(tmp_path / "b.npz", np.zeros((2, 3, 4)))
    with pytest.raises(ValueError, match="t_start"):
        read_flow_windows(tmp_path / "b.npz")
