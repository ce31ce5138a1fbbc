"""MVSEC reader: a ``*_data.hdf5`` and a ``*_gt_flow_dist.npz`` written here in the official layout."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi.io import detect_format, open_recording
from cmax_taichi.io._flow import NpzFrames

W, H = 346, 260


def write_mvsec(folder: Path, n: int = 20000, seed: int = 0, name: str = "indoor_flying9", chunks=True):
    """``<name>_data.hdf5`` with ``davis/left/events`` (N, 4) x y t p and an APS image stream."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    t = 1500000000.0 + np.sort(rng.uniform(0.0, 2.0, n))
    t[100:110] = t[100]  # equal timestamps happen in real data
    rows = np.column_stack(
        [rng.integers(0, W, n), rng.integers(0, H, n), t, rng.choice([-1.0, 1.0], n)]
    ).astype(np.float64)
    path = folder / f"{name}_data.hdf5"
    with h5py.File(path, "w") as f:
        left = f.create_group("davis/left")
        left.create_dataset("events", data=rows, chunks=(min(n, 4096), 4) if chunks else None)
        left.create_dataset("image_raw", data=np.zeros((3, H, W), dtype=np.uint8))
        left.create_dataset("image_raw_ts", data=t[[0, n // 2, -1]])
    return path, rows


def write_gt_flow(path: Path, ts: np.ndarray, seed: int = 0, compressed: bool = False):
    """``*_gt_flow_dist.npz``: per-frame flow (px between consecutive timestamps), zeros = no depth."""
    rng = np.random.default_rng(seed)
    M = len(ts)
    fx = rng.normal(2.0, 1.0, (M, H, W))
    fy = rng.normal(-1.0, 1.0, (M, H, W))
    fx[:, :20, :] = 0.0  # invalid band (no depth)
    fy[:, :20, :] = 0.0
    save = np.savez_compressed if compressed else np.savez
    save(path, timestamps=ts, x_flow_dist=fx, y_flow_dist=fy)
    return fx, fy


def evflownet_reference(x_flow_in, y_flow_in, gt_timestamps, start_time, end_time):
    """EV-FlowNet's estimate_corresponding_gt_flow, line by line, with cv2.remap(INTER_NEAREST)
    replaced by rounding and a zero border (float64 instead of float32)."""

    def remap(flow, xs, ys):
        xi, yi = np.rint(xs).astype(int), np.rint(ys).astype(int)
        ok = (xi >= 0) & (xi < flow.shape[1]) & (yi >= 0) & (yi < flow.shape[0])
        out = np.zeros_like(xs)
        out[ok] = flow[yi[ok], xi[ok]]
        return out

    def prop_flow(x_flow, y_flow, x_indices, y_indices, x_mask, y_mask, scale_factor=1.0):
        flow_x_interp = remap(x_flow, x_indices, y_indices)
        flow_y_interp = remap(y_flow, x_indices, y_indices)
        x_mask[flow_x_interp == 0] = False
        y_mask[flow_y_interp == 0] = False
        x_indices += flow_x_interp * scale_factor
        y_indices += flow_y_interp * scale_factor

    gt_iter = np.searchsorted(gt_timestamps, start_time, side="right") - 1
    gt_dt = gt_timestamps[gt_iter + 1] - gt_timestamps[gt_iter]
    x_flow = np.squeeze(x_flow_in[gt_iter, ...])
    y_flow = np.squeeze(y_flow_in[gt_iter, ...])
    dt = end_time - start_time
    if gt_dt > dt:
        return x_flow * dt / gt_dt, y_flow * dt / gt_dt
    x_indices, y_indices = np.meshgrid(np.arange(x_flow.shape[1]), np.arange(x_flow.shape[0]))
    x_indices = x_indices.astype(np.float64)
    y_indices = y_indices.astype(np.float64)
    orig_x_indices = np.copy(x_indices)
    orig_y_indices = np.copy(y_indices)
    x_mask = np.ones(x_indices.shape, dtype=bool)
    y_mask = np.ones(y_indices.shape, dtype=bool)
    scale_factor = (gt_timestamps[gt_iter + 1] - start_time) / gt_dt
    prop_flow(x_flow, y_flow, x_indices, y_indices, x_mask, y_mask, scale_factor=scale_factor)
    gt_iter += 1
    while gt_timestamps[gt_iter + 1] < end_time:
        x_flow = np.squeeze(x_flow_in[gt_iter, ...])
        y_flow = np.squeeze(y_flow_in[gt_iter, ...])
        prop_flow(x_flow, y_flow, x_indices, y_indices, x_mask, y_mask)
        gt_iter += 1
    final_dt = end_time - gt_timestamps[gt_iter]
    final_gt_dt = gt_timestamps[gt_iter + 1] - gt_timestamps[gt_iter]
    x_flow = np.squeeze(x_flow_in[gt_iter, ...])
    y_flow = np.squeeze(y_flow_in[gt_iter, ...])
    scale_factor = final_dt / final_gt_dt
    prop_flow(x_flow, y_flow, x_indices, y_indices, x_mask, y_mask, scale_factor)
    x_shift = x_indices - orig_x_indices
    y_shift = y_indices - orig_y_indices
    x_shift[~x_mask] = 0
    y_shift[~y_mask] = 0
    return x_shift, y_shift


def test_events_exact_by_index_and_time(tmp_path):
    path, rows = write_mvsec(tmp_path)
    assert detect_format(path) == "mvsec" and detect_format(tmp_path) == "mvsec"
    with open_recording(path) as rec:
        assert rec.format == "mvsec" and rec.sensor_size == (W, H) and rec.camera is None
        assert rec.n_events == len(rows) and (rec.t_start, rec.t_end) == (rows[0, 2], rows[-1, 2])
        ev = rec.read(1000, 31000)
        np.testing.assert_array_equal(ev.x, rows[1000:, 0])
        np.testing.assert_array_equal(ev.y, rows[1000:, 1])
        np.testing.assert_array_equal(ev.t, rows[1000:, 2])
        np.testing.assert_array_equal(ev.p, rows[1000:, 3])
        t = rows[:, 2]
        for t0, t1 in [(t[0], t[-1]), (t[100], t[5000]), (t[4095], t[4097]), (t[0] - 1, t[0]), (t[-1], 1e10)]:
            sel = (t >= t0) & (t < t1)
            np.testing.assert_array_equal(rec.read_time(t0, t1).t, t[sel])
        windows = list(rec.windows(n_events=6000))
        assert [len(w) for w in windows] == [6000] * 3
        assert sum(len(w) for w in rec.windows(duration=0.25)) == len(rows)
        assert rec.flow(t[0], t[10]) is None and rec.angular_velocity(t[0]) is None
    with pytest.raises(ValueError, match="closed"):
        rec.read(0, 10)


def test_folder_and_calibration_dataset(tmp_path):
    path, rows = write_mvsec(tmp_path, n=500, chunks=False)
    with h5py.File(path, "a") as f:
        f["davis/left/calibration"] = [226.4, 226.2, 173.6, 133.7, -0.048, 0.011, -0.055, 0.0215]
    rec = open_recording(tmp_path)
    assert rec.camera == cm.Camera(226.4, 226.2, 173.6, 133.7, dist=(-0.048, 0.011, -0.055, 0.0215))
    given = cm.Camera(200.0, 200.0, 170.0, 130.0)
    assert open_recording(path, camera=given).camera == given
    np.testing.assert_array_equal(rec.read().t, rows[:, 2])


@pytest.mark.parametrize("compressed", [False, True])
def test_gt_flow_accumulation(tmp_path, compressed):
    path, rows = write_mvsec(tmp_path, n=1000)
    ts = rows[0, 2] + np.arange(6) * 0.05  # 20 Hz, as MVSEC's depth frames
    fx, fy = write_gt_flow(tmp_path / "indoor_flying9_gt_flow_dist.npz", ts, compressed=compressed)
    frames = NpzFrames(tmp_path / "indoor_flying9_gt_flow_dist.npz", "x_flow_dist")
    assert (frames._map is None) == compressed
    np.testing.assert_array_equal(frames[3], fx[3])
    rec = open_recording(path)
    assert rec.gt_flow_file.name == "indoor_flying9_gt_flow_dist.npz"
    intervals = [
        (ts[1] + 0.01, ts[1] + 0.04),  # inside one frame: scaled
        (ts[1] + 0.03, ts[2] + 0.01),  # shorter than a frame, across a boundary: EV-FlowNet scales too
        (ts[1], ts[2]),  # exactly one frame
        (ts[0] + 0.02, ts[3] + 0.03),  # several frames: propagated
        (ts[0], ts[5]),
    ]
    # a compressed npz is read by seeking in the deflate stream (slow): one interval is enough
    for t0, t1 in intervals[3:4] if compressed else intervals:
        ours = rec.flow(t0, t1)
        ref = np.stack(evflownet_reference(fx, fy, ts, t0, t1))
        assert ours.shape == (2, H, W)
        valid = np.isfinite(ours).all(axis=0)
        np.testing.assert_allclose(ours[:, valid], ref[:, valid], rtol=0, atol=1e-9)
        assert np.all((ref[0, ~valid] == 0) | (ref[1, ~valid] == 0))
        assert not valid[:20].any() and valid[40:].mean() > 0.5
    one = rec.flow(ts[1], ts[2])  # one whole frame: that frame (where the end position stays valid)
    valid = np.isfinite(one[0])
    np.testing.assert_allclose(one[:, valid], np.stack([fx[1], fy[1]])[:, valid], atol=1e-12)
    with pytest.raises(ValueError, match="ground-truth flow covers"):
        rec.flow(ts[0] - 0.1, ts[1])
    with pytest.raises(ValueError, match="t1 > t0"):
        rec.flow(ts[1], ts[1])


def test_bad_files(tmp_path):
    with h5py.File(tmp_path / "other.hdf5", "w") as f:
        f["davis/right/events"] = np.zeros((3, 4))
    with pytest.raises(KeyError, match="no dataset 'davis/left/events'"):
        open_recording(tmp_path / "other.hdf5")
    with h5py.File(tmp_path / "wrong_data.hdf5", "w") as f:
        f["davis/left/events"] = np.zeros((3, 3))
    with pytest.raises(ValueError, match=r"has shape \(3, 3\); expected \(N, 4\)"):
        open_recording(tmp_path / "wrong_data.hdf5")
    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f["something"] = np.zeros(3)
    with pytest.raises(ValueError, match=r"HDF5 file without .*keys \['something'\]"):
        open_recording(tmp_path / "plain.h5")
    (tmp_path / "broken_data.hdf5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 20)
    with pytest.raises(OSError, match="broken_data.hdf5: not a readable HDF5 file"):
        open_recording(tmp_path / "broken_data.hdf5", format="mvsec")
    # a truncated file
    good, _ = write_mvsec(tmp_path / "t", n=5000)
    data = good.read_bytes()
    (tmp_path / "cut_data.hdf5").write_bytes(data[: len(data) // 2])
    with pytest.raises(OSError, match="cut_data.hdf5"):
        open_recording(tmp_path / "cut_data.hdf5", format="mvsec").read()


def test_bad_gt_flow(tmp_path):
    path, rows = write_mvsec(tmp_path, n=200)
    gt = tmp_path / "indoor_flying9_gt_flow_dist.npz"
    np.savez(gt, timestamps=rows[[0, 100], 2], x_flow_dist=np.zeros((2, H, W)))
    with pytest.raises(KeyError, match="no array 'y_flow_dist'"):
        open_recording(path).flow(rows[0, 2], rows[50, 2])
    np.savez(
        gt, timestamps=rows[[0, 100], 2], x_flow_dist=np.zeros((2, 10, 10)), y_flow_dist=np.zeros((2, 10, 10))
    )
    with pytest.raises(ValueError, match="expected x_flow_dist, y_flow_dist of shape"):
        open_recording(path).flow(rows[0, 2], rows[50, 2])
    gt.write_bytes(b"PK not a zip")
    with pytest.raises(ValueError, match="not a readable .npz file"):
        open_recording(path).flow(rows[0, 2], rows[50, 2])
    with pytest.raises(FileNotFoundError, match="no such ground-truth flow file"):
        open_recording(path, gt_flow=tmp_path / "missing.npz")
