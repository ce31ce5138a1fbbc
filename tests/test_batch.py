"""Batch estimation over several recordings (cmax_taichi.solve.batch, 'estimate PATH PATH ...'):
window-by-window the same results as separate serial runs on the local engine and on a local Ray
cluster, a worker killed mid-run does not stop the batch, and a re-run after an interruption skips the
written windows and completes the rest (warm-started from the checkpoint, so the results do not
change)."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi import cli
from cmax_taichi.solve import batch, sequence

pytestmark = pytest.mark.usefixtures("f64")

SENSOR = (64, 48)
VELOCITIES = [(150.0, -60.0), (-90.0, 40.0), (60.0, 110.0)]  # px/s, one per recording
OPTIONS = {"warp": "translation2", "n_events": 700, "max_windows": 3}


def write_recording(path: Path, velocity, n: int = 2600, duration: float = 0.1, seed: int = 0) -> Path:
    """A text recording ``t x y p`` (s, px, px, 0/1) of edges translating at ``velocity`` px/s."""
    rng = np.random.default_rng(seed)
    W, H = SENSOR
    centres = rng.uniform([14, 12], [W - 14, H - 12], size=(7, 2))
    angles = rng.uniform(0, np.pi, size=7)
    which = rng.integers(0, 7, n)
    s = rng.uniform(-7, 7, n)
    t = np.sort(rng.uniform(0, duration, n))
    x = centres[which, 0] + s * np.cos(angles[which]) + velocity[0] * (t - duration / 2)
    y = centres[which, 1] + s * np.sin(angles[which]) + velocity[1] * (t - duration / 2)
    keep = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = np.c_[t[keep], np.rint(x[keep]), np.rint(y[keep]), rng.integers(0, 2, n)[keep]]
    rows[-1, 1:3] = [W - 1, H - 1]  # the sensor size is read from the largest coordinates
    np.savetxt(path, rows, fmt=["%.9f", "%d", "%d", "%d"])
    return path


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> list[Path]:
    folder = tmp_path_factory.mktemp("recordings")
    return [write_recording(folder / f"rec{i}.txt", v, seed=i) for i, v in enumerate(VELOCITIES)]


@pytest.fixture(scope="module")
def serial(recordings) -> dict[str, sequence.SequenceResult]:
    """Separate serial runs in this process, the reference of every batch."""
    if cm.backend_info().precision != "f64":
        cm.init(precision="f64")
    return {p.stem: sequence.process(p, progress=False, **OPTIONS) for p in recordings}


def assert_same_windows(result: sequence.SequenceResult, reference: sequence.SequenceResult) -> None:
    """Window by window the same estimates (bit for bit: same code, same warm starts)."""
    assert [w.index for w in result.windows] == [w.index for w in reference.windows]
    for got, want in zip(result.windows, reference.windows, strict=True):
        assert (got.t_start, got.t_end, got.n_events) == (want.t_start, want.t_end, want.n_events)
        np.testing.assert_array_equal(got.theta, want.theta)
        assert got.value == want.value and got.fwl == want.fwl, (got, want)
        assert got.iterations == want.iterations and got.converged == want.converged


def test_cli_local_engine_matches_serial_runs_and_rerun_skips(recordings, serial, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["estimate", *map(str, recordings), "--window", "700", "--max-windows", "3"]
    code = cli.main([*argv, "--workers", "2", "--out", str(out), "--quiet"])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "3 of 3 recording(s) done" in text and "local engine, 2 worker(s)" in text
    for p in recordings:
        folder = out / p.stem
        assert_same_windows(sequence.read_results(folder / "results.json"), serial[p.stem])
        assert (folder / "results.csv").exists() and (folder / "figures" / "window_0000.png").exists()
        assert (folder / "figures" / "parameters.png").exists()
    with (out / "summary.csv").open() as fh:
        summary = list(csv.DictReader(fh))
    assert [r["recording"] for r in summary] == ["rec0", "rec1", "rec2"]
    assert all(r["status"] == "done" and r["windows"] == "3" for r in summary)
    for row in summary:
        median = float(np.median(serial[row["recording"]].theta[:, 0]))
        assert float(row["median v_x [px/s]"]) == median
    with (out / "windows.csv").open() as fh:
        merged = list(csv.reader(fh))
    assert merged[0][:2] == ["recording", "index"] and len(merged) == 1 + 9
    assert float(merged[4][5]) == serial["rec1"].windows[0].theta[0]  # rec1 window 0, v_x

    before = (out / "rec0" / "results.csv").read_text()
    code = cli.main([*argv, "--workers", "2", "--out", str(out), "--quiet"])
    text = capsys.readouterr().out
    assert code == 0 and text.count("0 new (already complete)") == 3, text
    assert (out / "rec0" / "results.csv").read_text() == before


def test_killed_worker_is_replaced_and_its_recording_resumes(recordings, serial, tmp_path, monkeypatch):
    marker = tmp_path / "crashed"
    monkeypatch.setenv(batch.CRASH_HOOK_ENV, f"rec1:1:{marker}")  # rec1's worker dies after window 1
    broken = tmp_path / "broken.txt"
    broken.write_text("0.1 3 4 1\nnot an event\n")  # a bad recording fails alone
    paths = [*recordings, broken]
    result = batch.run(paths, tmp_path / "out", workers=2, progress=False, **OPTIONS)
    assert marker.exists(), "the test hook did not fire"
    assert [r.name for r in result.failed] == ["broken"], result.recordings
    assert "broken.txt" in result.failed[0].error
    by_name = {r.name: r for r in result.recordings}
    assert by_name["rec1"].resumed_from == 2 and by_name["rec1"].new_windows == 1
    for p in recordings:
        assert_same_windows(result.results(p.stem), serial[p.stem])


def test_rerun_after_interruption_skips_written_windows(recordings, serial, tmp_path, monkeypatch):
    out = tmp_path / "out"
    marker = tmp_path / "crashed"
    monkeypatch.setenv(batch.CRASH_HOOK_ENV, f"rec0:0:{marker}")
    # no restart allowed: rec0 fails after its window 0 (like a killed job); its death is charged to rec0
    # alone, and rec1, queued behind it, runs on a fresh worker
    first = batch.run(recordings[:2], out, workers=1, max_restarts=0, progress=False, **OPTIONS)
    assert [r.status for r in first.recordings] == ["failed", "done"], first.recordings
    assert "worker process died 1 time(s) on it" in first.recordings[0].error
    assert not (out / "rec0" / "results.csv").exists()  # an unfinished recording has no results file
    checkpoint = json.loads((out / "rec0" / batch.CHECKPOINT_NAME).read_text())
    assert [w["index"] for w in checkpoint["windows"]] == [0]
    (out / "rec0" / ".checkpoint.json.partial.tmp").write_text('{"windows": [')  # never read
    monkeypatch.delenv(batch.CRASH_HOOK_ENV)

    second = batch.run(recordings[:2], out, workers=1, progress=False, **OPTIONS)
    assert not second.failed, second.recordings
    rec0 = second.recordings[0]
    assert (rec0.resumed_from, rec0.new_windows, rec0.windows) == (1, 2, 3)
    for p in recordings[:2]:
        assert_same_windows(second.results(p.stem), serial[p.stem])


class _StopAfterWindow1:
    """A recording hook that interrupts the run after window 1 (its checkpoint is written)."""

    def window(self, folder, row, prob, result) -> None:
        if row.index == 1:
            raise KeyboardInterrupt("interrupted after window 1")

    def finished(self, folder, result):
        return []


def test_resume_in_process_equals_uninterrupted(recordings, serial, tmp_path):
    """estimate_recording itself (no pool): a run interrupted after window 1 resumes to the same rows
    (its checkpoint carries window 1's warm start: estimate, J, the identity's J, the BFGS curvature)."""
    folder = tmp_path / "rec2"
    with pytest.raises(KeyboardInterrupt):
        batch.estimate_recording(recordings[2], folder, OPTIONS, hooks=_StopAfterWindow1())
    data = json.loads((folder / batch.CHECKPOINT_NAME).read_text())
    assert [w["index"] for w in data["windows"]] == [0, 1] and not data["checkpoint"]["complete"]
    assert data["checkpoint"]["warm_state"]["index"] == 1
    summary = batch.estimate_recording(recordings[2], folder, OPTIONS)
    assert summary.status == "done" and (summary.resumed_from, summary.new_windows) == (2, 1)
    assert_same_windows(sequence.read_results(folder / "results.json"), serial["rec2"])
    other = batch.estimate_recording(recordings[2], folder, {**OPTIONS, "n_events": 600})
    assert other.status == "failed" and "other settings" in other.error


@pytest.mark.slow
def test_ray_engine_matches_serial_runs_with_a_killed_worker(recordings, serial, tmp_path, monkeypatch):
    ray = pytest.importorskip("ray", reason='Ray is an optional extra: pip install -e ".[ray]"')
    assert not ray.is_initialized()
    marker = tmp_path / "crashed"
    monkeypatch.setenv(batch.CRASH_HOOK_ENV, f"rec2:1:{marker}")
    result = batch.run(recordings, tmp_path / "out", workers=2, engine="ray", progress=False, **OPTIONS)
    assert marker.exists(), "the test hook did not fire"
    assert not result.failed, result.recordings
    assert not ray.is_initialized()  # the local Ray instance that run() started is shut down
    assert {r.name: r.resumed_from for r in result.recordings}["rec2"] == 2
    for p in recordings:
        assert_same_windows(result.results(p.stem), serial[p.stem])


def test_recording_names():
    assert batch.recording_names(["a/rec.txt", "b/other"]) == ["rec", "other"]
    assert batch.recording_names(["a/x/events.txt", "b/x/events.txt", "c.txt"]) == [
        "a_x_events",
        "b_x_events",
        "c",
    ]
    with pytest.raises(ValueError, match="given twice"):
        batch.recording_names(["a/rec.txt", "a/../a/rec.txt"])


def test_bad_input(recordings, tmp_path, capsys):
    with pytest.raises(ValueError, match="engine must be one of"):
        batch.run(recordings, tmp_path, engine="dask")
    with pytest.raises(ValueError, match="workers must be"):
        batch.run(recordings, tmp_path, workers=0)
    with pytest.raises(ValueError, match="needs engine='ray'"):
        batch.run(recordings, tmp_path, address="auto")
    with pytest.raises(TypeError, match="unknown option"):
        batch.run(recordings, tmp_path, windows=3)
    with pytest.raises(OSError, match="no such file"):
        batch.run([*recordings, tmp_path / "missing.txt"], tmp_path)
    with pytest.raises(ValueError, match="no recording"):
        batch.run([], tmp_path)
    for extra, fragment in [
        (["--address", "auto"], "needs --engine ray"),
        (["--workers", "0"], "at least 1"),
        ([str(tmp_path / "missing"), "--workers", "2"], "no such file"),
    ]:
        code = cli.main(["estimate", str(recordings[0]), *extra, "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err
        assert code != 0 and len(err.strip().splitlines()) == 1 and fragment in err, err


def test_import_does_not_import_ray():
    code = "import sys, cmax_taichi, cmax_taichi.solve.batch; assert 'ray' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
