"""Batch estimation over several recordings (cmax_taichi.solve.batch, 'estimate PATH PATH ...'):
window-by-window the same results as separate serial runs on the local engine and on a local Ray
cluster, a worker killed mid-run does not stop the batch, and a re-run after an interruption skips the
written windows and completes the rest (warm-started from the checkpoint, so the results do not
change)."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
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


# --- batches that keep their word --------------------------------------------------------
def test_resume_refuses_a_recording_replaced_at_the_same_path(tmp_path):
    """A checkpoint is continued only on the recording that wrote it (size, mtime, content, camera)."""
    path = write_recording(tmp_path / "rec.txt", VELOCITIES[0], seed=0)
    folder = tmp_path / "out" / "rec"
    with pytest.raises(KeyboardInterrupt):
        batch.estimate_recording(path, folder, OPTIONS, hooks=_StopAfterWindow1())
    write_recording(path, VELOCITIES[1], seed=5)  # another recording at the same path
    summary = batch.estimate_recording(path, folder, OPTIONS)
    assert summary.status == "failed" and "changed since" in summary.error and "content" in summary.error
    checkpoint = json.loads((folder / batch.CHECKPOINT_NAME).read_text())
    assert [w["index"] for w in checkpoint["windows"]] == [0, 1]  # the old windows, not mixed with new ones


def test_a_dying_worker_fails_only_its_recording(recordings, serial, tmp_path, monkeypatch):
    """rec1 kills its worker in every attempt: after max_restarts it alone fails; the others are re-queued
    on fresh workers and give the serial results."""
    monkeypatch.setenv(batch.CRASH_HOOK_ENV, "rec1:0:")
    result = batch.run(recordings, tmp_path / "out", workers=2, max_restarts=1, progress=False, **OPTIONS)
    by_name = {r.name: r for r in result.recordings}
    assert by_name["rec1"].status == "failed" and "died 2 time(s) on it" in by_name["rec1"].error
    for name in ("rec0", "rec2"):
        assert by_name[name].status == "done", by_name[name]
        assert_same_windows(result.results(name), serial[name])


def test_a_second_batch_on_the_same_out_and_special_files_are_refused(recordings, tmp_path):
    from cmax_taichi.io import outputs

    out = tmp_path / "out"
    with (
        outputs.hold_lock(out, "a batch"),
        pytest.raises(outputs.OutputBusyError, match="in use by another cmax-taichi run"),
    ):
        batch.run(recordings, out, progress=False, **OPTIONS)
    fifo = tmp_path / "live.txt"
    os.mkfifo(fifo)
    with pytest.raises(OSError, match=r"live.txt: is a FIFO \(named pipe\), not a regular file"):
        batch.run([recordings[0], fifo], tmp_path / "out2", progress=False, **OPTIONS)


def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` and that are not zombies (Linux /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                state, ppid = (entry / "stat").read_text().rsplit(") ", 1)[1].split()[:2]
            except (OSError, IndexError, ValueError):
                continue
            if int(ppid) == pid and state != "Z":
                found.append(int(entry.name))
    return found


def _alive(pids: list[int]) -> list[int]:
    alive = []
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(") ", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if state != "Z":
            alive.append(pid)
    return alive


def _wait(condition, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture(scope="module")
def long_recordings(tmp_path_factory) -> list[Path]:
    folder = tmp_path_factory.mktemp("long")
    return [
        write_recording(folder / f"long{i}.txt", v, n=150_000, duration=3.0, seed=i)
        for i, v in enumerate([(5.0, -2.0), (-4.0, 3.0)])  # px/s: slow enough to stay on the sensor
    ]


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc")
def test_workers_die_with_their_driver(long_recordings, tmp_path):
    """kill -9 of the driver: its workers end too (PR_SET_PDEATHSIG / the watchdog) and stop writing."""
    out = tmp_path / "out"
    code = (
        "import sys\nfrom cmax_taichi.solve import batch\n"
        f"batch.run({[str(p) for p in long_recordings]!r}, {str(out)!r}, workers=2, progress=False, "
        "warp='translation2', n_events=2000)\n"
    )
    driver = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        _wait(lambda: len(list(out.glob("*/" + batch.CHECKPOINT_NAME))) == 2, 600, "both workers to write")
        workers = _children(driver.pid)
        assert len(workers) >= 2, workers
    finally:
        driver.kill()
        driver.wait()
    _wait(lambda: not _alive(workers), 15, f"the workers {workers} to end")
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    time.sleep(2)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before  # nobody writes into OUT any more


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc")
def test_sigterm_of_a_batch_is_handled_as_ctrl_c(long_recordings, tmp_path):
    out = tmp_path / "out"
    argv = [sys.executable, "-m", "cmax_taichi.cli", "estimate", *map(str, long_recordings), "--workers", "2"]
    argv += ["--window", "2000", "--out", str(out), "--quiet", "--figures", "0"]
    driver = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait(lambda: len(list(out.glob("*/" + batch.CHECKPOINT_NAME))) == 2, 600, "both workers to write")
    workers = _children(driver.pid)
    driver.send_signal(signal.SIGTERM)
    _, err = driver.communicate(timeout=120)
    assert driver.returncode == 143, err
    assert "terminated (SIGTERM)" in err and "Traceback" not in err
    _wait(lambda: not _alive(workers), 15, f"the workers {workers} to end")
    assert not list(out.rglob("*.tmp"))  # nothing partial
    unfinished = 0
    for path in out.glob("*/" + batch.CHECKPOINT_NAME):
        complete = json.loads(path.read_text())["checkpoint"]["complete"]  # whole, and resumable
        # results.csv only beside a complete checkpoint (a recording may have finished before the signal)
        assert (path.parent / "results.csv").exists() == complete
        unfinished += not complete
    assert unfinished >= 1, "both recordings finished before SIGTERM: nothing was interrupted"
