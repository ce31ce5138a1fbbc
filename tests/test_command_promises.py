"""Every command keeps the README's "Bad input" promises, not only estimate: flow, evaluate and bench
lose nothing, overwrite nothing, and say what went wrong. One regression test per class of failure:
user files overwritten, another command's outputs replaced, work without bound, events not accounted
for, ground truth and results trusted blindly, tracebacks and misleading messages, first-day defects.
The tests that need no kernel run the commands' refusals, which all come before any work."""

from __future__ import annotations

import errno
import json
import subprocess
import sys
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
from test_outputs import error_line, run, write_recording

from cmax_taichi.io import outputs
from cmax_taichi.io.writers import read_flow_npz, write_flo, write_flow_npz

pytestmark = pytest.mark.usefixtures("cache_in_tmp")

SIZE = (16, 12)
SIZE_ARGS = ["--sensor-size", "16", "12"]


def write_mvsec(
    folder: Path, t0: float = 1500000000.0, flow=(0.3, 0.2), n_gt: int = 40, seed: int = 0
) -> Path:
    """``indoor_flying1_data.hdf5`` and its ``_gt_flow_dist.npz`` (a constant flow per 20 Hz frame)."""
    rng = np.random.default_rng(seed)
    W, H = SIZE
    gt_ts = t0 + np.arange(n_gt) / 20.0
    n = 40 * n_gt
    t = np.sort(rng.uniform(gt_ts[0], gt_ts[-1], n))
    rows = np.column_stack([rng.integers(0, W, n), rng.integers(0, H, n), t, rng.choice([-1.0, 1.0], n)])
    folder.mkdir(parents=True, exist_ok=True)
    with h5py.File(folder / "indoor_flying1_data.hdf5", "w") as f:
        f.create_dataset("davis/left/events", data=rows)
    fx, fy = np.full((n_gt, H, W), flow[0]), np.full((n_gt, H, W), flow[1])
    np.savez(folder / "indoor_flying1_gt_flow_dist.npz", timestamps=gt_ts, x_flow_dist=fx, y_flow_dist=fy)
    return folder / "indoor_flying1_data.hdf5"


def write_flows(folder: Path, t0: float, fingerprint: str | None = None, n: int = 2) -> Path:
    """``n`` flow files of 50 ms each from ``t0`` + 0.1 s (what 'cmax-taichi flow' writes)."""
    folder.mkdir(parents=True, exist_ok=True)
    W, H = SIZE
    meta = {} if fingerprint is None else {"fingerprint": fingerprint}
    for k in range(n):
        a = t0 + 0.1 + 0.05 * k
        write_flow_npz(
            folder / f"flow_{k:04d}.npz", np.full((2, H, W), 0.3), t_start=a, t_end=a + 0.05, **meta
        )
    return folder


@pytest.fixture
def mvsec(tmp_path) -> Path:
    return write_mvsec(tmp_path / "rec")


def fingerprint_of(path: Path) -> str:
    from cmax_taichi import io

    with io.open_recording(path, sensor_size=SIZE) as rec:
        return rec.fingerprint()


# --- user files overwritten, another command's outputs replaced ---------------------------------------
def test_evaluate_never_replaces_a_users_file_nor_writes_into_the_recording(mvsec, tmp_path, capsys):
    flows = write_flows(tmp_path / "flows", 1500000000.0)
    (flows / "metrics.csv").write_text("mine\n")
    code, _, err = run(capsys, "evaluate", flows, "--data", mvsec, *SIZE_ARGS)
    assert code == 2 and "metrics.csv exists and was not written by a cmax-taichi run" in error_line(err)
    assert (flows / "metrics.csv").read_text() == "mine\n"
    code, _, err = run(capsys, "evaluate", flows, "--data", mvsec, *SIZE_ARGS, "--out", mvsec.parent)
    assert code == 2 and "holds the input" in error_line(err)
    assert not list(mvsec.parent.glob("metrics*"))
    # its own earlier outputs are replaced, whole, with the manifest
    out = tmp_path / "ev"
    assert run(capsys, "evaluate", flows, "--data", mvsec, *SIZE_ARGS, "--out", out)[0] == 0
    assert run(capsys, "evaluate", flows, "--data", mvsec, *SIZE_ARGS, "--out", out, "--npe", "1")[0] == 0
    manifest = json.loads((out / outputs.MANIFEST_NAME).read_text())["files"]
    assert {k: v["command"] for k, v in manifest.items()} == {
        "metrics.csv": "evaluate",
        "metrics.json": "evaluate",
    }
    assert not (out / outputs.LOCK_NAME).exists()  # no lock file left behind


