"""Shared fixtures: backend precision switching, synthetic event windows, the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

import cmax_taichi as cm

#: the real recordings beside the checkout (never copied into the repository)
SHARED_DATA = Path(
    os.environ.get("CMAX_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)

SENSOR = (64, 48)
DURATION = 0.05  # s
CAMERA = cm.Camera(fx=50.0, fy=52.0, cx=31.3, cy=23.7)

#: hand-picked moderate parameter vectors (displacements of a few px over DURATION)
_CHOSEN_THETAS = {
    "zoom1": [4.0],
    "translation2": [40.0, -25.0],
    "rotation3": [0.8, -1.2, 2.0],
    "se2": [30.0, -20.0, 3.0],
    "sim2": [30.0, -20.0, 3.0, 2.5],
    "mitrokhin4": [30.0, -20.0, 3.0, 2.0],
}
#: per parameter kind (WarpModel.parameter_kinds), a value that moves pixels by a few px over DURATION
_MODERATE = {"velocity": 40.0, "rate": 3.0, "focal": 1.0, None: 1.0}


def moderate_theta(model: cm.WarpModel) -> list[float]:
    """A moderate parameter vector from the model's declared parameter kinds (alternating signs)."""
    kinds = model.parameter_kinds or (None,) * model.n_params
    return [_MODERATE[k] * (-1.0) ** i for i, k in enumerate(kinds)]


#: every warp model of the registry (its built-ins) with a moderate parameter vector: the tests that
#: run "on every model" iterate over this, so a newly registered built-in is tested without an edit here
THETAS = {name: _CHOSEN_THETAS.get(name) or moderate_theta(cm.get_warp(name)) for name in cm.warp_names()}


@pytest.fixture
def cache_in_tmp(tmp_path_factory, monkeypatch):
    """Point the reader cache (``CMAX_TAICHI_CACHE``) at a fresh folder (never the user's home); the I/O test
    modules use it for every test through ``pytestmark = pytest.mark.usefixtures("cache_in_tmp")``."""
    monkeypatch.setenv("CMAX_TAICHI_CACHE", str(tmp_path_factory.mktemp("cache")))


def use_precision(precision: str) -> None:
    """Switch the backend to ``precision`` on the CPU if it is not already."""
    if cm.backend_info().precision != precision:
        cm.init(precision=precision)


def edge_events(n: int = 400, seed: int = 0, sensor=SENSOR, duration: float = DURATION):
    """Events on a few straight edges (plus 10% noise), times uniform over ``duration``."""
    rng = np.random.default_rng(seed)
    W, H = sensor
    n_edge = int(0.9 * n)
    starts = rng.uniform([8, 6], [W - 8, H - 6], size=(5, 2))
    angles = rng.uniform(0, np.pi, size=5)
    which = rng.integers(0, 5, size=n_edge)
    s = rng.uniform(-10, 10, size=n_edge)
    x = starts[which, 0] + s * np.cos(angles[which]) + rng.normal(0, 0.3, n_edge)
    y = starts[which, 1] + s * np.sin(angles[which]) + rng.normal(0, 0.3, n_edge)
    x = np.concatenate([x, rng.uniform(0, W - 1, n - n_edge)])
    y = np.concatenate([y, rng.uniform(0, H - 1, n - n_edge)])
    x = np.clip(x, 0, W - 1)
    y = np.clip(y, 0, H - 1)
    t = np.sort(rng.uniform(0, duration, n))
    t[0], t[-1] = 0.0, duration
    p = rng.integers(0, 2, n)
    return x, y, t, p


@pytest.fixture
def f64():
    use_precision("f64")


@pytest.fixture
def f32():
    use_precision("f32")


def shared_data_dir(*parts: str) -> Path:
    """Path inside ../shared/data, or skip the test with a clear message when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real-data folder {path} is absent (it sits beside the checkout, not in it)")
    return path
