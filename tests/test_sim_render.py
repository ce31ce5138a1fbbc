"""The simulator's render kernel against an independent float64 NumPy renderer: the painter's order
of 2-D scenes and the depth test of 3-D planes (mirror tiling, finite textures with their edge ramp,
occlusion), on the CPU in float64 and, with ``CMAX_TAICHI_ARCH`` set to a GPU arch (Vulkan through
lavapipe in CI), on the GPU path in float32:

    CMAX_TAICHI_ARCH=vulkan CMAX_TAICHI_PRECISION=f32 python -m pytest -q -n 0 tests/test_sim_render.py
"""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest

import cmax_taichi as cm
from cmax_taichi import sim as sm
from cmax_taichi.core import backend
from cmax_taichi.sim.depth import plane_layer
from cmax_taichi.sim.rigid import RigidMotion

GPU_ARCHS = ("vulkan", "cuda", "metal", "gpu")
REQUESTED = os.environ.get(backend.ARCH_ENV, "").strip().lower()


def _sample(tex, u, v):
    ny, nx = tex.shape
    i0 = np.clip(np.floor(u).astype(int), 0, nx - 2)
    j0 = np.clip(np.floor(v).astype(int), 0, ny - 2)
    a, b = u - i0, v - j0
    return (
        (1 - a) * (1 - b) * tex[j0, i0]
        + a * (1 - b) * tex[j0, i0 + 1]
        + (1 - a) * b * tex[j0 + 1, i0]
        + a * b * tex[j0 + 1, i0 + 1]
    )


def _mirror(u, n):
    period = 2.0 * (n - 1)
    w = u - period * np.floor(u / period)
    return np.where(w > n - 1, period - w, w)


def reference_render(sim: sm.Simulator, t: float, label_cover: float = 0.5):
    """``(log(I + eps), label)`` of ``sim``'s scene at ``t``, float64 NumPy."""
    scene = sim.scene
    W, H = scene.sensor_size
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    pts = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)])
    covers, colors, inv_depth = [], [], []
    for k, layer in enumerate(scene.layers):
        X = np.linalg.inv(sim.layer_matrix(k, t)) @ pts
        h, w = layer.texture.shape
        front = X[2] > 1e-9
        z = np.where(front, X[2], 1.0)
        u, v = X[0] / z, X[1] / z
        if layer.wrap == "mirror":
            u, v = _mirror(u, w), _mirror(v, h)
            inside = front
        else:
            inside = front & (u >= 0) & (v >= 0) & (u <= w - 1) & (v <= h - 1)
        u, v = np.where(inside, u, 0.0), np.where(inside, v, 0.0)
        color = np.where(inside, _sample(layer.texture, u, v), 0.0)
        alpha = np.ones_like(u) if layer.alpha is None else _sample(layer.alpha, u, v)
        covers.append(np.where(inside, alpha, 0.0))
        colors.append(color)
        inv_depth.append(X[2])
    L = len(scene.layers)
    value = np.zeros(xx.size)
    if scene.has_depth:
        label = np.full(xx.size, -1)
        nearest = np.zeros(xx.size)
        for k in range(L):
            through = np.ones(xx.size)
            for m in range(L):
                if m != k:
                    in_front = (inv_depth[m] > inv_depth[k]) | ((inv_depth[m] == inv_depth[k]) & (m > k))
                    through *= np.where(in_front, 1.0 - covers[m], 1.0)
            value += covers[k] * colors[k] * through
            better = (covers[k] > label_cover) & (inv_depth[k] > nearest)
            nearest = np.where(better, inv_depth[k], nearest)
            label = np.where(better, k, label)
    else:
        label = np.zeros(xx.size, dtype=int)
        for k in range(L):
            value = covers[k] * colors[k] + (1 - covers[k]) * value
            label = np.where(covers[k] > 0.5, k, label)
    log = np.log(value + sim.config.log_eps)
    return log.reshape(H, W), label.reshape(H, W)


def _depth_scene() -> sm.Scene:
    """An infinite tilted plane behind a finite one that turns, listed near-first (the depth test, not
    the order, must put it in front), and a third finite plane partly behind the second."""
    cam = sm.default_camera((96, 72))
    m = RigidMotion((0.4, -0.1, 0.2), (0.05, 0.1, -0.2))
    tex = sm.load_texture("mri")[::4, ::4]
    near = plane_layer(
        tex,
        cam,
        centre=(0.1, 0.05, 1.2),
        normal=(0.2, 0.1, 1.0),
        camera_motion=m,
        surface_motion=RigidMotion((0.0, 0.1, 0.0), (0.0, 0.0, 1.5), pivot=(0.1, 0.05, 1.2)),
        finite=True,
    )
    far = plane_layer(
        sm.load_texture("dem")[::3, ::3], cam, centre=(0, 0, 4.0), normal=(0.3, 0, 1), camera_motion=m
    )
    mid = plane_layer(tex[::2, ::2], cam, centre=(-0.3, 0.0, 2.0), camera_motion=m, finite=True)
    return sm.Scene((96, 72), [near, far, mid], camera=cam)


def _two_d_scene() -> sm.Scene:
    return sm.multi_object_scene((96, 72), n_objects=2, seed=3)


def _check(sim: sm.Simulator, tol: float) -> None:
    """Intensities ``exp(log)`` within ``tol`` (the log's slope 1 / (I + eps) would magnify float32
    rounding in the darkest pixels a thousandfold)."""
    for t in (0.0, 0.05, 0.1):
        log, label = sim.render(t)
        ref_log, ref_label = reference_render(sim, t)
        np.testing.assert_allclose(np.exp(log), np.exp(ref_log), atol=tol, rtol=0)
        # labels may differ only where a coverage sits at the threshold within the tolerance
        assert np.mean(label != ref_label) < 0.002


@pytest.mark.parametrize("make", [_depth_scene, _two_d_scene], ids=["depth", "painter"])
def test_render_kernel_against_numpy_f64(make, f64):
    sim = sm.Simulator(make(), sm.SimulatorConfig())
    assert sim.depth_test == make().has_depth
    _check(sim, 1e-12)


@pytest.mark.gpu
@pytest.mark.skipif(REQUESTED not in GPU_ARCHS, reason=f"runs with {backend.ARCH_ENV} set to a GPU arch")
@pytest.mark.parametrize("make", [_depth_scene, _two_d_scene], ids=["depth", "painter"])
def test_render_kernel_on_the_gpu_path_f32(make):
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        info = cm.init(arch=REQUESTED, precision="f32")
    if info.arch == "cpu":
        if os.environ.get("CMAX_TAICHI_REQUIRE_GPU", "") not in ("", "0"):
            pytest.fail(f"{backend.ARCH_ENV}={REQUESTED} fell back to the CPU", pytrace=False)
        pytest.skip(f"{backend.ARCH_ENV}={REQUESTED} fell back to the CPU")
    sim = sm.Simulator(make(), sm.SimulatorConfig(noise_rate=0.0))
    _check(sim, 5e-5)  # float32 homographies, texel coordinates and samples
    rec = sim.run(0.02)
    assert len(rec) > 500
