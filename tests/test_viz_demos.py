"""cmax_taichi.viz helpers, and every demo rendering headless to a non-blank picture.

The demos run in-process through their ``main(argv)`` with ``--save`` (Agg backend) and small event
subsets (``--max-events``) to stay fast; they use the real recordings when ../shared/data is present
and their synthetic scenes otherwise (``--synthetic`` forces the latter).
"""

from __future__ import annotations

import importlib
import re
import subprocess
import sys
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from conftest import SENSOR, edge_events
from matplotlib.colors import rgb_to_hsv

import cmax_taichi as cm
from cmax_taichi import viz

matplotlib.use("Agg")  # before any pyplot import (the demos choose Agg themselves with --save)

DEMOS = Path(__file__).resolve().parents[1] / "demos"


def _demo(name: str):
    if str(DEMOS) not in sys.path:
        sys.path.insert(0, str(DEMOS))
    return importlib.import_module(name)


def _assert_not_blank(png: Path) -> None:
    import matplotlib.image as mpimg

    assert png.is_file() and png.stat().st_size > 10_000, f"{png} missing or tiny"
    pixels = mpimg.imread(png)[..., :3].reshape(-1, 3)
    assert pixels.var() > 1e-3, "picture is (nearly) uniform"
    colours = np.unique((pixels[::7] * 255).astype(np.uint8), axis=0)
    assert len(colours) > 20, f"only {len(colours)} distinct colours"


# --- helpers ---------------------------------------------------------------------------------------------
def test_flow_colours_follow_the_direction():
    # right, down, left, up (image coordinates, y down) at full magnitude, and a half-magnitude flow
    flow = np.array([[1.0, 0.0, -1.0, 0.0, 0.5], [0.0, 1.0, 0.0, -1.0, 0.0]])
    hsv = rgb_to_hsv(viz.flow_to_rgb(flow, max_magnitude=1.0))
    np.testing.assert_allclose(hsv[:4, 0], [0.0, 0.25, 0.5, 0.75], atol=1e-6)
    np.testing.assert_allclose(hsv[:, 1], 1.0, atol=1e-9)
    np.testing.assert_allclose(hsv[:, 2], [1.0, 1.0, 1.0, 1.0, 0.5], atol=1e-9)
    np.testing.assert_allclose(viz.flow_to_rgb(np.zeros((2, 3, 3))), 0.0)  # no motion is black


def test_flow_wheel_is_the_legend_of_flow_to_rgb():
    wheel = viz.flow_wheel(21)
    assert wheel.shape == (21, 21, 4)
    assert wheel[0, 0, 3] == 0.0  # corners are transparent
    np.testing.assert_allclose(wheel[10, 10, :3], 0.0)  # centre: zero flow
    np.testing.assert_allclose(wheel[10, 20, :3], viz.flow_to_rgb(np.array([[1.0], [0.0]]), 1.0)[0])
    np.testing.assert_allclose(wheel[20, 10, :3], viz.flow_to_rgb(np.array([[0.0], [1.0]]), 1.0)[0])


@pytest.mark.parametrize("name", ["divergence", "deformation"])
def test_regularizer_maps_are_centred_on_the_neutral_value(name):
    import matplotlib.pyplot as plt

    neutral = cm.REGULARIZERS.get(name).neutral
    rng = np.random.default_rng(0)
    # asymmetric values around the neutral one: the centre must still be the neutral value
    values = neutral + np.abs(rng.normal(0, 0.5, (12, 16))) * np.where(rng.random((12, 16)) < 0.8, 1, -0.3)
    values = np.maximum(values, 0.05)
    count = (rng.random((12, 16)) < 0.7).astype(float)
    maps = {name: values, "count": count, "R_" + name: 0.1}
    fig, ax = plt.subplots()
    artist = viz.show_regularizer_map(ax, maps, name)
    assert artist.norm(neutral) == pytest.approx(0.5)
    lo, hi = artist.norm.vmin, artist.norm.vmax
    assert lo < neutral < hi
    rgba = artist.cmap(artist.norm(neutral))
    assert min(rgba[:3]) > 0.9, "the neutral value is not drawn (nearly) white"
    drawn = artist.get_array()
    np.testing.assert_array_equal(np.ma.getmaskarray(drawn), count <= 0)  # no-event pixels masked
    plt.close(fig)


