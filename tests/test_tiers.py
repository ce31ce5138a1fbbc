"""The compiled tiers of the fused kernels (cmax_taichi/pipeline/tiers.py): which tier serves a
configuration in each compile mode, the background compile that records the optimized one, the switch
at the next window, and the command line's warmup.

The suite runs in compile mode "fast" (tests/conftest.py); the tests here set the mode they need, with
Taichi's offline cache in a folder of their own."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import CAMERA, SENSOR, edge_events

import cmax_taichi as cm
from cmax_taichi.core import backend
from cmax_taichi.flow import DenseFlowProblem
from cmax_taichi.flow.solver import KINK_WIDTH
from cmax_taichi.pipeline import tiers
from cmax_taichi.pipeline.fused import FusedPipeline


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    """Taichi's offline cache (and the tier records) in a fresh folder; the backend in ``mode``."""

    def start(mode: str):
        monkeypatch.setenv("TI_OFFLINE_CACHE_FILE_PATH", str(tmp_path / "ticache"))
        cm.init(precision="f64", compile_mode=mode)
        return tmp_path / "ticache"

    yield start
    monkeypatch.undo()
    cm.init(precision="f64")  # the suite's backend again (its mode from the environment)


@pytest.fixture
def no_background(monkeypatch):
    """Record background-compile requests instead of starting processes."""
    requests = []
    monkeypatch.setattr(tiers, "request_background_compile", lambda config: requests.append(config) or True)
    return requests


def _problem(warp="translation2", n=400, seed=0, **options):
    events = cm.Events(*edge_events(n=n, seed=seed), SENSOR)
    return cm.ContrastMaximization(events, warp=warp, camera=CAMERA, **options)


def _mark_ready(config: tiers.KernelConfig) -> None:
    path = tiers.cache_folder() / "ready" / f"{config.key()}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"config": json.loads(config.to_json()), "seconds": 12.5}))


def test_a_problem_and_warmup_name_the_same_configuration(own_cache):
    own_cache("fast")
    regs = {"divergence": 1.0, "deformation": 1.0}
    prob = _problem("mitrokhin4", regularizers=regs, blur_sigma=0.9, polarity="split")
    want = tiers.config_for(
        warp="mitrokhin4", regularizers=tuple(regs), blur_sigma=1.0, polarity="split", sensor_size=SENSOR
    )  # sigma 0.9 and 1.0: the same footprint, the same kernels
    assert prob._fused.kernel_config == want and prob._fused.kernel_config.key() == want.key()
    W, H = SENSOR
    assert want.describe() == f"mitrokhin4 + variance + divergence, deformation on {W}x{H}"
    other = tiers.config_for(
        warp="mitrokhin4", regularizers=("deformation", "divergence"), polarity="split", sensor_size=SENSOR
    )
    assert other.key() != want.key()  # the regularizers' order is the kernels' quantity order
    # the optimized kernels of another sensor are another compile (the sensor is compiled in)
    bigger = tiers.config_for(
        warp="mitrokhin4", regularizers=tuple(regs), polarity="split", sensor_size=(W + 1, H)
    )
    assert bigger.key() != want.key()
    events = cm.Events(*edge_events(n=400), SENSOR)
    flow = DenseFlowProblem(events, (2, 2), regularizers=regs, kink_width=KINK_WIDTH)  # the estimator's
    dense = tiers.config_for(warp=None, objective="gradient_magnitude", regularizers=tuple(regs))
    assert flow.kernel_config == dense and dense.kink_width == KINK_WIDTH
    exact = DenseFlowProblem(events, (2, 2), regularizers=regs)
    assert exact.kernel_config == tiers.config_for(
        warp=None, objective="gradient_magnitude", regularizers=tuple(regs), kink_width=0.0
    )
    with pytest.raises(ValueError, match="unknown warp"):
        tiers.config_for(warp="warp9")


def test_each_mode_chooses_its_tier(own_cache, no_background):
    own_cache("fast")
    assert _problem().kernels == "fast" and no_background == []
    own_cache("auto")
    prob = _problem()
    assert prob.kernels == "fast" and no_background == [prob._fused.kernel_config]
    _problem(seed=1)  # the same configuration: asked once per process
    assert len(no_background) == 1
    _mark_ready(prob._fused.kernel_config)
    assert tiers.current_tier(prob._fused.kernel_config) == "full"
    own_cache("full")
    assert tiers.current_tier(tiers.config_for(warp="zoom1")) == "full" and len(no_background) == 1


def test_a_configuration_registered_in_the_script_compiles_optimized_in_process(own_cache, no_background):
    own_cache("auto")
    model = cm.get_warp("translation2")
    mine = cm.WarpModel(
        "my_shift", model.params, model.units, model.warp, model.flow, det=model.det, div=model.div,
        param_jac=model.param_jac,
    )  # fmt: skip
    cm.register_warp(mine)
    try:
        prob = _problem("my_shift")
        assert not prob._fused.kernel_config.rebuildable
        assert prob.kernels == "full" and no_background == []
        with pytest.raises(ValueError, match="registered in this script"):
            cm.warmup("my_shift")
    finally:
        cm.unregister_warp("my_shift")


