"""Exports: dense flow as Middlebury .flo (checked byte by byte against the format's definition) and
.npz, estimate results as HDF5, and the 'estimate' command writing results.h5 and per-window flow
files (run on a Prophesee RAW file written with faery)."""

from __future__ import annotations

import csv
import json
import struct

import h5py
import numpy as np
import pytest
from test_cli_estimate import V, write_ecd_folder

from cmax_taichi import cli
from cmax_taichi.io.writers import (
    FLO_MAGIC,
    read_flo,
    read_flow,
    read_flow_npz,
    write_flo,
    write_flow,
    write_flow_npz,
)
from cmax_taichi.solve.sequence import SequenceResult, WindowResult


def sample_flow(H: int = 5, W: int = 7) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    return np.stack([xx + 0.25 * yy, -2.5 * yy + 0.125]).astype(np.float64)


def test_flo_bytes_follow_the_middlebury_layout(tmp_path):
    flow = sample_flow()
    flow[1, 2, 3] = np.nan  # unknown
    path = write_flo(tmp_path / "f.flo", flow)
    data = path.read_bytes()
    assert data[:4] == b"PIEH" and struct.unpack("<f", data[:4])[0] == 202021.25 == FLO_MAGIC
    assert struct.unpack("<ii", data[4:12]) == (7, 5)  # width, height
    assert len(data) == 12 + 5 * 7 * 2 * 4
    values = struct.unpack(f"<{5 * 7 * 2}f", data[12:])
    for y in range(5):  # row by row, u v interleaved per pixel
        for x in range(7):
            u, v = values[2 * (y * 7 + x) : 2 * (y * 7 + x) + 2]
            assert u == pytest.approx(flow[0, y, x])
            if (y, x) == (2, 3):
                assert v > 1e9  # Middlebury's unknown flow
            else:
                assert v == pytest.approx(flow[1, y, x])
    back = read_flo(path)
    assert back.shape == (2, 5, 7) and back.dtype == np.float32
    assert np.isnan(back[:, 2, 3]).all() and np.isnan(back).sum() == 2  # the pixel is unknown
    flow[0, 2, 3] = np.nan
    np.testing.assert_allclose(back, flow, rtol=1e-7, equal_nan=True)


def test_reads_a_hand_written_flo(tmp_path):
    """A file written with struct alone, as the Middlebury C code does: 3 wide, 2 high."""
    uv = [(1.5, -2.0), (0.0, 3.25), (4.0, 1e10), (-1.0, -1.0), (2.0, 0.5), (7.0, -7.0)]
    raw = (
        struct.pack("<f", 202021.25) + struct.pack("<ii", 3, 2) + b"".join(struct.pack("<ff", *p) for p in uv)
    )
    (tmp_path / "hand.flo").write_bytes(raw)
    flow = read_flo(tmp_path / "hand.flo")
    np.testing.assert_array_equal(flow[0], [[1.5, 0.0, np.nan], [-1.0, 2.0, 7.0]])
    np.testing.assert_array_equal(flow[1], [[-2.0, 3.25, np.nan], [-1.0, 0.5, -7.0]])


def test_bad_flo_files(tmp_path):
    good = write_flo(tmp_path / "good.flo", sample_flow()).read_bytes()
    (tmp_path / "cut.flo").write_bytes(good[:-4])
    with pytest.raises(ValueError, match=r"cut.flo: .* expected 280 \(truncated\?\)"):
        read_flo(tmp_path / "cut.flo")
    (tmp_path / "magic.flo").write_bytes(b"XXXX" + good[4:])
    with pytest.raises(ValueError, match="magic.flo: not a .flo file"):
        read_flo(tmp_path / "magic.flo")
    (tmp_path / "size.flo").write_bytes(good[:4] + struct.pack("<ii", -1, 5) + good[12:])
    with pytest.raises(ValueError, match="size.flo: implausible .flo size -1x5"):
        read_flo(tmp_path / "size.flo")
    with pytest.raises(ValueError, match=r"shape \(2, H, W\)"):
        write_flo(tmp_path / "x.flo", np.zeros((5, 7, 2)))


