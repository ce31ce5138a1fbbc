"""cmax-taichi estimate draws its figures in a forked child process (cli/estimate.py FigureWriter):
matplotlib's import and the drawing overlap the estimate. The figures are the same files; a figure that
fails is reported as one error line."""

from __future__ import annotations

import multiprocessing

import numpy as np
import pytest

from cmax_taichi.cli import CliError, estimate
from cmax_taichi.core import backend

PNG = b"\x89PNG\r\n\x1a\n"


def window_data() -> dict:
    rng = np.random.default_rng(0)
    return {
        "identity": rng.random((12, 16)),
        "estimate": rng.random((12, 16)),
        "flow": rng.normal(size=(2, 12, 16)),
        "value": 1.25,
        "warp": "translation2",
        "title": "window 0",
    }


def parameters_data() -> dict:
    return {
        "t": np.array([0.0, 0.01, 0.02]),
        "theta": np.array([[1.0, 2.0], [1.5, 2.5], [2.0, 3.0]]),
        "fwl": [1.1, 1.2, 1.3],
        "names": ("v_x", "v_y"),
        "units": ("px/s", "px/s"),
        "warp": "translation2",
    }


def test_figures_drawn_by_the_child(tmp_path):
    """In a process where Taichi has started (the other tests), the figures are drawn in-process."""
    writer = estimate.FigureWriter()
    if "fork" in multiprocessing.get_all_start_methods() and not backend.is_initialized():
        assert writer._process is not None and writer._process.is_alive()
    writer.draw("window", tmp_path / "window_0000.png", window_data())
    writer.draw("parameters", tmp_path / "parameters.png", parameters_data())
    writer.close()
    for name in ("window_0000.png", "parameters.png"):
        assert (tmp_path / name).read_bytes()[:8] == PNG


def test_a_failing_figure_is_one_error(tmp_path):
    writer = estimate.FigureWriter()
    writer.draw("window", tmp_path / "missing_folder" / "window_0000.png", window_data())
    with pytest.raises(CliError, match="figures: .*missing_folder"):
        writer.close()


def test_abandon_stops_the_child():
    writer = estimate.FigureWriter()
    writer.abandon()
    assert writer._process is None or not writer._process.is_alive()
    writer.close()  # nothing left to wait for
