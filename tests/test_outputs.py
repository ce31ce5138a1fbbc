"""Outputs never touch inputs: estimate / segment / reproduce / batch refuse an output folder
that is or holds a recording, never replace a file that no cmax-taichi run wrote (the manifest), stage
what they write and move it into place when the run completes, refuse a second run on the same folder
(the lock), and leave the folder as it was on Ctrl-C or SIGTERM. One regression test per case."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cmax_taichi import cli
from cmax_taichi.io import outputs
from cmax_taichi.solve import batch

pytestmark = pytest.mark.usefixtures("cache_in_tmp", "f64")

SENSOR = (64, 48)
FAST = ["--window", "1000", "--quiet", "--figures", "0", "--n-init", "20"]


def write_recording(folder: Path, n: int = 2500, duration: float = 0.1, seed: int = 0) -> Path:
    """An ECD-layout folder of edges translating at (100, -50) px/s, with calib.txt (sensor on line 2)."""
    rng = np.random.default_rng(seed)
    W, H = SENSOR
    t = np.sort(rng.uniform(0, duration, n))
    k = rng.integers(0, 6, n)
    cx, cy = rng.uniform(10, W - 10, 6), rng.uniform(8, H - 8, 6)
    x = np.clip(np.rint(cx[k] + rng.uniform(-6, 6, n) + 100 * (t - duration / 2)), 0, W - 1)
    y = np.clip(np.rint(cy[k] + rng.uniform(-6, 6, n) - 50 * (t - duration / 2)), 0, H - 1)
    folder.mkdir(parents=True, exist_ok=True)
    np.savetxt(folder / "events.txt", np.c_[t, x, y, rng.integers(0, 2, n)], fmt=["%.9f", "%d", "%d", "%d"])
    (folder / "calib.txt").write_text(f"60 60 {(W - 1) / 2} {(H - 1) / 2} 0 0 0 0 0\n{W} {H}\n")
    return folder


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return write_recording(tmp_path_factory.mktemp("rec") / "rec")


def run(capsys, *argv) -> tuple[int, str, str]:
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip() and ": warning: " not in line]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in sorted(folder.rglob("*"))}


# --- the output folder itself ---------------------------------------------------------------------
def test_output_folder_stages_commits_and_recognises_its_own_files(tmp_path):
    out = tmp_path / "out"
    with outputs.OutputFolder(out, patterns=["a.txt", "figures/*.png"]) as folder:
        folder.path("a.txt").write_text("one")
        folder.path("figures/w_0.png").write_bytes(b"png")
        folder.path("figures/w_1.png").write_bytes(b"png")
        assert not (out / "a.txt").exists()  # nothing in place before the commit
        written = folder.commit()
    assert sorted(p.name for p in written) == ["a.txt", "w_0.png", "w_1.png"]
    manifest = json.loads((out / outputs.MANIFEST_NAME).read_text())
    assert sorted(manifest["files"]) == ["a.txt", "figures/w_0.png", "figures/w_1.png"]
    assert not list(out.glob(outputs.STAGING_PREFIX + "*"))
    # a second run replaces its own files and removes those it did not write again
    with outputs.OutputFolder(out, patterns=["a.txt", "figures/*.png"]) as folder:
        folder.path("a.txt").write_text("two")
        folder.path("figures/w_0.png").write_bytes(b"png2")
        folder.commit()
    assert (out / "a.txt").read_text() == "two" and not (out / "figures" / "w_1.png").exists()
    # a file changed by the user since is not replaced; nor is one no run wrote
    (out / "a.txt").write_text("edited by hand")
    with pytest.raises(outputs.OutputConflictError, match="changed since a cmax-taichi run wrote it"):
        outputs.OutputFolder(out, patterns=["a.txt"]).__enter__()
    (out / "notes.png").write_text("mine")
    with pytest.raises(outputs.OutputConflictError, match=r"notes.png exists and was not written by a"):
        outputs.OutputFolder(out, patterns=["*.png"]).__enter__()
    assert (out / "notes.png").read_text() == "mine" and (out / "a.txt").read_text() == "edited by hand"


def test_output_folder_leaves_nothing_when_the_run_fails(tmp_path):
    out = tmp_path / "fresh"
    with pytest.raises(KeyboardInterrupt), outputs.OutputFolder(out, patterns=["a.txt"]) as folder:
        folder.path("a.txt").write_text("half")
        raise KeyboardInterrupt
    assert not out.exists()  # a folder this run created is removed again
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(RuntimeError), outputs.OutputFolder(out, patterns=["a.txt"]) as folder:
        folder.path("a.txt").write_text("half")
        raise RuntimeError("the run failed")
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]  # no lock file left behind


def test_output_folder_refuses_inputs_and_a_second_run(tmp_path):
    data = tmp_path / "data"
    (data / "rec").mkdir(parents=True)
    for out, message in [
        (data / "rec", "is the input"),
        (data, "holds the input"),
        (tmp_path, "holds the input"),
        (data / "rec" / "out", "is inside the input folder"),  # nothing is written into a recording
    ]:
        with pytest.raises(outputs.OutputConflictError, match=message):
            outputs.OutputFolder(out, inputs=[data / "rec"]).__enter__()
    (tmp_path / "file").write_text("x")
    with pytest.raises(outputs.OutputConflictError, match="is an existing file, not a folder"):
        outputs.OutputFolder(tmp_path / "file").__enter__()
    with outputs.OutputFolder(tmp_path / "out", command="first run"):
        busy = r"in use by another cmax-taichi run \(pid \d+, first run"
        with pytest.raises(outputs.OutputBusyError, match=busy):
            outputs.OutputFolder(tmp_path / "out").__enter__()
    with outputs.OutputFolder(tmp_path / "out"):  # released: the next run goes on
        pass


def test_atomic_path_never_leaves_half_a_file(tmp_path):
    target = tmp_path / "results.csv"
    target.write_text("old")
    with pytest.raises(ValueError), outputs.atomic_path(target) as tmp:
        tmp.write_text("half of the new")
        raise ValueError("interrupted")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["results.csv"]
    outputs.atomic_write_text(target, "new")
    umask = os.umask(0)
    os.umask(umask)
    assert target.read_text() == "new" and target.stat().st_mode & 0o777 == 0o666 & ~umask  # not 0600


# --- the commands ----------------------------------------------------------------------------------
def test_estimate_refuses_an_out_that_is_or_holds_the_recording(recording, tmp_path, capsys):
    before = snapshot(recording)
    code, _, err = run(capsys, "estimate", recording, "--out", recording, *FAST)
    assert code == 2 and "--out" in error_line(err) and "is the input" in err
    code, _, err = run(capsys, "estimate", recording / "events.txt", "--out", recording, *FAST)
    assert code == 2 and "holds the input" in error_line(err)
    code, _, err = run(capsys, "estimate", recording, "--out", tmp_path, "--flow-out", recording, *FAST)
    assert code == 2 and "--flow-out" in error_line(err)
    assert snapshot(recording) == before  # not a byte written beside the data


def test_every_command_refuses_an_out_that_holds_any_recording(recording, tmp_path, capsys):
    """bench has no input to protect, so `bench --out` wrote its tables beside a recording's events;
    a folder holding a recording (any, not only the run's input) is refused by every command."""
    other = write_recording(tmp_path / "other")
    before = snapshot(other)
    commands = [
        ("bench", "--quick", "--no-solve"),
        ("estimate", recording, *FAST),
        ("segment", recording, "-k", "2", "--max-iterations", "1", "--no-figures"),
        ("flow", recording, "--grid", "2", "2", "--levels", "1", "--quiet"),
    ]
    for argv in commands:
        code, _, err = run(capsys, *argv, "--out", other)
        assert code == 2 and f"--out {other} holds a recording (ecd)" in error_line(err), argv
    assert snapshot(other) == before


def test_a_symbolic_link_where_a_run_writes_a_folder_is_not_followed(recording, tmp_path, capsys):
    """OUT/flow linked to another folder (a user's, a recording's): flow wrote its files there, outside
    OUT, where the input checks never looked."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "keep").write_text("x")
    out = tmp_path / "F"
    out.mkdir()
    (out / "flow").symlink_to(mine)
    argv = ["flow", recording, "--grid", "2", "2", "--levels", "1", "--quiet", "--out", out]
    code, _, err = run(capsys, *argv)
    assert code == 2 and "is a symbolic link where this run writes a folder" in error_line(err)
    assert sorted(p.name for p in mine.iterdir()) == ["keep"]


def test_an_out_that_cannot_be_written_is_refused_before_the_work(recording, tmp_path, capsys, monkeypatch):
    """segment and bench did their work (minutes for bench) and only then found that --out could not
    be created (a read-only file system): now refused before anything runs."""
    locked = tmp_path / "ro"
    locked.mkdir()
    real_access = os.access
    monkeypatch.setattr(outputs.os, "access", lambda p, mode: Path(p) != locked and real_access(p, mode))
    commands = [
        ("segment", recording, "-k", "2", "--max-iterations", "1", "--no-figures"),
        ("bench", "--quick", "--no-solve"),
    ]
    for argv in commands:
        code, out, err = run(capsys, *argv, "--out", locked / "new")
        assert code == 2 and f"--out: cannot create {locked / 'new'}" in error_line(err), argv
        assert not out and "step" not in err  # no work began
    code, _, err = run(capsys, "segment", recording, "-k", "2", "--out", locked)
    assert code == 2 and f"--out: cannot write in {locked}" in error_line(err)


@pytest.mark.parametrize("name", ["results.h5", "results.csv"])
def test_a_recording_named_like_an_output_is_never_overwritten(tmp_path, capsys, name):
    folder = write_recording(tmp_path / "x")
    source = tmp_path / "d" / name
    source.parent.mkdir()
    if name == "results.h5":
        import h5py

        rows = np.loadtxt(folder / "events.txt")
        with h5py.File(source, "w") as f:
            f["davis/left/events"] = rows[:, [1, 2, 0, 3]]
        argv = [source, "--format", "mvsec"]
    else:
        (folder / "events.txt").rename(source)
        argv = [source, "--format", "ecd"]
    size = source.stat().st_size
    code, _, err = run(capsys, "estimate", *argv, "--out", source.parent, *FAST)
    assert code == 2 and "holds the input" in error_line(err) and source.stat().st_size == size


def test_estimate_never_replaces_a_file_it_did_not_write(recording, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "results.csv").write_text("the user's own table\n")
    code, _, err = run(capsys, "estimate", recording, "--out", out, *FAST)
    assert code == 2 and "not written by a cmax-taichi run" in error_line(err)
    assert (out / "results.csv").read_text() == "the user's own table\n"
    assert sorted(p.name for p in out.iterdir()) == ["results.csv"]


def test_estimate_reruns_on_its_own_outputs_and_keeps_one_run(recording, tmp_path, capsys):
    out = tmp_path / "out"
    code, stdout, err = run(capsys, "estimate", recording, "--out", out, *FAST, "--figures", "2")
    assert code == 0, err
    assert (out / "figures" / "window_0001.png").exists() and (out / "results.h5").exists()
    code, _, err = run(capsys, "estimate", recording, "--out", out, *FAST, "--max-windows", "1")
    assert code == 0, err
    rows = json.loads((out / "results.json").read_text())["windows"]
    assert [w["index"] for w in rows] == [0]
    # the second run's outputs only: no figure of the first run is left beside them
    assert not (out / "figures").exists() or not list((out / "figures").glob("window_*.png"))
    manifest = json.loads((out / outputs.MANIFEST_NAME).read_text())
    assert sorted(manifest["files"]) == ["results.csv", "results.h5", "results.json"]


def test_segment_and_reproduce_refuse_their_inputs(recording, tmp_path, capsys):
    before = snapshot(recording)
    argv = ["segment", recording, "-k", "2", "--warp", "translation2", "--events", "1000", "--no-figures"]
    code, _, err = run(capsys, *argv, "--out", recording)
    assert code == 2 and "is the input" in error_line(err)
    argv = ["reproduce", "table3", "--quick", "--data", recording, "--out", recording.parent]
    code, _, err = run(capsys, *argv)
    assert code == 2 and "holds the input" in error_line(err)
    assert snapshot(recording) == before


def test_segment_writes_only_when_complete(recording, tmp_path, capsys):
    out = tmp_path / "seg"
    argv = ["segment", recording, "-k", "2", "--warp", "translation2", "--events", "1000", "--no-figures"]
    code, stdout, err = run(capsys, *argv, "--max-iterations", "1", "--out", out)
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == [
        ".cmax-taichi-manifest.json",
        "labels.csv",
        "labels.npy",
        "segmentation.json",
    ]
    (out / "labels.csv").write_text("edited")
    code, _, err = run(capsys, *argv, "--max-iterations", "1", "--out", out)
    assert code == 2 and "labels.csv exists and was changed since" in error_line(err)


def test_batch_refuses_an_out_holding_recordings_and_clashing_names(recording, tmp_path):
    other = write_recording(tmp_path / "data" / "other", seed=1)
    with pytest.raises(outputs.OutputConflictError, match="holds the input"):
        batch.run([recording, other], tmp_path, warp="translation2", n_events=1000, progress=False)
    clash = write_recording(tmp_path / "data" / "summary.csv", seed=2)
    clash_message = r"summary.csv, a name the batch uses for its own table"
    with pytest.raises(outputs.OutputConflictError, match=clash_message):
        batch.run([clash, other], tmp_path / "out", warp="translation2", n_events=1000, progress=False)
    assert not (tmp_path / "out" / "summary.csv").exists()
    foreign = tmp_path / "out2"
    (foreign / "other").mkdir(parents=True)
    (foreign / "other" / "results.csv").write_text("mine")
    with pytest.raises(outputs.OutputConflictError, match="that no batch run wrote"):
        batch.run([other], foreign, warp="translation2", n_events=1000, progress=False)
    (foreign / "summary.csv").write_text("mine too")
    with pytest.raises(outputs.OutputConflictError, match="summary.csv exists and was not written"):
        batch.run([recording], foreign, warp="translation2", n_events=1000, progress=False)


# --- interrupted runs (a subprocess each: signals) -------------------------------------------------
def _start_estimate(recording: Path, out: Path) -> subprocess.Popen:
    env = dict(os.environ, MPLBACKEND="Agg")
    argv = [sys.executable, "-m", "cmax_taichi.cli", "estimate", str(recording), "--out", str(out)]
    argv += ["--window", "2000", "--quiet", "--figures", "3"]
    # SIGINT as a terminal delivers it: a suite started in the background (``cmd &``) passes SIGINT on
    # ignored, and Python then installs no KeyboardInterrupt handler
    return subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip


def _wait_for_staging(out: Path, proc: subprocess.Popen, seconds: float = 300) -> None:
    """Until the run has made its staging folder and holds OUT's lock (it is mid-run: the figures, drawn
    by a child process, may come only when a short run is nearly done)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if list(out.glob(outputs.STAGING_PREFIX + "*")) and (out / ".cmax-taichi.lock").exists():
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.1)
    raise AssertionError("the run did not reach its first window")