def test_npz_round_trip_and_dispatch(tmp_path):
    flow = sample_flow()
    path = write_flow_npz(tmp_path / "f.npz", flow, t_start=0.5, t_end=0.75, unit="px", window=3)
    with np.load(path) as raw:  # plain NumPy reads it
        assert set(raw.files) == {"flow", "t_start", "t_end", "unit", "window"}
        assert raw["flow"].dtype == np.float32 and raw["flow"].shape == (2, 5, 7)
    back, meta = read_flow_npz(path)
    np.testing.assert_allclose(back, flow, rtol=1e-7)
    assert meta == {"t_start": 0.5, "t_end": 0.75, "unit": "px", "window": 3}
    for suffix in ("flo", "npz"):
        np.testing.assert_allclose(read_flow(write_flow(tmp_path / f"g.{suffix}", flow)), flow, rtol=1e-7)
    # .png is DSEC's 16-bit flow PNG: 1/128 px steps
    np.testing.assert_allclose(read_flow(write_flow(tmp_path / "g.png", flow)), flow, atol=1 / 256 + 1e-9)
    with pytest.raises(ValueError, match="unknown flow file type 'tif'"):
        write_flow(tmp_path / "g.tif", flow)
    with pytest.raises(TypeError, match="metadata 'note' must be a number or a string"):
        write_flow_npz(tmp_path / "h.npz", flow, note=[1, 2])
    for interval in ({"t_start": 2.0, "t_end": 1.0}, {"t_start": float("nan"), "t_end": 1.0}, {"t_end": 1.0}):
        with pytest.raises(ValueError, match="the interval needs finite t_start < t_end"):  # not scorable
            write_flow_npz(tmp_path / "i.npz", flow, **interval)
    assert not (tmp_path / "i.npz").exists()
    np.savez(tmp_path / "other.npz", something=np.zeros(3))
    with pytest.raises(KeyError, match="other.npz: no 'flow' array"):
        read_flow_npz(tmp_path / "other.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="junk.npz: not a readable .npz file"):
        read_flow_npz(tmp_path / "junk.npz")


def _result() -> SequenceResult:
    result = SequenceResult(
        warp="translation2",
        param_names=("v_x", "v_y"),
        units=("px/s", "px/s"),
        settings={
            "source": "rec.raw",
            "format": "raw",
            "window_events": 1000,
            "stride": None,
            "regs": {"a": 1},
        },
    )
    for k in range(3):
        result.windows.append(
            WindowResult(
                index=k,
                t_start=0.1 * k,
                t_end=0.1 * k + 0.05,
                n_events=1000 + k,
                theta=np.array([150.0 + k, -60.0 - k]),
                value=2.0 + k,
                fwl=np.nan if k == 1 else 1.1,
                iterations=10 * k,
                seconds=0.5,
                converged=k != 2,
            )
        )
    return result


def test_results_to_hdf5(tmp_path):
    result = _result()
    path = result.to_hdf5(tmp_path / "results.h5")
    with h5py.File(path, "r") as f:
        assert list(f.attrs["columns"]) == [
            "index", "t_start", "t_end", "n_events", "v_x", "v_y",
            "value", "fwl", "iterations", "evaluations", "seconds", "converged", "n_dropped", "status",
            "kernels",
        ]  # fmt: skip
        assert [s.decode() for s in f["status"][()]] == ["estimated"] * 3
        np.testing.assert_array_equal(f["n_dropped"][()], [0, 0, 0])
        np.testing.assert_array_equal(f["index"][()], [0, 1, 2])
        np.testing.assert_array_equal(f["t_end"][()], [w.t_end for w in result.windows])
        np.testing.assert_array_equal(f["v_x"][()], result.theta[:, 0])
        np.testing.assert_array_equal(f["v_y"][()], result.theta[:, 1])
        np.testing.assert_array_equal(f["fwl"][()], [1.1, np.nan, 1.1])
        np.testing.assert_array_equal(f["converged"][()], [True, True, False])
        assert f["v_x"].attrs["unit"] == "px/s" and f["t_start"].attrs["unit"] == "s"
        assert f.attrs["warp"] == "translation2" and list(f.attrs["units"]) == ["px/s", "px/s"]
        assert f.attrs["setting_window_events"] == 1000 and f.attrs["setting_format"] == "raw"
        assert json.loads(f.attrs["setting_regs"]) == {"a": 1} and f.attrs["setting_stride"] == "null"
        assert json.loads(f.attrs["settings_json"]) == result.settings


def test_estimate_writes_hdf5_and_flow_of_a_raw_file(tmp_path, capsys):
    faery = pytest.importorskip("faery", reason="needs 'faery' (cmax-taichi[formats]) to write the .raw file")
    folder = write_ecd_folder(tmp_path / "rec")
    rows = np.loadtxt(folder / "events.txt")
    events = np.zeros(len(rows), dtype=faery.EVENTS_DTYPE)
    events["t"] = np.rint(rows[:, 0] * 1e6).astype(np.uint64)
    events["x"], events["y"], events["on"] = rows[:, 1], rows[:, 2], rows[:, 3] > 0
    raw = tmp_path / "rec.raw"
    faery.events_stream_from_array(events, dimensions=(64, 48)).to_file(raw, version="evt3")

    out = tmp_path / "out"
    argv = ["estimate", str(raw), "--window", "1000", "--out", str(out), "--figures", "0", "--quiet"]
    assert cli.main([*argv, "--flow-out", str(out / "flow"), "--flow-format", "npz"]) == 0
    assert "results.h5" in capsys.readouterr().out
    with (out / "results.csv").open() as fh:
        table = list(csv.DictReader(fh))
    # two windows of 1000 events, then the partial tail's row (not estimated, counted)
    assert [r["status"] for r in table] == ["estimated", "estimated", "partial_tail"]
    with h5py.File(out / "results.h5", "r") as f:
        np.testing.assert_array_equal(f["v_x"][()], [float(r["v_x [px/s]"]) for r in table])
        np.testing.assert_array_equal(f["t_start"][()], [float(r["t_start [s]"]) for r in table])
        assert [s.decode() for s in f["status"][()]] == [r["status"] for r in table]
        assert f.attrs["setting_format"] == "raw" and f.attrs["setting_window_events"] == 1000
    table = table[:2]  # the estimated windows have a flow file each
    for k, row in enumerate(table):
        flow, meta = read_flow_npz(out / "flow" / f"flow_{k:04d}.npz")
        assert flow.shape == (2, 48, 64) and meta["unit"] == "px" and meta["window"] == k
        span = float(row["t_end [s]"]) - float(row["t_start [s]"])
        assert meta["t_end"] - meta["t_start"] == pytest.approx(span)
        # a translation: the same displacement everywhere, velocity x window span, near the truth
        np.testing.assert_allclose(flow[0], float(row["v_x [px/s]"]) * span, rtol=1e-5)
        np.testing.assert_allclose(flow[1], float(row["v_y [px/s]"]) * span, rtol=1e-5)
        assert abs(float(row["v_x [px/s]"]) - V[0]) < 10 and abs(float(row["v_y [px/s]"]) - V[1]) < 10

    assert cli.main([*argv, "--max-windows", "1", "--flow-out", str(out / "flo")]) == 0
    flo = read_flo(out / "flo" / "flow_0000.flo")
    npz = read_flow(out / "flow" / "flow_0000.npz")
    np.testing.assert_allclose(flo, npz, rtol=1e-5)
    assert not (out / "flo" / "flow_0001.flo").exists()
