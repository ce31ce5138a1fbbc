"""Sequence processing: windows by count and by duration, warm start, CSV / JSON round trip, the
progress bar, and that consecutive windows reuse one pooled workspace (compile once)."""

from __future__ import annotations

import csv
import io
import json
import math
import warnings

import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi.core import workspace
from cmax_taichi.core.checks import EventsDroppedWarning, IdentityEstimateWarning
from cmax_taichi.solve import sequence

pytestmark = pytest.mark.usefixtures("f64")

SENSOR = (64, 48)
V = (150.0, 60.0)  # px/s
QUICK = {"init": "none", "max_iter": 3}  # the optimizer's least: for tests of the windows, not the estimates


def translating_edges(v=V, n=3300, duration=0.12, seed=4, sensor=SENSOR):
    """Edges translating at ``v`` px/s for ``duration`` s (events leaving the sensor are dropped)."""
    rng = np.random.default_rng(seed)
    W, H = sensor
    k = 8
    centres = rng.uniform([12, 10], [W - 12, H - 10], size=(k, 2))
    angles = rng.uniform(0, np.pi, size=k)
    which = rng.integers(0, k, n)
    s = rng.uniform(-7, 7, n)
    t = np.sort(rng.uniform(0, duration, n))
    x = centres[which, 0] + s * np.cos(angles[which]) + v[0] * (t - duration / 2)
    y = centres[which, 1] + s * np.sin(angles[which]) + v[1] * (t - duration / 2)
    keep = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    return cm.Events(x[keep], y[keep], t[keep], rng.integers(0, 2, n)[keep], sensor)


@pytest.fixture(scope="module")
def events():
    return translating_edges()


def test_windows_by_count_with_warm_start(events, tmp_path):
    seen = []
    stream = io.StringIO()  # not a terminal: one line per 10%
    result = sequence.process(
        events,
        "translation2",
        n_events=1000,
        progress=stream,
        on_window=lambda row, prob, res: seen.append((row.index, res.init, len(workspace._POOL))),
    )
    assert len(result) == 3 and [w.n_events for w in result.windows] == [1000] * 3
    for w in result.windows:
        assert abs(w.theta[0] - V[0]) < 8.0 and abs(w.theta[1] - V[1]) < 8.0, w
        assert w.fwl > 1.0 and w.t_end > w.t_start and w.iterations > 0 and w.seconds > 0
    assert [s[1] for s in seen] == ["pyramid", "warm", "warm"]  # warm start after the first window
    assert [w.search for w in result.windows] == ["global", "warm", "warm"]
    # the warm refinement converges in few evaluations; the first window pays for the global search
    assert all(w.evaluations <= 25 for w in result.windows[1:]), [w.evaluations for w in result.windows]
    assert 40 < result.windows[0].evaluations <= 150  # the coarse-to-fine search and its local run
    assert seen[1][2] == seen[2][2]  # the same pooled fields for every window (no new compile)
    assert stream.getvalue().splitlines()[-1].startswith("windows: 100%")
    assert "3/3" in stream.getvalue().splitlines()[-1] and "\r" not in stream.getvalue()

    csv_path = result.to_csv(tmp_path / "r.csv")
    with csv_path.open() as fh:
        rows = list(csv.reader(fh))
    header = sequence.SequenceResult
    assert rows[0] == [*header.WINDOW_COLUMNS, "v_x [px/s]", "v_y [px/s]", *header.DIAGNOSTIC_COLUMNS]
    assert header.WINDOW_COLUMNS[:2] == ("index", "t_start [s]") and "converged" in header.DIAGNOSTIC_COLUMNS
    # the three windows, then the row of the partial tail (273 events, not estimated, counted)
    assert len(rows) == 5 and float(rows[1][4]) == pytest.approx(result.windows[0].theta[0])
    status = rows[0].index("status")
    assert [r[status] for r in rows[1:]] == ["estimated"] * 3 + ["partial_tail"]
    assert rows[4][:4] == ["3", repr(float(events.t[3000])), repr(float(events.t[-1])), "273"]
    assert result.events["partial_tail"] == 273 and result.events["estimated"] == 3000
    json_path = result.to_json(tmp_path / "r.json")
    data = json.loads(json_path.read_text())
    assert data["params"] == ["v_x", "v_y"] and data["units"] == ["px/s", "px/s"]
    assert data["settings"]["window_events"] == 1000
    back = sequence.read_results(json_path)
    np.testing.assert_allclose(back.theta, result.theta)
    assert [w.evaluations for w in back.windows] == [w.evaluations for w in result.windows]
    assert result.real_time_factor() > 0
    assert [w.t_start for w in back.windows] == [w.t_start for w in result.windows]


