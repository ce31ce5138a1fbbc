"""Event simulator with exact ground truth: textured planes from real photographs under the exact motion
of every warp model of the core, independently moving objects, and presets that stand in for MVSEC.

How it works (ESIM-like; kernels in ``kernels/simulator.py``):

* A :class:`Scene` is a stack of textured :class:`Layer` s (photographs shipped with matplotlib, so
  nothing is downloaded). Layer 0 is an infinite background plane (the texture repeats mirrored); the
  others are objects with a coverage mask. Each layer moves with its own :class:`Motion`.
* A motion is the exact image motion that the core's warp with the same parameters undoes:
  ``W(x_t, t - t_ref; theta(t_ref)) = x_{t_ref}`` for every point of the layer (docs/FORMULAS.md).
  It is stored as a homography ``G(t)`` that moves image points at time 0 to time ``t``, so that
  ``W(x, t - t_ref) = G(t_ref) G(t)^-1 x``.
* The :class:`Simulator` renders the log intensity ``log(I + log_eps)`` of every pixel at an adaptive
  rate (each step moves no point by more than ``step_px`` pixels and changes no pixel's log intensity
  by more than ``step_log_change * C``; the change is measured and the step retried when too large),
  and emits an event each time a pixel's log intensity crosses its reference plus or minus its own
  contrast threshold, with the timestamp interpolated linearly between the renders.
  Sensor effects: per-pixel threshold mismatch, refractory period, background-activity noise, hot
  pixels. All randomness comes from one NumPy generator seeded by ``SimulatorConfig.seed``.

Ground truth of a :class:`SimulatedRecording`: ``theta_at(t)`` per layer, the dense flow ``flow(t_a, t_b)``
between any two times (px, indexed at the start positions, the front-most layer at each pixel), and a
label per event (layer index; -1 for noise and hot-pixel events). :meth:`SimulatedRecording.write` saves it in
the MVSEC-like layout read by :func:`read_simulation` (and by the dataset readers).
"""

from __future__ import annotations

import gzip
import json
import math
import sys
import time
import warnings
import weakref
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import taichi as ti

from cmax_taichi.core import backend
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.kernels import simulator as ksim
from cmax_taichi.models.warps import get_warp

__all__ = [
    "Motion",
    "Layer",
    "Scene",
    "SimulatorConfig",
    "Simulator",
    "SimulatedRecording",
    "SimulationData",
    "PRESETS",
    "Preset",
    "SENSORS",
    "TEXTURES",
    "load_texture",
    "default_camera",
    "warp_scene",
    "multi_object_scene",
    "preset_scene",
    "simulate",
    "simulate_preset",
    "read_simulation",
]

#: sensor sizes (W, H) by name
SENSORS = {
    "davis240": (240, 180),
    "davis346": (346, 260),
    "vga": (640, 480),
    "hd": (1280, 720),
}

#: the images shipped with matplotlib that serve as textures (nothing is downloaded)
TEXTURES = ("grace_hopper", "minduka", "dem", "mri")

# Focal lengths of the real sensors (ECD DAVIS240C, MVSEC DAVIS346), px; other sizes use 0.65 W.
_FOCAL = {(240, 180): 199.0, (346, 260): 226.0}

#: a moderate parameter vector per warp model: a few px of motion per 50 ms on a DAVIS240
DEFAULT_THETAS = {
    "zoom1": (0.8,),
    "translation2": (60.0, -35.0),
    "rotation3": (0.3, -0.4, 0.8),
    "se2": (50.0, -30.0, 0.6),
    "sim2": (50.0, -30.0, 0.6, 0.5),
    "mitrokhin4": (50.0, -30.0, 0.5, 0.6),
}


# --- textures ------------------------------------------------------------------------------------
def _srgb_to_linear(v: np.ndarray) -> np.ndarray:
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def load_texture(name: str) -> np.ndarray:
    """A grey-level texture from the sample data that ships with matplotlib.

    Parameters
    ----------
    name : str
        One of :data:`TEXTURES`: ``"grace_hopper"`` (photograph, 600x512), ``"minduka"`` (photograph,
        128x128), ``"dem"`` (hill-shaded elevation model of the Jacksboro fault, 344x403), ``"mri"``
        (MRI slice, 256x256).

    Returns
    -------
    numpy.ndarray
        (H, W) float64 linear intensity in [0, 1] (photographs are converted from sRGB).
    """
    import matplotlib.cbook as cbook
    import matplotlib.image as mimage

    if name == "grace_hopper" or name == "minduka":
        fname = "grace_hopper.jpg" if name == "grace_hopper" else "Minduka_Present_Blue_Pack.png"
        img = np.asarray(mimage.imread(cbook.get_sample_data(fname, asfileobj=False)), dtype=np.float64)
        if img.max() > 1.0:
            img = img / 255.0
        rgb = img[..., :3]
        grey = _srgb_to_linear(rgb) @ np.array([0.2126, 0.7152, 0.0722])
    elif name == "dem":
        from matplotlib.colors import LightSource

        dem = cbook.get_sample_data("jacksboro_fault_dem.npz")
        elevation = np.asarray(dem["elevation"], dtype=np.float64)
        grey = LightSource(azdeg=315, altdeg=45).hillshade(elevation, vert_exag=0.05, dx=10.0, dy=10.0)
        grey = _srgb_to_linear(grey)
    elif name == "mri":
        with cbook.get_sample_data("s1045.ima.gz") as f:
            raw = f.read()
            if isinstance(f, gzip.GzipFile) or raw[:2] != b"\x1f\x8b":
                data = raw
            else:
                data = gzip.decompress(raw)
        img = np.frombuffer(data, np.uint16).reshape(256, 256).astype(np.float64)
        grey = _srgb_to_linear(img / img.max())
    else:
        raise ValueError(f"unknown texture {name!r}; valid textures: {', '.join(TEXTURES)}")
    return np.clip(grey, 0.0, 1.0)


