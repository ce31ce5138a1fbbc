"""The event simulator (ESIM-like; Taichi kernels in ``kernels/simulator.py``).

The :class:`Simulator` renders the log intensity ``log(I + log_eps)`` of every pixel at an adaptive rate
(each step moves no point by more than ``step_px`` pixels and changes no pixel's log intensity by more
than ``step_log_change * C``; the change is measured and the step retried when too large), and emits an
event each time a pixel's log intensity crosses its reference plus or minus its own contrast threshold,
with the timestamp interpolated linearly between the renders. Sensor effects: per-pixel threshold
mismatch, refractory period, background-activity noise, hot pixels. All randomness comes from one NumPy
generator seeded by ``SimulatorConfig.seed``.
"""

from __future__ import annotations

import math
import sys
import time
import warnings
import weakref
from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np
import taichi as ti

from cmax_taichi.core import backend, workspace
from cmax_taichi.kernels import simulator as ksim
from cmax_taichi.sim.recording import SimulatedRecording
from cmax_taichi.sim.rigid import PlaneMotion
from cmax_taichi.sim.scenes import PRESETS, Scene, preset_scene

__all__ = ["SimulatorConfig", "Simulator", "simulate", "simulate_preset"]


@dataclass(frozen=True)
class SimulatorConfig:
    """Sensor model and rendering settings.

    Parameters
    ----------
    contrast_threshold : float
        C of positive events (log-intensity units).
    contrast_threshold_neg : float, optional
        C of negative events (default: the same).
    threshold_sigma : float
        Per-pixel mismatch: each pixel's thresholds are ``C (1 + sigma n)``, ``n ~ N(0, 1)``, clipped to
        at least ``0.25 C`` (relative, unitless).
    refractory : float
        Seconds a pixel stays blind after an event (its reference still follows the crossings).
    noise_rate : float
        Background-activity noise events per pixel per second (Hz), random polarity, label -1.
    hot_pixel_fraction : float
        Fraction of pixels that are hot (fire at ``hot_pixel_rate`` regardless of the scene).
    hot_pixel_rate : float
        Events per second of a hot pixel (Hz).
    log_eps : float
        Offset of the log: the sensor reports changes of ``log(I + log_eps)``, I linear in [0, 1].
    step_px : float
        Largest image motion of any point between two renders, px.
    step_log_change : float
        Largest change of any pixel's log intensity between two renders, in units of C (the step is
        retried with a shorter interval when exceeded).
    min_step, max_step : float
        Bounds of the render interval, seconds.
    seed : int
        Seed of every random draw (mismatch, noise, hot pixels).
    capacity : int, optional
        Event buffer size (default ``max(2**20, 4 W H)``); it is flushed to the host when full.
    """

    contrast_threshold: float = 0.2
    contrast_threshold_neg: float | None = None
    threshold_sigma: float = 0.03
    refractory: float = 1e-4
    noise_rate: float = 0.1
    hot_pixel_fraction: float = 0.0
    hot_pixel_rate: float = 50.0
    log_eps: float = 1e-3
    step_px: float = 0.5
    step_log_change: float = 4.0
    min_step: float = 1e-6
    max_step: float = 2e-3
    seed: int = 0
    capacity: int | None = None

    def __post_init__(self) -> None:
        def positive(name, value):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")

        def non_negative(name, value):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")

        positive("contrast_threshold", self.contrast_threshold)
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"seed must be a whole number >= 0, got {self.seed!r}")
        if self.contrast_threshold_neg is not None:
            positive("contrast_threshold_neg", self.contrast_threshold_neg)
        for name in ("threshold_sigma", "refractory", "noise_rate", "hot_pixel_rate"):
            non_negative(name, getattr(self, name))
        if self.threshold_sigma > 1.0:
            raise ValueError(f"threshold_sigma is relative to C and must be <= 1, got {self.threshold_sigma}")
        if not (0.0 <= self.hot_pixel_fraction <= 1.0):
            raise ValueError(f"hot_pixel_fraction must be in [0, 1], got {self.hot_pixel_fraction}")
        for name in ("log_eps", "step_px", "step_log_change", "min_step", "max_step"):
            positive(name, getattr(self, name))
        if self.min_step > self.max_step:
            raise ValueError(f"min_step ({self.min_step}) must not exceed max_step ({self.max_step})")
        if self.capacity is not None and int(self.capacity) < 1024:
            raise ValueError(f"capacity must be at least 1024 events, got {self.capacity}")

    @property
    def c_neg(self) -> float:
        return self.contrast_threshold if self.contrast_threshold_neg is None else self.contrast_threshold_neg


