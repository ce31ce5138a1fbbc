"""Property-based tests (hypothesis): generated bad and edge inputs of the input layer raise only the
documented exception types, within a deadline, and whatever is accepted keeps the containers'
invariants.

Documented types: ``Events`` and ``Camera`` raise TypeError or ValueError; ``Recording.read``,
``read_time`` and ``windows`` raise TypeError or ValueError; the readers (``open_recording`` and
reading) raise ValueError, OSError or KeyError (TypeError only for arguments). Anything else (an
OverflowError, an IndexError, a UnicodeDecodeError that names no file, a hang) fails these tests.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import tempfile
import warnings
from datetime import timedelta
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import cmax_taichi as cm
from cmax_taichi import io

DOCUMENTED = (ValueError, TypeError, OSError, KeyError)
# small example counts: the file runs in well under a minute on a loaded 2-core machine. CI (CI=true)
# draws the same examples every run, so that a red CI means a change, not a new draw; local runs explore
# new examples each time (a failure prints the case to add as a regression test).
DERANDOMIZE = bool(os.environ.get("CI"))
FAST = settings(max_examples=100, deadline=timedelta(seconds=2), database=None, derandomize=DERANDOMIZE)
FILES = settings(
    max_examples=40,
    deadline=timedelta(seconds=5),
    database=None,
    derandomize=DERANDOMIZE,
    suppress_health_check=[HealthCheck.too_slow],
)

numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(10**20), 10**20),
    st.sampled_from([0, 1, -1, 0.5, 240.0, 240.5, 1e308, -0.0]),
)
anything = st.one_of(
    numbers,
    st.none(),
    st.booleans(),
    st.text(max_size=4),
    st.complex_numbers(max_magnitude=1e3),
    st.lists(st.integers(0, 5), max_size=3),
)


def _array(n):
    dtypes = st.sampled_from(["f8", "f4", "i8", "u1", "c16", "bool", "U3", "O", "m8[us]"])
    return dtypes.flatmap(
        lambda dt: hnp.arrays(np.dtype(dt), n) if dt != "O" else st.just(np.array([None] * n))
    )


@FAST
@given(
    n=st.integers(0, 20),
    extra=st.integers(-1, 1),
    data=st.data(),
    size=st.one_of(st.tuples(numbers, numbers), anything),
)
def test_events_raise_only_documented_errors(n, extra, data, size):
    """``Events``: TypeError or ValueError, or a valid container (sorted, on the sensor, p = -1/+1)."""
    arrays = [data.draw(_array(n)) for _ in range(3)] + [data.draw(_array(max(0, n + extra)))]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            events = cm.Events(*arrays, size)
    except (TypeError, ValueError):
        return
    W, H = events.sensor_size
    assert isinstance(W, int) and isinstance(H, int) and W > 0 and H > 0
    assert len(events) + events.n_dropped == n
    assert np.all(np.diff(events.t) >= 0) and np.all(np.isfinite(events.t))
    assert np.all((events.x >= 0) & (events.x <= W - 1) & (events.y >= 0) & (events.y <= H - 1))
    assert set(np.unique(events.p).tolist()) <= {-1, 1}


@FAST
@given(
    params=st.lists(st.one_of(anything, st.floats(1e-3, 1e3)), min_size=4, max_size=4),
    dist=st.one_of(anything, st.lists(st.one_of(numbers, anything), max_size=7)),
)
def test_camera_raises_only_documented_errors(params, dist):
    """``Camera``: TypeError or ValueError, or finite float intrinsics with positive focal lengths."""
    try:
        camera = cm.Camera(*params, dist=dist)
    except (TypeError, ValueError):
        return
    values = [camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist]
    assert all(type(v) is float and math.isfinite(v) for v in values)
    assert camera.fx > 0 and camera.fy > 0 and len(camera.dist) == 5


@FAST
@given(n_events=anything, duration=anything, stride=st.one_of(st.none(), anything))
def test_events_windows_raise_only_documented_errors(n_events, duration, stride):
    """``Events.windows_by_count`` / ``windows_by_duration``: TypeError or ValueError when called, or
    non-empty windows in time order."""
    rng = np.random.default_rng(1)
    t = np.sort(np.concatenate([rng.uniform(0, 0.01, 200), rng.uniform(2.0, 2.01, 200)]))
    events = cm.Events(np.zeros(400), np.zeros(400), t, np.ones(400), (4, 4))
    for make in (
        lambda: events.windows_by_count(n_events, stride),
        lambda: events.windows_by_duration(duration, stride),
    ):
        try:
            windows = list(itertools.islice(make(), 50))
        except (TypeError, ValueError):
            continue
        assert all(len(w) > 0 for w in windows)
        assert all(a.t[0] <= b.t[0] for a, b in itertools.pairwise(windows))


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    folder = tmp_path_factory.mktemp("seq")
    rng = np.random.default_rng(0)
    t = np.sort(np.concatenate([rng.uniform(0, 0.01, 300), rng.uniform(0.5, 0.51, 300)]))
    lines = [f"{tk:.9f} {k % 60} {k % 40} {k % 2}\n" for k, tk in enumerate(t)]
    (folder / "events.txt").write_text("".join(lines))
    rec = io.open_recording(folder, cache_dir=tmp_path_factory.mktemp("cache"))
    yield rec
    rec.close()


@settings(FAST, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n_events=anything, duration=st.one_of(st.none(), anything), stride=st.one_of(st.none(), anything))
def test_recording_windows_raise_only_documented_errors(recording, n_events, duration, stride):
    """``Recording.windows``: TypeError or ValueError when called, or windows that hold events."""
    try:
        windows = recording.windows(n_events=n_events, duration=duration, stride=stride)
        for window in itertools.islice(windows, 50):
            assert len(window) > 0
    except (TypeError, ValueError):
        pass
    assert len(recording.read(0, 10)) == 10  # still usable


@settings(FAST, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(a=anything, b=anything)
def test_recording_reads_raise_only_documented_errors(recording, a, b):
    """``read_time`` and ``read``: TypeError or ValueError, or the events asked for."""
    try:
        events = recording.read_time(a, b)
        assert np.all((events.t >= a) & (events.t < b))
    except (TypeError, ValueError):
        pass
    with contextlib.suppress(TypeError, ValueError):
        recording.read(a, b)
    assert len(recording.read(0, 10)) == 10


text_line = st.one_of(
    st.tuples(
        st.one_of(st.floats(-1, 10), st.sampled_from([math.nan, math.inf])),
        st.integers(-5, 300),
        st.integers(-5, 300),
        st.sampled_from([-1, 0, 1, 2]),
    ).map(lambda r: " ".join(str(v) for v in r)),
    st.binary(max_size=12).map(lambda b: b.decode("latin-1")),
    st.sampled_from(["", "# comment", "0.1 2 3", "0.1 2 3 1 5", "nan nan nan nan", "1e400 1 1 1"]),
)


@FILES
@given(
    lines=st.lists(text_line, max_size=12),
    calib=st.one_of(st.none(), st.binary(max_size=40), st.lists(text_line, max_size=3).map("\n".join)),
)
def test_text_reader_raises_only_documented_errors(lines, calib):
    """A generated ``events.txt`` (and ``calib.txt``): ValueError / OSError / KeyError, or events."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "seq"
        folder.mkdir()
        (folder / "events.txt").write_text("\n".join(lines) + "\n", encoding="latin-1")
        if isinstance(calib, bytes):
            (folder / "calib.txt").write_bytes(calib)
        elif calib is not None:
            (folder / "calib.txt").write_text(calib, encoding="latin-1")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                with io.open_recording(folder, cache_dir=Path(tmp) / "cache") as rec:
                    events = rec.read()
                    assert len(events) == rec.n_events
                    list(itertools.islice(rec.windows(2), 5))
        except DOCUMENTED:
            pass