def test_a_configuration_from_a_plugin_is_rebuilt_with_its_plugin(own_cache, tmp_path):
    from cmax_taichi.core.registry import load_plugin

    own_cache("fast")
    plugin = tmp_path / "shift_plugin.py"
    plugin.write_text(
        "import cmax_taichi as cm\n"
        "m = cm.get_warp('translation2')\n"
        "cm.register_warp(cm.WarpModel('plugin_shift', m.params, m.units, m.warp, m.flow, det=m.det,\n"
        "                              div=m.div, param_jac=m.param_jac))\n"
    )
    load_plugin(str(plugin))
    try:
        config = tiers.config_for(warp="plugin_shift", regularizers=("divergence",))
        assert config.rebuildable and config.plugins == (str(plugin.resolve()),)
        assert cm.WARPS.origin("plugin_shift") == str(plugin.resolve()) and cm.WARPS.origin("zoom1") == ""
    finally:
        cm.unregister_warp("plugin_shift")


def test_the_next_window_takes_the_optimized_kernels(own_cache, no_background, monkeypatch):
    """A sequence's problem starts on the fast tier; once the optimized kernels are recorded ready, its
    next window runs on them (a kernel of their own, compiled with Taichi's advanced optimizations),
    with the same values and gradients to rounding."""
    from taichi._lib.core import taichi_python

    own_cache("auto")
    compiled = []
    compile_kernel = taichi_python.Program.compile_kernel

    def recording(self, config, caps, kernel):
        compiled.append(config.advanced_optimization)
        return compile_kernel(self, config, caps, kernel)

    monkeypatch.setattr(taichi_python.Program, "compile_kernel", recording)
    saved = FusedPipeline.loops
    FusedPipeline.loops = "serial"  # one schedule: one optimized compile
    try:
        prob = _problem()
        theta = np.array([60.0, -20.0])
        fast = prob.value_and_grad(theta)
        assert prob.kernels == "fast" and set(compiled) == {False}
        _mark_ready(prob._fused.kernel_config)  # as the background process does once it is done
        prob.set_events(cm.Events(*edge_events(n=400, seed=0), SENSOR))
        assert prob.kernels == "full" and compiled[-1] is True
        full = prob.value_and_grad(theta)
    finally:
        FusedPipeline.loops = saved
    schedules = prob._fused._schedules
    fast_kernel, full_kernel = schedules.kernel(True, "fast", SENSOR), schedules.kernel(True, "full", SENSOR)
    assert full_kernel is not fast_kernel
    other = (SENSOR[0] + 8, SENSOR[1])  # the fast kernel serves every sensor, the optimized one has it in
    assert schedules.kernel(True, "fast", other) is fast_kernel
    assert schedules.kernel(True, "full", other) is not full_kernel
    assert full[0] == pytest.approx(fast[0], rel=1e-12)
    np.testing.assert_allclose(full[1], fast[1], rtol=1e-9, atol=1e-12 * np.abs(fast[1]).max())


def test_background_requests_are_not_repeated(own_cache, monkeypatch):
    """A request while another process compiles the configuration starts nothing; a stale record of a
    dead process is replaced."""
    own_cache("auto")
    started = []

    class FakeProcess:
        pid = 4242

    monkeypatch.setattr(tiers.subprocess, "Popen", lambda *a, **k: started.append(a) or FakeProcess())
    config = tiers.config_for(warp="zoom1")
    monkeypatch.setattr(tiers, "_pending_alive", lambda path: True)
    assert tiers.request_background_compile(config) and len(started) == 1
    assert not tiers.request_background_compile(config) and len(started) == 1
    monkeypatch.setattr(tiers, "_pending_alive", lambda path: False)
    assert tiers.request_background_compile(config) and len(started) == 2


