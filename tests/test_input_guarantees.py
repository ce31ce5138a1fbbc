"""Hostile and edge inputs of the input layer: one regression test per case.

Each case answers with one error naming the problem (or a correct result), and the process stays
usable: after every failure a normal ``Events`` / ``open_recording`` / ``process`` works.
"""

from __future__ import annotations

import math
import os
import re
import time
import warnings

import h5py
import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi import io
from cmax_taichi.cli import main
from cmax_taichi.core import checks
from cmax_taichi.core.checks import EventsDroppedWarning
from cmax_taichi.io import text as text_module
from cmax_taichi.io._cache import content_fingerprint
from cmax_taichi.solve import sequence

SENSOR = (64, 48)


pytestmark = pytest.mark.usefixtures("cache_in_tmp")


def _random_events(n=300, seed=0, sensor=SENSOR, duration=0.05):
    rng = np.random.default_rng(seed)
    W, H = sensor
    t = np.sort(rng.uniform(0, duration, n))
    return rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n), t, rng.integers(0, 2, n)


def _normal_events() -> cm.Events:
    """A normal construction, to show the process is intact after a failure."""
    events = cm.Events(*_random_events(), SENSOR)
    assert len(events) == 300
    return events


def _write_text(folder, lines, name="events.txt"):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text("".join(line + "\n" for line in lines))
    return folder


def _normal_recording(tmp_path):
    folder = _write_text(
        tmp_path / "normal", [f"{0.001 * k:.3f} {k % 60} {k % 40} {k % 2}" for k in range(50)]
    )
    with io.open_recording(folder) as rec:
        assert rec.read().x.shape == (50,)


# --- Events ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("column", ["x", "y", "t", "p"])
def test_complex_values_are_refused_not_truncated(column):
    arrays = dict(zip("xytp", _random_events(n=20), strict=True))
    arrays[column] = arrays[column] + 0.5j
    with pytest.raises(TypeError, match=rf"^{column} has complex values"):
        cm.Events(*arrays.values(), SENSOR)
    arrays[column] = arrays[column].real + 0j  # an imaginary part of exactly 0 is refused all the same
    with pytest.raises(TypeError, match="complex"):
        cm.Events(*arrays.values(), SENSOR)
    _normal_events()


def test_datetime_and_ragged_arrays_are_refused():
    x, y, t, p = _random_events(n=5)
    with pytest.raises(TypeError, match="timedelta64.*seconds"):
        cm.Events(x, y, (t * 1e6).astype("timedelta64[us]"), p, SENSOR)
    with pytest.raises(ValueError, match="^x cannot be read as a one-dimensional numeric array"):
        cm.Events([[1, 2], [3]], y[:2], t[:2], p[:2], SENSOR)
    _normal_events()


def test_polarity_conventions_do_not_mix():
    x, y, t, _ = _random_events(n=3)
    with pytest.raises(ValueError, match=r"p mixes the polarity conventions \(it holds -1, 0, 1\)"):
        cm.Events(x, y, t, [-1, 0, 1], SENSOR)
    with pytest.raises(ValueError, match="mixes"):
        cm.Events(x, y, t, [-1, 0, 0], SENSOR)
    with pytest.raises(ValueError, match=r"in \{0, 1\} or \{-1, \+1\}, got values such as \[2.0\]"):
        cm.Events(x, y, t, [0, 1, 2], SENSOR)
    # each convention alone (and bools) is read as OFF = -1, ON = +1
    for p in ([0, 1, 1], [-1, 1, 1], [False, True, True]):
        assert cm.Events(x, y, t, p, SENSOR).p.tolist() == [-1, 1, 1]
    _normal_events()


@pytest.mark.parametrize(
    "size,error,message",
    [
        ((240.5, 180), ValueError, r"sensor_size W = 240.5 is not a whole number of pixels"),
        ((240, 180.25), ValueError, r"sensor_size H = 180.25 is not a whole number"),
        ((math.inf, 180), ValueError, r"sensor_size W must be finite, got inf"),
        ((240, math.nan), ValueError, r"sensor_size H must be finite"),
        (("240", 180), TypeError, r"sensor_size W must be an integer number of pixels, got '240' \(str\)"),
        ((240, None), TypeError, r"sensor_size H must be an integer"),
        ((True, 180), TypeError, r"sensor_size W must be an integer"),
        ((240, 180, 3), ValueError, r"sensor_size must be a pair \(W, H\)"),
        (None, ValueError, r"sensor_size must be a pair"),
        ("ab", ValueError, r"sensor_size must be a pair"),
        ((0, 10), ValueError, r"sensor_size must be positive, got \(W, H\) = \(0, 10\)"),
    ],
)
def test_sensor_size_is_whole_finite_and_positive(size, error, message):
    x, y, t, p = _random_events(n=4)
    with pytest.raises(error, match=message):
        cm.Events(x, y, t, p, size)
    _normal_events()


