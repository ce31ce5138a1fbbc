"""Shared fixtures: backend precision switching, synthetic event windows, the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import cmax_taichi as cm
from cmax_taichi.core import backend
from cmax_taichi.testing import samples
from cmax_taichi.testing.samples import edge_events  # noqa: F401 - the tests import it from here

# The suite compiles a few hundred kernel variants (every model x objective x regularizer, both
# precisions, the GPU path): with Taichi's advanced IR optimizations a fused variant takes 10-60 s,
# without them 1-3 s, for the same values and gradients to rounding (docs/performance.md, "Compile
# time"; the autodiff kernels are optimized in both modes). The tests check what the kernels compute,
# so they compile fast; the tests marked ``full_compile`` run the optimized compile that users get by
# default, on a covering set (every model, both objectives, every regularizer, both kernel paths). Set
# CMAX_TAICHI_COMPILE=full to run the whole suite on optimized kernels. The backend reads it when it
# starts (not at import); subprocesses inherit it.
os.environ.setdefault(backend.COMPILE_ENV, "fast")

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


@pytest.fixture(autouse=True)
def _compile_mode_of_the_test(request):
    """A test marked ``full_compile`` runs on the optimized compile (the users' default); the others
    on the compile mode of the suite (CMAX_TAICHI_COMPILE, "fast" unless set). No ``monkeypatch``
    here: it would be set up before, and undone after, the modules' own autouse fixtures."""
    full = request.node.get_closest_marker("full_compile") is not None
    suite_mode = os.environ.get(backend.COMPILE_ENV, "fast")
    wanted = "full" if full else suite_mode
    if full:
        os.environ[backend.COMPILE_ENV] = "full"  # any re-initialisation inside keeps it
    # a backend not started yet starts in the wanted mode from the environment; a running one is
    # re-initialised with its arch and precision (the GPU-path run keeps its GPU)
    if backend.is_initialized():
        info = cm.backend_info()
        if info.compile_mode != wanted:
            cm.init(arch=info.requested_arch, precision=info.precision, compile_mode=wanted)
    try:
        yield
    finally:
        os.environ[backend.COMPILE_ENV] = suite_mode


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