def test_windows_by_duration_without_warm_start(events, capsys):
    result = sequence.process(
        events,
        "translation2",
        duration=0.04,
        warm_start=False,
        compute_fwl=False,
        max_windows=2,
        progress=False,
        optimize_options={"n_init": 300},
    )
    assert len(result) == 2
    assert all(np.isnan(w.fwl) for w in result.windows)
    assert all(abs(w.theta[0] - V[0]) < 8.0 for w in result.windows)
    assert result.windows[1].t_start >= 0.04 - 1e-9
    assert "windows" not in capsys.readouterr().err  # progress=False: no progress output at all


class _Terminal(io.StringIO):
    """A text stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True


def test_progress_bar_on_a_terminal_is_redrawn_in_place():
    stream = _Terminal()
    bar = sequence.ProgressBar(20, stream=stream)
    for k in range(20):
        bar.update(f"J={k}")
    bar.close()
    text = stream.getvalue()
    assert text.count("\r") >= 2 and text.endswith("\n")  # tqdm redraws one line, kept at the end
    assert "20/20" in text.split("\r")[-1] and "J=19" in text.split("\r")[-1]


def test_progress_bar_off_a_terminal_writes_one_line_per_tenth():
    stream = io.StringIO()
    bar = sequence.ProgressBar(20, stream=stream)
    for k in range(20):
        bar.update(f"J={k}")
    bar.close()
    lines = stream.getvalue().splitlines()
    assert "\r" not in stream.getvalue()
    assert len(lines) == 11  # the first window, then each 10% (deciles 1..10)
    assert lines[-1].startswith("windows: 100%") and "20/20" in lines[-1] and "J=19" in lines[-1]
    unknown = io.StringIO()
    bar = sequence.ProgressBar(None, stream=unknown)
    for _ in range(3):
        bar.update()
    assert len(unknown.getvalue().splitlines()) == 3  # total unknown: one line per window


def test_bad_inputs(events, tmp_path):
    with pytest.raises(TypeError, match="source must be"):
        sequence.process([1, 2, 3])
    with pytest.raises(ValueError, match="needs a camera"):
        sequence.process(events, "rotation3", progress=False)
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="not a results JSON"):
        sequence.read_results(bad)
    bad.write_text('{"warp": "zoom1"}')
    with pytest.raises(ValueError, match=r"not a cmax-taichi results file \(missing entry 'params'\)"):
        sequence.read_results(bad)
    # a window whose parameters are a string: the window and the entry named, not Python's indexing error
    window = {"index": 0, "t_start": 0.0, "t_end": 1.0, "n_events": 5, "theta": "abc"}
    bad.write_text(json.dumps({"warp": "zoom1", "params": ["h"], "units": ["1/s"], "windows": [window]}))
    message = r"bad entry: window 0: its 'theta' is not an object \(of the parameters h\)"
    with pytest.raises(ValueError, match=message):
        sequence.read_results(bad)


def test_warm_refinement_stops_at_warm_xtol_unless_the_caller_gives_one(events):
    """The warm windows' local run stops at WARM_XTOL px (a step the windows' data do not resolve is not
    chased); an ``xtol`` in ``optimize_options`` replaces it, and the first window's search keeps
    ``maximize``'s own default."""

    def run(**kwargs):
        seen = []
        result = sequence.process(
            events,
            "translation2",
            n_events=1000,
            progress=False,
            on_window=lambda row, prob, res: seen.append(res.message),
            **kwargs,
        )
        return result, seen

    default, messages = run()
    assert "xtol=0.01 px" not in " ".join(messages[1:])
    assert any(f"xtol={sequence.WARM_XTOL:g} px" in m for m in messages[1:]), messages
    tight, tight_messages = run(optimize_options={"xtol": 0.01})
    assert not any(f"xtol={sequence.WARM_XTOL:g} px" in m for m in tight_messages), tight_messages
    # the same first window (its search takes maximize's defaults either way); the warm windows of the
    # tighter rule take at least as many evaluations in all, and each ends within about two of the
    # looser rule's steps of it (2 px/s: 0.07 px over these 36 ms windows)
    assert len(default) == len(tight) == 3
    assert default.windows[0].evaluations == tight.windows[0].evaluations
    assert np.array_equal(default.windows[0].theta, tight.windows[0].theta)
    assert sum(w.evaluations for w in default.windows[1:]) <= sum(w.evaluations for w in tight.windows[1:])
    for loose, fine in zip(default.windows[1:], tight.windows[1:], strict=True):
        assert np.allclose(loose.theta, fine.theta, atol=2.0), (loose.theta, fine.theta)


