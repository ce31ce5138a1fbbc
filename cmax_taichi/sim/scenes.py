"""Scenes of the simulator: textured layers (a background plane and objects with a coverage mask), each
under its own :class:`~cmax_taichi.sim.motions.Motion`, and the presets that stand in for MVSEC."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cmax_taichi.core.events import Camera
from cmax_taichi.models.warps import get_warp
from cmax_taichi.sim.motions import Motion, default_theta
from cmax_taichi.sim.rigid import PlaneMotion
from cmax_taichi.sim.textures import default_camera, fit_texture, load_texture, resize_image

__all__ = ["Layer", "Scene", "warp_scene", "multi_object_scene", "Preset", "PRESETS", "preset_scene"]


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
    motion : Motion or PlaneMotion
        Its image motion: a 2-D motion of a warp model (:class:`Motion`), or a 3-D plane seen by a
        moving camera (:class:`~cmax_taichi.sim.rigid.PlaneMotion`, which needs a metric
        ``placement``: see :func:`~cmax_taichi.sim.depth.plane_layer`).
    alpha : numpy.ndarray, optional
        (Ht, Wt) coverage in [0, 1] (an object's shape, anti-aliased); default: opaque.
    placement : numpy.ndarray, optional
        3x3 homography from texel coordinates (column, row) to image px at time 0; default: texture
        centre at the principal point, one texel per pixel. For a :class:`PlaneMotion` it is required
        and scaled by depth: ``K [s e_u, s e_v, X_origin]`` (texel size s, metres).
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
        if not isinstance(self.motion, (Motion, PlaneMotion)):
            raise TypeError(f"motion must be a Motion or a PlaneMotion, got {type(self.motion).__name__}")
        if isinstance(self.motion, PlaneMotion) and self.placement is None:
            raise ValueError("a layer with a PlaneMotion needs its metric placement (see plane_layer)")
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
        kinds = {isinstance(layer.motion, PlaneMotion) for layer in self.layers}
        if len(kinds) > 1:
            raise ValueError(
                "a scene's layers are either all 3-D planes (PlaneMotion, drawn by depth) or all 2-D "
                "motions (Motion, drawn in layer order), not a mixture"
            )
        for layer in self.layers:
            if layer.placement is None:
                layer.placement = _placement_centred(layer.texture.shape, self.camera.cx, self.camera.cy)

    @property
    def has_depth(self) -> bool:
        """True when every layer is a 3-D plane (:class:`PlaneMotion`): the renderer then draws the
        nearest surface in front, and the ground truth has a depth per pixel."""
        return isinstance(self.layers[0].motion, PlaneMotion)


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
        Its parameters at time 0 (default :func:`~cmax_taichi.sim.motions.default_theta`).
    sensor_size : (int, int)
        ``(W, H)``, px.
    texture : str
        One of :data:`TEXTURES`.
    segment : float, optional
        Window duration (s) for ``mitrokhin4`` with a non-zero angle (see :class:`Motion`).
    camera : Camera, optional
        Default :func:`default_camera`.
    """
    theta = default_theta(warp) if theta is None else theta
    W, H = (int(v) for v in sensor_size)
    tex = fit_texture(load_texture(texture), W, H)
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
    layers = [Layer(fit_texture(load_texture("grace_hopper"), W, H), background_motion, name="background")]
    if object_motions is not None and len(object_motions) != n_objects:
        raise ValueError(f"object_motions has {len(object_motions)} motions for {n_objects} objects")
    sources = ["dem", "mri", "minduka"]
    base = min(W, H)
    # objects on a ring around the centre, so that they start apart from each other
    phase = rng.uniform(0, 2 * np.pi)
    for k in range(n_objects):
        size = int(round(base * rng.uniform(0.22, 0.32)))
        src = load_texture(sources[k % len(sources)])
        src = resize_image(src, size + 4, size + 4)
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
    tex = fit_texture(load_texture(p.texture), W, H)
    return Scene((W, H), [Layer(tex, _scaled_motion(p.motion, scale), name=p.texture)], name=name)
