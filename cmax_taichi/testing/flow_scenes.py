"""Small event scenes with an exact dense flow, to test the dense-flow estimator.

:func:`depth_scene` renders a textured scene whose image motion is a known, spatially varying velocity
field ``v(x)`` (px/s), steady over the window: the log intensity at pixel ``p`` and time ``t`` is that of
the texture at ``p - t v(p)``, so the events of pixel ``p`` are exactly compensated by the dense warp with
``u = v`` and the ground truth of the displacement over ``dt`` at pixel ``p`` is ``dt v(p)``. Events are
the threshold crossings of each pixel's log intensity (contrast threshold with per-pixel mismatch,
timestamps interpolated within a render step of at most 0.25 px of motion), plus background noise.

The default field is the image motion of a sideways-moving camera in a box room: the flow is
proportional to the inverse depth, which grows smoothly from the far wall at the top to the floor at the
bottom and from left to right (a slanted wall), so it is not one affine field.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from cmax_taichi.core.events import Events

__all__ = ["DenseScene", "depth_scene", "room_velocity"]


@dataclass(frozen=True)
class DenseScene:
    """Events with their exact flow.

    Attributes
    ----------
    events : Events
    velocity : ndarray, shape (2, H, W)
        ``v(p)`` on every pixel, px/s.
    duration : float
        Rendered time span, s (the events lie in ``[0, duration]``).
    """

    events: Events
    velocity: np.ndarray
    duration: float

    def displacement(self, dt: float | None = None) -> np.ndarray:
        """The true displacement over ``dt`` s (default the duration), ``(2, H, W)`` px."""
        return self.velocity * (self.duration if dt is None else dt)


def room_velocity(sensor_size: tuple[int, int], displacement: tuple[float, float], duration: float):
    """The velocity field (px/s) of the box room: ``v(x, y) = d0 s(x, y) / duration`` with the inverse
    depth ``s = 1 + 0.8 (y / H)^2 + 0.35 x / W`` (1 at the top-left, 2.15 at the bottom-right) and
    ``d0 = displacement`` (px over the window at the top-left)."""
    W, H = sensor_size
    d0 = np.asarray(displacement, dtype=np.float64)

    def velocity(x, y):
        s = (
            1.0
            + 0.8 * (np.asarray(y, dtype=np.float64) / H) ** 2
            + 0.35 * np.asarray(x, dtype=np.float64) / W
        )
        return np.stack([d0[0] * s, d0[1] * s]) / duration

    return velocity


def _texture(shape: tuple[int, int], rng: np.random.Generator, feature_px: float) -> np.ndarray:
    """Log intensity of a random texture: smoothed noise with steep edges (tanh), range about [0, 2]."""
    noise = ndimage.gaussian_filter(rng.standard_normal(shape), feature_px)
    noise /= noise.std()
    return 1.0 + np.tanh(2.0 * noise)


def depth_scene(
    sensor_size: tuple[int, int] = (346, 260),
    *,
    duration: float = 0.05,
    displacement: tuple[float, float] = (5.0, 2.0),
    velocity: Callable | None = None,
    n_events: int | None = 30000,
    threshold: float = 0.25,
    noise_fraction: float = 0.02,
    feature_px: float = 3.0,
    seed: int = 0,
) -> DenseScene:
    """Simulate a window (see the module docstring).

    Parameters
    ----------
    sensor_size : (int, int)
        ``(W, H)``, px.
    duration : float
        Window duration, s.
    displacement : (float, float)
        Displacement over the window at the top-left of the default room field, px.
    velocity : callable, optional
        ``velocity(x, y) -> (2, N)`` px/s for flat pixel coordinates (default :func:`room_velocity`).
    n_events : int, optional
        Keep this many events (a uniform random subset, time order kept); None keeps all.
    threshold : float
        Contrast threshold (log-intensity units), with 5% per-pixel mismatch.
    noise_fraction : float
        Background-noise events as a share of the signal events.
    feature_px : float
        Scale of the texture's features, px.
    seed : int
        Seed of every random draw.
    """
    W, H = sensor_size
    rng = np.random.default_rng(seed)
    vel = velocity or room_velocity(sensor_size, displacement, duration)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    v = np.asarray(vel(xx.reshape(-1), yy.reshape(-1)), dtype=np.float64).reshape(2, H, W)
    reach = float(np.abs(v).max() * duration) + 4.0
    pad = int(np.ceil(reach)) + 4
    tex = _texture((H + 2 * pad, W + 2 * pad), rng, feature_px)

    def log_intensity(t: float) -> np.ndarray:
        coords = np.stack([yy - t * v[1] + pad, xx - t * v[0] + pad])
        return ndimage.map_coordinates(tex, coords, order=1, mode="nearest")

    n_steps = max(8, int(np.ceil(float(np.abs(v).max()) * duration / 0.25)))
    times = np.linspace(0.0, duration, n_steps + 1)
    c = threshold * (1.0 + 0.05 * rng.standard_normal((H, W)))
    ref = log_intensity(0.0)
    prev = ref.copy()
    xs, ys, ts, ps = [], [], [], []
    for k in range(1, n_steps + 1):
        cur = log_intensity(times[k])
        while True:
            up = cur - ref >= c
            down = ref - cur >= c
            fire = up | down
            if not fire.any():
                break
            level = ref + np.where(up, c, -c)  # the crossed level, between prev and cur
            with np.errstate(invalid="ignore", divide="ignore"):
                frac = np.clip((level - prev) / (cur - prev), 0.0, 1.0)
            tk = times[k - 1] + frac * (times[k] - times[k - 1])
            ys.append(yy[fire])
            xs.append(xx[fire])
            ts.append(tk[fire])
            ps.append(np.where(up[fire], 1, -1))
            ref = np.where(fire, level, ref)
        prev = cur
    x, y, t, p = (np.concatenate(a) if a else np.zeros(0) for a in (xs, ys, ts, ps))
    n_noise = int(noise_fraction * len(t))
    x = np.concatenate([x, rng.integers(0, W, n_noise).astype(np.float64)])
    y = np.concatenate([y, rng.integers(0, H, n_noise).astype(np.float64)])
    t = np.concatenate([t, rng.uniform(0.0, duration, n_noise)])
    p = np.concatenate([p, rng.choice([-1, 1], n_noise)])
    if n_events is not None and len(t) > n_events:
        keep = np.sort(rng.choice(len(t), n_events, replace=False))
        x, y, t, p = x[keep], y[keep], t[keep], p[keep]
    order = np.argsort(t, kind="stable")
    events = Events(x[order], y[order], t[order], p[order], (W, H))
    return DenseScene(events=events, velocity=v, duration=duration)