def test_lost_track_runs_the_global_search_again(events, monkeypatch):
    """When the tracking test says the track is lost, the global search runs after the refinement and
    the better of both is kept ("warm+global"). The warm refinement itself is robust to a reversal of
    the motion (the identity is one of its starts), so the test forces the loss with a ratio no window
    can meet."""
    from cmax_taichi.solve import warm

    monkeypatch.setattr(warm, "TRACKING_LOSS_RATIO", 10.0)  # where the tracking test reads it
    result = sequence.process(events, "translation2", n_events=1000, max_windows=2, progress=False)
    assert [w.search for w in result.windows] == ["global", "warm+global"]
    assert result.windows[1].evaluations > 40  # the refinement's plus the global search's
    assert abs(result.windows[1].theta[0] - V[0]) < 8.0 and abs(result.windows[1].theta[1] - V[1]) < 8.0


def test_tracking_test_allows_for_shorter_windows():
    """Windows of varying sizes: a shorter window of the same motion gains less over the identity (the
    identity's motion blur is shorter); that is not a loss of track. A gain near 0 is."""
    state = sequence.WarmState(theta=np.array(V), value=1.40, value_identity=1.0, duration=0.044)
    assert not state.lost_track(1.075, 1.0, duration=0.016)  # the same motion, a window of 16 ms
    assert state.lost_track(1.01, 1.0, duration=0.016)  # J and the gain both fell: lost
    assert state.lost_track(1.1, 1.0, duration=0.044)  # same duration, a quarter of the gain
    assert not state.lost_track(1.35, 1.0, duration=0.060)
    weak = sequence.WarmState(theta=np.array(V), value=1.06, value_identity=1.0, duration=0.017)
    assert not weak.lost_track(1.03, 1.0, duration=0.017)  # half the gain of a weak contrast, J 97%
    legacy = sequence.WarmState(theta=np.array(V), value=2.0)  # identity unknown: J alone
    assert legacy.lost_track(1.5, math.nan, 0.01) and not legacy.lost_track(1.7, math.nan, 0.01)
    back = sequence.WarmState.from_dict(json.loads(json.dumps(state.as_dict())))
    assert back.value == state.value and back.duration == state.duration and back.hess_inv is None
    with pytest.raises(TypeError, match="warm_state must be a sequence.WarmState"):
        sequence.process(translating_edges(), "translation2", n_events=1000, warm_state=[1.0, 2.0])


def test_fwl_of_a_regularized_sequence_is_the_fwl(events):
    """With regularizers, the FWL comes from a problem with the same regularizers at weight 0 (it runs
    on the estimate's compiled kernel): the same value as metrics.fwl on the window."""
    from cmax_taichi.metrics import fwl

    regs = {"divergence": 1.0, "deformation": 1.0}
    result = sequence.process(
        events, "mitrokhin4", regularizers=regs, n_events=1000, max_windows=2, progress=False
    )
    for w, window in zip(result.windows, events.windows_by_count(1000), strict=False):
        assert w.fwl == pytest.approx(fwl(window, "mitrokhin4", w.theta), rel=1e-9)


