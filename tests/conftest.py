"""Shared fixtures: backend precision switching, synthetic event windows, the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import cmax_taichi as cm
from cmax_taichi.testing import samples
from cmax_taichi.testing.samples import edge_events  # noqa: F401 - the tests import it from here

#: the real recordings beside the checkout (never copied into the repository)
SHARED_DATA = Path(
    os.environ.get("CMAX_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)

#: examples/: the user extensions that the recipes walk through (a plugin file)
EXAMPLES_DIR = Path(__file__).resolve().parents[1] / "examples"

# the synthetic window of the tests: sensor (px), duration (s), camera (cmax_taichi/testing/samples.py)
SENSOR = samples.SENSOR
DURATION = samples.DURATION
CAMERA = samples.CAMERA

#: every warp model of the registry (its built-ins) with a moderate parameter vector derived from its
#: declarations (a few px of motion over DURATION, unequal non-special magnitudes: never on a
#: regularizer's kink); the tests that run "on every model" iterate over this, so a newly registered
#: built-in is tested without an edit here
THETAS = {name: samples.moderate_theta(name).tolist() for name in cm.warp_names()}


@pytest.fixture
def cache_in_tmp(tmp_path_factory, monkeypatch):
    """Point the reader cache (``CMAX_TAICHI_CACHE``) at a fresh folder (never the user's home); the I/O test
    modules use it for every test through ``pytestmark = pytest.mark.usefixtures("cache_in_tmp")``."""
    monkeypatch.setenv("CMAX_TAICHI_CACHE", str(tmp_path_factory.mktemp("cache")))


def use_precision(precision: str) -> None:
    """Switch the backend to ``precision`` on the CPU if it is not already."""
    if cm.backend_info().precision != precision:
        cm.init(precision=precision)


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