@FILES
@given(
    rows=st.one_of(
        hnp.arrays(np.float64, st.tuples(st.integers(0, 6), st.just(4))),
        hnp.arrays(np.int32, st.tuples(st.integers(0, 6), st.sampled_from([3, 4]))),
        hnp.arrays(np.dtype("S2"), st.tuples(st.integers(1, 4), st.just(4))),
        hnp.arrays(np.complex64, st.tuples(st.integers(1, 4), st.just(4))),
    ),
    calibration=st.one_of(st.none(), hnp.arrays(np.float64, st.integers(0, 10))),
)
def test_mvsec_reader_raises_only_documented_errors(rows, calibration):
    """A generated MVSEC file (any dtype, NaN anywhere): ValueError / OSError / KeyError, or events."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "gen_data.hdf5"
        with h5py.File(path, "w") as f:
            f["davis/left/events"] = rows
            if calibration is not None:
                f["davis/left/calibration"] = calibration
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                with io.open_recording(path) as rec:
                    events = rec.read()
                    assert len(events) <= rec.n_events
                    list(itertools.islice(rec.windows(duration=0.5), 5))
        except DOCUMENTED:
            pass


@FILES
@given(
    t=st.one_of(
        hnp.arrays(np.int64, 3, elements=st.integers(-(10**12), 10**12)),
        hnp.arrays(np.float64, 3),
        hnp.arrays(np.dtype("S3"), 3),
    ),
    xy=hnp.arrays(np.int64, 3, elements=st.integers(-5, 700)),
    p=hnp.arrays(np.int8, 3, elements=st.integers(-2, 2)),
    offset=st.one_of(st.integers(-(10**9), 10**9), st.floats(allow_nan=True, allow_infinity=True)),
)
def test_dsec_reader_raises_only_documented_errors(t, xy, p, offset):
    """A generated DSEC ``events.h5``: ValueError / OSError / KeyError, or events."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "events.h5"
        with h5py.File(path, "w") as f:
            f["events/x"] = xy
            f["events/y"] = xy[::-1]
            f["events/t"] = t
            f["events/p"] = p
            f["ms_to_idx"] = np.array([0], dtype=np.uint64)
            f["t_offset"] = offset
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                with io.open_recording(path) as rec:
                    rec.read()
                    rec.read_time(rec.t_start, rec.t_end)
        except DOCUMENTED:
            pass