def test_windows_not_estimated_have_rows_and_every_event_is_counted(tmp_path):
    """A window of one event and one of zero duration get rows (status, NaN parameters); the
    totals sum to the events in, match count_events (the same pass without estimating), and survive the
    JSON and HDF5 round trips; one warning gives them."""
    rng = np.random.default_rng(1)
    t = np.sort(np.r_[rng.uniform(0, 0.02, 600), np.full(40, 0.05), [0.07], rng.uniform(0.1, 0.12, 600)])
    n = len(t)
    events = cm.Events(rng.uniform(5, 58, n), rng.uniform(5, 42, n), t, np.ones(n), SENSOR)
    options = dict(duration=0.02, progress=False, compute_fwl=False, optimize_options=QUICK)
    counted = r"41 of 1241 event\(s\) not estimated: 1 in 1 window\(s\) of fewer than 2 events, 40 in 1"
    with pytest.warns(EventsDroppedWarning, match=counted):
        result = sequence.process(events, "translation2", **options)
    assert [w.status for w in result.rows()] == ["estimated", "zero_duration", "too_few_events", "estimated"]
    assert len(result) == 2 and [w.index for w in result.skipped] == [1, 2]
    assert np.isnan(result.skipped[0].theta).all() and result.skipped[0].n_events == 40
    counts = result.events
    assert counts["estimated"] == 1200 and counts["zero_duration"] == 40 and counts["too_few_events"] == 1
    assert sum(v for k, v in counts.items() if k not in ("total", "windows")) == counts["total"] == n
    assert counts == sequence.count_events(events, duration=0.02)
    for path in (result.to_json(tmp_path / "r.json"), result.to_hdf5(tmp_path / "r.h5")):
        back = sequence.read_results(path)
        assert [w.status for w in back.rows()] == [w.status for w in result.rows()]
        assert back.events == counts and len(back) == 2
        np.testing.assert_array_equal(back.theta, result.theta)


def test_keep_tail_estimates_the_partial_last_window(events):
    options = dict(n_events=500, progress=False, compute_fwl=False, optimize_options=QUICK)
    kept = sequence.process(events, "translation2", keep_tail=True, **options)  # a tail of 273 >= 250
    assert [w.status for w in kept.rows()] == ["estimated"] * 6 + ["short_tail"]
    assert kept.windows[-1].n_events == len(events) - 3000
    assert kept.events["estimated"] == len(events)
    short = sequence.process(events, "translation2", max_windows=1, keep_tail=True, **options)
    assert short.events["after_max_windows"] == len(events) - 500  # counted, not dropped silently


def _on_pixels(ev: cm.Events) -> cm.Events:
    """``ev`` with its coordinates rounded to whole pixels, as a camera records them."""
    return cm.Events(np.round(ev.x), np.round(ev.y), ev.t, ev.p, SENSOR)


def test_windows_at_the_identity_are_counted_in_one_warning(events):
    """A still scene recorded on whole pixels is sharpest unwarped: every window comes out at the
    identity exactly, counted (``identity_windows``) and named in one IdentityEstimateWarning that says
    what to change; a moving one raises none."""
    still = _on_pixels(translating_edges(v=(0.0, 0.0)))
    with pytest.warns(IdentityEstimateWarning) as caught:
        result = sequence.process(still, "translation2", n_events=1000)
    identity = [w for w in caught if issubclass(w.category, IdentityEstimateWarning)]
    assert len(identity) == 1
    message = str(identity[0].message)
    assert "3 of 3 estimated window(s) came out at the identity warp exactly" in message
    assert "Use windows of more events" in message
    assert result.identity_windows() == 3 and not np.any(result.theta)
    with warnings.catch_warnings():
        warnings.simplefilter("error", IdentityEstimateWarning)
        moving = sequence.process(_on_pixels(events), "translation2", n_events=1000)
    assert moving.identity_windows() == 0