def test_sensor_size_accepts_integral_floats():
    x, y, t, p = _random_events(n=4)
    for size in ((64.0, 48.0), (np.int64(64), np.float32(48.0)), [64, 48], np.array([64, 48])):
        events = cm.Events(x, y, t, p, size)
        assert events.sensor_size == (64, 48) and all(type(v) is int for v in events.sensor_size)


@pytest.mark.parametrize(
    "kwargs,error,message",
    [
        ({"fx": "200"}, TypeError, r"Camera fx must be a real number \(px\), got '200' \(str\)"),
        ({"cy": None}, TypeError, r"Camera cy must be a real number"),
        ({"fy": True}, TypeError, r"Camera fy must be a real number"),
        ({"cx": 1 + 2j}, TypeError, r"Camera cx must be a real number"),
        ({"dist": 0.1}, TypeError, r"Camera dist must be a sequence of real numbers"),
        ({"dist": "abcde"}, TypeError, r"Camera dist must be a sequence"),
        ({"dist": (0.1, "x")}, TypeError, r"Camera dist must be a sequence"),
        ({"dist": (0.1,) * 6}, ValueError, r"dist must be \(k1, k2, p1, p2, k3\)"),
        ({"fx": -1.0}, ValueError, r"focal lengths must be positive"),
        ({"cx": math.inf}, ValueError, r"camera intrinsics must be finite"),
    ],
)
def test_camera_refuses_what_is_not_a_real_number(kwargs, error, message):
    params = {"fx": 200.0, "fy": 200.0, "cx": 32.0, "cy": 24.0, **kwargs}
    with pytest.raises(error, match=message):
        cm.Camera(**params)
    camera = cm.Camera(np.float32(200), 200, 32, 24, dist=np.array([0.1, 0.0, 0.0, 0.0]))
    assert type(camera.fx) is float and camera.dist == (pytest.approx(0.1), 0.0, 0.0, 0.0, 0.0)


def test_undistortion_drops_with_a_warning_that_counts():
    rng = np.random.default_rng(1)
    n = 30000
    W, H = 240, 180
    events = cm.Events(
        rng.uniform(0, W - 1, n),
        rng.uniform(0, H - 1, n),
        np.sort(rng.uniform(0, 0.1, n)),
        np.ones(n),
        (W, H),
    )
    camera = cm.Camera(200.0, 200.0, 120.0, 90.0, dist=(-50.0, 0.0, 0.0, 0.0, 0.0))
    with pytest.warns(
        EventsDroppedWarning, match=r"dropped (\d+) of 30000 event\(s\) in undistortion"
    ) as caught:
        kept, mask = events.undistort(camera, return_mask=True)
    assert len(caught) == 1
    assert len(kept) == int(mask.sum()) < n // 10
    assert kept.n_dropped == n - len(kept)
    assert f"dropped {n - len(kept)} of {n}" in str(caught[0].message)
    assert "does not invert" in str(caught[0].message)
    # the Events warning for events outside the sensor is the same one (one place)
    with pytest.warns(EventsDroppedWarning, match=r"dropped 1 of 2 event\(s\) outside the 240x180 sensor"):
        cm.Events([1.0, 500.0], [1.0, 1.0], [0.0, 0.1], [1, 1], (W, H))
    # no distortion, nothing dropped: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(events.undistort(cm.Camera(200.0, 200.0, 120.0, 90.0))) == n


def _reference_time_windows(t, duration, stride):
    """Every window stepped through one by one (the behaviour the jump must reproduce)."""
    out, k = [], 0
    while t[0] + k * stride <= t[-1]:
        a = t[0] + k * stride
        i0, i1 = np.searchsorted(t, [a, a + duration], side="left")
        if i1 > i0:
            out.append((int(i0), int(i1)))
        k += 1
    return out