# --- window accounting: events in = events estimated + events counted as not estimated -------------
def _oracle_counts(t, inside, n_events, duration, stride, keep_tail, max_windows):
    """Where every event goes, by brute force: every window listed (time windows stepped one by one),
    then each event given its best fate over the windows that hold it (see cmax_taichi.core.windows)."""
    n = len(t)
    windows = []  # (start, stop, tail, keep)
    if duration is None:
        step = stride or n_events
        starts = list(range(0, n - n_events + 1, step))
        windows = [(s, s + n_events, False, True) for s in starts]
        following = starts[-1] + step if starts else 0
        if following < n:
            least = max(2, math.ceil(0.5 * n_events))
            windows.append((following, n, True, keep_tail and n - following >= least))
    elif n:
        step = stride or duration
        k = 0
        while t[0] + k * step <= t[-1]:
            a = t[0] + k * step
            i0, i1 = (int(i) for i in np.searchsorted(t, [a, a + duration], side="left"))
            if i1 > i0:
                windows.append((i0, i1, False, True))
            k += 1
    stopped = max_windows is not None and len(windows) > max_windows
    if max_windows is not None:
        windows = windows[:max_windows]
    rank = ["between_windows", "partial_tail", "too_few_events", "zero_duration", "outside_sensor"]
    rank.append("estimated")
    fate = np.zeros(n, dtype=int)
    for i0, i1, _tail, keep in windows:
        ok = inside[i0:i1]
        used = t[i0:i1][ok]
        if not keep:
            code = 1
        elif len(used) < 2:
            code = 2
        elif not used[-1] - used[0] > 0:
            code = 3
        else:
            code = 5
        window = np.full(i1 - i0, code)
        window[~ok] = 4
        fate[i0:i1] = np.maximum(fate[i0:i1], window)
    counts = {name: int(np.sum(fate == k)) for k, name in enumerate(rank)}
    counts["after_max_windows"] = 0
    last = max((i1 for _, i1, _, _ in windows), default=0)
    if stopped:
        counts["after_max_windows"] = int(np.sum(fate[last:] == 0))
        counts["between_windows"] -= counts["after_max_windows"]
    return counts


@st.composite
def _bursts(draw):
    """Event times in bursts separated by gaps (some bursts on a coarse grid: repeated timestamps)."""
    times = []
    t = 0.0
    for _ in range(draw(st.integers(0, 5))):
        t += draw(st.sampled_from([0.0, 0.001, 0.05, 0.5, 3.0]))
        count = draw(st.integers(0, 120))
        spread = draw(st.sampled_from([0.0, 1e-4, 0.01, 0.1]))
        burst = t + np.random.default_rng(draw(st.integers(0, 99))).uniform(0, spread, count)
        if draw(st.booleans()):
            burst = np.round(burst, 3)
        times.append(burst)
        t += spread
    return np.sort(np.concatenate(times)) if times else np.zeros(0)


_WINDOW_ARGS = {
    "n_events": st.integers(2, 70),
    "stride": st.one_of(st.none(), st.integers(1, 90)),
    "duration_share": st.one_of(st.none(), st.floats(0.005, 1.5)),
    "time_stride_share": st.one_of(st.none(), st.floats(0.005, 2.0)),
    "keep_tail": st.booleans(),
    "max_windows": st.one_of(st.none(), st.integers(1, 12)),
}