def _resize(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resample an image to (height, width) with an antialiasing filter (Pillow ships with matplotlib)."""
    from PIL import Image

    im = Image.fromarray(np.asarray(img, dtype=np.float32), mode="F")
    out = im.resize((int(width), int(height)), Image.Resampling.LANCZOS)
    return np.clip(np.asarray(out, dtype=np.float64), 0.0, 1.0)


def _fit_texture(tex: np.ndarray, width: int, height: int, margin: float = 1.0) -> np.ndarray:
    """Resample ``tex`` to one texel per pixel so that it covers a ``width x height`` view (times
    ``margin``), keeping its aspect ratio."""
    th, tw = tex.shape
    scale = margin * max(width / tw, height / th)
    return _resize(tex, max(2, round(tw * scale)), max(2, round(th * scale)))


def default_camera(sensor_size: tuple[int, int]) -> Camera:
    """Pinhole camera of a sensor: the real focal length of the DAVIS240C / DAVIS346 (0.65 W for other
    sizes) and the principal point at the image centre ``((W-1)/2, (H-1)/2)``, which is also the centre
    the core uses without a camera."""
    W, H = (int(v) for v in sensor_size)
    f = _FOCAL.get((W, H), 0.65 * W)
    return Camera(fx=f, fy=f, cx=(W - 1) / 2.0, cy=(H - 1) / 2.0)


# --- motions -------------------------------------------------------------------------------------
def _centre_conj(M: np.ndarray, cx: float, cy: float) -> np.ndarray:
    """``C M C^-1`` with ``C`` the translation by the centre (M acts on centred coordinates)."""
    C = np.array([[1.0, 0.0, cx], [0.0, 1.0, cy], [0.0, 0.0, 1.0]])
    Ci = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [0.0, 0.0, 1.0]])
    return C @ M @ Ci


def _rodrigues(a: np.ndarray) -> np.ndarray:
    """``exp([a]_x)`` (3x3) for a rotation vector ``a`` (rad)."""
    A = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    phi = float(np.linalg.norm(a))
    if phi < 1e-8:
        return np.eye(3) + A + A @ A / 2.0
    return np.eye(3) + math.sin(phi) / phi * A + (1.0 - math.cos(phi)) / phi**2 * (A @ A)


def _sim2_group(t: float, vx: float, vy: float, w: float, s: float) -> np.ndarray:
    """``expm(t xi^)`` for ``xi^ = [[s, -w, vx], [w, s, vy], [0, 0, 0]]`` (centred coordinates)."""
    z = complex(t * s, t * w)
    ez = complex(math.exp(z.real) * math.cos(z.imag), math.exp(z.real) * math.sin(z.imag))
    E = (ez - 1.0) / z if abs(z) > 1e-9 else 1.0 + z / 2.0 + z * z / 6.0
    u = E * complex(t * vx, t * vy)
    return np.array([[ez.real, -ez.imag, u.real], [ez.imag, ez.real, u.imag], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Motion:
    """The exact image motion that the core's warp ``warp`` with parameters ``theta`` undoes.

    Parameters
    ----------
    warp : str
        A built-in warp model (``cm.warp_names()``).
    theta : sequence of float
        Parameters at time 0, in the model's physical units (px/s, 1/s, rad/s).
    segment : float, optional
        Seconds. Required by ``mitrokhin4`` with a non-zero ``theta`` (its angular part): that model
        normalises time by the window duration T, so the motion is defined window by window; the
        motion restarts with the same parameters every ``segment`` seconds and the ground truth is
        exact for windows ``[k segment, (k+1) segment]`` with ``T = segment``. Ignored otherwise.

    Notes
    -----
    With ``G(t)`` the homography that moves image points from time 0 to time t (centre ``c``, the
    camera's principal point; ``x~ = x - c``):

    * ``translation2``: ``x(t) = x + t v``; ``theta`` is constant.
    * ``se2`` / ``sim2``: ``G(t) = expm(t xi^)`` in centred coordinates; ``theta`` is constant.
    * ``rotation3``: ``G(t) = K exp(-t [w]_x) K^-1`` (camera rotation); ``theta`` is constant.
    * ``zoom1`` and ``mitrokhin4`` with ``theta = 0`` (angular part): camera translation at constant
      velocity towards a fronto-parallel plane, ``x~(t) = (x~ + t h) / (1 - h_z t)``. The parameters
      grow as the plane approaches: ``theta(t) = theta(0) / (1 - h_z(0) t)``, exact for windows
      starting at any time. The plane must stay ahead: ``1 - h_z t > 0.1`` over the simulation.
    """

    warp: str
    theta: tuple[float, ...]
    segment: float | None = None

    def __post_init__(self) -> None:
        model = get_warp(self.warp)
        if self.warp not in DEFAULT_THETAS:
            raise ValueError(
                f"the simulator knows the exact motion of the built-in warps only "
                f"({', '.join(DEFAULT_THETAS)}), not {self.warp!r}"
            )
        try:
            theta = tuple(float(v) for v in np.asarray(self.theta, dtype=np.float64).reshape(-1))
        except (TypeError, ValueError):
            raise TypeError(f"theta must be a sequence of numbers, got {self.theta!r}") from None
        if len(theta) != model.n_params:
            raise ValueError(f"warp {self.warp!r} takes {model.n_params} parameter(s), got {len(theta)}")
        if not all(math.isfinite(v) for v in theta):
            raise ValueError(f"theta has non-finite values: {theta}")
        object.__setattr__(self, "theta", theta)
        segment_ok = self.segment is not None and math.isfinite(self.segment) and self.segment > 0
        if self.windowed and not segment_ok:
            raise ValueError(
                "mitrokhin4 with a non-zero angular velocity is defined per window: pass "
                f"segment=<window duration in s> (got {self.segment!r})"
            )

    @property
    def windowed(self) -> bool:
        """True for the window-normalised model (``mitrokhin4`` with a non-zero angle)."""
        return self.warp == "mitrokhin4" and self.theta[3] != 0.0

    @property
    def forward(self) -> bool:
        """True for camera translation towards a plane (``zoom1``, ``mitrokhin4`` without angle)."""
        return self.warp == "zoom1" or (self.warp == "mitrokhin4" and self.theta[3] == 0.0)

    def _hz(self) -> float:
        return self.theta[0] if self.warp == "zoom1" else self.theta[2]

    def check(self, t_end: float) -> None:
        """Raise ValueError if the motion is not defined up to ``t_end`` seconds."""
        if self.forward:
            hz = self._hz()
            if 1.0 - hz * t_end <= 0.1:
                raise ValueError(
                    f"{self.warp} with h_z = {hz} 1/s reaches the plane (1 - h_z t <= 0.1) before "
                    f"t = {t_end} s: use a smaller h_z or a shorter simulation"
                )
        if self.windowed:
            for tau in np.linspace(0.0, self.segment, 9):
                if abs(np.linalg.det(self._m4_warp(tau, 0.0, 0.0)[:2, :2])) < 1e-3:
                    raise ValueError("mitrokhin4 parameters give a singular warp within a segment")

    def _m4_warp(self, tau: float, cx: float, cy: float) -> np.ndarray:
        """The mitrokhin4 warp matrix over ``tau`` seconds (window T = segment)."""
        hx, hy, hz, ang = self.theta
        T = float(self.segment)
        sig = tau / T
        k = hz * T + 1.0
        ac, as_ = k * math.cos(ang * T), k * math.sin(ang * T)
        A = np.array([[ac, -as_], [as_, ac]])
        M = np.eye(3)
        M[:2, :2] = (1.0 + sig) * np.eye(2) - sig * A
        M[:2, 2] = [-tau * hx, -tau * hy]
        return _centre_conj(M, cx, cy)

    def matrix(self, t: float, camera: Camera) -> np.ndarray:
        """``G(t)``: 3x3 homography moving image points (px) from time 0 to time ``t`` (s)."""
        cx, cy = camera.cx, camera.cy
        th = self.theta
        if self.warp == "translation2":
            return np.array([[1.0, 0.0, t * th[0]], [0.0, 1.0, t * th[1]], [0.0, 0.0, 1.0]])
        if self.warp in ("se2", "sim2"):
            s = th[3] if self.warp == "sim2" else 0.0
            return _centre_conj(_sim2_group(t, th[0], th[1], th[2], s), cx, cy)
        if self.warp == "rotation3":
            return camera.K @ _rodrigues(-t * np.asarray(th)) @ np.linalg.inv(camera.K)
        if self.forward:
            hx, hy, hz = (0.0, 0.0, th[0]) if self.warp == "zoom1" else th[:3]
            k = 1.0 / (1.0 - hz * t)
            M = np.array([[k, 0.0, t * hx * k], [0.0, k, t * hy * k], [0.0, 0.0, 1.0]])
            return _centre_conj(M, cx, cy)
        # windowed mitrokhin4: G(t) = M(t - t_k)^-1 G(t_k), G(0) = I
        T = float(self.segment)
        n_seg = int(math.floor(t / T + 1e-12))
        step = np.linalg.inv(self._m4_warp(T, cx, cy))
        G = np.linalg.matrix_power(step, n_seg) if n_seg > 0 else np.eye(3)
        return np.linalg.inv(self._m4_warp(t - n_seg * T, cx, cy)) @ G

    def theta_at(self, t: float) -> np.ndarray:
        """Parameters (physical units) of the warp that undoes the motion of a window starting at
        ``t`` seconds (for the windowed mitrokhin4: of the segment holding ``t``, exact when ``t`` is a
        segment start)."""
        th = np.asarray(self.theta, dtype=np.float64)
        if self.forward:
            out = th / (1.0 - self._hz() * t)
            if self.warp == "mitrokhin4":
                out[3] = 0.0
            return out
        return th.copy()


# --- scenes --------------------------------------------------------------------------------------
def _placement_centred(tex_shape: tuple[int, int], x: float, y: float, scale: float = 1.0) -> np.ndarray:
    """Homography texel -> image px placing the texture centre at ``(x, y)`` with ``scale`` px/texel."""
    th, tw = tex_shape
    return np.array(
        [[scale, 0.0, x - scale * (tw - 1) / 2.0], [0.0, scale, y - scale * (th - 1) / 2.0], [0, 0, 1.0]]
    )


@dataclass
class Layer:
    """A textured plane of a scene.

    Parameters
    ----------
    texture : numpy.ndarray
        (Ht, Wt) linear intensity in [0, 1].
    motion : Motion
        Its image motion.
    alpha : numpy.ndarray, optional
        (Ht, Wt) coverage in [0, 1] (an object's shape, anti-aliased); default: opaque.
    placement : numpy.ndarray, optional
        3x3 homography from texel coordinates (column, row) to image px at time 0; default: texture
        centre at the principal point, one texel per pixel.
    wrap : {"mirror", "none"}
        ``"mirror"``: an infinite plane tiled by the mirrored texture (backgrounds); ``"none"``:
        transparent outside the texture (objects).
    name : str
        For listings.
    """

    texture: np.ndarray
    motion: Motion
    alpha: np.ndarray | None = None
    placement: np.ndarray | None = None
    wrap: str = "mirror"
    name: str = ""

    def __post_init__(self) -> None:
        tex = np.asarray(self.texture, dtype=np.float64)
        if tex.ndim != 2 or min(tex.shape) < 2:
            raise ValueError(f"a texture must be a 2-D image of at least 2x2, got shape {tex.shape}")
        if not np.all(np.isfinite(tex)) or tex.min() < 0.0 or tex.max() > 1.0:
            raise ValueError("texture values must be finite linear intensities in [0, 1]")
        self.texture = tex
        if self.alpha is not None:
            a = np.asarray(self.alpha, dtype=np.float64)
            if a.shape != tex.shape:
                raise ValueError(f"alpha has shape {a.shape}, the texture {tex.shape}")
            if not np.all(np.isfinite(a)) or a.min() < 0.0 or a.max() > 1.0:
                raise ValueError("alpha values must be in [0, 1]")
            self.alpha = a
        if not isinstance(self.motion, Motion):
            raise TypeError(f"motion must be a Motion, got {type(self.motion).__name__}")
        if self.wrap not in ("mirror", "none"):
            raise ValueError(f"wrap must be 'mirror' or 'none', got {self.wrap!r}")
        if self.placement is not None:
            P = np.asarray(self.placement, dtype=np.float64)
            if P.shape != (3, 3) or not np.all(np.isfinite(P)) or abs(np.linalg.det(P)) < 1e-12:
                raise ValueError("placement must be an invertible 3x3 homography")
            self.placement = P


@dataclass
class Scene:
    """Layers (back to front; the index is the event label) seen by a camera.

    Parameters
    ----------
    sensor_size : (int, int)
        ``(W, H)``, px.
    layers : list of Layer
        Layer 0 is the background; its motion is "the" camera motion of the scene.
    camera : Camera, optional
        Intrinsics (default :func:`default_camera`); the principal point is the centre of the motions.
    name : str
        Used in file names.
    """

    sensor_size: tuple[int, int]
    layers: list[Layer]
    camera: Camera | None = None
    name: str = "scene"

    def __post_init__(self) -> None:
        try:
            W, H = (int(v) for v in self.sensor_size)
        except (TypeError, ValueError):
            raise ValueError(f"sensor_size must be (W, H), got {self.sensor_size!r}") from None
        if W < 8 or H < 8:
            raise ValueError(f"sensor_size must be at least 8x8 px, got {W}x{H}")
        self.sensor_size = (W, H)
        if not self.layers:
            raise ValueError("a scene needs at least one layer")
        if len(self.layers) > 100:
            raise ValueError("at most 100 layers (labels are stored as int8)")
        if self.camera is None:
            self.camera = default_camera(self.sensor_size)
        for layer in self.layers:
            if layer.placement is None:
                layer.placement = _placement_centred(layer.texture.shape, self.camera.cx, self.camera.cy)


def _disk_alpha(size: int, radius: float) -> np.ndarray:
    """Anti-aliased disk coverage (one-texel ramp) of a ``size x size`` texture."""
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size]
    return np.clip(radius - np.hypot(xx - c, yy - c) + 0.5, 0.0, 1.0)


def _box_alpha(size: int, half: float) -> np.ndarray:
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size]
    d = np.maximum(np.abs(xx - c), np.abs(yy - c))
    return np.clip(half - d + 0.5, 0.0, 1.0)


def warp_scene(
    warp: str,
    theta: Sequence[float] | None = None,
    sensor_size: tuple[int, int] = (240, 180),
    texture: str = "grace_hopper",
    segment: float | None = None,
    camera: Camera | None = None,
) -> Scene:
    """A textured plane filling the view under the exact motion of one warp model.

    Parameters
    ----------
    warp : str
        Warp model name.
    theta : sequence of float, optional
        Its parameters at time 0 (default :data:`DEFAULT_THETAS`).
    sensor_size : (int, int)
        ``(W, H)``, px.
    texture : str
        One of :data:`TEXTURES`.
    segment : float, optional
        Window duration (s) for ``mitrokhin4`` with a non-zero angle (see :class:`Motion`).
    camera : Camera, optional
        Default :func:`default_camera`.
    """
    theta = DEFAULT_THETAS.get(warp) if theta is None else theta
    if theta is None:
        raise ValueError(f"unknown warp {warp!r}; valid: {', '.join(DEFAULT_THETAS)}")
    W, H = (int(v) for v in sensor_size)
    tex = _fit_texture(load_texture(texture), W, H)
    motion = Motion(warp, tuple(theta), segment=segment)
    return Scene((W, H), [Layer(tex, motion, name=texture)], camera=camera, name=f"{warp}_{texture}")


def multi_object_scene(
    sensor_size: tuple[int, int] = (346, 260),
    n_objects: int = 3,
    background_motion: Motion | None = None,
    object_motions: Sequence[Motion] | None = None,
    seed: int = 0,
) -> Scene:
    """Several independently moving textured objects over a moving textured background.

    Parameters
    ----------
    sensor_size : (int, int)
        ``(W, H)``, px.
    n_objects : int
        Number of objects (1..8); labels 1..n_objects (0 is the background).
    background_motion : Motion, optional
        Default: slow translation ``(15, 8)`` px/s (camera motion).
    object_motions : sequence of Motion, optional
        One per object. Default: alternating translation2 / se2 / sim2 motions with velocities of
        60-120 px/s in different directions, drawn from ``seed``.
    seed : int
        Positions, sizes and default motions of the objects.
    """
    W, H = (int(v) for v in sensor_size)
    n_objects = int(n_objects)
    if not 1 <= n_objects <= 8:
        raise ValueError(f"n_objects must be in 1..8, got {n_objects}")
    rng = np.random.default_rng(seed)
    camera = default_camera((W, H))
    background_motion = background_motion or Motion("translation2", (15.0, 8.0))
    layers = [Layer(_fit_texture(load_texture("grace_hopper"), W, H), background_motion, name="background")]
    if object_motions is not None and len(object_motions) != n_objects:
        raise ValueError(f"object_motions has {len(object_motions)} motions for {n_objects} objects")
    sources = ["dem", "mri", "minduka"]
    base = min(W, H)
    # objects on a ring around the centre, so that they start apart from each other
    phase = rng.uniform(0, 2 * np.pi)
    for k in range(n_objects):
        size = int(round(base * rng.uniform(0.22, 0.32)))
        src = load_texture(sources[k % len(sources)])
        src = _resize(src, size + 4, size + 4)
        shape = "disk" if k % 2 == 0 else "box"
        r = size / 2.0
        alpha = _disk_alpha(size + 4, r) if shape == "disk" else _box_alpha(size + 4, r * 0.85)
        ang = phase + 2 * np.pi * k / n_objects
        px = camera.cx + 0.28 * W * math.cos(ang)
        py = camera.cy + 0.25 * H * math.sin(ang)
        if object_motions is not None:
            motion = object_motions[k]
        else:
            speed = rng.uniform(60.0, 120.0)
            d = ang + np.pi + rng.uniform(-0.6, 0.6)  # roughly towards the other side
            v = (speed * math.cos(d), speed * math.sin(d))
            kind = ("translation2", "se2", "sim2")[k % 3]
            if kind == "translation2":
                motion = Motion(kind, v)
            else:
                # about the object's own centre: v_c = v - w Jr (p - c) - s (p - c)
                w = rng.uniform(-1.5, 1.5)
                s = rng.uniform(-0.4, 0.4) if kind == "sim2" else 0.0
                qx, qy = px - camera.cx, py - camera.cy
                vx = v[0] + w * qy - s * qx
                vy = v[1] - w * qx - s * qy
                motion = Motion(kind, (vx, vy, w) if kind == "se2" else (vx, vy, w, s))
        layers.append(
            Layer(
                src,
                motion,
                alpha=alpha,
                placement=_placement_centred(src.shape, px, py),
                wrap="none",
                name=f"object{k + 1}_{shape}",
            )
        )
    return Scene((W, H), layers, camera=camera, name=f"objects{n_objects}")


# --- presets -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Preset:
    """A scene with the sensor settings that stand in for one of the paper's MVSEC settings.

    Attributes
    ----------
    name : str
    description : str
    sensor_size : (int, int)
    motion : Motion
        Camera motion (background plane).
    texture : str
    config : dict
        Overrides of :class:`SimulatorConfig`.
    frame_rate : float
        Ground-truth frame rate, Hz (MVSEC's grey-scale frames: about 32 Hz).
    dt_frames : int
        Evaluation interval in frames (the paper: 4).
    duration : float
        Default simulated seconds.
    """

    name: str
    description: str
    sensor_size: tuple[int, int]
    motion: Motion
    texture: str
    config: dict
    frame_rate: float = 32.0
    dt_frames: int = 4
    duration: float = 1.0


PRESETS = {
    "indoor_flying": Preset(
        "indoor_flying",
        "DAVIS346, camera flying slowly past a textured wall: mostly translational flow of a few px per "
        "dt = 4 frames (MVSEC indoor_flying-like), about 30k events per interval",
        (346, 260),
        # lateral drift + slow approach (exact for zoom1's h_z part and for mitrokhin4)
        Motion("mitrokhin4", (30.0, -14.0, 0.08, 0.0)),
        "grace_hopper",
        {"contrast_threshold": 0.6, "log_eps": 0.02},
        duration=1.0,
    ),
    "driving": Preset(
        "driving",
        "DAVIS346, camera driving towards a textured plane: strong expansion about a focus of "
        "expansion off the image centre and large flow at the periphery (MVSEC outdoor_day-like)",
        (346, 260),
        Motion("mitrokhin4", (12.0, 6.0, 0.45, 0.0)),
        "grace_hopper",
        {"contrast_threshold": 0.7, "log_eps": 0.02},
        duration=1.0,
    ),
}


def _scaled_motion(motion: Motion, scale: float) -> Motion:
    """The same motion on a sensor ``scale`` times as large: px/s parameters scale, rates do not."""
    units = get_warp(motion.warp).units
    theta = tuple(v * scale if u == "px/s" else v for v, u in zip(motion.theta, units, strict=True))
    return Motion(motion.warp, theta, segment=motion.segment)


def preset_scene(name: str, sensor_size: tuple[int, int] | None = None, scale: float = 1.0) -> Scene:
    """The scene of preset ``name``.

    Parameters
    ----------
    name : str
        A key of :data:`PRESETS`.
    sensor_size : (int, int), optional
        Another sensor size with the same motion parameters.
    scale : float
        Shrink or grow the whole preset: the sensor size and the px/s parameters are multiplied by it
        (so the flow in px scales too, and the flow relative to the image size is kept).
    """
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; valid presets: {', '.join(PRESETS)}")
    if not (math.isfinite(scale) and 0.05 <= scale <= 10.0):
        raise ValueError(f"scale must be in [0.05, 10], got {scale}")
    p = PRESETS[name]
    W, H = sensor_size or (round(p.sensor_size[0] * scale), round(p.sensor_size[1] * scale))
    W, H = int(W), int(H)
    tex = _fit_texture(load_texture(p.texture), W, H)
    return Scene((W, H), [Layer(tex, _scaled_motion(p.motion, scale), name=p.texture)], name=name)


# --- simulator -----------------------------------------------------------------------------------
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
        ns = _POOL[key] = SimpleNamespace(owner=None)
        build(ns)
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
        cap = int(config.capacity) if config.capacity is not None else max(2**20, 4 * W * H)
        self.capacity = cap
        gen = self._backend.generation
        # Fields are pooled by shape: kernels take them as templates, so new fields mean new compiles.
        self._sf = _pooled(("scene", gen, L, ht, wt), lambda ns: _build_scene_fields(ns, L, ht, wt))
        self._pf = _pooled(("sensor", gen, W, H, cap), lambda ns: _build_sensor_fields(ns, W, H, cap))
        key = ("render", gen, mirror, opaque, W, H)
        if key not in _KERNELS:
            _KERNELS[key] = ksim.make_render_kernel(mirror, opaque, W, H)
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
        """Largest motion (px) of a point of a 5x5 grid over the image (corners included) between two
        times, over all layers."""
        W, H = self.width, self.height
        gx, gy = np.meshgrid(np.linspace(0, W - 1, 5), np.linspace(0, H - 1, 5))
        pts = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)])
        worst = 0.0
        cam = self.scene.camera
        for layer in self.scene.layers:
            D = layer.motion.matrix(t1, cam) @ np.linalg.inv(layer.motion.matrix(t0, cam))
            q = D @ pts
            q = q[:2] / q[2]
            worst = max(worst, float(np.max(np.hypot(q[0] - pts[0], q[1] - pts[1]))))
        return worst

    def _render(self, t: float, out_log, out_label) -> None:
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
            out_log,
            out_label,
        )

    def render(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The log intensity ``log(I + log_eps)`` (H, W) and the label map (index of the front-most
        layer per pixel) at time ``t`` seconds. Does not disturb a running simulation."""
        self._check_alive()
        pf = self._pf
        self._render(float(t), pf.scratch_log, pf.scratch_label)
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


# --- results ---------------------------------------------------------------------------------------
@dataclass
class SimulatedRecording:
    """Simulated events with their exact ground truth.

    Attributes
    ----------
    x, y : numpy.ndarray
        Pixel coordinates (integers stored as float64), px.
    t : numpy.ndarray
        Timestamps, s (sorted).
    p : numpy.ndarray
        Polarities, int8 in {-1, +1}.
    labels : numpy.ndarray
        int16: the index of the layer that produced the event (0 background, k object k), -1 for noise
        and hot pixels.
    t_start, t_end : float
        Simulated interval, s.
    sensor_size : (int, int)
    camera : Camera
    simulator : Simulator
        The scene and its renderer (ground truth at any time).
    n_steps : int
        Number of renders.
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray
    labels: np.ndarray
    t_start: float
    t_end: float
    sensor_size: tuple[int, int]
    camera: Camera
    simulator: Simulator = field(repr=False)
    n_steps: int = 0

    def __len__(self) -> int:
        return len(self.t)

    @property
    def scene(self) -> Scene:
        return self.simulator.scene

    def events(self, t0: float | None = None, t1: float | None = None) -> Events:
        """The events with ``t0 <= t < t1`` (default all) as :class:`cmax_taichi.Events`."""
        lo, hi = self._range(t0, t1)
        return Events(self.x[lo:hi], self.y[lo:hi], self.t[lo:hi], self.p[lo:hi], self.sensor_size)

    def label_slice(self, t0: float | None = None, t1: float | None = None) -> np.ndarray:
        """The labels of :meth:`events` with the same arguments."""
        lo, hi = self._range(t0, t1)
        return self.labels[lo:hi]

    def _range(self, t0, t1) -> tuple[int, int]:
        lo = 0 if t0 is None else int(np.searchsorted(self.t, t0, side="left"))
        hi = len(self.t) if t1 is None else int(np.searchsorted(self.t, t1, side="left"))
        return lo, hi

    def theta_at(self, t: float, layer: int = 0) -> np.ndarray:
        """Parameters of layer ``layer``'s warp for a window starting at ``t`` s (see
        :meth:`Motion.theta_at`)."""
        return self.scene.layers[layer].motion.theta_at(float(t))

    @property
    def warp(self) -> str:
        """Warp model of the camera (background) motion."""
        return self.scene.layers[0].motion.warp

    def displacement(self, t_a: float, t_b: float, x, y, layer: int = 0) -> np.ndarray:
        """Exact displacement (px) from ``t_a`` to ``t_b`` of the points of layer ``layer`` that are at
        ``(x, y)`` at ``t_a``; shape ``(2,) + x.shape``."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        m = self.scene.layers[layer].motion
        D = m.matrix(t_b, self.camera) @ np.linalg.inv(m.matrix(t_a, self.camera))
        q = np.tensordot(D, np.stack([x, y, np.ones_like(x)]), axes=1)
        return np.stack([q[0] / q[2] - x, q[1] / q[2] - y])

    def flow(self, t_a: float, t_b: float) -> np.ndarray:
        """Dense ground-truth flow (2, H, W), px: where the scene point seen at each pixel at ``t_a``
        is at ``t_b``, minus the pixel (MVSEC's ``*_flow_dist`` convention: indexed at the start
        positions). Each pixel follows the front-most layer covering it at ``t_a``."""
        W, H = self.sensor_size
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
        _, label = self.simulator.render(t_a)
        out = np.zeros((2, H, W))
        for k in range(len(self.scene.layers)):
            mask = label == k
            if np.any(mask):
                out[:, mask] = self.displacement(t_a, t_b, xx[mask], yy[mask], layer=k)
        return out

    def frame_times(self, frame_rate: float) -> np.ndarray:
        """Ground-truth frame timestamps ``t_start + k / frame_rate`` within the recording, s."""
        if not (math.isfinite(frame_rate) and frame_rate > 0):
            raise ValueError(f"frame_rate must be positive (Hz), got {frame_rate}")
        n = int(math.floor((self.t_end - self.t_start) * frame_rate + 1e-9)) + 1
        return self.t_start + np.arange(n) / frame_rate

    def write(self, out_dir, name: str, frame_rate: float = 32.0) -> tuple[Path, Path]:
        """Save in the MVSEC-like layout.

        Writes ``<out_dir>/<name>_data.hdf5``: ``davis/left/events`` (N, 4) float64 ``x, y, t [s], p``
        (p in {-1, +1}), ``davis/left/labels`` (N,) int16, attributes ``fx fy cx cy width height`` on
        ``davis/left``; ``ground_truth/t`` (M,) s and ``ground_truth/theta`` (M, P) of the camera
        (layer 0) motion with attribute ``warp``; ``ground_truth/layers/<k>/{t,theta}`` with attributes
        ``warp``, ``segment``, ``name`` for every layer; and the simulator settings as a JSON attribute.
        And ``<out_dir>/<name>_gt_flow_dist.npz``: ``timestamps`` (M,), ``x_flow_dist``, ``y_flow_dist``
        (M, H, W) float32, the flow in px from ``timestamps[i]`` to ``timestamps[i + 1]`` (the last one to
        ``timestamps[-1] + 1 / frame_rate``, within the recording when it is long enough, else
        extrapolated by the exact motion).

        Returns
        -------
        (Path, Path)
            The HDF5 and the npz paths.
        """
        import h5py

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        h5_path = out / f"{name}_data.hdf5"
        npz_path = out / f"{name}_gt_flow_dist.npz"
        ts = self.frame_times(frame_rate)
        W, H = self.sensor_size
        with h5py.File(h5_path, "w") as f:
            left = f.create_group("davis/left")
            ev = np.stack([self.x, self.y, self.t, self.p.astype(np.float64)], axis=1)
            left.create_dataset("events", data=ev, compression="gzip", compression_opts=4)
            left.create_dataset("labels", data=self.labels, compression="gzip", compression_opts=4)
            cam = self.camera
            for key, value in (("fx", cam.fx), ("fy", cam.fy), ("cx", cam.cx), ("cy", cam.cy)):
                left.attrs[key] = float(value)
            left.attrs["width"] = W
            left.attrs["height"] = H
            left.attrs["dist"] = np.asarray(cam.dist, dtype=np.float64)
            # the layout the MVSEC reader (cmax_taichi.io) takes intrinsics from
            calib = [cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist]
            left.create_dataset("calibration", data=np.asarray(calib, dtype=np.float64))
            gt = f.create_group("ground_truth")
            gt.create_dataset("t", data=ts)
            gt.create_dataset("theta", data=np.stack([self.theta_at(t) for t in ts]))
            gt.attrs["warp"] = self.warp
            layers = gt.create_group("layers")
            for k, layer in enumerate(self.scene.layers):
                g = layers.create_group(str(k))
                g.create_dataset("t", data=ts)
                g.create_dataset("theta", data=np.stack([layer.motion.theta_at(t) for t in ts]))
                g.attrs["warp"] = layer.motion.warp
                g.attrs["segment"] = float(layer.motion.segment or 0.0)
                g.attrs["name"] = layer.name
            f.attrs["simulator"] = json.dumps(
                {
                    "scene": self.scene.name,
                    "config": asdict(self.simulator.config),
                    "t_start": self.t_start,
                    "t_end": self.t_end,
                    "frame_rate": frame_rate,
                }
            )
        flows = np.stack([self.flow(t, t + 1.0 / frame_rate) for t in ts]).astype(np.float32)
        np.savez_compressed(npz_path, timestamps=ts, x_flow_dist=flows[:, 0], y_flow_dist=flows[:, 1])
        return h5_path, npz_path


@dataclass
class SimulationData:
    """A simulated recording read back from disk (see :meth:`SimulatedRecording.write`)."""

    events: Events
    labels: np.ndarray
    camera: Camera
    gt_t: np.ndarray
    gt_theta: np.ndarray
    warp: str
    flow_timestamps: np.ndarray
    flow: np.ndarray  # (M, 2, H, W) px between consecutive timestamps
    meta: dict


def read_simulation(h5_path) -> SimulationData:
    """Read ``<name>_data.hdf5`` and the ``<name>_gt_flow_dist.npz`` beside it."""
    import h5py

    h5_path = Path(h5_path)
    if not h5_path.name.endswith("_data.hdf5"):
        raise ValueError(f"expected a '<name>_data.hdf5' file, got {h5_path.name}")
    npz_path = h5_path.with_name(h5_path.name[: -len("_data.hdf5")] + "_gt_flow_dist.npz")
    with h5py.File(h5_path, "r") as f:
        left = f["davis/left"]
        ev = left["events"][()]
        labels = left["labels"][()]
        a = left.attrs
        camera = Camera(float(a["fx"]), float(a["fy"]), float(a["cx"]), float(a["cy"]))
        sensor = (int(a["width"]), int(a["height"]))
        gt_t = f["ground_truth/t"][()]
        gt_theta = f["ground_truth/theta"][()]
        warp = str(f["ground_truth"].attrs["warp"])
        meta = json.loads(f.attrs["simulator"])
    d = np.load(npz_path)
    flow = np.stack([d["x_flow_dist"], d["y_flow_dist"]], axis=1).astype(np.float64)
    events = Events(ev[:, 0], ev[:, 1], ev[:, 2], ev[:, 3], sensor)
    return SimulationData(events, labels, camera, gt_t, gt_theta, warp, d["timestamps"], flow, meta)


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
    scene = preset_scene(name, sensor_size, scale)
    p = PRESETS[name]
    settings = {**p.config, **overrides, "seed": seed}
    unknown = set(settings) - set(SimulatorConfig.__dataclass_fields__)
    if unknown:
        raise TypeError(f"unknown simulator settings: {', '.join(sorted(unknown))}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sim = Simulator(scene, SimulatorConfig(**settings), progress=progress)
    return sim.run(p.duration if duration is None else duration)