@pytest.mark.parametrize("duration,stride", [(0.01, None), (0.003, 0.001), (0.001, 0.0025), (0.02, 0.007)])
def test_time_windows_skip_empty_runs_exactly(duration, stride):
    # bursts separated by long gaps: most windows are empty
    rng = np.random.default_rng(3)
    t = np.sort(np.concatenate([rng.uniform(a, a + 0.004, 40) for a in (0.0, 0.2, 0.2071, 0.9, 3.0)]))
    n = len(t)
    events = cm.Events(np.zeros(n), np.zeros(n), t, np.ones(n), SENSOR)
    got = [
        (int(np.searchsorted(t, w.t[0])), int(np.searchsorted(t, w.t[0])) + len(w))
        for w in events.windows_by_duration(duration, stride)
    ]
    assert got == _reference_time_windows(t, duration, stride or duration)


def test_tiny_windows_are_refused_at_once():
    events = cm.Events(*_random_events(n=30000), SENSOR)
    start = time.perf_counter()
    with pytest.raises(
        ValueError, match=r"duration = 1e-12 s is below 0.001 x the mean event spacing \(1.67e-06 s"
    ):
        events.windows_by_duration(1e-12)
    with pytest.raises(ValueError, match=r"would be 5e\+08 windows, more than the limit of 10000000"):
        events.windows_by_duration(0.001, 1e-10)
    with pytest.raises(ValueError, match="more than the limit of 100"):
        events.windows_by_duration(0.001, 0.0001, max_windows=100)
    assert time.perf_counter() - start < 1.0
    with pytest.raises(ValueError, match=r"stride \(events\) must be a whole number, got 0.5"):
        events.windows_by_count(100, 0.5)
    with pytest.raises(TypeError, match="n_events must be a whole number, got None"):
        events.windows_by_count(None)
    assert [len(w) for w in events.windows_by_count(10000)] == [10000] * 3


# --- readers --------------------------------------------------------------------------------------
def test_binary_calib_names_the_file(tmp_path):
    folder = _write_text(tmp_path / "seq", ["0.0 1 2 1", "0.1 3 4 0", "0.2 5 6 1"])
    (folder / "calib.txt").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe")
    with pytest.raises(
        ValueError, match=r"calib.txt: not a text file \(byte 0x89 at offset 0 is not UTF-8\)"
    ):
        io.open_recording(folder)
    for line, message in (("240.5 180", "240.5 is not a whole number"), ("inf 180", "W must be finite")):
        (folder / "calib.txt").write_text(f"200 200 120 90\n{line}\n")
        with pytest.raises(ValueError, match=rf"calib.txt, line 2: expected the sensor size .*{message}"):
            io.open_recording(folder)
    (folder / "calib.txt").write_text("200 200 120 90\n240.0 180\n")
    with io.open_recording(folder) as rec:
        assert rec.sensor_size == (240, 180)
    _normal_recording(tmp_path)


def test_text_polarity_conventions_do_not_mix_across_chunks(tmp_path, monkeypatch):
    monkeypatch.setattr(text_module, "_CHUNK", 64)  # many chunks: the check spans them
    lines = [f"{0.01 * k:.2f} {k % 10} 3 {k % 2}" for k in range(40)] + ["0.50 1 2 -1"]
    folder = _write_text(tmp_path / "seq", lines)
    with pytest.raises(
        ValueError, match=r"events.txt, line 41 \('0.50 1 2 -1'\): polarity -1 after earlier \+0"
    ):
        io.open_recording(folder)
    _normal_recording(tmp_path)


def test_an_option_the_format_does_not_take_is_named(tmp_path, capsys):
    """`--topic` on a text recording printed "TextRecording.__init__() got an unexpected keyword
    argument 'topic'"; a path of the wrong type printed pathlib's message."""
    folder = _write_text(tmp_path / "seq", ["0.0 1 2 1", "0.1 3 4 0", "0.2 5 6 1"])
    with pytest.raises(ValueError, match=r"the ecd reader takes no option topic \(it takes cache, .*sort"):
        io.open_recording(folder, topic="/dvs/events")
    with pytest.raises(TypeError, match=r"path must be a file or folder \(str or os.PathLike\), got int"):
        io.open_recording(123)
    assert main(["estimate", str(folder), "--topic", "/dvs/events", "--out", str(tmp_path / "E")]) == 2
    err = capsys.readouterr().err
    assert "the ecd reader takes no option topic" in err and "Traceback" not in err


