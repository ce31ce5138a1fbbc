"""The limits of ``core/limits.py`` (sensor pixels, bytes, blur sigma, clusters) and a process that survives
every refusal and every failed Taichi allocation: after each failure a normal problem is built and
evaluated, and gives the float64 reference's value."""

from __future__ import annotations

import dataclasses
import os
import time
import warnings

import numpy as np
import pytest
import taichi as ti
from conftest import SENSOR, edge_events

import cmax_taichi as cm
from cmax_taichi.core import backend, limits
from cmax_taichi.pipeline.clusters import MultiClusterCMax
from cmax_taichi.pipeline.footprint import n_slices
from cmax_taichi.testing import reference

THETA = [40.0, -25.0]  # translation2, px/s


@pytest.fixture(autouse=True)
def restore_limits():
    """Every test leaves the process's limits as it found them."""
    previous = cm.get_limits()
    yield
    cm.set_limits(previous)


def _window(sensor=SENSOR, n: int = 300) -> cm.Events:
    """Edge events inside the first 64 x 48 px (or the whole sensor where it is smaller)."""
    x, y, t, p = edge_events(n, sensor=(min(sensor[0], SENSOR[0]), min(sensor[1], SENSOR[1])))
    return cm.Events(x, y, t, p, sensor)


def assert_session_usable() -> None:
    """A normal problem builds and evaluates to the reference's J."""
    x, y, t, p = edge_events(300)
    prob = cm.ContrastMaximization(cm.Events(x, y, t, p, SENSOR), "translation2")
    expected = reference.evaluate(x, y, t, p, THETA, warp="translation2", sensor_size=SENSOR)["J"]
    assert prob.value(THETA) == pytest.approx(expected, rel=1e-5)
    assert not backend.is_broken()


# --- the limits themselves -------------------------------------------------------------------------------
def test_set_limits_returns_previous_and_validates():
    before = cm.get_limits()
    previous = cm.set_limits(max_clusters=3, max_blur_sigma=2.5)
    assert previous == before
    assert cm.get_limits().max_clusters == 3 and cm.get_limits().max_blur_sigma == 2.5
    assert cm.get_limits().max_bytes == before.max_bytes
    cm.set_limits(previous)
    assert cm.get_limits() == before
    with pytest.raises(ValueError, match="max_clusters"):
        cm.set_limits(max_clusters=0)
    with pytest.raises(ValueError, match="max_clusters .* whole number"):
        cm.set_limits(max_clusters=2.5)
    with pytest.raises(ValueError, match="max_bytes"):
        cm.set_limits(max_bytes=float("nan"))
    with pytest.raises(TypeError, match="max_blur_sigma"):
        cm.set_limits(max_blur_sigma="big")
    with pytest.raises(TypeError, match="unknown limit.*max_pixels"):
        cm.set_limits(max_pixels=10)
    with pytest.raises(TypeError, match="cmax_taichi.Limits"):
        cm.set_limits({"max_clusters": 3})
    assert cm.get_limits() == before  # a refused change changes nothing


def test_limits_from_the_environment(monkeypatch):
    monkeypatch.setattr(limits, "_current", None)
    monkeypatch.setenv("CMAX_TAICHI_MAX_CLUSTERS", "3")
    monkeypatch.setenv("CMAX_TAICHI_MAX_BLUR_SIGMA", "1.5")
    got = cm.get_limits()
    assert got.max_clusters == 3 and got.max_blur_sigma == 1.5
    assert got.max_sensor_pixels == limits.DEFAULTS.max_sensor_pixels
    monkeypatch.setattr(limits, "_current", None)
    monkeypatch.setenv("CMAX_TAICHI_MAX_BYTES", "lots")
    with pytest.raises(ValueError, match="CMAX_TAICHI_MAX_BYTES"):
        cm.get_limits()
    for bad in ("-1", "inf", "nan"):
        monkeypatch.setattr(limits, "_current", None)
        monkeypatch.setenv("CMAX_TAICHI_MAX_BYTES", bad)
        with pytest.raises(ValueError, match="max_bytes"):
            cm.get_limits()


def test_default_limits_are_documented_values():
    d = dataclasses.asdict(limits.DEFAULTS)
    assert d["max_sensor_pixels"] == 4096 * 4096
    assert d["max_bytes"] == os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2  # half the RAM
    assert set(d) == set(limits.ENV_VARS)


def test_estimate_bounds_what_the_fused_pipeline_allocates():
    prob = cm.ContrastMaximization(_window(), "translation2")
    if prob._fused is None:
        pytest.skip(f"the fused pipeline does not serve this problem here: {prob.path_reason}")
    itemsize = np.dtype(backend.numpy_real()).itemsize
    estimate = limits.problem_bytes(*SENSOR, 1, 0, prob.n_events, itemsize, n_slices())
    allocated = prob._fused.nbytes()
    assert allocated <= estimate <= 10 * allocated


