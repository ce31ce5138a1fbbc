"""Prophesee RAW / DAT and Event Stream readers (optional package ``faery``): files written by faery
itself (EVT 3.0, EVT 2.0, DAT, ES) and EVT 2.1 files built word by word from Prophesee's
specification are read back through ``open_recording``; damaged files and a missing package give one
clear error each."""

from __future__ import annotations

import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from cmax_taichi.io import detect_format, open_recording
from cmax_taichi.io.faery_formats import read_header

SENSOR = (346, 260)  # (W, H) px, a DAVIS346-sized sensor: not a faery default


pytestmark = pytest.mark.usefixtures("cache_in_tmp")


def _faery():
    return pytest.importorskip(
        "faery", reason="the Prophesee / ES readers need 'faery': pip install faery (or cmax-taichi[formats])"
    )


def known_events(n: int = 3000, seed: int = 0) -> np.ndarray:
    """Events with strictly increasing integer-microsecond times (from 1.5 s, with a 3 s gap in the
    middle: several EVT time-high words and a jump), random pixels and polarities, as a structured
    array with faery's field names."""
    rng = np.random.default_rng(seed)
    dt = rng.integers(1, 200, n)
    dt[n // 2] = 3_000_000
    events = np.zeros(n, dtype=[("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("on", "?")])
    events["t"] = 1_500_000 + np.cumsum(dt)
    events["x"] = rng.integers(0, SENSOR[0], n)
    events["y"] = rng.integers(0, SENSOR[1], n)
    events["on"] = rng.integers(0, 2, n).astype(bool)
    return events


def write_with_faery(path: Path, events: np.ndarray, version: str | None = None) -> Path:
    faery = _faery()
    packet = np.zeros(len(events), dtype=faery.EVENTS_DTYPE)
    for name in ("t", "x", "y", "on"):
        packet[name] = events[name]
    # zero_t0=False: an .es file would otherwise drop the first time stamp (RAW and DAT keep it in the header)
    faery.events_stream_from_array(packet, dimensions=SENSOR).to_file(path, version=version, zero_t0=False)
    return path


def evt21_words(events: np.ndarray, legacy: bool) -> bytes:
    """EVT 2.1 payload per Prophesee's specification: a TIME_HIGH word (type 8, ts[33:6]) whenever the
    high time changes, then one CD word (type 1 ON / 0 OFF, ts[5:0], x, y, a one-bit validity mask) per
    event. ``legacy``: the IMX636 order (the type half is the lower 32 bits of the 64-bit word)."""
    out = []
    high = None
    for t, x, y, on in zip(events["t"], events["x"], events["y"], events["on"], strict=True):
        t = int(t)
        if t >> 6 != high:
            high = t >> 6
            out.append(((8 << 28) | (high & 0x0FFFFFFF), 0))
        out.append(((int(on) << 28) | ((t & 0x3F) << 22) | (int(x) << 11) | int(y), 1))
    words = [(mask << 32) | head if legacy else (head << 32) | mask for head, mask in out]
    return b"".join(struct.pack("<Q", w) for w in words)


def write_evt21(path: Path, events: np.ndarray, legacy: bool = False) -> Path:
    W, H = SENSOR
    header = f"% evt 2.1\n% format EVT21;height={H};width={W}" + (";endianness=legacy" if legacy else "")
    path.write_bytes(header.encode() + b"\n% end\n" + evt21_words(events, legacy))
    return path


CASES = {
    "evt3": lambda d, ev: write_with_faery(d / "rec_evt3.raw", ev, "evt3"),
    "evt2": lambda d, ev: write_with_faery(d / "rec_evt2.raw", ev, "evt2"),
    "evt2.1": lambda d, ev: write_evt21(d / "rec_evt21.raw", ev),
    "evt2.1 legacy": lambda d, ev: write_evt21(d / "rec_evt21_legacy.raw", ev, legacy=True),
    "dat2": lambda d, ev: write_with_faery(d / "rec.dat", ev),
    "es": lambda d, ev: write_with_faery(d / "rec.es", ev),
}
FORMAT_OF = {"evt3": "raw", "evt2": "raw", "evt2.1": "raw", "evt2.1 legacy": "raw", "dat2": "dat", "es": "es"}
ENCODING_OF = {"evt2.1 legacy": "evt2.1", "es": "es dvs"}


@pytest.mark.parametrize("case", list(CASES))
def test_round_trip(tmp_path, case):
    if case != "evt2.1" and case != "evt2.1 legacy":
        _faery()
    events = known_events()
    path = CASES[case](tmp_path, events)
    assert detect_format(path) == FORMAT_OF[case]
    with open_recording(path) as rec:
        assert rec.format == FORMAT_OF[case]
        assert rec.encoding == ENCODING_OF.get(case, case)
        assert rec.sensor_size == SENSOR, "the sensor size comes from the header"
        assert rec.n_events == len(events) and rec.camera is None and not rec.undistorted
        ev = rec.read()
        np.testing.assert_array_equal(ev.x, events["x"])
        np.testing.assert_array_equal(ev.y, events["y"])
        np.testing.assert_array_equal(ev.p, np.where(events["on"], 1, -1))
        # microseconds, the formats' resolution: exact after rounding
        np.testing.assert_array_equal(np.rint(ev.t * 1e6).astype(np.int64), events["t"].astype(np.int64))
        assert rec.t_start == pytest.approx(events["t"][0] / 1e6, abs=1e-9)
        assert rec.t_end == pytest.approx(events["t"][-1] / 1e6, abs=1e-9)

        by_count = list(rec.windows(n_events=700))
        assert [len(w) for w in by_count] == [700] * (len(events) // 700)
        for k, w in enumerate(by_count):
            np.testing.assert_array_equal(w.x, ev.x[700 * k : 700 * (k + 1)])
            np.testing.assert_array_equal(w.t, ev.t[700 * k : 700 * (k + 1)])

        duration = 0.05
        by_time = list(rec.windows(duration=duration))
        assert sum(len(w) for w in by_time) == len(events)  # non-overlapping windows cover every event
        np.testing.assert_array_equal(np.concatenate([w.t for w in by_time]), ev.t)
        for w in by_time:
            k = np.floor((w.t[0] - rec.t_start) / duration)
            assert rec.t_start + k * duration <= w.t[0] and w.t[-1] < rec.t_start + (k + 1) * duration
        assert len(by_time) < len(events) / 100  # the 3 s gap has no (empty) windows
    # the second open maps the cache and gives the same events
    with open_recording(path) as again:
        np.testing.assert_array_equal(again.read(100, 200).t, ev.t[100:200])


def test_evt21_vector_word(tmp_path):
    """One EVT 2.1 CD word with several validity bits is several events at x_base + bit."""
    W, H = SENSOR
    head = (1 << 28) | (5 << 22) | (40 << 11) | 17  # ON, ts[5:0] = 5, x_base = 40, y = 17
    words = [((8 << 28) | 1000) << 32, (head << 32) | 0b1001_0000_0000_0000_0000_0000_0000_0101]
    path = tmp_path / "vector.raw"
    path.write_bytes(
        f"% evt 2.1\n% format EVT21;height={H};width={W}\n% end\n".encode()
        + b"".join(struct.pack("<Q", w) for w in words)
    )
    ev = open_recording(path).read()
    np.testing.assert_array_equal(ev.x, [40, 42, 68, 71])
    np.testing.assert_array_equal(ev.y, [17] * 4)
    np.testing.assert_array_equal(np.rint(ev.t * 1e6), [1000 * 64 + 5] * 4)
    np.testing.assert_array_equal(ev.p, [1] * 4)


def test_text_dat_files_stay_text(tmp_path):
    """A ``.dat`` file of ``t x y p`` lines is still the text format; a ``%`` header makes it DAT."""
    path = tmp_path / "events.dat"
    path.write_text("0.0 1 2 1\n0.1 3 4 0\n")
    assert detect_format(path) == "ecd"
    assert detect_format(write_with_faery(tmp_path / "cd.dat", known_events(50))) == "dat"


def test_truncated_files(tmp_path):
    events = known_events()
    raw = write_with_faery(tmp_path / "full.raw", events, "evt3").read_bytes()
    cut = tmp_path / "cut.raw"
    cut.write_bytes(raw[: len(raw) // 2] + raw[len(raw) // 2 : len(raw) // 2 + 1] * (len(raw) % 2 == 0))
    assert (len(cut.read_bytes()) - len(raw)) % 2 == 1  # half a 16-bit word at the end
    with pytest.raises(ValueError, match=r"cut.raw: truncated or damaged file: .* EVT3 words"):
        open_recording(cut)
    dat = write_with_faery(tmp_path / "full.dat", events).read_bytes()
    (tmp_path / "cut.dat").write_bytes(dat[: len(dat) - 3])
    with pytest.raises(ValueError, match=r"cut.dat: truncated or damaged file: .* 8-byte events"):
        open_recording(tmp_path / "cut.dat")
    evt21 = write_evt21(tmp_path / "full21.raw", events).read_bytes()
    (tmp_path / "cut21.raw").write_bytes(evt21[:-5])
    with pytest.raises(ValueError, match=r"cut21.raw: truncated or damaged file: .* EVT2.1 words"):
        open_recording(tmp_path / "cut21.raw")
    (tmp_path / "empty.raw").write_bytes(b"")
    with pytest.raises(ValueError, match="empty.raw: empty file"):
        open_recording(tmp_path / "empty.raw")


def test_corrupt_files(tmp_path):
    _faery()
    W, H = SENSOR
    garbage = np.random.default_rng(3).bytes(4000)  # whole EVT 3.0 words, but coordinates out of range
    (tmp_path / "bad.raw").write_bytes(f"% evt 3.0\n% format EVT3;width={W};height={H}\n".encode() + garbage)
    with pytest.raises(ValueError, match=r"bad.raw: cannot decode the Prophesee RAW \(EVT\) file after"):
        open_recording(tmp_path / "bad.raw")
    (tmp_path / "bad.es").write_bytes(b"Event Stream\x09\x00")
    with pytest.raises(ValueError, match="bad.es: not a readable Event Stream file"):
        open_recording(tmp_path / "bad.es")
    (tmp_path / "bad21.raw").write_bytes(f"% evt 2.1\n% geometry {W}x{H}\n".encode() + garbage)
    with pytest.raises(ValueError, match=r"bad21.raw: cannot decode .* outside the 346x260 sensor"):
        open_recording(tmp_path / "bad21.raw")


def test_evt21_word_order_from_the_data(tmp_path):
    """An IMX636 EVT 2.1 file whose header does not say endianness=legacy is still read right (the
    word order is judged from the data), and so is a specification-order file marked legacy."""
    events = known_events(400)
    data = write_evt21(tmp_path / "legacy.raw", events, legacy=True).read_bytes()
    (tmp_path / "unmarked.raw").write_bytes(data.replace(b";endianness=legacy", b""))
    data = write_evt21(tmp_path / "spec.raw", events).read_bytes()
    (tmp_path / "mismarked.raw").write_bytes(data.replace(b"width=346", b"width=346;endianness=legacy"))
    for name in ("unmarked.raw", "mismarked.raw"):
        ev = open_recording(tmp_path / name).read()
        np.testing.assert_array_equal(ev.x, events["x"])
        np.testing.assert_array_equal(np.rint(ev.t * 1e6), events["t"].astype(float))


def test_header_without_size_or_version(tmp_path):
    _faery()
    events = known_events(500)
    path = write_with_faery(tmp_path / "full.raw", events, "evt3")
    (tmp_path / "bare.raw").write_bytes(
        path.read_bytes()[read_header(path)[1] :]
    )  # no header at all: EVT 3.0 is faery's default
    with pytest.raises(ValueError, match=r"bare.raw: .* needs sensor_size=\(W, H\)"):
        open_recording(tmp_path / "bare.raw")
    with open_recording(tmp_path / "bare.raw", sensor_size=SENSOR) as rec:
        assert rec.sensor_size == SENSOR and rec.encoding == "evt3"
        np.testing.assert_array_equal(rec.read().x, events["x"])
        # without the header's t0 the times are relative to it
        np.testing.assert_array_equal(
            np.diff(np.rint(rec.read().t * 1e6)), np.diff(events["t"].astype(float))
        )
    with pytest.raises(ValueError, match=r"version='evt4' is not a Prophesee RAW \(EVT\) encoding"):
        open_recording(tmp_path / "bare.raw", sensor_size=SENSOR, version="evt4")


def test_missing_package_is_named(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "faery", None)  # behaves as "not installed"
    (tmp_path / "x.raw").write_bytes(b"% evt 3.0\n% format EVT3;width=64;height=48\n\x00\x80")
    with pytest.raises(
        ImportError, match=r"x.raw: reading Prophesee RAW \(EVT\) files needs .*cmax-taichi\[formats\]"
    ):
        open_recording(tmp_path / "x.raw")
    (tmp_path / "x.es").write_bytes(b"Event Stream\x02\x00\x01")
    with pytest.raises(ImportError, match=r"pip install faery"):
        open_recording(tmp_path / "x.es")