def test_cache_notices_a_rewrite_with_the_same_size_and_mtime(tmp_path):
    folder = _write_text(tmp_path / "seq", ["0.0 1 2 1", "0.1 3 4 0", "0.2 5 6 1"])
    path = folder / "events.txt"
    cache = tmp_path / "cache"
    with io.open_recording(folder, cache_dir=cache) as rec:
        assert rec.read().x.tolist() == [1.0, 3.0, 5.0]
    before = path.stat()
    path.write_text("0.0 1 2 1\n0.1 3 4 0\n0.2 7 6 1\n")
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert (path.stat().st_size, path.stat().st_mtime_ns) == (before.st_size, before.st_mtime_ns)
    with io.open_recording(folder, cache_dir=cache) as rec:
        assert rec.read().x.tolist() == [1.0, 3.0, 7.0]


def test_content_fingerprint_samples_large_files(tmp_path):
    path = tmp_path / "big.bin"
    data = bytearray(np.random.default_rng(0).integers(0, 256, 3 << 20, dtype=np.uint8).tobytes())
    path.write_bytes(data)
    first = content_fingerprint(path, len(data))
    data[-1] ^= 0xFF  # the last byte
    path.write_bytes(data)
    assert content_fingerprint(path, len(data)) != first


def test_pickled_flow_npy_is_refused(tmp_path):
    folder = _write_text(tmp_path / "seq", ["0.0 1 2 1", "0.1 3 4 0", "0.2 5 6 1"])
    np.save(folder / "flow.npy", np.array([{"code": 1}], dtype=object), allow_pickle=True)
    with io.open_recording(folder) as rec:
        with pytest.raises(
            ValueError, match=r"flow.npy: not a plain numeric .npy array .*pickled object arrays"
        ):
            rec.flow(0.0, 0.1)
        np.save(folder / "flow.npy", np.ones((2, 180, 240)))
        assert rec.flow(0.0, 0.1).shape == (2, 180, 240)  # the same recording, still usable


def _mvsec(path, rows):
    with h5py.File(path, "w") as f:
        f["davis/left/events"] = rows
    return path


def test_hdf5_string_dtype_and_nan_t_name_file_and_dataset(tmp_path):
    path = tmp_path / "s_data.hdf5"
    _mvsec(path, np.array([[b"1", b"2", b"0", b"1"]] * 3))
    with pytest.raises(
        ValueError, match=r"s_data.hdf5: dataset 'davis/left/events' holds values of type \|S1"
    ):
        io.open_recording(path)
    _mvsec(path, np.array([[1, 2, np.nan, 1], [1, 2, 0.1, 1], [1, 2, 0.2, 1]]))
    with pytest.raises(ValueError, match=r"s_data.hdf5: dataset 'davis/left/events', rows 0..3: the first"):
        io.open_recording(path)
    _mvsec(path, np.array([[1, 2, 0.0, 1], [1, 2, np.nan, 1], [1, 2, 0.2, 1]]))
    with io.open_recording(path) as rec:
        with pytest.raises(ValueError, match=r"'davis/left/events', rows 0..3: t has 1 non-finite value"):
            rec.read()
        assert len(rec.read(2)) == 1  # the rest of the file is still readable
    _mvsec(path, np.array([[1, 2, 0.0, 1], [1, 2, 0.1, 1], [1, 2, 0.2, 1]]))
    with io.open_recording(path) as rec:
        assert len(rec.read()) == 3


def _dsec(path, t, t_offset=0):
    with h5py.File(path, "w") as f:
        f["events/x"] = np.array([1, 2, 3], dtype=np.uint16)
        f["events/y"] = np.array([1, 2, 3], dtype=np.uint16)
        f["events/t"] = t
        f["events/p"] = np.array([0, 1, 1], dtype=np.uint8)
        f["ms_to_idx"] = np.array([0], dtype=np.uint64)
        f["t_offset"] = t_offset
    return path


