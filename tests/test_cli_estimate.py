"""The 'estimate' and 'evaluate' commands: bad input gives one line on stderr and exit code != 0;
a small ECD-layout recording runs end to end (results, figures, metrics against flow.npy)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cmax_taichi import cli
from cmax_taichi.core.windows import describe_events

SENSOR = (64, 48)
V = (150.0, -60.0)  # px/s


def write_ecd_folder(folder: Path, n: int = 2400, duration: float = 0.08, seed: int = 0) -> Path:
    """An ECD-layout folder: events.txt (t x y p, integer px) of translating edges, calib.txt (no
    distortion, sensor size on line 2) and flow.npy (the ground-truth flow over the whole recording)."""
    rng = np.random.default_rng(seed)
    W, H = SENSOR
    k = 7
    centres = rng.uniform([12, 10], [W - 12, H - 10], size=(k, 2))
    angles = rng.uniform(0, np.pi, size=k)
    which = rng.integers(0, k, n)
    s = rng.uniform(-7, 7, n)
    t = np.sort(rng.uniform(0, duration, n))
    x = np.rint(centres[which, 0] + s * np.cos(angles[which]) + V[0] * (t - duration / 2))
    y = np.rint(centres[which, 1] + s * np.sin(angles[which]) + V[1] * (t - duration / 2))
    keep = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    folder.mkdir(parents=True, exist_ok=True)
    rows = np.c_[t[keep], x[keep], y[keep], rng.integers(0, 2, n)[keep]]
    np.savetxt(folder / "events.txt", rows, fmt=["%.9f", "%d", "%d", "%d"])
    (folder / "calib.txt").write_text(f"60 60 {(W - 1) / 2} {(H - 1) / 2} 0 0 0 0 0\n{W} {H}\n")
    span = rows[-1, 0] - rows[0, 0]
    flow = np.empty((1, 2, H, W))
    flow[0, 0], flow[0, 1] = V[0] * span, V[1] * span
    np.save(folder / "flow.npy", flow)
    return folder


def run_main(capsys, *argv: str) -> tuple[int, str, str]:
    code = cli.main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_one_line_error(code: int, err: str, *fragments: str) -> None:
    assert code != 0
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def test_missing_path(capsys, tmp_path):
    code, _, err = run_main(capsys, "estimate", str(tmp_path / "nope"), "--out", str(tmp_path / "o"))
    assert_one_line_error(code, err, "estimate: error:", "no such file")


def test_unknown_format(capsys, tmp_path):
    folder = write_ecd_folder(tmp_path / "rec", n=50)
    code, _, err = run_main(capsys, "estimate", str(folder), "--format", "xyz", "--out", str(tmp_path / "o"))
    assert_one_line_error(code, err, "unknown format 'xyz'")
    odd = tmp_path / "events.bin"
    odd.write_bytes(b"\x00\x01")
    code, _, err = run_main(capsys, "estimate", str(odd), "--out", str(tmp_path / "o"))
    assert_one_line_error(code, err, "unknown file type")


@pytest.mark.parametrize(
    ("reg", "fragment"),
    [
        ("divergence", "NAME=WEIGHT"),
        ("=1", "NAME=WEIGHT"),
        ("divergence=abc", "must be a number"),
        ("divergence=-1", ">= 0"),
        ("sharpness=1", "unknown regularizer 'sharpness'"),
    ],
)
def test_bad_reg_syntax(capsys, tmp_path, reg, fragment):
    code, _, err = run_main(capsys, "estimate", str(tmp_path), "--reg", reg)
    assert_one_line_error(code, err, fragment)


def test_unknown_warp_objective_method(capsys, tmp_path):
    code, _, err = run_main(capsys, "estimate", str(tmp_path), "--warp", "affine9")
    assert_one_line_error(code, err, "unknown warp 'affine9'", "translation2")
    code, _, err = run_main(capsys, "estimate", str(tmp_path), "--objective", "entropy")
    assert_one_line_error(code, err, "unknown objective 'entropy'")
    code, _, err = run_main(capsys, "estimate", str(tmp_path), "--method", "sgd")
    assert_one_line_error(code, err, "unknown method 'sgd'")


def test_corrupt_and_truncated_files(capsys, tmp_path):
    folder = tmp_path / "corrupt"
    folder.mkdir()
    (folder / "events.txt").write_text("0.0 1 2 1\n0.1 3 four 0\n0.2 5 6 1\n")
    code, _, err = run_main(capsys, "estimate", str(folder), "--window", "2", "--out", str(tmp_path / "o"))
    assert_one_line_error(code, err, "estimate: error:")
    truncated = tmp_path / "truncated"
    truncated.mkdir()
    (truncated / "events.txt").write_text("0.0 1 2 1\n0.1 3 4 0\n0.2 5\n")
    code, _, err = run_main(capsys, "estimate", str(truncated), "--window", "2", "--out", str(tmp_path / "o"))
    assert_one_line_error(code, err, "estimate: error:")


def test_hdf5_without_the_needed_keys(capsys, tmp_path):
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "rec_data.hdf5"
    with h5py.File(path, "w") as f:
        f.create_dataset("something/else", data=np.zeros(3))
    code, _, err = run_main(capsys, "estimate", str(path), "--out", str(tmp_path / "o"))
    assert_one_line_error(code, err, "estimate: error:")
    code, _, err = run_main(capsys, "estimate", str(path), "--format", "mvsec", "--out", str(tmp_path / "o"))
    assert_one_line_error(code, err, "estimate: error:")


def test_evaluate_bad_input(capsys, tmp_path):
    code, _, err = run_main(capsys, "evaluate", str(tmp_path / "missing.json"))
    assert_one_line_error(code, err, "evaluate: error:", "no such results file")
    bad = tmp_path / "results.json"
    bad.write_text("[1, 2")
    code, _, err = run_main(capsys, "evaluate", str(bad))
    assert_one_line_error(code, err, "not a results JSON")
    code, _, err = run_main(capsys, "evaluate", str(bad), "--npe", "3,x")
    assert_one_line_error(code, err, "--npe")


def test_help_has_an_example():
    parser = cli.build_parser()
    sub = {a.dest: a for a in parser._actions}["command"].choices
    text = sub["estimate"].format_help()
    assert "example" in text and "--reg divergence=1" in text and "--window" in text
    assert "example" in sub["evaluate"].format_help()


def test_estimate_then_evaluate_end_to_end(tmp_path):
    folder = write_ecd_folder(tmp_path / "rec")
    out = tmp_path / "out"
    env = dict(os.environ, MPLBACKEND="Agg")
    cmd = [sys.executable, "-m", "cmax_taichi.cli"]
    proc = subprocess.run(
        [*cmd, "estimate", str(folder), "--window", "1000", "--out", str(out), "--figures", "1", "--quiet"],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    results = json.loads((out / "results.json").read_text())
    assert [w["status"] for w in results["windows"]] == ["estimated", "estimated", "partial_tail"]
    tail = results["windows"][2]
    assert tail["theta"] == {"v_x": None, "v_y": None}
    assert tail["n_events"] + 2000 == results["events"]["total"]
    # the summary line renders the counts as the end-of-run warning does (one renderer)
    reasons = describe_events(results["events"], 1000)
    assert reasons.startswith(f"{tail['n_events']} in the partial last window")
    assert f"{tail['n_events']} not estimated ({reasons}; " in proc.stdout, proc.stdout
    for w in results["windows"][:2]:
        assert abs(w["theta"]["v_x"] - V[0]) < 10 and abs(w["theta"]["v_y"] - V[1]) < 10, w
    header = (out / "results.csv").read_text().splitlines()[0]
    assert header.startswith("index,t_start [s],t_end [s],n_events,v_x [px/s],v_y [px/s],value,fwl")
    assert (out / "figures" / "window_0000.png").stat().st_size > 10_000
    assert (out / "figures" / "parameters.png").is_file()
    assert "wrote:" in proc.stdout

    proc = subprocess.run([*cmd, "evaluate", str(out)], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["summary"]["mean_AEE"] < 1.0  # px over a ~35 ms window
    assert "mean AEE" in proc.stdout and (out / "metrics.csv").is_file()