def test_map_norm_linear_and_log():
    norm = viz.map_norm(np.array([-1.0, 3.0, 0.5]), 0.0, percentile=100)
    assert (norm.vmin, norm.vmax) == (-3.0, 3.0)
    norm = viz.map_norm(np.array([0.5, 1.0, 4.0]), 1.0, log=True, percentile=100)
    assert norm.vmin == pytest.approx(0.25) and norm.vmax == pytest.approx(4.0)
    assert norm(1.0) == pytest.approx(0.5)
    norm = viz.map_norm(np.zeros(5), 0.0)  # a flat map still gets a valid range
    assert norm.vmin < 0.0 < norm.vmax


def test_iwe_limits_ignore_empty_pixels():
    image = np.zeros((10, 10))
    image[2, 3] = 4.0
    assert viz.iwe_limits(image) == (0.0, 4.0)
    assert viz.iwe_limits(-image) == (-4.0, 4.0)


def test_landscapes_equal_prob_value(f64):
    x, y, t, p = edge_events(300)
    events = cm.Events(x, y, t, p, SENSOR)
    problems = viz.regularizer_variants(events, weight=0.5, names=("deformation",), warp="mitrokhin4")
    assert list(problems) == ["no regularizer", "Def. (λ=0.5)"]
    theta = np.array([10.0, -5.0, 1.0, 0.5])
    values = np.array([-2.0, 0.0, 3.0])
    curves = viz.landscape_1d(problems, 2, values, theta)
    for label, prob in problems.items():
        expected = [prob.value(np.r_[theta[:2], v, theta[3]]) for v in values]
        np.testing.assert_allclose(curves[label], expected, rtol=1e-12)
    prob = problems["no regularizer"]
    np.testing.assert_allclose(viz.landscape_1d(prob, 2, values, theta), curves["no regularizer"])
    grid = viz.landscape_2d(prob, (0, 3), [0.0, 20.0], [-1.0, 0.0, 1.0], theta)
    assert grid.shape == (3, 2)
    assert grid[2, 1] == pytest.approx(prob.value([20.0, -5.0, 1.0, 1.0]), rel=1e-12)
    assert viz.param_label("mitrokhin4", 2) == "h_z [1/s]"


