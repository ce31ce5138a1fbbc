"""The implementations that the benchmark compares, on identical inputs, and their agreement check.

Each :class:`Impl` binds one implementation (this library's fused Taichi kernels, the generic Taichi
kernel chain, the PyTorch autograd twin, the float64 NumPy reference) to one synthetic window of
:func:`make_window`; :func:`check_agreement` holds their values and gradients against each other and
against central differences of the reference before anything is timed.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cmax_taichi.core.events import Camera, Events
from cmax_taichi.pipeline.fused import FusedPipeline
from cmax_taichi.pipeline.problem import ContrastMaximization
from cmax_taichi.testing import reference

__all__ = [
    "THETAS",
    "SENSORS",
    "REGS",
    "TOLERANCES",
    "BenchConfig",
    "Impl",
    "make_window",
    "build_taichi",
    "build_torch",
    "build_numpy",
    "check_agreement",
]

#: the benchmark's parameter vector per warp (a moderate motion, a few px over the window)
THETAS = {
    "translation2": (120.0, -80.0),
    "rotation3": (0.6, -0.4, 1.5),
    "mitrokhin4": (120.0, -80.0, 4.0, 3.0),
}
SENSORS = {"240x180": (240, 180), "346x260": (346, 260), "640x480": (640, 480), "1280x720": (1280, 720)}
REGS = {"none": {}, "div+def": {"divergence": 1.0, "deformation": 1.0}}
DURATION = 0.05  # s, window length
FD_CHECK_MAX_EVENTS = 10_000  # central differences of the reference (2P evaluations) up to this N
FD_STEPS = (1e-7, 1e-8)  # relative steps: the second is tried when a pixel kink spoils the first
TOLERANCES = {  # relative to max(1, |J|) for values, to max |grad| for gradients
    "f64": {"value": 1e-9, "grad": 1e-6, "fd": 1e-4},
    "f32": {"value": 2e-3, "grad": 5e-2, "fd": 5e-2},
}


@dataclass
class BenchConfig:
    """One row group of the sweep."""

    n: int
    sensor_name: str
    warp: str
    regs: str
    precision: str = "f64"
    impls: tuple[str, ...] = ("taichi", "torch", "numpy")
    window: str = "edges"  # lab/bench_windows.py: "textured", "uniform" or "edges"
    stream_events: int | None = None  # textured windows: the length of the sensor's stream (its prefix)

    @property
    def sensor(self) -> tuple[int, int]:
        """``(W, H)`` of a named sensor, or of a ``"WxH"`` name."""
        if self.sensor_name in SENSORS:
            return SENSORS[self.sensor_name]
        w, h = self.sensor_name.lower().split("x")
        return int(w), int(h)


# ----------------------------------------------------------------------------------------------
# inputs
# ----------------------------------------------------------------------------------------------
def camera_for(sensor: tuple[int, int]) -> Camera:
    """A pinhole camera with a ~70 degree horizontal field of view, centred."""
    W, H = sensor
    f = 0.7 * W
    return Camera(fx=f, fy=f, cx=(W - 1) / 2.0, cy=(H - 1) / 2.0)


def make_window(n: int, sensor: tuple[int, int], seed: int = 0):
    """``n`` synthetic events (x, y, t, p) on 40 moving straight edges plus 10 % noise, time-sorted.

    Returns float64 arrays ``x, y`` (px), ``t`` (s, spanning exactly ``DURATION``) and ``p`` in {0, 1}.
    """
    rng = np.random.default_rng(seed)
    W, H = sensor
    n_edge = int(0.9 * n)
    k = 40
    centres = rng.uniform([0.1 * W, 0.1 * H], [0.9 * W, 0.9 * H], size=(k, 2))
    angles = rng.uniform(0, np.pi, k)
    length = 0.15 * min(W, H)
    which = rng.integers(0, k, n_edge)
    s = rng.uniform(-length, length, n_edge)
    t_edge = rng.uniform(0, DURATION, n_edge)
    vel = np.array([100.0, -60.0])  # px/s: the edges move, so the identity warp is blurred
    x = centres[which, 0] + s * np.cos(angles[which]) + vel[0] * t_edge + rng.normal(0, 0.5, n_edge)
    y = centres[which, 1] + s * np.sin(angles[which]) + vel[1] * t_edge + rng.normal(0, 0.5, n_edge)
    n_noise = n - n_edge
    x = np.concatenate([x, rng.uniform(0, W - 1, n_noise)])
    y = np.concatenate([y, rng.uniform(0, H - 1, n_noise)])
    t = np.concatenate([t_edge, rng.uniform(0, DURATION, n_noise)])
    x = np.clip(x, 0, W - 1)
    y = np.clip(y, 0, H - 1)
    order = np.argsort(t, kind="stable")
    x, y, t = x[order], y[order], t[order]
    t[0], t[-1] = 0.0, DURATION
    p = rng.integers(0, 2, n)
    return x, y, t, p


# ----------------------------------------------------------------------------------------------
# implementations
# ----------------------------------------------------------------------------------------------
@dataclass
class Impl:
    """One implementation bound to one window: ``vg(theta)`` and ``value(theta)`` callables."""

    name: str
    vg: Callable | None
    value: Callable
    setup_s: float
    field_bytes: int = 0


def build_taichi(win, cfg, *, fused: bool = True) -> Impl:
    x, y, t, p = win
    FusedPipeline.enabled = fused
    try:
        t0 = time.perf_counter()
        prob = ContrastMaximization(
            Events(x, y, t, p, cfg.sensor),
            warp=cfg.warp,
            regularizers=REGS[cfg.regs],
            camera=camera_for(cfg.sensor),
            blur_sigma=1.0,
        )
        prob.value_and_grad(THETAS[cfg.warp])  # compiles the gradient kernels too
        setup = time.perf_counter() - t0
    finally:
        FusedPipeline.enabled = True
    nbytes = prob._fused.nbytes() if prob._fused is not None else 0
    return Impl("taichi" if fused else "taichi-chain", prob.value_and_grad, prob.value, setup, nbytes)


def build_torch(win, cfg, precision: str) -> Impl:
    import torch

    from cmax_taichi.testing.torch_cmax import TorchCMax

    x, y, t, _ = win
    t0 = time.perf_counter()
    # the twin takes the same problem description as the reference
    dtype = torch.float64 if precision == "f64" else torch.float32
    twin = TorchCMax(x, y, t, **reference_kwargs(cfg), dtype=dtype)
    twin.value_and_grad(THETAS[cfg.warp])
    return Impl("torch", twin.value_and_grad, twin.value, time.perf_counter() - t0)


def reference_kwargs(cfg) -> dict:
    cam = camera_for(cfg.sensor)
    regs = REGS[cfg.regs]
    return dict(
        warp=cfg.warp,
        sensor_size=cfg.sensor,
        center=(cam.cx, cam.cy),
        focal=(cam.fx, cam.fy),
        blur_sigma=1.0,
        lambda_div=regs.get("divergence", 0.0),
        lambda_def=regs.get("deformation", 0.0),
    )


def build_numpy(win, cfg) -> Impl:
    kwargs = reference_kwargs(cfg)

    def value(theta):
        return reference.evaluate(*win, theta, **kwargs)["J"]

    t0 = time.perf_counter()
    value(THETAS[cfg.warp])
    return Impl("numpy", None, value, time.perf_counter() - t0)


def reference_fd_grad(win, cfg, theta, rel_step: float = 1e-7) -> np.ndarray:
    """Central differences of the reference J (2P evaluations).

    The bilinear IWE makes J piecewise smooth in theta: it has a kink wherever an event's warped
    position crosses a pixel boundary. A step of 1e-6 (relative) crossed such kinks at 1e4 events and
    missed the exact gradient by 3e-4 to 1.4e-3 (relative) while Taichi and PyTorch agreed to 1e-15;
    1e-7 agreed to 1e-8. In float64 the rounding error of a 1e-7 step is about 1e-9.
    """
    return reference.central_difference_grad(*win, theta, rel_step=rel_step, **reference_kwargs(cfg))


# ----------------------------------------------------------------------------------------------
# agreement
# ----------------------------------------------------------------------------------------------
def _rel(a, b, scale) -> float:
    return float(np.max(np.abs(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64))) / scale)


def check_agreement(impls: dict[str, Impl], win, cfg, precision: str) -> dict[str, str]:
    """Status of every implementation: "ok", or "DISAGREES: ..." naming what and by how much.

    Values are held against the NumPy reference where it runs (else against PyTorch), gradients
    against each other (Taichi, the chain, PyTorch) and, up to ``FD_CHECK_MAX_EVENTS`` events, against
    central differences of the reference (:func:`reference_fd_grad`). Tolerances: :data:`TOLERANCES`.
    """
    tol = TOLERANCES[precision]
    theta = np.asarray(THETAS[cfg.warp], dtype=np.float64)
    values, grads = {}, {}
    for name, impl in impls.items():
        if impl.vg is not None:
            values[name], grads[name] = impl.vg(theta)
        else:
            values[name] = impl.value(theta)
    status = {name: "ok" for name in impls}
    # values: against the reference when it runs, else against torch, else taichi
    anchor = "numpy" if "numpy" in values else ("torch" if "torch" in values else "taichi")
    # a float32 implementation is checked against the float64 reference with the f32 tolerance
    v_ref = values[anchor]
    for name, v in values.items():
        err = abs(v - v_ref) / max(1.0, abs(v_ref))
        if not (math.isfinite(v) and err <= tol["value"]):
            status[name] = f"DISAGREES: J = {v:.12g} vs {anchor} {v_ref:.12g} (rel {err:.1e})"
    # gradients: the exact derivatives against each other (PyTorch's autograd is the anchor), then
    # against central differences of the reference (a second, smaller step when a kink spoils the first)
    exact = grads.get("torch", grads.get("taichi"))
    anchor_name = "torch" if "torch" in grads else "taichi"
    if exact is not None:
        scale = max(float(np.max(np.abs(exact))), 1e-300)
        for name, g in grads.items():
            err = _rel(g, exact, scale)
            if not (np.all(np.isfinite(g)) and err <= tol["grad"]) and status[name] == "ok":
                status[name] = f"DISAGREES: gradient vs {anchor_name} (rel {err:.1e})"
    if cfg.n <= FD_CHECK_MAX_EVENTS and grads:
        fds: dict[float, np.ndarray] = {}  # computed on first use, shared by the implementations
        for name, g in grads.items():
            if status[name] != "ok":
                continue
            errs = []
            for step in FD_STEPS:
                if step not in fds:
                    fds[step] = reference_fd_grad(win, cfg, theta, rel_step=step)
                scale = max(float(np.max(np.abs(fds[step]))), 1e-300)
                errs.append(_rel(g, fds[step], scale))
                if np.all(np.isfinite(g)) and errs[-1] <= tol["fd"]:
                    break
            else:
                status[name] = (
                    f"DISAGREES: gradient vs finite differences of the reference (rel {min(errs):.1e})"
                )
    return status