def test_dsec_string_and_nan_values_name_file_and_dataset(tmp_path):
    path = tmp_path / "events.h5"
    _dsec(path, np.array([b"0", b"1", b"2"]))
    with pytest.raises(ValueError, match=r"events.h5: dataset 'events/t' holds values of type \|S1"):
        io.open_recording(path)
    _dsec(path, np.array([0.0, np.nan, 20.0]))
    with (
        io.open_recording(path) as rec,
        pytest.raises(ValueError, match=r"events.h5: dataset 'events/t', rows 0..3 has 1 non-finite"),
    ):
        rec.read()
    _dsec(path, np.array([0, 10, 20]), t_offset=np.nan)
    with pytest.raises(ValueError, match=r"events.h5: dataset 't_offset' has 1 non-finite"):
        io.open_recording(path)
    _dsec(path, np.array([0, 10, 20]))
    with io.open_recording(path) as rec:
        assert rec.read().t.tolist() == pytest.approx([0.0, 1e-5, 2e-5])


def test_recording_window_and_read_arguments(tmp_path):
    folder = _write_text(
        tmp_path / "seq", [f"{0.001 * k:.3f} {k % 60} {k % 40} {k % 2}" for k in range(1000)]
    )
    with io.open_recording(folder) as rec:
        start = time.perf_counter()
        with pytest.raises(
            ValueError, match=r"duration = 1e-12 s is below 0.001 x the mean event spacing \(0.001 s"
        ):
            rec.windows(duration=1e-12)
        with pytest.raises(
            ValueError, match=r"over the events' 0.999 s would be 9.99e\+07 windows, more than"
        ):
            rec.windows(duration=0.01, stride=1e-8)
        rec.max_time_windows = 50
        with pytest.raises(ValueError, match="more than the limit of 50"):
            rec.windows(duration=0.01)
        rec.max_time_windows = checks.MAX_TIME_WINDOWS
        assert time.perf_counter() - start < 1.0
        with pytest.raises(TypeError, match=r"windows needs n_events \(events per window\) or duration"):
            rec.windows(n_events=None)
        with pytest.raises(ValueError, match=r"stride \(events\) must be at least 1, got 0"):
            rec.windows(100, stride=0)
        with pytest.raises(ValueError, match=r"stride \(events\) must be a whole number, got 0.5"):
            rec.windows(100, stride=0.5)
        with pytest.raises(ValueError, match=r"n_events must be a whole number, got 2.5"):
            rec.windows(2.5)
        with pytest.raises(ValueError, match="stride must be a positive number of seconds, got 0.0"):
            rec.windows(duration=0.01, stride=0)
        with pytest.raises(TypeError, match=r"read_time t0 must be a number of seconds, got None"):
            rec.read_time(None, 1.0)
        with pytest.raises(ValueError, match="read_time t1 must be a finite number of seconds, got nan"):
            rec.read_time(0.0, math.nan)
        with pytest.raises(TypeError, match=r"start must be an integer event index, got 0.5"):
            rec.read(0.5)
        # the recording still works, and windows by time match the one-by-one stepping
        t = rec.read().t
        got = [len(w) for w in rec.windows(duration=0.0105, stride=0.05)]
        assert got == [i1 - i0 for i0, i1 in _reference_time_windows(t, 0.0105, 0.05)]
        assert [len(w) for w in rec.windows(300, stride=300)] == [300] * 3


# --- sequence and CLI -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs,error,message",
    [
        ({"stride": 0}, ValueError, r"stride \(events\) must be at least 1, got 0"),
        ({"stride": 0.5}, ValueError, r"stride \(events\) must be a whole number, got 0.5"),
        ({"n_events": None}, TypeError, r"n_events must be a whole number, got None"),
        ({"n_events": 1}, ValueError, r"n_events must be at least 2, got 1"),
        ({"max_windows": 0}, ValueError, r"max_windows must be at least 1, got 0"),
        ({"max_windows": -1}, ValueError, r"max_windows must be at least 1, got -1"),
        ({"duration": 0.01, "stride": 0}, ValueError, r"stride must be a positive number of seconds"),
        ({"duration": "1"}, TypeError, r"duration must be a number of seconds, got '1'"),
    ],
)
def test_process_refuses_bad_windows_before_reading(kwargs, error, message):
    events = _normal_events()
    with pytest.raises(error, match=message):
        sequence.process(events, **{"n_events": 100, **kwargs}, progress=False)