def test_viz_is_a_module_and_import_cmax_taichi_leaves_matplotlib_out():
    code = (
        "import sys, cmax_taichi\n"
        "assert 'matplotlib' not in sys.modules, 'import cmax_taichi imported matplotlib'\n"
        "from cmax_taichi import viz\n"
        "assert 'matplotlib.pyplot' not in sys.modules, 'viz imported pyplot'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


# --- demos -----------------------------------------------------------------------------------------------
def test_collapse_explorer_zoom_with_optimizer_renders(tmp_path):
    out = tmp_path / "zoom.png"
    argv = [
        "--save",
        str(out),
        "--max-events",
        "2500",
        "--samples",
        "9",
        "--theta",
        "2",
        "--optimize",
        "none",
    ]
    assert _demo("collapse_explorer").main(argv) == 0
    _assert_not_blank(out)


def test_collapse_explorer_4dof_renders(tmp_path):
    out = tmp_path / "m4.png"
    argv = ["--save", str(out), "--warp", "mitrokhin4", "--synthetic", "--max-events", "2000"]
    assert _demo("collapse_explorer").main(argv + ["--samples", "7", "--theta", "20", "-10", "2", "1"]) == 0
    _assert_not_blank(out)


def test_rotation_estimation_renders(tmp_path):
    out = tmp_path / "rot.png"
    rc = _demo("rotation_estimation").main(
        ["--save", str(out), "--max-events", "3000", "--grid", "5", "--compact"]
    )
    assert rc == 0
    _assert_not_blank(out)


def test_rotation_estimation_synthetic_recovers_the_rotation(tmp_path, capsys):
    out = tmp_path / "rot_syn.png"
    argv = ["--save", str(out), "--synthetic", "--max-events", "4000", "--grid", "4"]
    assert _demo("rotation_estimation").main(argv) == 0
    _assert_not_blank(out)
    printed = capsys.readouterr().out
    estimate = re.search(r"estimate w_x = (\S+), w_y = (\S+), w_z = (\S+) rad/s", printed)
    truth = re.search(r"true w: (\S+), (\S+), (\S+) rad/s", printed)
    assert estimate and truth, printed
    est = np.array([float(v) for v in estimate.groups()])
    np.testing.assert_allclose(est, [float(v) for v in truth.groups()], atol=0.05)  # rad/s


def test_demo_without_display_or_save_explains_itself(monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    assert _demo("collapse_explorer").main([]) == 2
    assert "--save" in capsys.readouterr().err


def test_collapse_explorer_widgets_work_without_a_window(monkeypatch):
    """The interactive callbacks (sliders, curve pick, release, Optimize + animation) on an Agg canvas."""
    import matplotlib.pyplot as plt
    from matplotlib.backend_bases import MouseEvent

    ce = _demo("collapse_explorer")
    common = _demo("_common")
    scene = common.synthetic_zoom(2000)
    explorer = ce.Explorer(scene, "mitrokhin4", 5.0, 7, interactive=True)
    explorer.draw(np.zeros(4))
    # Agg draws synchronously on draw_idle (a GUI defers it): skip the drawing, test the logic.
    monkeypatch.setattr(explorer.fig.canvas, "draw_idle", lambda *a, **k: None)
    explorer.sliders[0].set_val(30.0)  # another parameter than the curve's: the curve goes stale
    assert explorer.curve_stale
    canvas = explorer.fig.canvas
    release = MouseEvent("button_release_event", canvas, 5, 5, button=1)
    canvas.callbacks.process("button_release_event", release)  # the mouse release redraws the curve
    assert not explorer.curve_stale
    explorer.pick.set_active(3)  # curve over theta
    assert explorer.curve_index == 3 and not explorer.curve_stale
    explorer.radio.set_active(2)  # optimize the deformation-regularized objective
    explorer.button._observers.process("clicked", None)
    timer = explorer._animation
    for _ in range(200):  # drive the animation timer by hand (Agg timers never fire)
        for func, args, kwargs in list(timer.callbacks):
            func(*args, **kwargs)
        if explorer.path_artists:
            break
    assert explorer.path_artists, "the optimizer path was not drawn"
    plt.close(explorer.fig)


def test_segmentation_viewer_renders_and_separates_the_objects(tmp_path, capsys):
    out = tmp_path / "seg.png"
    assert _demo("segmentation_viewer").main(["--save", str(out), "--max-events", "3000"]) == 0
    _assert_not_blank(out)
    found = re.search(r"agreement with the true labels: (\S+)%", capsys.readouterr().out)
    assert found and float(found.group(1)) > 85.0


def test_dense_flow_collapse_demo_renders(tmp_path, capsys):
    """demos/dense_flow_collapse.py on its synthetic box room, a coarse grid: every variant's FWL is printed
    and the picture is drawn."""
    out = tmp_path / "dense.png"
    argv = ["--save", str(out), "--synthetic", "--max-events", "3000", "--grid", "4", "4", "--levels", "2"]
    assert _demo("dense_flow_collapse").main(argv) == 0
    assert capsys.readouterr().out.count(" FWL ") == 5
    _assert_not_blank(out)