# --- refusals before allocating ------------------------------------------------------------------------
def test_sensor_above_the_limit_is_refused_before_allocating():
    huge = _window(sensor=(100_000, 100_000))
    for build in (
        lambda: cm.ContrastMaximization(huge, "translation2"),
        lambda: MultiClusterCMax(huge, 2, "translation2"),
        lambda: cm.segment(huge, n_clusters=2, warp="translation2"),
    ):
        with pytest.raises(ValueError, match=r"sensor_size \(100000, 100000\).*max_sensor_pixels"):
            build()
        assert_session_usable()


def test_bytes_above_the_limit_raise_memory_error():
    cm.set_limits(max_bytes=10**6)
    big = _window(sensor=(1000, 1000))
    with pytest.raises(MemoryError, match=r"sensor 1000x1000.*max_bytes = "):
        cm.ContrastMaximization(big, "translation2")
    with pytest.raises(MemoryError, match=r"n_clusters = 3.*max_bytes = "):
        MultiClusterCMax(big, 3, "translation2")
    cm.set_limits(max_bytes=10**8)
    assert_session_usable()


@pytest.mark.parametrize("factor", [4, 1e9])  # 1e9: the taps alone would take tens of GB
def test_blur_sigma_above_the_limit_is_refused_at_once(factor):
    window = _window()
    sigma = factor * cm.get_limits().max_blur_sigma
    for build in (
        lambda: cm.ContrastMaximization(window, "translation2", blur_sigma=sigma),
        lambda: MultiClusterCMax(window, 2, "translation2", blur_sigma=sigma),
        lambda: cm.segment(window, n_clusters=2, warp="translation2", blur_sigma=sigma),
        lambda: cm.warmup("translation2", blur_sigma=sigma),
    ):
        start = time.perf_counter()
        with pytest.raises(ValueError, match=r"blur_sigma = .* max_blur_sigma"):
            build()
        assert time.perf_counter() - start < 5.0  # nothing compiled
        assert_session_usable()


def test_warmup_refuses_a_sensor_above_the_limit_before_compiling():
    with pytest.raises(ValueError, match="max_sensor_pixels = .* of this warmup"):
        cm.warmup("translation2", sensor_size=(10**6, 10**6))


def test_warmup_refuses_a_blur_that_is_not_a_number():
    with pytest.raises(ValueError, match="blur_sigma must be a finite number >= 0, got nan"):
        cm.warmup("translation2", blur_sigma=float("nan"))


def test_n_clusters_above_the_limit_is_refused_at_once():
    window = _window()
    K = cm.get_limits().max_clusters + 1
    for build in (
        lambda: MultiClusterCMax(window, K, "translation2"),
        lambda: cm.segment(window, n_clusters=K, warp="translation2"),
        lambda: cm.segment(window, n_clusters=100, warp="translation2"),
    ):
        start = time.perf_counter()
        with pytest.raises(ValueError, match=r"n_clusters = \d+ is above the limit max_clusters"):
            build()
        assert time.perf_counter() - start < 5.0
        assert_session_usable()


def test_dense_flow_sensor_is_checked():
    with pytest.raises(ValueError, match=r"sensor_size must be positive.*\(0, 0\)"):
        cm.dense_flow("translation2", THETA, (0, 0))
    assert_session_usable()
    with pytest.raises(ValueError, match="max_sensor_pixels"):
        cm.dense_flow("translation2", THETA, (100_000, 100_000))
    with pytest.raises(TypeError, match="sensor_size W"):
        cm.dense_flow("translation2", THETA, ("64", 48))
    cm.set_limits(max_bytes=1000)
    with pytest.raises(MemoryError, match=r"dense flow.*sensor 64x48.*max_bytes"):
        cm.dense_flow("translation2", THETA, SENSOR)
    cm.set_limits(max_bytes=10**8)
    flow = cm.dense_flow("translation2", THETA, SENSOR)
    assert flow.shape == (2, SENSOR[1], SENSOR[0]) and np.all(np.isfinite(flow))
    assert_session_usable()


