"""AEDAT4 reader (optional package ``aedat``): the shared sample file, the cache, missing package."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from conftest import shared_data_dir

from cmax_taichi.io import detect_format, open_recording

pytestmark = pytest.mark.usefixtures("cache_in_tmp")


def _aedat():
    return pytest.importorskip(
        "aedat", reason="the optional AEDAT4 reader needs 'aedat': pip install aedat (or cmax-taichi[aedat])"
    )


def test_sample_file():
    aedat = _aedat()
    path = shared_data_dir("aedat4_sample", "sample.aedat4")
    assert detect_format(path) == "aedat4" and detect_format(path.parent) == "aedat4"
    chunks = [p["events"] for p in aedat.Decoder(str(path)) if "events" in p]
    ref = np.concatenate(chunks)
    with open_recording(path) as rec:
        assert rec.format == "aedat4" and rec.sensor_size == (320, 240) and rec.n_events == 111954
        assert rec.camera is None and not rec.undistorted
        ev = rec.read()
        np.testing.assert_array_equal(ev.x, ref["x"])
        np.testing.assert_array_equal(ev.y, ref["y"])
        np.testing.assert_array_equal(ev.t, ref["t"] / 1e6)
        np.testing.assert_array_equal(ev.p, np.where(ref["on"], 1, -1))
        assert rec.t_end - rec.t_start == pytest.approx(0.59, abs=0.01)
        w = rec.read_time(rec.t_start + 0.1, rec.t_start + 0.2)
        assert w.t[0] >= rec.t_start + 0.1 and w.t[-1] < rec.t_start + 0.2
        assert [len(w) for w in rec.windows(30000)] == [30000] * 3
        imu = rec.imu()
        assert imu.shape == (475, 7) and np.all(np.diff(imu[:, 0]) >= 0)
        assert rec.angular_velocity(rec.t_start) is None and rec.flow(rec.t_start, rec.t_end) is None
    # the second open maps the cache
    again = open_recording(path)
    np.testing.assert_array_equal(again.read(500, 600).t, ev.t[500:600])


def test_bad_aedat4_file(tmp_path):
    _aedat()
    (tmp_path / "bad.aedat4").write_bytes(b"#!AER-DAT4.0\r\n" + b"\x00" * 64)
    with pytest.raises(ValueError, match="bad.aedat4: not a readable AEDAT4 file"):
        open_recording(tmp_path / "bad.aedat4")
    data = shared_data_dir("aedat4_sample", "sample.aedat4").read_bytes()
    (tmp_path / "cut.aedat4").write_bytes(data[: len(data) // 2])  # a truncated file
    with pytest.raises(ValueError, match="cut.aedat4: cannot decode the AEDAT4 file after"):
        open_recording(tmp_path / "cut.aedat4")


def test_missing_package_is_named(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "aedat", None)  # behaves as "not installed"
    (tmp_path / "x.aedat4").write_bytes(b"#!AER-DAT4.0\r\n")
    with pytest.raises(ImportError, match=r"x.aedat4: reading AEDAT4 files needs .*pip install aedat"):
        open_recording(tmp_path / "x.aedat4")