def test_another_commands_outputs_are_refused_before_any_work(mvsec, tmp_path, capsys):
    """flow --out on an estimate's folder replaced results.csv and removed results.json / results.h5."""
    out = tmp_path / "est"
    with outputs.OutputFolder(out, patterns=["results.*"], command="estimate") as folder:
        for name in ("results.csv", "results.json", "results.h5"):
            folder.path(name).write_text(name)
        folder.commit()
    before = {p.name: p.read_text() for p in out.iterdir()}
    code, _, err = run(capsys, "flow", mvsec, *SIZE_ARGS, "--out", out)
    line = error_line(err)
    assert code == 2 and "is an output of 'cmax-taichi estimate'" in line and "results.csv" in line
    assert {p.name: p.read_text() for p in out.iterdir()} == before
    # the commands share a folder where their files do not collide: evaluate beside estimate's results
    with outputs.OutputFolder(out, patterns=["metrics.*"], command="evaluate") as folder:
        folder.path("metrics.json").write_text("{}")
        folder.commit()
    assert {p.name for p in out.iterdir()} >= {"results.csv", "results.json", "results.h5", "metrics.json"}
    # and a rerun of estimate keeps evaluate's file
    with outputs.OutputFolder(out, patterns=["results.*"], command="estimate") as folder:
        folder.path("results.csv").write_text("new")
        folder.commit()
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "metrics.json",
        "results.csv",
    ]


def test_bench_refuses_a_users_results_before_its_minutes_of_work(tmp_path, capsys):
    out = tmp_path / "bench"
    out.mkdir()
    (out / "results.md").write_text("my notes\n")
    code, _, err = run(capsys, "bench", "--quick", "--no-solve", "--out", out)
    assert code == 2 and "results.md exists and was not written by a cmax-taichi run" in error_line(err)
    assert (out / "results.md").read_text() == "my notes\n"


def _state(out: Path) -> dict:
    """The files of ``out`` and what its manifest lists (its text may be written again, the same)."""
    files = {p.name: p.read_bytes() for p in out.iterdir() if p.name != outputs.MANIFEST_NAME}
    return {**files, "manifest": outputs.read_manifest(out)}


def test_a_full_disk_at_the_commit_leaves_out_as_it_was(tmp_path, monkeypatch):
    """Outputs either all in place with their manifest, or not there: a full disk at the manifest (it
    is written first) or at a move (the moved files go back, the replaced ones are restored)."""
    out = tmp_path / "out"
    with outputs.OutputFolder(out, patterns=["*.txt"], command="estimate") as folder:
        folder.path("a.txt").write_text("old a")
        folder.path("b.txt").write_text("old b")
        folder.commit()
    before = _state(out)

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(outputs, "_write_manifest_file", full)
        with (
            pytest.raises(outputs.OutputSpaceError, match="nothing of the run was committed"),
            outputs.OutputFolder(out, patterns=["*.txt"], command="estimate") as folder,
        ):
            folder.path("a.txt").write_text("new a")
            folder.commit()
    assert _state(out) == before
    real_replace, calls = outputs.os.replace, []

    def replace_then_fail(src, dst):
        calls.append(dst)
        if len(calls) == 3:  # the second file's move, after the first is in place
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_replace(src, dst)

    with monkeypatch.context() as m:
        m.setattr(outputs.os, "replace", replace_then_fail)
        with (
            pytest.raises(outputs.OutputSpaceError),
            outputs.OutputFolder(out, patterns=["*.txt"], command="estimate") as folder,
        ):
            folder.path("a.txt").write_text("new a")
            folder.path("b.txt").write_text("new b")
            folder.commit()
    assert _state(out) == before
    # a full disk while the run writes: one error naming the folder, nothing changed
    with (
        pytest.raises(outputs.OutputSpaceError, match=str(out)),
        outputs.OutputFolder(out, patterns=["*.txt"], command="estimate"),
    ):
        raise OSError(errno.ENOSPC, "No space left on device")
    assert _state(out) == before