def test_command_line_reports_a_limit_in_one_line(tmp_path, capsys):
    from cmax_taichi.cli import main

    x, y, t, p = edge_events(500)
    path = tmp_path / "events.txt"
    np.savetxt(path, np.c_[t, np.round(x), np.round(y), p], fmt=["%.6f", "%d", "%d", "%d"])
    cm.set_limits(max_bytes=1000)
    args = ["estimate", str(path), "--window", "250", "--warp", "translation2", "--quiet"]
    assert main(args + ["--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "error:" in err and "max_bytes" in err and "Traceback" not in err
    cm.set_limits(max_bytes=10**8, max_clusters=8)
    assert main(["segment", str(path), "-k", "9", "--out", str(tmp_path / "seg")]) == 2
    err = capsys.readouterr().err
    assert "n_clusters = 9 is above the limit max_clusters = 8" in err and "Traceback" not in err
    assert_session_usable()


# --- a Taichi allocation that fails all the same ------------------------------------------------------
def _fail_next_materialize(monkeypatch):
    """Make the next allocation of fields (not a launch with none pending) fail as a failed
    virtual-memory allocation does: the field builder is left finalized (every later field then
    failed with "FieldsBuilder finalized")."""
    runtime_type = type(ti.lang.impl.get_runtime())
    original = runtime_type.materialize
    calls = []

    def failing(self):
        pending = ti.lang.impl._root_fb
        # only an allocation fails: a kernel launch materializes too, with nothing to allocate
        if calls or pending.finalized or (self.materialized and pending.empty):
            return original(self)
        calls.append(1)
        pending.finalized = True
        raise RuntimeError("[host_memory_pool.cpp:allocate_raw_memory@62] Virtual memory allocation failed.")

    monkeypatch.setattr(runtime_type, "materialize", failing)


def test_failed_allocation_leaves_the_session_usable(monkeypatch):
    old = cm.ContrastMaximization(_window(), "translation2")
    generation = cm.backend_info().generation
    new = cm.ContrastMaximization(_window(sensor=(37, 29)), "translation2")  # host arrays, no field
    _fail_next_materialize(monkeypatch)
    reason = r"Taichi could not allocate.*37x29.*Virtual memory.*re-initialised"
    with pytest.raises(MemoryError, match=reason):
        new.maps(THETA)  # the maps are Taichi fields
    info = cm.backend_info()
    assert info.generation == generation + 1 and info.precision in ("f32", "f64")
    with pytest.raises(RuntimeError, match="after a failed allocation.*build it again"):
        old.value(THETA)
    assert_session_usable()


@pytest.mark.parametrize("what", ["maps", "clusters"])
def test_failed_allocation_elsewhere_leaves_the_session_usable(monkeypatch, what):
    prob = cm.ContrastMaximization(_window(sensor=(41, 31)), "translation2")
    _fail_next_materialize(monkeypatch)
    with pytest.raises(MemoryError, match="Taichi could not allocate"):
        if what == "maps":
            prob.maps(THETA)
        else:
            MultiClusterCMax(_window(sensor=(45, 35)), 2, "translation2")
    assert_session_usable()


def test_dense_flow_allocates_no_field(monkeypatch):
    """``cm.dense_flow`` writes into a NumPy array (no Taichi field): an allocation of fields that would
    fail does not touch it, and still fails, and is repaired, at the next use that makes fields."""
    _fail_next_materialize(monkeypatch)
    flow = cm.dense_flow("translation2", THETA, (43, 33))
    assert flow.shape == (2, 33, 43) and np.isfinite(flow).all()
    with pytest.raises(MemoryError, match="Taichi could not allocate"):
        cm.ContrastMaximization(_window(sensor=(47, 37)), "translation2").maps(THETA)
    assert_session_usable()


@pytest.mark.parametrize("how", ["failed allocation", "ti.reset"])
def test_runtime_broken_outside_the_guard_is_repaired(how):
    """A failure outside cmax-taichi (e.g. the user's own field) or a ``ti.reset()`` left Taichi unable
    to make fields."""
    if how == "ti.reset":
        ti.reset()
    else:
        ti.lang.impl._root_fb.finalized = True
    assert backend.is_broken()
    with pytest.warns(RuntimeWarning, match="re-initialised"):
        assert_session_usable()


def _address_space_refuses(n_bytes: int) -> bool:
    """Whether Linux's default overcommit heuristic refuses one mapping of ``n_bytes`` at once."""
    try:
        with open("/proc/sys/vm/overcommit_memory") as f:
            if f.read().strip() != "0":
                return False
        with open("/proc/meminfo") as f:
            info = {line.split(":")[0]: int(line.split()[1]) * 1024 for line in f}
    except OSError:
        return False
    return n_bytes > 2 * (info["MemTotal"] + info.get("SwapTotal", 0))


@pytest.mark.skipif(
    os.environ.get("CMAX_TAICHI_ARCH", "cpu") != "cpu" or not _address_space_refuses(4 * 10**11),
    reason="needs the CPU backend and a kernel that refuses a 400 GB mapping at once (overcommit mode 0)",
)
def test_real_allocation_failure_leaves_the_session_usable():
    cm.set_limits(max_sensor_pixels=10**11, max_bytes=2**62)
    start = time.perf_counter()
    with pytest.raises(MemoryError, match=r"could not allocate the arrays of a 100000x100000 problem"):
        cm.ContrastMaximization(_window(sensor=(100_000, 100_000)), "translation2")
    assert time.perf_counter() - start < 30.0
    assert_session_usable()


def test_too_many_fields_leave_the_session_usable():
    """K = 100 clusters exceed Taichi's limit on fields per tree (an assertion in Taichi)."""
    cm.set_limits(max_clusters=100)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(MemoryError, match="Taichi could not allocate.*100-cluster"):
            MultiClusterCMax(_window(), 100, "translation2")
    assert_session_usable()
