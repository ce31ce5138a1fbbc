"""User extensions from a plugin file (examples/user_extensions.py): a 6-DOF affine warp, an objective
with only a pixel term and a per-pixel log-area penalty, run end to end in the API (the simulator's exact
motion of the new model, an estimate with the new objective and penalty) and through
``cmax-taichi estimate --plugin ...``; bad plugins and examples that a model cannot express give one
clear error before any work."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import EXAMPLES_DIR
from test_cli_estimate import assert_one_line_error, run_main, write_ecd_folder

import cmax_taichi as cm
from cmax_taichi import sim
from cmax_taichi.core.registry import PluginError, load_plugin
from cmax_taichi.sim.examples import check_example

PLUGIN = EXAMPLES_DIR / "user_extensions.py"
THETA = (2.0, -1.0, 1.5, 1.0, 40.0, -25.0)  # user_affine6: a few px over 50 ms on a 96 x 72 sensor


@pytest.fixture(scope="module")
def user():
    module = load_plugin(str(PLUGIN))
    module.register()
    yield module
    module.unregister()


@pytest.mark.usefixtures("f64")  # the core's dense flow to 1e-8 px
def test_the_simulator_derives_the_exact_motion_of_a_model_registered_at_run_time(user):
    """The displacement of the simulated motion over [t_a, t_a + dt] is the core's warp of the new model
    with theta_at(t_a) (its parameters grow: first order in time), as for the built-ins."""
    sensor = (96, 72)
    cam = sim.default_camera(sensor)
    motion = sim.Motion(user.WARP, THETA)
    yy, xx = np.mgrid[0 : sensor[1], 0 : sensor[0]].astype(np.float64)
    for t_a in (0.0, 0.05, 0.3):
        theta = motion.theta_at(t_a)
        flow = cm.dense_flow(user.WARP, theta, sensor, camera=cam, duration=0.05, dt=0.04)
        # a point at the end position x was at x - flow(x) at t_a; the motion carries it to x
        forward = np.linalg.inv(motion.window_warp(t_a, 0.04, cam))
        q = np.tensordot(forward, np.stack([xx - flow[0], yy - flow[1], np.ones_like(xx)]), axes=1)
        np.testing.assert_allclose(q[0] / q[2], xx, atol=1e-8)
        np.testing.assert_allclose(q[1] / q[2], yy, atol=1e-8)
    assert not np.allclose(motion.theta_at(0.3), THETA)  # the rates grow as for a plane approached


def test_an_estimate_with_a_pixel_term_objective_and_a_penalty_on_the_simulator(user):
    scene = sim.warp_scene(user.WARP, THETA, sensor_size=(96, 72), texture="minduka")
    rec = sim.simulate(scene, 0.05, contrast_threshold=0.3, noise_rate=0.0)
    truth = rec.theta_at(0.0)
    prob = cm.ContrastMaximization(
        rec.events(),
        user.WARP,
        objective=user.OBJECTIVE,
        regularizers={user.REGULARIZER: 1.0},
        camera=scene.camera,
    )
    assert prob.path == "chain" and user.OBJECTIVE in prob.path_reason  # a pixel term only: the chain
    res = cm.maximize(prob, 0.8 * truth, init="warm")
    assert np.all(np.isfinite(res.theta)) and res.value >= prob.value(0.8 * truth)
    assert res.value > prob.value(np.zeros(6)) + 0.05  # the motion is found: sharper than no motion
    # the translation part is the best constrained: within 10 px/s (0.5 px over the window) of the truth
    np.testing.assert_allclose(res.theta[4:], truth[4:], atol=10.0)
    ev = prob.evaluate(res.theta)
    assert np.isfinite(ev.R[user.REGULARIZER]) and ev.R[user.REGULARIZER] >= 0


def test_estimate_with_a_plugin_on_the_command_line(tmp_path):
    """The plugin is imported before the registries are read: its warp, objective and regularizer are
    valid choices, and the run writes its results."""
    folder = write_ecd_folder(tmp_path / "rec")
    out = tmp_path / "out"
    argv = [sys.executable, "-m", "cmax_taichi.cli", "estimate", str(folder), "--plugin", str(PLUGIN)]
    argv += ["--warp", "user_affine6", "--objective", "xlogx_contrast", "--reg", "log_area=1"]
    argv += ["--window", "1200", "--max-windows", "1", "--figures", "0", "--quiet", "--out", str(out)]
    proc = subprocess.run(
        argv, capture_output=True, text=True, env=dict(os.environ, MPLBACKEND="Agg"), timeout=900
    )
    assert proc.returncode == 0, proc.stderr
    results = json.loads((out / "results.json").read_text())
    assert results["warp"] == "user_affine6" and len(results["windows"]) == 1
    theta = results["windows"][0]["theta"]
    assert set(theta) == {"a11", "a12", "a21", "a22", "b_x", "b_y"} and all(np.isfinite(list(theta.values())))
    help_text = subprocess.run(
        [sys.executable, "-m", "cmax_taichi.cli", "estimate", "--help", "--plugin", str(PLUGIN)],
        capture_output=True,
        text=True,
        timeout=300,
    ).stdout
    help_text = " ".join(help_text.split())  # argparse wraps the lines
    assert "user_affine6 (a11 [1/s]" in help_text
    assert "xlogx_contrast" in help_text and "log_area" in help_text


def test_bad_plugins_give_one_line(capsys, tmp_path):
    code, _, err = run_main(capsys, "info", "--plugin", str(tmp_path / "nope.py"))
    assert_one_line_error(code, err, "--plugin", "no such file")
    code, _, err = run_main(capsys, "info", "--plugin", "no_such_module_of_cmax")
    assert_one_line_error(code, err, "no such module")
    broken = tmp_path / "broken.py"
    broken.write_text("import cmax_taichi as cm\ncm.register_warp(cm.get_warp('zoom1'))\n")  # already there
    code, _, err = run_main(capsys, "estimate", "--example", "rotation", f"--plugin={broken}")
    assert_one_line_error(code, err, "broken.py", "already registered")
    with pytest.raises(PluginError, match="no such file"):
        load_plugin(str(tmp_path / "missing.py"))


def test_a_plugin_before_the_command_is_the_command_s_option(user, capsys):
    """``cmax-taichi --plugin F.py COMMAND ...`` reads as ``cmax-taichi COMMAND --plugin F.py ...``."""
    from cmax_taichi.cli import _plugins_after_the_command

    code, out, _ = run_main(capsys, "--plugin", str(PLUGIN), "info")
    assert code == 0 and "user_affine6" in out
    args = ["--plugin", "a.py", "--plugin=b.py", "estimate", "x.txt", "--plugin", "c.py"]
    assert _plugins_after_the_command(args) == [
        "estimate", "--plugin", "a.py", "--plugin=b.py", "x.txt", "--plugin", "c.py"
    ]
    assert _plugins_after_the_command(["--plugin", "a.py"]) == ["--plugin", "a.py"]


@pytest.mark.parametrize(
    "argv, fragments",
    [
        (["estimate", "--example", "rotation", "--warp", "se2"], ("'rotation'", "rotation3 motion", "'se2'")),
        (["estimate", "--example", "collapse", "--warp", "zoom1"], ("mitrokhin4 motion", "cannot express")),
        (["estimate", "--example", "collapse", "--warp", "affine7"], ("unknown warp 'affine7'",)),
        (["segment", "--example", "two-objects", "--warp", "zoom1"], ("translation2 motion", "'zoom1'")),
    ],
)
def test_an_example_is_checked_against_the_warp_before_any_work(argv, fragments, capsys, tmp_path):
    start = time.process_time()
    code, _, err = run_main(capsys, *argv, "--out", str(tmp_path / "out"))
    assert time.process_time() - start < 1.0  # CPU seconds: nothing simulated, nothing compiled
    assert_one_line_error(code, err, *fragments)
    assert not (tmp_path / "out").exists()


def test_an_example_is_expressed_in_another_model_where_it_can_be(user):
    example = check_example("collapse", user.WARP)  # a translation: an affine flow with A = 0
    np.testing.assert_allclose(example.truth_in(user.WARP), [0, 0, 0, 0, 150.0, -80.0], atol=1e-9)
    np.testing.assert_allclose(example.truth_in("translation2"), [150.0, -80.0], atol=1e-9)
    with pytest.raises(ValueError, match="'rotation'.*cannot express.*estimate it with warp 'rotation3'"):
        check_example("rotation", [user.WARP, "se2"])


def test_batch_workers_import_the_plugin(user, tmp_path):
    """Batch workers are fresh interpreters: they import the plugins before reading the options."""
    from test_batch import write_recording

    from cmax_taichi.solve import batch

    recording = write_recording(tmp_path / "rec0.txt", (150.0, -60.0))
    result = batch.run(
        [recording],
        tmp_path / "out",
        workers=1,
        progress=False,
        plugins=[str(PLUGIN)],
        warp=user.WARP,
        regularizers={user.REGULARIZER: 1.0},
        n_events=700,
        max_windows=1,
    )
    assert not result.failed, [r.error for r in result.recordings]
    assert result.recordings[0].windows == 1
    rows = json.loads((tmp_path / "out" / "rec0" / "results.json").read_text())
    assert rows["warp"] == user.WARP