def test_process_reports_undistortion_once_with_totals():
    """A distorted camera drops events in every window: one warning for the first window, one with the
    totals at the end (not one per window); the run works after the failures above."""
    rng = np.random.default_rng(4)
    n = 600
    events = cm.Events(
        rng.uniform(0, 63, n), rng.uniform(0, 47, n), np.sort(rng.uniform(0, 0.06, n)), np.ones(n), SENSOR
    )
    camera = cm.Camera(60.0, 60.0, 32.0, 24.0, dist=(-0.3, 0.05, 0.0, 0.0, 0.0))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = sequence.process(
            events,
            n_events=200,
            camera=camera,
            progress=False,
            compute_fwl=False,
            optimize_options={"init": "none", "max_iter": 3},
        )
    assert len(result) == 3
    dropped = [str(w.message) for w in caught if issubclass(w.category, EventsDroppedWarning)]
    assert len(dropped) == 2, dropped
    assert dropped[0].startswith("dropped ") and "of 200 event(s) in undistortion" in dropped[0]
    total = sum(w.n_events for w in result.windows)
    assert dropped[1] == (
        f"Events(n=600): {600 - total} of 600 event(s) not estimated: {600 - total} lost in undistortion "
        "(the first such window's warning says why)"
    )
    # per window in the results, and in the totals
    assert [w.n_events + w.n_dropped for w in result.windows] == [200] * 3
    assert result.events["undistortion"] == 600 - total and result.events["estimated"] == total


