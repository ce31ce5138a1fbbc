"""The command as a process (``cli.console_main``): it ends without the interpreter's teardown, and still
writes the kernels it compiled to Taichi's offline cache, keeps its exit codes and flushes its output;
under a profiler it exits normally, so that the profile is written."""

import os
import subprocess
import sys

import pytest

CMD = [sys.executable, "-m", "cmax_taichi.cli"]


def _run(argv, tmp_path, cache=None, prefix=()):
    env = dict(os.environ, MPLBACKEND="Agg")
    if cache is not None:
        env["TI_OFFLINE_CACHE_FILE_PATH"] = str(cache)
    return subprocess.run(
        [*prefix, *argv], capture_output=True, text=True, env=env, timeout=900, cwd=tmp_path
    )


@pytest.mark.slow
def test_a_fresh_cache_is_written_and_read_back(tmp_path):
    cache = tmp_path / "ticache"
    argv = [*CMD, "estimate", "--example", "translation", "--window", "2000", "--max-windows", "1"]
    argv += ["--quiet", "--figures", "0"]
    first = _run([*argv, "--out", str(tmp_path / "a")], tmp_path, cache)
    assert first.returncode == 0, first.stderr
    assert first.stdout.rstrip().splitlines()[-1].startswith("wrote: "), first.stdout  # flushed whole
    cached = sorted(p.name for p in cache.rglob("*.tic"))
    assert cached, "no kernel reached the offline cache"
    second = _run([*argv, "--out", str(tmp_path / "b")], tmp_path, cache)
    assert second.returncode == 0, second.stderr
    assert sorted(p.name for p in cache.rglob("*.tic")) == cached  # nothing compiled again


def test_exit_codes_and_error_lines(tmp_path):
    missing = _run([*CMD, "estimate", str(tmp_path / "nothing-here")], tmp_path)
    assert missing.returncode == 2
    assert missing.stderr.strip().splitlines()[-1].endswith("no such file or folder"), missing.stderr
    usage = _run([*CMD, "estimate", "--no-such-option"], tmp_path)
    assert usage.returncode == 2 and "unrecognized arguments" in usage.stderr
    # a first day's commands: the version, and the package run as a module
    for argv in ([*CMD, "--version"], [sys.executable, "-m", "cmax_taichi", "--version"]):
        version = _run(argv, tmp_path)
        assert version.returncode == 0 and version.stdout.startswith("cmax-taichi "), version.stderr


def test_a_profiler_still_gets_its_profile(tmp_path):
    profile = tmp_path / "run.prof"
    argv = ["-m", "cmax_taichi.cli", "estimate", str(tmp_path / "nothing-here")]
    proc = _run(argv, tmp_path, prefix=[sys.executable, "-m", "cProfile", "-o", str(profile)])
    assert "no such file or folder" in proc.stderr, proc.stderr
    assert profile.stat().st_size > 0  # written after the program returned: not skipped by the quick exit