@pytest.mark.slow
def test_the_background_process_compiles_and_records(own_cache):
    """The background program compiles a configuration's optimized kernels into the offline cache and
    records them; a later process of that sensor runs on them without compiling."""
    cache = own_cache("auto")
    config = tiers.config_for(warp="zoom1", blur_sigma=0.0, sensor_size=SENSOR)
    env = {"TI_OFFLINE_CACHE_FILE_PATH": str(cache), "CMAX_TAICHI_COMPILE": "full"}
    done = subprocess.run(
        [sys.executable, "-c", tiers._WORKER, config.to_json()],
        capture_output=True, text=True, env={**__import__("os").environ, **env}, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert tiers.is_ready(config)
    record = tiers.ready_record(config)
    assert record["seconds"] > 0 and record["peak_rss_mb"] > 0
    assert [c for c, _ in tiers.ready_records()] == [config]
    assert "1 optimized configuration(s) recorded" in tiers.cache_summary()
    prob = cm.ContrastMaximization(
        cm.Events(*edge_events(n=300), SENSOR), "zoom1", camera=CAMERA, blur_sigma=0.0
    )
    assert prob.kernels == "full"


def test_warmup_command_lists_and_refuses_nothing_to_do(tmp_path):
    env = {**__import__("os").environ, "TI_OFFLINE_CACHE_FILE_PATH": str(tmp_path / "c")}
    run = [sys.executable, "-m", "cmax_taichi.cli", "warmup"]
    listed = subprocess.run([*run, "--list"], capture_output=True, text=True, env=env, timeout=300)
    assert listed.returncode == 0 and str(tmp_path / "c") in listed.stdout
    assert "0 optimized configuration(s) recorded" in listed.stdout
    nothing = subprocess.run(run, capture_output=True, text=True, env=env, timeout=300)
    assert nothing.returncode == 2 and "nothing to compile" in nothing.stderr
    bad = subprocess.run([*run, "--warp", "warp9"], capture_output=True, text=True, env=env, timeout=300)
    assert bad.returncode == 2 and "unknown warp 'warp9'" in bad.stderr
    cleared = subprocess.run([*run, "--clear"], capture_output=True, text=True, env=env, timeout=300)
    assert cleared.returncode == 0 and not (tmp_path / "c").exists()


def test_warmup_clear_deletes_the_kernels_and_nothing_else(tmp_path):
    # TI_OFFLINE_CACHE_FILE_PATH may name any folder: its other files are the user's
    cache = tmp_path / "c"
    (cache / "cmax-taichi" / "ready").mkdir(parents=True)
    (cache / "cmax-taichi" / "ready" / "0123.json").write_text("{}")
    (cache / "notes.txt").write_text("mine")
    env = {**__import__("os").environ, "TI_OFFLINE_CACHE_FILE_PATH": str(cache)}
    cleared = subprocess.run(
        [sys.executable, "-m", "cmax_taichi.cli", "warmup", "--clear"],
        capture_output=True, text=True, env=env, timeout=300,
    )  # fmt: skip
    assert cleared.returncode == 0 and "kept 1 other item(s)" in cleared.stdout
    assert (cache / "notes.txt").read_text() == "mine" and not (cache / "cmax-taichi").exists()


def test_results_record_the_kernels_of_each_window(own_cache, no_background, tmp_path):
    own_cache("auto")
    from cmax_taichi.solve import sequence
    from cmax_taichi.solve.results import read_results

    x, y, t, p = edge_events(n=3000, seed=3)
    result = sequence.process(
        cm.Events(x, y, t, p, SENSOR), "translation2", n_events=1000, progress=False, compute_fwl=False
    )
    assert [w.kernels for w in result.windows] == ["fast"] * 3
    result.to_json(tmp_path / "r.json")
    result.to_hdf5(tmp_path / "r.h5")
    result.to_csv(tmp_path / "r.csv")
    for name in ("r.json", "r.h5"):
        assert [w.kernels for w in read_results(tmp_path / name).windows] == ["fast"] * 3
    assert (tmp_path / "r.csv").read_text().splitlines()[0].endswith(",kernels")
    assert backend.info().compile_mode == "auto"


def test_a_kernel_cache_that_cannot_be_written_moves_to_the_temporary_folder(tmp_path):
    """Under a read-only HOME, Taichi crashed (SIGSEGV) when the program ended, after a complete run: it
    creates its cache folder then whether the cache is on or not. The cache moves to the temporary
    folder, said once; and with auto compilation no background compile is asked where none can write."""
    import os

    (tmp_path / "a file").write_text("x")  # the cache's parent is a file: it cannot be created
    (tmp_path / "tmp").mkdir()
    env = {
        **os.environ,
        "TI_OFFLINE_CACHE_FILE_PATH": str(tmp_path / "a file" / "ticache"),
        "TMPDIR": str(tmp_path / "tmp"),
        "CMAX_TAICHI_COMPILE": "fast",
    }
    script = (
        "import numpy as np, cmax_taichi as cm\n"
        "r = np.random.default_rng(0)\n"
        "ev = cm.Events(r.uniform(0, 63, 500), r.uniform(0, 47, 500), np.sort(r.uniform(0, .05, 500)),\n"
        "               r.choice([-1., 1.], 500), (64, 48))\n"
        "print(cm.ContrastMaximization(ev, 'translation2').evaluate([1., 2.]).J)\n"
    )
    argv = [sys.executable, "-c", script]
    done = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "cannot be written: using" in done.stderr and np.isfinite(float(done.stdout.split()[-1]))
    assert (tmp_path / "tmp" / f"cmax-taichi-ticache-{os.getuid()}").is_dir()