@pytest.mark.parametrize(
    "argv,message",
    [
        (
            ["--stride", "0"],
            "--stride must be a whole number of events >= 1 (or seconds with --duration), got 0",
        ),
        (
            ["--stride", "0.5"],
            "--stride must be a whole number of events >= 1 (or seconds with --duration), got 0.5",
        ),
        (["--max-windows", "0"], "--max-windows must be at least 1, got 0"),
        (["--max-windows", "-3"], "--max-windows must be at least 1, got -3"),
        (["--duration", "0.01", "--stride", "0"], "--stride must be a positive number of seconds, got 0"),
        (["--duration", "1e-12"], "duration = 1e-12 s is below 0.001 x the mean event spacing"),
    ],
)
def test_cli_window_options_one_line_exit_2(tmp_path, capsys, argv, message):
    folder = _write_text(tmp_path / "seq", [f"{0.001 * k:.3f} {k % 60} {k % 40} {k % 2}" for k in range(100)])
    out = tmp_path / "out"
    assert main(["estimate", str(folder), "--out", str(out), "--quiet", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"cmax-taichi estimate: error: {message}") and "\n" not in err, err
    assert "Traceback" not in err
    assert sorted(p.name for p in folder.iterdir()) == ["events.txt"]  # nothing written beside the data


def test_mvsec_pickled_flow_timestamps_are_refused(tmp_path):
    data = _mvsec(tmp_path / "s_data.hdf5", np.array([[1, 2, 0.0, 1], [1, 2, 0.1, 1], [1, 2, 0.2, 1]]))
    frames = np.zeros((2, 260, 346))
    np.savez(
        tmp_path / "s_gt_flow_dist.npz",
        timestamps=np.array([0.0, "x"], dtype=object),
        x_flow_dist=frames,
        y_flow_dist=frames,
        allow_pickle=True,
    )
    with io.open_recording(data) as rec:
        with pytest.raises(ValueError, match=r"s_gt_flow_dist.npz: 'timestamps' is not a numeric array"):
            rec.flow(0.0, 0.1)
        assert len(rec.read()) == 3


def test_cli_segment_refuses_a_nan_start_time(tmp_path, capsys):
    folder = _write_text(tmp_path / "seq", [f"{0.001 * k:.3f} {k % 60} {k % 40} {k % 2}" for k in range(100)])
    assert main(["segment", str(folder), "--out", str(tmp_path / "out"), "--t-start", "nan"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "cmax-taichi segment: error: --t-start must be a finite number of seconds, got nan"


# --- timestamps checked once, early ------------------------------------------------------
def _mvsec_times(path, t):
    n = len(t)
    with h5py.File(path, "w") as f:
        f["davis/left/events"] = np.c_[np.full(n, 10.0), np.full(n, 12.0), t, np.ones(n)]
    return path


@pytest.mark.parametrize("mode", [{"n_events": 100}, {"duration": 0.02}])
def test_unsorted_and_nan_hdf5_times_name_the_file_dataset_and_first_row(tmp_path, mode):
    t = np.linspace(0.0, 0.1, 500)
    t[300] = 0.01  # earlier than row 299
    path = _mvsec_times(tmp_path / "u_data.hdf5", t)
    where = r"u_data.hdf5: dataset 'davis/left/events', column 2 \(t\), row 300: time 0.010000000 s is "
    where += r"earlier.*must be sorted by time \(open_recording\(\.\.\., sort=True\)"
    with io.open_recording(path) as rec:
        with pytest.raises(ValueError, match=where):
            rec.windows(**mode)  # both window modes, at the call, before any window is read
        with pytest.raises(ValueError, match="row 300"):
            sequence.process(rec, **mode, progress=False)
        with pytest.raises(ValueError, match="row 300"):
            rec.read_time(0.0, 0.05)  # a search by time relies on the order too
        assert len(rec.read(0, 100)) == 100  # rows in order are still readable
    with io.open_recording(path, sort=True) as rec:  # sorting on request
        assert rec.rows_out_of_order == 1 and np.all(np.diff(rec.read().t) >= 0)
        assert len(list(rec.windows(100))) == 5
    t[300] = np.nan
    _mvsec_times(path, t)
    with io.open_recording(path) as rec:
        nan = r"column 2 \(t\), row 300: time nan is not finite"
        with pytest.raises(ValueError, match=nan):
            rec.windows(**mode)  # not "cannot convert float NaN to integer"


def test_all_equal_times_are_refused_in_both_modes(tmp_path, capsys):
    folder = _write_text(tmp_path / "eq", [f"0.5 {k % 60} {k % 40} {k % 2}" for k in range(100)])
    with io.open_recording(folder) as rec:
        for mode in ({"n_events": 50}, {"duration": 0.01}):
            with pytest.raises(ValueError, match=r"all 100 events have the same time t = 0.500000000 s"):
                rec.windows(**mode)
    events = cm.Events(np.zeros(5), np.zeros(5), np.full(5, 2.0), np.ones(5), SENSOR)
    with pytest.raises(ValueError, match="all 5 events have the same time"):
        sequence.process(events, n_events=2, progress=False)
    for argv in (["--window", "50"], ["--duration", "0.01"]):
        assert main(["estimate", str(folder), "--out", str(tmp_path / "o"), "--quiet", *argv]) == 2
        err = capsys.readouterr().err
        assert "all 100 events have the same time" in err and "--window" not in err, err


def test_no_window_messages_name_the_mode_given(tmp_path, capsys):
    empty = tmp_path / "empty_data.hdf5"
    with h5py.File(empty, "w") as f:
        f["davis/left/events"] = np.zeros((0, 4))
    assert main(["estimate", str(empty), "--out", str(tmp_path / "o"), "--quiet", "--duration", "0.01"]) == 2
    assert capsys.readouterr().err.strip().endswith("no window to estimate: the recording has no events")
    folder = _write_text(tmp_path / "few", [f"{0.001 * k:.3f} {k % 60} {k % 40} {k % 2}" for k in range(100)])
    assert main(["estimate", str(folder), "--out", str(tmp_path / "o"), "--quiet", "--window", "150"]) == 2
    err = capsys.readouterr().err
    assert "100 events, fewer than one window of --window 150: --keep-tail estimates a shorter window" in err


def test_a_broken_external_link_names_the_file(tmp_path):
    path = tmp_path / "ext_data.hdf5"
    with h5py.File(path, "w") as f:
        f["davis/left/events"] = h5py.ExternalLink("missing.h5", "/events")
    broken = r"ext_data.hdf5: dataset 'davis/left/events' cannot be opened \(a broken link"
    with pytest.raises(OSError, match=broken):
        io.open_recording(path)


# --- special files never block --------------------------------------------------------------
@pytest.mark.parametrize("kind", ["fifo", "socket", "device"])
def test_special_files_are_refused_at_open(tmp_path, capsys, kind):
    import socket

    if kind == "fifo":
        path = tmp_path / "events.txt"
        os.mkfifo(path)
    elif kind == "socket":
        path = tmp_path / "events.sock"
        with socket.socket(socket.AF_UNIX) as s:
            s.bind(str(path))
    else:
        path = tmp_path / "zero"
        if not os.path.exists("/dev/zero"):
            pytest.skip("no /dev/zero")
        path = type(tmp_path)("/dev/zero")
    message = r"is a (FIFO \(named pipe\)|socket|character device), not a regular file"
    start = time.perf_counter()
    for call in (
        lambda: io.open_recording(path),
        lambda: io.open_recording(path, format="text"),
        lambda: io.open_recording(path, format="mvsec"),
        lambda: sequence.read_results(path),
        lambda: sequence.process(path, progress=False),
    ):
        with pytest.raises(OSError, match=message):
            call()
    assert main(["estimate", str(path), "--format", "text", "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert re.search(message, capsys.readouterr().err)
    assert time.perf_counter() - start < 30  # refused, not read


def test_a_refused_input_ends_the_command_in_one_line_figure_process_included(tmp_path):
    """A fresh ``estimate`` forks its figure process before it reads the input; the refusal ends both
    without a traceback (the child once inherited the command's SIGTERM handler and raised in it)."""
    import subprocess
    import sys

    path = tmp_path / "events.txt"
    os.mkfifo(path)
    args = [sys.executable, "-m", "cmax_taichi.cli", "estimate", str(path), "--out", str(tmp_path / "o")]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert re.search(r"error: .*events.txt: is a FIFO \(named pipe\)", proc.stderr), proc.stderr
    assert not (tmp_path / "o").exists()


def test_a_fifo_where_a_side_file_is_expected_is_refused(tmp_path):
    folder = _write_text(tmp_path / "seq", ["0.0 1 2 1", "0.1 3 4 0", "0.2 5 6 1"])
    os.mkfifo(folder / "calib.txt")  # Path.is_file() would say False and hide it
    with pytest.raises(OSError, match=r"calib.txt: is a FIFO"):
        io.open_recording(folder)


# --- unclear answers made clear -----------------------------------------------------------------
def test_evaluate_of_a_binary_file_names_it(tmp_path, capsys):
    raw = tmp_path / "some.raw"
    raw.write_bytes(b"\x81\x00\xff\xfe" * 8)
    assert main(["evaluate", str(raw)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"cmax-taichi evaluate: error: {raw}: not a results JSON file (byte 0x81 at offset")
    assert "codec" not in err


def test_segment_refuses_a_negative_sensor_size_by_name(tmp_path, capsys):
    folder = _write_text(tmp_path / "seq", [f"{0.001 * k:.3f} {k % 60} {k % 40} {k % 2}" for k in range(100)])
    argv = ["segment", str(folder), "--sensor-size", "-5", "10", "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "cmax-taichi segment: error: --sensor-size: sensor_size must be positive, got (W, H) = (-5, 10)"
    )
    with pytest.raises(ValueError, match="sensor_size must be positive"):
        io.open_recording(tmp_path / "seq", sensor_size=(-5, 10))


def test_vote_weights_are_checked_as_event_arrays_are():
    events = _normal_events()
    n = len(events)
    for weights, error, message in [
        (np.full(n, 1 + 1j), TypeError, r"weights has complex values"),
        (["1.5"] * n, TypeError, r"weights must be real numbers, got dtype <U3"),
        (np.full(n, 1e300), ValueError, r"weights up to 1e\+300 in magnitude would overflow"),
        (np.full(n - 1, 1.0), ValueError, r"weights has 299 values for 300 events"),
        (np.r_[np.nan, np.ones(n - 1)], ValueError, r"weights has 1 non-finite value"),
    ]:
        with pytest.raises(error, match=message):
            cm.ContrastMaximization(events, warp="translation2", weights=weights)
    prob = cm.ContrastMaximization(events, warp="translation2", weights=np.full(n, 1e6))
    assert np.isfinite(prob.value(np.zeros(2)))


def test_a_tiny_blur_is_no_blur_not_a_nan():
    events = _normal_events()
    tiny = cm.ContrastMaximization(events, warp="translation2", blur_sigma=1e-300)
    none = cm.ContrastMaximization(events, warp="translation2", blur_sigma=0.0)
    theta = np.array([30.0, -20.0])
    assert tiny.value(theta) == pytest.approx(none.value(theta), rel=1e-12)


@pytest.mark.parametrize("name", ["flow.flo", "flow.npz", "flow.png", "x_gt_flow_dist.npz"])
def test_a_fifo_given_as_a_flow_file_is_refused(tmp_path, name):
    from cmax_taichi.io._flow import NpzFrames
    from cmax_taichi.io.writers import read_flow

    path = tmp_path / name
    os.mkfifo(path)
    start = time.perf_counter()
    read = (lambda: NpzFrames(path, "x_flow_dist")) if name.startswith("x_gt") else (lambda: read_flow(path))
    with pytest.raises(OSError, match=r"is a FIFO \(named pipe\), not a regular file"):
        read()
    assert time.perf_counter() - start < 10  # refused, not opened