@pytest.mark.slow
@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_interrupted_estimate_leaves_out_as_it_was(tmp_path, sig, code, capsys):
    # long enough (240 windows) that the run is still estimating when the signal comes
    long = write_recording(tmp_path / "long", n=480000, duration=12.0)
    out = tmp_path / "out"
    # the command's modules imported here first, so that the refusal below takes a moment, not the run
    assert run(capsys, "estimate", long, "--out", long, *FAST)[0] == 2
    proc = _start_estimate(long, out)
    _wait_for_staging(out, proc)
    # meanwhile a second run on the same folder is refused at once, naming the first
    second, _, err = run(capsys, "estimate", long, "--out", out, *FAST)
    assert second == 2 and f"pid {proc.pid}" in error_line(err) and "in use" in err
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=300)
    assert proc.returncode == code, stderr
    assert "Traceback" not in stderr, stderr  # the figure process included
    assert not out.exists()  # the folder this run created, its staging and its lock: all gone


def test_flow_out_may_be_out_itself(recording, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["estimate", recording, "--out", out, "--flow-out", out, *FAST, "--max-windows", "1"]
    code, stdout, err = run(capsys, *argv)
    assert code == 0, err
    assert (out / "flow_0000.flo").exists() and (out / "results.csv").exists()
    assert "flow_0000.flo" in json.loads((out / outputs.MANIFEST_NAME).read_text())["files"]


def test_a_copied_output_folder_is_recognised_by_its_content(recording, tmp_path, capsys):
    """``cp -r`` keeps the files and changes their times: a rerun into the copy replaces the outputs it
    recognises by their content, and still refuses one whose content changed."""
    import shutil

    out = tmp_path / "out"
    argv = ["estimate", recording, *FAST, "--max-windows", "1"]
    assert run(capsys, *argv, "--out", out)[0] == 0
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)  # new modification times (copy2 keeps them: touch them to be sure)
    for path in copy.rglob("*"):
        if path.is_file():
            os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 10**9))
    code, _, err = run(capsys, *argv, "--out", copy)
    assert code == 0, err
    (copy / "results.csv").write_text((copy / "results.csv").read_text().replace("0", "1", 1))
    os.utime(copy / "results.csv", ns=(0, 10**9))
    code, _, err = run(capsys, *argv, "--out", copy)
    assert code == 2 and "results.csv exists and was changed since" in error_line(err)