def _time_args(t, duration_share, time_stride_share):
    span = float(t[-1] - t[0]) if len(t) > 1 else 1.0
    span = span if span > 0 else 1.0
    if duration_share is None:
        return None, None
    return duration_share * span, None if time_stride_share is None else time_stride_share * span


@FAST
@given(t=_bursts(), **_WINDOW_ARGS)
def test_every_event_is_accounted_for(
    t, n_events, stride, duration_share, time_stride_share, keep_tail, max_windows
):
    """Any window size, stride, duration, gaps and repeated times: the events estimated plus those counted
    under each reason are the events in, and each count is the brute-force one (count_events runs the
    windows, statuses and ledger of sequence.process, without estimating)."""
    from cmax_taichi.solve.sequence import count_events

    events = cm.Events(np.zeros(len(t)), np.zeros(len(t)), t, np.ones(len(t)), (4, 4))
    duration, time_stride = _time_args(t, duration_share, time_stride_share)
    kwargs = dict(n_events=n_events, duration=duration, stride=time_stride if duration else stride)
    if len(t) > 1 and t[0] == t[-1]:
        with pytest.raises(ValueError, match="have the same time"):
            count_events(events, **kwargs, keep_tail=keep_tail, max_windows=max_windows)
        return
    got = count_events(events, **kwargs, keep_tail=keep_tail, max_windows=max_windows)
    want = _oracle_counts(
        t, np.ones(len(t), dtype=bool), n_events, duration, kwargs["stride"], keep_tail, max_windows
    )
    assert sum(v for k, v in got.items() if k not in ("total", "windows")) == got["total"] == len(t)
    assert {k: v for k, v in got.items() if k not in ("total", "windows", "undistortion")} == want


@pytest.fixture(scope="module")
def recording_with_outside_events(tmp_path_factory):
    """A text recording of undistorted (float) coordinates, 5% of them a little off the 40x30 sensor,
    in three bursts with gaps."""
    folder = tmp_path_factory.mktemp("outside")
    rng = np.random.default_rng(7)
    t = np.sort(np.concatenate([rng.uniform(a, a + 0.02, 150) for a in (0.0, 0.021, 0.5)]))
    x, y = rng.uniform(0, 39, len(t)), rng.uniform(0, 29, len(t))
    off = rng.random(len(t)) < 0.05
    x[off] = rng.choice([-0.4, 39.4], int(off.sum()))
    np.savetxt(folder / "events.txt", np.c_[t, x, y, np.ones(len(t))], fmt="%.9f")
    (folder / "calib.txt").write_text("30 30 19.5 14.5\n40 30\n")
    rec = io.open_recording(folder, cache_dir=tmp_path_factory.mktemp("cache"))
    yield rec, np.loadtxt(folder / "events.txt")[:, 0], ~off  # the times as the file holds them
    rec.close()


@settings(FAST, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(**_WINDOW_ARGS)
def test_every_event_of_a_recording_is_accounted_for(
    recording_with_outside_events, n_events, stride, duration_share, time_stride_share, keep_tail, max_windows
):
    """The same through a Recording whose reader drops events outside the sensor (counted once each,
    however many windows hold them)."""
    from cmax_taichi.solve.sequence import count_events

    rec, t, inside = recording_with_outside_events
    duration, time_stride = _time_args(t, duration_share, time_stride_share)
    kwargs = dict(n_events=n_events, duration=duration, stride=time_stride if duration else stride)
    got = count_events(rec, **kwargs, keep_tail=keep_tail, max_windows=max_windows)
    want = _oracle_counts(t, inside, n_events, duration, kwargs["stride"], keep_tail, max_windows)
    assert sum(v for k, v in got.items() if k not in ("total", "windows")) == got["total"] == len(t)
    assert {k: v for k, v in got.items() if k not in ("total", "windows", "undistortion")} == want


def test_the_last_time_window_is_not_lost_to_rounding():
    """[3.0, 3.001] in windows of 5 us: the span over the step rounds below 200, and the window that
    starts at the last event was left out (its event counted between windows)."""
    from cmax_taichi.solve.sequence import count_events

    t = np.array([3.0, 3.001])
    events = cm.Events(np.zeros(2), np.zeros(2), t, np.ones(2), (4, 4))
    got = count_events(events, n_events=2, duration=0.005 * 0.001)
    assert got["between_windows"] == 0 and got["too_few_events"] == 2