_KERNELS: dict = {}
_POOL: dict = {}
backend.on_reset(_KERNELS.clear)
backend.on_reset(_POOL.clear)


def _bucket(n: int) -> int:
    """Texture sizes are padded to multiples of 64 texels so that similar scenes share fields."""
    return 64 * ((int(n) + 63) // 64)


def _pooled(key: tuple, build) -> SimpleNamespace:
    ns = _POOL.get(key)
    if ns is None:
        ns = SimpleNamespace(owner=None)
        # a failed allocation re-initialises the backend and raises MemoryError (core/workspace.py)
        with workspace.allocating(f"the simulator's {key[0]} fields {key[2:]}"):
            build(ns)
        _POOL[key] = ns
    return ns


def _build_scene_fields(ns: SimpleNamespace, n_layers: int, ht: int, wt: int) -> None:
    real = backend.real()
    ns.tex = ti.field(real, shape=(n_layers, ht, wt))
    ns.alpha = ti.field(real, shape=(n_layers, ht, wt))
    ns.tex_shape = ti.Vector.field(2, ti.i32, shape=n_layers)
    ns.hinv = ti.Matrix.field(3, 3, real, shape=n_layers)


def _build_sensor_fields(ns: SimpleNamespace, W: int, H: int, cap: int) -> None:
    real = backend.real()
    for name in ("log_now", "prev", "ref", "cpos", "cneg", "last_t", "scratch_log"):
        setattr(ns, name, ti.field(real, shape=(H, W)))
    for name in ("label_now", "label_prev", "scratch_label"):
        setattr(ns, name, ti.field(ti.i32, shape=(H, W)))
    ns.ev_pix = ti.field(ti.i32, shape=cap)
    ns.ev_frac = ti.field(real, shape=cap)
    ns.ev_pol = ti.field(ti.i8, shape=cap)
    ns.ev_label = ti.field(ti.i8, shape=cap)
    ns.ev_step = ti.field(ti.i32, shape=cap)
    ns.counter = ti.field(ti.i32, shape=())
    ns.total = ti.field(ti.i32, shape=())
    ns.max_change = ti.field(real, shape=())


_NEVER = -1.0e9  # "last event time" of a pixel that has not fired yet, s
_EVENT_LABEL_COVER = 0.02  # coverage from which a surface's edge labels the events of a pixel (depth scenes)


class Simulator:
    """Renders a :class:`Scene` and generates its events (fields allocated once per instance).

    Parameters
    ----------
    scene : Scene
    config : SimulatorConfig, optional
    progress : bool
        Print the progress of long runs on stderr.
    """

    def __init__(self, scene: Scene, config: SimulatorConfig | None = None, progress: bool = False) -> None:
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a Scene, got {type(scene).__name__}")
        config = config or SimulatorConfig()
        if not isinstance(config, SimulatorConfig):
            raise TypeError(f"config must be a SimulatorConfig, got {type(config).__name__}")
        self.scene = scene
        self.config = config
        self.progress = progress
        self._backend = backend.ensure_initialized()
        self.width, self.height = scene.sensor_size
        W, H = self.width, self.height
        L = len(scene.layers)
        rng = np.random.default_rng(config.seed)
        # per-pixel thresholds (mismatch), drawn before anything else so they depend on the seed only
        floor = 0.25
        n_pos = rng.standard_normal((H, W))
        n_neg = rng.standard_normal((H, W))
        self.c_pos = config.contrast_threshold * np.maximum(1.0 + config.threshold_sigma * n_pos, floor)
        self.c_neg = config.c_neg * np.maximum(1.0 + config.threshold_sigma * n_neg, floor)
        self._rng = rng

        ht = _bucket(max(layer.texture.shape[0] for layer in scene.layers))
        wt = _bucket(max(layer.texture.shape[1] for layer in scene.layers))
        tex = np.zeros((L, ht, wt))
        alpha = np.zeros((L, ht, wt))
        shapes = np.zeros((L, 2), dtype=np.int32)
        for k, layer in enumerate(scene.layers):
            h, w = layer.texture.shape
            tex[k, :h, :w] = layer.texture
            alpha[k, :h, :w] = 1.0 if layer.alpha is None else layer.alpha
            shapes[k] = (w, h)
        npr = backend.numpy_real()
        self._host_scene = (tex.astype(npr), alpha.astype(npr), shapes)
        mirror = tuple(layer.wrap == "mirror" for layer in scene.layers)
        opaque = tuple(layer.alpha is None for layer in scene.layers)
        # 3-D planes know their depth: the nearest surface is drawn in front (occlusion by depth)
        self.depth_test = scene.has_depth
        cap = int(config.capacity) if config.capacity is not None else max(2**20, 4 * W * H)
        self.capacity = cap
        gen = self._backend.generation
        # Fields are pooled by shape: kernels take them as templates, so new fields mean new compiles.
        self._sf = _pooled(("scene", gen, L, ht, wt), lambda ns: _build_scene_fields(ns, L, ht, wt))
        self._pf = _pooled(("sensor", gen, W, H, cap), lambda ns: _build_sensor_fields(ns, W, H, cap))
        key = ("render", gen, mirror, opaque, W, H, self.depth_test)
        if key not in _KERNELS:
            _KERNELS[key] = ksim.make_render_kernel(mirror, opaque, W, H, depth_test=self.depth_test)
        self._render_kernel = _KERNELS[key]
        self._placements = [layer.placement for layer in scene.layers]
        self.n_steps = 0

    def _load_scene(self) -> None:
        """Upload this simulator's textures into the pooled scene fields if another one used them."""
        sf = self._sf
        if sf.owner is not None and sf.owner() is self:
            return
        tex, alpha, shapes = self._host_scene
        sf.tex.from_numpy(tex)
        sf.alpha.from_numpy(alpha)
        sf.tex_shape.from_numpy(shapes)
        sf.owner = weakref.ref(self)

    # --- geometry ----------------------------------------------------------------------------------
    def layer_matrix(self, k: int, t: float) -> np.ndarray:
        """Homography texel -> image px of layer ``k`` at time ``t`` (s)."""
        return self.scene.layers[k].motion.matrix(t, self.scene.camera) @ self._placements[k]

    def _max_displacement(self, t0: float, t1: float) -> float:
        """Largest motion (px) between two times of a point of a grid over the image (corners
        included), over all layers: 5x5 points for 2-D motions; for 3-D planes 9x9 points plus the
        corners and centre of a finite layer's texture, only those where the layer is in front of the
        camera (and inside its texture), so that a plane seen edge-on does not stall the simulation."""
        W, H = self.width, self.height
        gx, gy = np.meshgrid(np.linspace(0, W - 1, 5), np.linspace(0, H - 1, 5))
        pts = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)])
        gx, gy = np.meshgrid(np.linspace(0, W - 1, 9), np.linspace(0, H - 1, 9))
        fine = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)])
        worst = 0.0
        cam = self.scene.camera
        for k, layer in enumerate(self.scene.layers):
            D = layer.motion.matrix(t1, cam) @ np.linalg.inv(layer.motion.matrix(t0, cam))
            if isinstance(layer.motion, PlaneMotion):
                sample = self._visible_points(k, t0, fine)
                if sample.shape[1] == 0:
                    continue
            else:
                sample = pts
            q = D @ sample
            q = q[:2] / q[2]
            worst = max(worst, float(np.max(np.hypot(q[0] - sample[0], q[1] - sample[1]))))
        return worst

    def _visible_points(self, k: int, t: float, grid: np.ndarray) -> np.ndarray:
        """The points of ``grid`` (3, N homogeneous px) where layer ``k`` (a 3-D plane) is in front of
        the camera at time ``t`` and inside its texture, plus the projections of a finite texture's
        corners and centre that are in front of the camera."""
        layer = self.scene.layers[k]
        L = self.layer_matrix(k, t)
        h, w = layer.texture.shape
        if layer.wrap != "mirror":
            corners = np.array([[0.0, w - 1, 0.0, w - 1, (w - 1) / 2], [0.0, 0.0, h - 1, h - 1, (h - 1) / 2]])
            q = L @ np.vstack([corners, np.ones(5)])
            front = q[2] > 1e-12
            extra = q[:, front] / q[2, front]
            grid = np.hstack([grid, extra])
        X = np.linalg.solve(L, grid)  # texel coordinates / depth
        keep = X[2] > 1e-12
        if layer.wrap != "mirror":
            u, v = X[0] / np.where(keep, X[2], 1.0), X[1] / np.where(keep, X[2], 1.0)
            tol = 1e-6  # the corners themselves
            keep &= (u >= -tol) & (v >= -tol) & (u <= w - 1 + tol) & (v <= h - 1 + tol)
        return grid[:, keep]

    def _render(self, t: float, out_log, out_label, label_cover: float = _EVENT_LABEL_COVER) -> None:
        """Render at ``t`` s. Depth scenes label the pixels of the simulation's renders (whose labels go
        to the events) by the nearest surface with any coverage ``> label_cover``, so that the events
        of a surface's anti-aliased edge carry that surface's label; the ground-truth maps
        (:meth:`render`) take coverage > 0.5."""
        self._load_scene()
        sf = self._sf
        hinv = np.stack([np.linalg.inv(self.layer_matrix(k, t)) for k in range(len(self.scene.layers))])
        sf.hinv.from_numpy(hinv.astype(backend.numpy_real()))
        self._render_kernel(
            sf.tex,
            sf.alpha,
            sf.tex_shape,
            sf.hinv,
            float(self.config.log_eps),
            float(label_cover),
            out_log,
            out_label,
        )

    def render(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The log intensity ``log(I + log_eps)`` (H, W) and the label map (index of the front-most
        layer per pixel) at time ``t`` seconds. Does not disturb a running simulation."""
        self._check_alive()
        pf = self._pf
        self._render(float(t), pf.scratch_log, pf.scratch_label, label_cover=0.5)
        return pf.scratch_log.to_numpy().astype(np.float64), pf.scratch_label.to_numpy().astype(np.int16)

    def _check_alive(self) -> None:
        if backend.info().generation != self._backend.generation:
            raise RuntimeError("Taichi was re-initialised (cm.init) after this Simulator was built")

    # --- event generation ------------------------------------------------------------------------
    def run(self, duration: float, t_start: float = 0.0) -> SimulatedRecording:
        """Simulate ``[t_start, t_start + duration]`` seconds and return the events with their ground
        truth. The sensor starts at rest at ``t_start`` (reference = the first render)."""
        self._check_alive()
        cfg = self.config
        duration = float(duration)
        t_start = float(t_start)
        if not (math.isfinite(duration) and duration > 0):
            raise ValueError(f"duration must be a positive number of seconds, got {duration}")
        if not (math.isfinite(t_start) and t_start >= 0):
            raise ValueError(f"t_start must be >= 0 s, got {t_start}")
        t_end = t_start + duration
        for layer in self.scene.layers:
            layer.motion.check(t_end)
        c_min = float(min(self.c_pos.min(), self.c_neg.min()))
        max_change = cfg.step_log_change * c_min
        pf = self._pf
        npr = backend.numpy_real()
        pf.cpos.from_numpy(self.c_pos.astype(npr))
        pf.cneg.from_numpy(self.c_neg.astype(npr))
        pf.last_t.fill(_NEVER)
        self._render(t_start, pf.log_now, pf.label_now)
        ksim.reset_state(pf.log_now, pf.label_now, pf.prev, pf.label_prev, pf.ref, pf.last_t, _NEVER)
        pf.counter[None] = 0
        chunks: list[tuple] = []
        step_t0: list[float] = []
        step_dt: list[float] = []
        t = t_start
        dt = min(cfg.max_step, duration)
        last_print = time.monotonic()
        wall0 = last_print
        while t < t_end - 1e-12:
            dt = min(dt, cfg.max_step, t_end - t)
            # shrink until no point moves more than step_px
            for _ in range(60):
                disp = self._max_displacement(t, t + dt)
                if disp <= cfg.step_px or dt <= cfg.min_step:
                    break
                dt = max(cfg.min_step, dt * 0.9 * cfg.step_px / disp)
            # render; shrink until no pixel changes more than step_log_change * C and the events fit
            for _ in range(60):
                self._render(t + dt, pf.log_now, pf.label_now)
                pf.total[None] = 0
                pf.max_change[None] = 0.0
                ksim.count_crossings(
                    pf.log_now,
                    pf.ref,
                    pf.prev,
                    pf.cpos,
                    pf.cneg,
                    pf.total,
                    pf.max_change,
                    pf.label_now,
                    pf.label_prev,
                    int(self.depth_test),
                )
                change = float(pf.max_change[None])
                n_new = int(pf.total[None])
                too_big = change > max_change or n_new > self.capacity // 2
                if not too_big or dt <= cfg.min_step:
                    break
                factor = 0.9 * max_change / change if change > max_change else 0.5
                dt = max(cfg.min_step, dt * min(factor, 0.9))
            if n_new > self.capacity:
                raise RuntimeError(
                    f"{n_new} events in one render step of {dt:.2e} s exceed the buffer of "
                    f"{self.capacity}: raise SimulatorConfig.capacity or lower min_step"
                )
            if int(pf.counter[None]) + n_new > self.capacity:
                chunks.append(self._flush())
            step = len(step_t0)
            step_t0.append(t)
            step_dt.append(dt)
            ksim.emit(
                pf.log_now,
                pf.label_now,
                pf.prev,
                pf.label_prev,
                pf.ref,
                pf.cpos,
                pf.cneg,
                pf.last_t,
                t,
                t + dt,
                float(cfg.refractory),
                step,
                pf.ev_pix,
                pf.ev_frac,
                pf.ev_pol,
                pf.ev_label,
                pf.ev_step,
                pf.counter,
                self.capacity,
            )
            t = t + dt if t + dt < t_end - 1e-12 else t_end
            # grow the next step gently (the displacement and change checks shrink it again)
            dt = dt * 1.5
            if self.progress and time.monotonic() - last_print > 2.0:
                last_print = time.monotonic()
                frac = (t - t_start) / duration
                print(
                    f"  simulate {self.scene.name}: {100 * frac:5.1f}% ({len(step_t0)} renders, "
                    f"{time.monotonic() - wall0:.0f} s)",
                    file=sys.stderr,
                    flush=True,
                )
        chunks.append(self._flush())
        self.n_steps = len(step_t0)
        pix = np.concatenate([c[0] for c in chunks])
        frac = np.concatenate([c[1] for c in chunks])
        pol = np.concatenate([c[2] for c in chunks])
        lab = np.concatenate([c[3] for c in chunks])
        stp = np.concatenate([c[4] for c in chunks])
        t0s = np.asarray(step_t0, dtype=np.float64)
        dts = np.asarray(step_dt, dtype=np.float64)
        ts = t0s[stp] + frac.astype(np.float64) * dts[stp]
        xs = (pix % self.width).astype(np.float64)
        ys = (pix // self.width).astype(np.float64)
        ps = pol.astype(np.int8)
        labels = lab.astype(np.int16)
        # background activity and hot pixels (label -1)
        nx, ny, nt, npol = self._noise_events(t_start, t_end)
        xs = np.concatenate([xs, nx])
        ys = np.concatenate([ys, ny])
        ts = np.concatenate([ts, nt])
        ps = np.concatenate([ps, npol])
        labels = np.concatenate([labels, np.full(len(nt), -1, dtype=np.int16)])
        # a deterministic order: the buffer order depends on thread scheduling
        order = np.lexsort((ps, xs, ys, ts))
        return SimulatedRecording(
            x=xs[order],
            y=ys[order],
            t=ts[order],
            p=ps[order],
            labels=labels[order],
            t_start=t_start,
            t_end=t_end,
            sensor_size=(self.width, self.height),
            camera=self.scene.camera,
            simulator=self,
            n_steps=self.n_steps,
        )

    def _flush(self) -> tuple:
        pf = self._pf
        n = min(int(pf.counter[None]), self.capacity)
        out = (
            pf.ev_pix.to_numpy()[:n],
            pf.ev_frac.to_numpy()[:n],
            pf.ev_pol.to_numpy()[:n],
            pf.ev_label.to_numpy()[:n],
            pf.ev_step.to_numpy()[:n],
        )
        pf.counter[None] = 0
        return out

    def _noise_events(self, t0: float, t1: float):
        """Background activity (Poisson per pixel, ``noise_rate``) and hot pixels, NumPy."""
        cfg = self.config
        rng = self._rng
        W, H = self.width, self.height
        T = t1 - t0
        n = int(rng.poisson(cfg.noise_rate * W * H * T)) if cfg.noise_rate > 0 else 0
        x = rng.integers(0, W, n).astype(np.float64)
        y = rng.integers(0, H, n).astype(np.float64)
        t = rng.uniform(t0, t1, n)
        p = rng.choice(np.array([-1, 1], dtype=np.int8), n)
        n_hot = int(round(cfg.hot_pixel_fraction * W * H))
        if n_hot and cfg.hot_pixel_rate > 0:
            idx = rng.choice(W * H, n_hot, replace=False)
            counts = rng.poisson(cfg.hot_pixel_rate * T, n_hot)
            hp = np.repeat(idx, counts)
            x = np.concatenate([x, (hp % W).astype(np.float64)])
            y = np.concatenate([y, (hp // W).astype(np.float64)])
            t = np.concatenate([t, rng.uniform(t0, t1, hp.size)])
            p = np.concatenate([p, np.repeat(rng.choice(np.array([-1, 1], dtype=np.int8), n_hot), counts)])
        return x, y, t, p


# --- one-call helpers --------------------------------------------------------------------------------
def simulate(
    scene: Scene, duration: float, config: SimulatorConfig | None = None, **overrides
) -> SimulatedRecording:
    """Simulate ``duration`` seconds of ``scene``; keyword arguments override ``config`` fields."""
    config = config or SimulatorConfig()
    progress = bool(overrides.pop("progress", False))
    if overrides:
        unknown = set(overrides) - set(SimulatorConfig.__dataclass_fields__)
        if unknown:
            raise TypeError(f"unknown simulator settings: {', '.join(sorted(unknown))}")
        config = replace(config, **overrides)
    return Simulator(scene, config, progress=progress).run(duration)


def simulate_preset(
    name: str,
    duration: float | None = None,
    seed: int = 0,
    sensor_size: tuple[int, int] | None = None,
    progress: bool = False,
    scale: float = 1.0,
    **overrides,
) -> SimulatedRecording:
    """Simulate preset ``name`` (:data:`PRESETS`) for ``duration`` s (default the preset's); see
    :func:`preset_scene` for ``sensor_size`` and ``scale``; keyword arguments override the preset's
    :class:`SimulatorConfig` fields."""
    p = PRESETS[name]
    return run_preset(preset_scene(name, sensor_size, scale), p, seed, duration, progress, overrides)


def run_preset(scene, preset, seed: int, duration: float | None, progress: bool, overrides: dict):
    """Simulate ``scene`` with a preset's settings (``preset.config``, ``preset.duration``), the
    ``overrides`` of :class:`SimulatorConfig` fields (TypeError naming an unknown one) and ``seed``;
    ``duration`` None: the preset's."""
    settings = {**preset.config, **overrides, "seed": seed}
    unknown = set(settings) - set(SimulatorConfig.__dataclass_fields__)
    if unknown:
        raise TypeError(f"unknown simulator settings: {', '.join(sorted(unknown))}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sim = Simulator(scene, SimulatorConfig(**settings), progress=progress)
    return sim.run(preset.duration if duration is None else duration)