def test_an_out_removed_during_the_run_is_an_error_not_a_wrote(tmp_path):
    import shutil

    out = tmp_path / "out"
    with (
        pytest.raises(OSError, match="removed or replaced while the run wrote into it"),
        outputs.OutputFolder(out, patterns=["*.txt"]) as folder,
    ):
        folder.path("a.txt").write_text("a")
        shutil.rmtree(out)
        folder.path("b.txt").write_text("b")
        folder.commit()
    assert not out.exists()


# --- ground truth and results checked, not trusted -----------------------------------------------------
def test_a_ground_truth_that_cannot_be_read_is_named(mvsec, tmp_path, capsys):
    flows = write_flows(tmp_path / "flows", 1500000000.0)
    gt = mvsec.with_name("indoor_flying1_gt_flow_dist.npz")
    data = gt.read_bytes()
    gt.write_bytes(data[: len(data) // 2])  # truncated
    code, out, err = run(capsys, "evaluate", flows, "--data", mvsec, *SIZE_ARGS, "--out", tmp_path / "ev")
    assert code == 2 and "indoor_flying1_gt_flow_dist.npz: not a readable .npz file" in error_line(err)
    flipped = bytearray(data)
    flipped[len(flipped) // 2] ^= 0xFF  # a bad CRC in the memory-mapped frames
    gt.write_bytes(bytes(flipped))
    code, _, err = run(capsys, "evaluate", flows, "--data", mvsec, *SIZE_ARGS, "--out", tmp_path / "ev")
    assert code == 2 and "indoor_flying1_gt_flow_dist.npz" in error_line(err)


def test_an_empty_ground_truth_is_said_as_such(tmp_path, capsys):
    rec = write_mvsec(tmp_path / "nan", flow=(np.nan, np.nan))
    flows = write_flows(tmp_path / "flows", 1500000000.0)
    code, out, err = run(capsys, "evaluate", flows, "--data", rec, *SIZE_ARGS, "--out", tmp_path / "ev")
    line = error_line(err)
    assert code == 2 and "nothing to score" in line and "no valid ground-truth pixel" in line
    assert "nan" not in out.lower()


def test_evaluate_refuses_another_recording_than_the_results_name(mvsec, tmp_path, capsys):
    other = write_mvsec(tmp_path / "other", seed=1)
    flows = write_flows(tmp_path / "flows", 1500000000.0, fingerprint=fingerprint_of(mvsec))
    code, _, err = run(capsys, "evaluate", flows, "--data", other, *SIZE_ARGS, "--out", tmp_path / "ev")
    assert code == 2 and "is not the recording" in error_line(err) and "--ignore-fingerprint" in err
    args = ["evaluate", flows, *SIZE_ARGS, "--out", tmp_path / "ev"]
    assert run(capsys, *args, "--data", other, "--ignore-fingerprint")[0] == 0
    assert run(capsys, *args, "--data", mvsec)[0] == 0
    # the results of estimate carry it too
    from cmax_taichi.solve.results import SequenceResult

    res = SequenceResult("translation2", ("v_x", "v_y"), ("px/s", "px/s"), settings={"source": str(mvsec)})
    res.settings["fingerprint"] = "123-0000000000000000"
    (tmp_path / "est").mkdir()
    res.to_json(tmp_path / "est" / "results.json")
    code, _, err = run(capsys, "evaluate", tmp_path / "est", *SIZE_ARGS)
    assert code == 2 and "is not the recording" in error_line(err)


def test_timestamps_in_the_wrong_unit_are_said(tmp_path, capsys):
    rec = write_mvsec(tmp_path / "rec", t0=0.0)
    flos = tmp_path / "flos"
    flos.mkdir()
    for k in range(2):
        write_flo(flos / f"{k:06d}.flo", np.zeros((2, SIZE[1], SIZE[0])))
    (tmp_path / "stamps.txt").write_text("0 1\n1 2\n")  # whole seconds: read as microseconds
    args = ["evaluate", flos, "--data", rec, *SIZE_ARGS, "--timestamps", tmp_path / "stamps.txt"]
    code, _, err = run(capsys, *args, "--out", tmp_path / "ev")
    line = error_line(err)
    assert code == 2 and "read as microseconds" in line and "read as seconds they would fall inside" in line


def test_results_no_run_could_have_written_are_refused(tmp_path):
    from cmax_taichi.solve.results import SequenceResult, WindowResult, read_results

    res = SequenceResult("translation2", ("v_x", "v_y"), ("px/s", "px/s"))
    res.add(WindowResult(0, 1.0, 1.1, 100, np.array([1.0, 2.0]), 1.5, 1.2, 3, 0.1, True))
    path = res.to_json(tmp_path / "results.json")
    good = json.loads(path.read_text())
    for change, message in [
        (lambda d: d["windows"][0].update(t_start=2.0), "is not a time span"),
        (lambda d: d.update(settings=[]), "'settings' is a list"),
        (lambda d: d["windows"][0].update(status="junk"), "unknown status"),
        (lambda d: d["windows"].append(d["windows"][0]), "window 0 follows window 0: repeated"),
    ]:
        data = json.loads(json.dumps(good))
        change(data)
        path.write_text(json.dumps(data))
        with pytest.raises(ValueError, match=message):
            read_results(path)


def test_evaluate_scores_no_window_outside_the_recording(mvsec, tmp_path, capsys):
    """Results whose windows were moved 100 s past the recording (an edited file, the fingerprint
    intact) were scored against the ground truth all the same."""
    from cmax_taichi.solve.results import SequenceResult, WindowResult

    settings = {"source": str(mvsec), "format": "mvsec", "fingerprint": fingerprint_of(mvsec)}
    res = SequenceResult("translation2", ("v_x", "v_y"), ("px/s", "px/s"), settings=settings)
    t0 = 1500000000.0 + 100.0
    res.add(WindowResult(0, t0, t0 + 0.05, 100, np.array([6.0, 4.0]), 1.5, 1.2, 3, 0.1, True))
    (tmp_path / "est").mkdir()
    res.to_json(tmp_path / "est" / "results.json")
    code, _, err = run(capsys, "evaluate", tmp_path / "est", *SIZE_ARGS)
    line = error_line(err)
    assert code == 2 and "1 window(s) with a time span outside the recording's" in line


def test_batch_tables_come_from_the_checked_results(tmp_path):
    from cmax_taichi.solve import batch
    from cmax_taichi.solve.results import SequenceResult, WindowResult

    folder = tmp_path / "out" / "rec"
    folder.mkdir(parents=True)
    res = SequenceResult("translation2", ("v_x", "v_y"), ("px/s", "px/s"))
    res.add(WindowResult(0, 1.0, 1.1, 100, np.array([1.0, 2.0]), 1.5, 1.2, 3, 0.1, True))
    res.to_json(folder / "results.json")
    (folder / "results.csv").write_text("junk,row\n")
    summary = batch.RecordingSummary(name="rec", path="rec", status="done")
    _, windows_csv = batch._write_tables(tmp_path / "out", [summary])
    assert "junk" not in windows_csv.read_text() and windows_csv.read_text().count("\n") == 2


# --- tracebacks and misleading messages -----------------------------------------------------------------
@pytest.mark.parametrize("damage", ["truncate", "crc"])
def test_a_damaged_flow_file_is_named(tmp_path, damage):
    path = write_flows(tmp_path / "flows", 0.0, n=1) / "flow_0000.npz"
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    else:
        data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="flow_0000.npz: not a readable .npz file"):
        read_flow_npz(path)


def test_plugins_load_all_or_nothing_and_never_exit(tmp_path, capsys):
    import cmax_taichi as cm
    from cmax_taichi.core.registry import PluginError, load_plugin

    half = tmp_path / "half.py"
    half.write_text(
        "import cmax_taichi as cm\n"
        "from cmax_taichi.testing.samples import *\n"
        "cm.register_objective(cm.Objective('half_objective', 1, pixel=cm.OBJECTIVES.get('variance').pixel,"
        " finalize=cm.OBJECTIVES.get('variance').finalize))\n"
        "raise RuntimeError('fails after its first registration')\n"
    )
    with pytest.raises(PluginError, match="fails after its first registration"):
        load_plugin(str(half))
    assert "half_objective" not in cm.objective_names()  # nothing of it stays registered
    leaving = tmp_path / "leaving.py"
    leaving.write_text("import sys\nsys.exit(0)\n")
    with pytest.raises(PluginError, match=r"called sys.exit\(0\)"):
        load_plugin(str(leaving))
    code, _, err = run(capsys, "info", "--plugin", leaving)
    assert code == 2 and "sys.exit(0)" in error_line(err)


def test_a_plugin_that_fails_in_the_workers_is_named(tmp_path):
    from cmax_taichi.solve.workers import run_tasks

    results = run_tasks([(_never_called, (), {})] * 2, 2, _fail_to_start, max_restarts=1)
    assert set(results) == {0, 1}
    assert all("the worker could not start: RuntimeError: no licence server" in r for r in results.values())
    assert all("__main__" not in r for r in results.values())


def _fail_to_start():
    raise RuntimeError("no licence server")


def _never_called(state):  # pragma: no cover - the workers never start
    return state


def test_a_missing_optional_package_and_ctrl_c_in_a_plugin_are_one_line(tmp_path, capsys, monkeypatch):
    """`estimate x.bag` without rosbags printed an ImportError traceback (exit 1), and Ctrl-C while a
    plugin loads a KeyboardInterrupt traceback."""
    monkeypatch.setitem(sys.modules, "rosbags", None)  # as where it is not installed
    (tmp_path / "x.bag").write_bytes(b"#ROSBAG V2.0\n")
    code, _, err = run(capsys, "estimate", tmp_path / "x.bag", "--out", tmp_path / "E")
    assert code == 2 and "needs the optional package 'rosbags'" in error_line(err)
    (tmp_path / "slow.py").write_text("raise KeyboardInterrupt\n")
    code, _, err = run(capsys, "info", "--plugin", tmp_path / "slow.py")
    assert code == 130 and err.strip() == "cmax-taichi: interrupted"


def test_an_empty_segment_window_names_the_recordings_span(tmp_path, capsys):
    rec = write_recording(tmp_path / "rec")  # 0.1 s
    code, _, err = run(capsys, "segment", rec, "-k", "2", "--t-start", "5", "--out", tmp_path / "S")
    line = error_line(err)
    assert code == 2 and "the window from --t-start 5 s is empty" in line and "recording spans 0.0" in line


def test_count_strides_are_whole_numbers_on_every_command(capsys):
    for command in ("flow", "estimate"):
        code, _, err = run(capsys, command, "/nonexistent", "--stride", "0.5")
        assert code == 2 and "--stride must be a whole number of events" in error_line(err)


def test_strict_json_everywhere():
    text = outputs.json_text({"a": float("nan"), "b": [np.float32("inf"), np.int64(3)], "c": np.array([1.5])})

    def bare(token):
        raise ValueError(token)

    assert json.loads(text, parse_constant=bare) == {"a": None, "b": [None, 3], "c": [1.5]}


def test_a_full_event_cache_falls_back_then_names_both(tmp_path, monkeypatch):
    from cmax_taichi.io import _cache

    source = tmp_path / "events.bin"
    source.write_bytes(b"x" * 100)
    rows = np.arange(8, dtype=np.float64).reshape(2, 4)

    def build(out):
        out.write(rows.tobytes())
        return {"n": 2}

    real_store = _cache._store

    def cache_full(source, kind, build, sort, fd, tmp, table_path, *rest):
        if table_path is not None:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_store(source, kind, build, sort, fd, tmp, table_path, *rest)

    monkeypatch.setattr(_cache, "_store", cache_full)
    with pytest.warns(RuntimeWarning, match="cannot write the event cache in .*No space left"):
        table, _ = _cache.cached_table(source, "test", {}, build, cache_dir=tmp_path / "cache")
    np.testing.assert_array_equal(table, rows)

    def everywhere_full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_cache, "_store", everywhere_full)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        with pytest.raises(OSError, match="neither in the event cache .* nor in the temporary folder"):
            _cache.cached_table(source, "test2", {}, build, cache_dir=tmp_path / "cache")


# --- first-day defects ------------------------------------------------------------------------------------
def test_no_taichi_banner_and_true_help(tmp_path):
    from cmax_taichi.flow.solver import AUTO_PADDING

    run_help = subprocess.run(
        [sys.executable, "-m", "cmax_taichi.cli", "flow", "--help"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert run_help.returncode == 0
    assert "[Taichi]" not in run_help.stdout + run_help.stderr
    assert f"default {AUTO_PADDING * 100:g}% of the larger" in " ".join(run_help.stdout.split())
    assert "--keep-tail" in run_help.stdout


def test_info_lists_the_smoothness_terms_flow_accepts(capsys):
    from cmax_taichi.flow.smoothness import smoothness_names

    code, out, _ = run(capsys, "info")
    assert code == 0 and "[Taichi]" not in out
    assert all(f"  {name} " in out for name in smoothness_names())


def test_a_weight_that_drowns_the_data_term_is_refused(capsys):
    """deformation=1e308 made the dense flow's optimizer return "nodes has non-finite values"."""
    import cmax_taichi as cm
    from cmax_taichi.pipeline.setup import MAX_REGULARIZER_WEIGHT, check_regularizers

    for command in ("flow", "estimate", "segment"):
        code, _, err = run(capsys, command, "/nonexistent", "--reg", "deformation=1e308")
        assert code == 2 and "weight 1e308 is above 1e+09" in error_line(err)
    with pytest.raises(ValueError, match="data term would vanish"):
        check_regularizers({"deformation": 10 * MAX_REGULARIZER_WEIGHT})
    assert check_regularizers({"divergence": cm.RECOMMENDED_LAMBDA}) == {"divergence": cm.RECOMMENDED_LAMBDA}


def test_a_denormal_stride_is_refused_not_overflowed():
    """A time stride of 5e-324 s made the window count infinite: an OverflowError escaped (found by
    tests/test_input_properties.py)."""
    from cmax_taichi.core import checks

    with pytest.raises(ValueError, match="would be inf windows, more than the limit"):
        list(checks.time_windows(0.0, 0.5, 600, 1.0, 5e-324, lambda t: 0, lambda i: 0.0))


def test_evaluate_reads_the_recording_and_intervals_of_a_flow_run(mvsec, tmp_path, capsys):
    # .flo files carry no interval: the flow run's flow_timestamps.txt and summary.json say what they are
    run_folder = tmp_path / "flow_run"
    (run_folder / "flow").mkdir(parents=True)
    t0 = 1500000000.0
    for k in range(2):
        write_flo(run_folder / "flow" / f"flow_{k:04d}.flo", np.full((2, SIZE[1], SIZE[0]), 0.3))
    stamps = "".join(f"{t0 + 0.1 + 0.05 * k:.9f} {t0 + 0.15 + 0.05 * k:.9f}\n" for k in range(2))
    (run_folder / "flow_timestamps.txt").write_text(stamps)
    recording = {"source": str(mvsec), "format": "mvsec", "fingerprint": fingerprint_of(mvsec)}
    (run_folder / "summary.json").write_text(json.dumps({"recording": recording}))
    code, out, err = run(capsys, "evaluate", run_folder, *SIZE_ARGS)
    assert code == 0, err
    assert f"2 flow file(s) of {run_folder / 'flow'} against {mvsec} (2 with pixels to score)" in out
    recording["source"] = str(tmp_path / "moved_away.hdf5")
    (run_folder / "summary.json").write_text(json.dumps({"recording": recording}))
    code, _, err = run(capsys, "evaluate", run_folder, *SIZE_ARGS)
    assert code == 2 and "moved_away.hdf5, which is not there: give it with --data PATH" in error_line(err)


def test_flow_references_take_the_fractions_its_error_offers(mvsec, tmp_path, capsys):
    from cmax_taichi.cli import build_parser

    parse = build_parser().parse_args
    assert parse(["flow", "rec", "--references", "0.25"]).references == 0.25
    assert parse(["flow", "rec", "--references", "first,0.5"]).references == ("first", 0.5)
    assert parse(["flow", "rec", "--references", "multi"]).references == "multi"
    code, _, err = run(capsys, "flow", mvsec, *SIZE_ARGS, "--references", "1.5", "--out", tmp_path / "o")
    assert code == 2 and "fraction of the window in [0, 1], got 1.5" in error_line(err)


def test_live_run_whose_only_window_the_end_closes_writes_strict_json(tmp_path):
    # no window was closed by its own events: no latency measured, printed as such and null in the JSON
    rng = np.random.default_rng(0)
    n = 3000
    t = 1.0 + np.sort(rng.uniform(0, 0.1, n))
    rows = np.column_stack([t, rng.integers(0, 64, n), rng.integers(0, 48, n), rng.integers(0, 2, n)])
    np.savetxt(tmp_path / "dots.txt", rows, fmt=["%.9f", "%d", "%d", "%d"])
    out = tmp_path / "out"
    args = ["--live", tmp_path / "dots.txt", "--out", out, "--speed", "10", "--warp", "translation2"]
    done = subprocess.run(
        [sys.executable, "-m", "cmax_taichi.cli", "estimate", *map(str, args), "--no-display"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0 and "no latency measured" in done.stdout, done.stderr
    assert "nan" not in done.stdout
    summary = json.loads((out / "results.json").read_text(), parse_constant=pytest.fail)
    assert summary["live"]["latency_median_s"] is None and summary["events"]["estimated"] == n


@pytest.mark.parametrize("command", ["estimate", "flow"])
def test_a_recording_shorter_than_a_window_is_one_error_line(tmp_path, capsys, command):
    """Fewer events than one --window: the one error line says why, with the counts; the end-of-pass
    warning of the events not estimated is not printed beside it."""
    recording = write_recording(tmp_path / "short", n=600)
    argv = [command, recording, "--window", "1000", "--quiet", "--out", tmp_path / "out"]
    if command == "flow":
        argv += ["--grid", "2", "2", "--levels", "1"]
    code, _, err = run(capsys, *argv)
    assert code == 2 and err.count("\n") == 1, err
    assert "600 events, fewer than one window of --window 1000" in error_line(err)


# --- the fourth sweep's cases ------------------------------------------------------------------------
def test_a_live_run_refuses_another_commands_outputs_and_leaves_out_as_it_was(tmp_path, capsys):
    """flow --live into an estimate's folder replaced its results.csv (exit 0, a mixed folder); a live run
    refused after its source opened (a numeric --t-ref) left a header-only results.csv without a manifest,
    which every later run then refused."""
    rec = write_recording(tmp_path / "rec")
    out = tmp_path / "est"
    out.mkdir()
    (out / "results.csv").write_text("estimate's rows\n")
    outputs.write_manifest(out, ["results.csv"], "estimate")
    code, _, err = run(capsys, "flow", "--live", rec, "--speed", 50, "--window", 1000, "--no-display",
                       "--quiet", "--grid", 4, 4, "--levels", 1, "--out", out)  # fmt: skip
    assert code == 2 and "is an output of 'cmax-taichi estimate'" in error_line(err)
    assert (out / "results.csv").read_text() == "estimate's rows\n"

    live = tmp_path / "live"
    code, _, err = run(capsys, "estimate", "--live", rec, "--speed", 50, "--window-mode", "count",
                       "--window", 1000, "--t-ref", 0.01, "--no-display", "--out", live)  # fmt: skip
    assert code == 2 and "one time on the events' clock" in error_line(err)
    assert not live.exists()  # nothing written, not even the folder


def test_live_options_that_would_be_ignored_are_refused(tmp_path, capsys):
    """--window with the live default (adaptive windows) was ignored without a word; --figures -3 and an
    empty --out were accepted (the latter wrote into the current folder)."""
    rec = write_recording(tmp_path / "rec")
    code, _, err = run(capsys, "estimate", "--live", rec, "--window", 500, "--no-display",
                       "--out", tmp_path / "a")  # fmt: skip
    assert code == 2 and "not with --window" in error_line(err) and not (tmp_path / "a").exists()
    code, _, err = run(capsys, "estimate", rec, "--figures", -3, "--out", tmp_path / "b")
    assert code == 2 and "--figures must be" in error_line(err)
    code, _, err = run(capsys, "estimate", rec, "--out", "")
    assert code == 2 and "--out is empty" in error_line(err)


def test_segment_window_options_that_would_be_ignored_are_refused(tmp_path, capsys):
    rec = write_recording(tmp_path / "rec")
    code, _, err = run(capsys, "segment", rec, "--start", 300, "--t-start", 0.01, "--out", tmp_path / "s")
    assert code == 2 and "--start gives the window by event index" in error_line(err)
    code, _, err = run(capsys, "segment", "--example", "two-objects", "--t-start", 0.01,
                       "--out", tmp_path / "e")  # fmt: skip
    assert code == 2 and "--t-start: options of a recording's window" in error_line(err)


def test_reproduce_refuses_a_negative_seed_before_simulating(tmp_path, capsys):
    code, out, err = run(capsys, "reproduce", "table1", "--quick", "--seed", -1, "--windows", 1,
                         "--out", tmp_path / "r")  # fmt: skip
    assert code == 2 and "seed must be" in error_line(err) and "simulating" not in out + err


def test_open_recording_sort_must_be_a_bool(tmp_path):
    from cmax_taichi import io

    rec = write_recording(tmp_path / "rec")
    with pytest.raises(TypeError, match="sort must be True or False, got 'x'"):
        io.open_recording(rec, sort="x")
