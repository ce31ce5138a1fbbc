"""Scenes with depth: textured 3-D planes seen by a moving camera, whose flow is not one parametric
field, with exact dense ground truth (flow, depth, occlusion by the nearest surface).

Each surface is a :class:`~cmax_taichi.sim.Layer` whose motion is a
:class:`~cmax_taichi.sim.rigid.PlaneMotion` (a plane under a camera motion and its own rigid motion),
built by :func:`plane_layer`. The renderer draws, at every pixel, the nearest surface in front
(``Scene.has_depth``), so occlusions follow the geometry, and the ground truth of a pixel is the flow
of the surface seen there. Presets (:data:`DEPTH_PRESETS`, seeded, 346x260 like MVSEC):

* ``planes``: three textured planes at 1.6 m (tilted), 2.5 m and 4 m, the camera translating sideways
  with a slight rotation: flow from about 50 to 130 px/s, in steps at the planes' edges;
* ``room``: the camera flying forward and yawing inside a textured box room (floor, ceiling, walls):
  expansion about a focus of expansion, flow growing towards the image borders;
* ``object``: a textured square 1.8 m away, moving and spinning on its own in front of a background
  plane at 3.5 m while the camera translates: two motions, the object occluding the background;
* ``corridor``: the camera translating sideways along a corridor, facing its far wall 3 m away, the
  floor and the ceiling receding towards it: 5-14 px over the 75 ms window, growing towards the image's
  top and bottom (a factor 2.5), continuous: every plane contains the direction of travel, so nothing
  is occluded or uncovered.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from cmax_taichi.core.events import Camera, Events
from cmax_taichi.sim.recording import SimulatedRecording
from cmax_taichi.sim.rigid import STATIC, PlaneMotion, RigidMotion, orthonormal_axes
from cmax_taichi.sim.scenes import Layer, Scene
from cmax_taichi.sim.textures import default_camera, load_texture, resize_image

__all__ = [
    "plane_layer",
    "rectangle_alpha",
    "DepthPreset",
    "DEPTH_PRESETS",
    "depth_scene",
    "simulate_depth",
    "DepthExample",
    "depth_example",
]


def rectangle_alpha(height: int, width: int) -> np.ndarray:
    """Coverage of a whole ``height x width`` texture with an anti-aliased edge: 0 on the border texels,
    1 from the next ones in (bilinear sampling ramps it over one texel, so the coverage is continuous
    across the edge and a moving edge changes a pixel's intensity gradually)."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    edge = np.minimum(np.minimum(xx, width - 1 - xx), np.minimum(yy, height - 1 - yy))
    return np.clip(edge, 0.0, 1.0)


def plane_layer(
    texture: np.ndarray,
    camera: Camera,
    *,
    centre: Sequence[float],
    normal: Sequence[float] = (0.0, 0.0, 1.0),
    axis_u: Sequence[float] = (1.0, 0.0, 0.0),
    texel_size: float | None = None,
    camera_motion: RigidMotion = STATIC,
    surface_motion: RigidMotion = STATIC,
    finite: bool = False,
    name: str = "",
) -> Layer:
    """A textured plane in 3-D as a simulator layer.

    Parameters
    ----------
    texture : numpy.ndarray
        (Ht, Wt) linear intensity in [0, 1].
    camera : Camera
        The scene's camera (its intrinsics fix the placement).
    centre : 3 floats
        Where the texture's centre is, m, in the camera frame at t = 0 (x right, y down, z forward).
    normal : 3 floats
        The plane's normal (its sign does not matter).
    axis_u : 3 floats
        The direction of the texture's rows (u, columns increasing), projected onto the plane; the
        texture's v axis is ``normal x u``.
    texel_size : float, optional
        Metres per texel; default: one texel per pixel at the centre (``Z / fx``).
    camera_motion, surface_motion : RigidMotion
        The camera's motion (the same for every layer of a scene) and the plane's own.
    finite : bool
        False: an infinite plane tiled by the mirrored texture; True: the texture's rectangle only
        (anti-aliased edge), transparent around it.
    name : str
        For listings.
    """
    c = np.asarray(centre, dtype=np.float64).reshape(-1)
    n = np.asarray(normal, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or n.shape != (3,) or not (np.all(np.isfinite(c)) and np.all(np.isfinite(n))):
        raise ValueError("centre and normal must be three finite numbers each")
    if np.linalg.norm(n) < 1e-12:
        raise ValueError("normal must not be the zero vector")
    n = n / np.linalg.norm(n)
    d = float(n @ c)
    if d < 0:
        n, d = -n, -d
    if d < 1e-6:
        raise ValueError(
            f"the plane through {tuple(c)} with normal {tuple(normal)} passes through the camera"
        )
    if c[2] <= 0:
        raise ValueError(f"the texture centre {tuple(c)} must be in front of the camera (z > 0)")
    if texel_size is None:
        texel_size = float(c[2] / camera.fx)
    if not (math.isfinite(texel_size) and texel_size > 0):
        raise ValueError(f"texel_size must be a positive number of metres, got {texel_size!r}")
    tex = np.asarray(texture, dtype=np.float64)
    if tex.ndim != 2:
        raise ValueError(f"a texture must be a 2-D image, got shape {tex.shape}")
    h, w = tex.shape
    e_u, e_v = orthonormal_axes(n, axis_u)
    s = float(texel_size)
    origin = c - s * (w - 1) / 2.0 * e_u - s * (h - 1) / 2.0 * e_v
    placement = camera.K @ np.column_stack([s * e_u, s * e_v, origin])
    motion = PlaneMotion(tuple(n), d, camera=camera_motion, surface=surface_motion)
    return Layer(
        tex,
        motion,
        alpha=rectangle_alpha(h, w) if finite else None,
        placement=placement,
        wrap="none" if finite else "mirror",
        name=name,
    )


def _texture(name: str, width: int, height: int, blur: float = 1.0) -> np.ndarray:
    """A texture resampled to ``width x height`` texels and low-passed (Gaussian, ``blur`` texels):
    planes seen at a slant are sampled at less than one texel per pixel, and finer detail would
    alias (moire that does not move with the surface)."""
    from scipy.ndimage import gaussian_filter

    tex = resize_image(load_texture(name), width, height)
    return np.clip(gaussian_filter(tex, blur, mode="mirror"), 0.0, 1.0) if blur > 0 else tex


# --- presets ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Surface:
    """One textured plane of a preset: :func:`plane_layer`'s arguments, the texture by name and size
    (texels at scale 1), the texel size in m at scale 1 (None: one texel per pixel at the centre)."""

    name: str
    texture: str
    size: tuple[int, int]
    centre: tuple[float, float, float]
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    axis_u: tuple[float, float, float] = (1.0, 0.0, 0.0)
    texel: float | None = None
    finite: bool = False
    motion: RigidMotion = STATIC


def _layers(camera: Camera, scale: float, motion: RigidMotion, surfaces: Sequence[_Surface]) -> list[Layer]:
    """The layers of ``surfaces`` seen by ``camera`` under the camera motion ``motion``; textures and
    texel sizes follow the sensor's ``scale``."""
    px = lambda n: max(8, round(n * scale))  # noqa: E731
    return [
        plane_layer(
            _texture(s.texture, px(s.size[0]), px(s.size[1])),
            camera,
            centre=s.centre,
            normal=s.normal,
            axis_u=s.axis_u,
            texel_size=None if s.texel is None else s.texel / scale,
            camera_motion=motion,
            surface_motion=s.motion,
            finite=s.finite,
            name=s.name,
        )
        for s in surfaces
    ]


_SIZES = {"grace_hopper": (600, 512), "dem": (344, 403), "mri": (256, 256), "minduka": (160, 160)}


def _planes(camera: Camera, scale: float) -> list[Layer]:
    motion = RigidMotion(velocity=(0.9, -0.25, 0.15), angular_velocity=(0.02, 0.06, 0.03))
    return _layers(
        camera,
        scale,
        motion,
        (
            _Surface("wall_4m", "grace_hopper", (600, 512), (0.0, 0.0, 4.0)),
            _Surface("plane_2.5m", "dem", (150, 176), (-0.95, -0.15, 2.5), finite=True),
            _Surface("tilted_plane_1.6m", "mri", (128, 128), (0.5, 0.3, 1.6), (0.3, -0.1, 1.0), finite=True),
        ),
    )


def _room(camera: Camera, scale: float) -> list[Layer]:
    motion = RigidMotion(velocity=(0.35, 0.1, 1.0), angular_velocity=(0.0, 0.1, 0.0))
    x, y, z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
    return _layers(
        camera,
        scale,
        motion,
        (
            # name, texture, size, centre, normal, axis_u, texel size (m)
            _Surface("left_wall", "grace_hopper", _SIZES["grace_hopper"], (-1.6, -0.15, 3.0), x, z, 0.012),
            _Surface(
                "right_wall",
                "grace_hopper",
                _SIZES["grace_hopper"],
                (1.6, -0.15, 3.0),
                x,
                (0.0, 0.0, -1.0),
                0.012,
            ),
            _Surface("floor", "dem", _SIZES["dem"], (0.0, 1.1, 3.0), y, x, 0.012),
            _Surface("ceiling", "mri", _SIZES["mri"], (0.0, -1.4, 3.0), y, x, 0.014),
            _Surface("back_wall", "minduka", _SIZES["minduka"], (0.0, -0.15, 6.0), z, x, 0.02),
        ),
    )


def _corridor(camera: Camera, scale: float) -> list[Layer]:
    # every plane contains the direction of travel (x), so the depth seen at a pixel changes only with
    # the slight vertical motion: a smooth flow without an occluding edge (the box room of
    # cmax_taichi.testing.flow_scenes, rendered in 3-D)
    motion = RigidMotion(velocity=(1.0, 0.15, 0.0))
    y = (0.0, 1.0, 0.0)
    return _layers(
        camera,
        scale,
        motion,
        (
            _Surface("far_wall_3m", "grace_hopper", _SIZES["grace_hopper"], (0.0, -0.1, 3.0), texel=0.012),
            _Surface("floor", "dem", _SIZES["dem"], (0.0, 0.7, 2.0), y, texel=0.01),
            _Surface("ceiling", "mri", _SIZES["mri"], (0.0, -0.9, 2.0), y, texel=0.012),
        ),
    )


def _object(camera: Camera, scale: float) -> list[Layer]:
    motion = RigidMotion(velocity=(1.2, 0.1, 0.0), angular_velocity=(0.0, -0.03, 0.0))
    centre = (0.35, 0.1, 1.8)
    own = RigidMotion(velocity=(-0.2, 0.15, -0.1), angular_velocity=(0.0, 0.0, 1.0), pivot=centre)
    return _layers(
        camera,
        scale,
        motion,
        (
            _Surface("background_3.5m", "grace_hopper", (600, 512), (0.0, 0.0, 3.5)),
            _Surface("object_1.8m", "minduka", (110, 110), centre, finite=True, motion=own),
        ),
    )


@dataclass(frozen=True)
class DepthPreset:
    """A depth scene with the sensor settings that simulate it.

    Attributes
    ----------
    name, description : str
    build : callable
        ``build(camera, scale) -> list of Layer``.
    sensor_size : (int, int)
        ``(W, H)``, px.
    config : dict
        Overrides of :class:`~cmax_taichi.sim.SimulatorConfig`.
    duration : float
        Default simulated seconds.
    window : float
        A window length (s) for estimation and scoring: the displacement over it is 5-15 px over most
        of the image for ``planes``.
    frame_rate : float
        Ground-truth frame rate of the files :meth:`SimulatedRecording.write` writes, Hz.
    """

    name: str
    description: str
    build: Callable[[Camera, float], list[Layer]] = field(repr=False)
    sensor_size: tuple[int, int] = (346, 260)
    config: dict = field(default_factory=dict)
    duration: float = 0.3
    window: float = 0.1
    frame_rate: float = 32.0


_SIM = {"contrast_threshold": 0.6, "log_eps": 0.02}

_PRESET_LIST = (
    DepthPreset(
        "planes",
        "DAVIS346 translating sideways (0.9 m/s) with a slight rotation past three textured planes at "
        "1.6 m (tilted), 2.5 m and 4 m: flow of about 50-130 px/s, in steps at the planes' edges",
        _planes,
        config=_SIM,
    ),
    DepthPreset(
        "room",
        "DAVIS346 flying forward (1 m/s) and yawing inside a textured box room 3.2 m wide, 2.5 m "
        "high, 6 m deep: expansion about an off-centre focus of expansion, faster at the borders",
        _room,
        config=_SIM,
        window=0.08,
    ),
    DepthPreset(
        "object",
        "a textured square 1.8 m away moving and spinning on its own (1.2 rad/s) in front of a "
        "background plane at 3.5 m while the DAVIS346 translates sideways: two motions, occlusion",
        _object,
        config=_SIM,
    ),
    DepthPreset(
        "corridor",
        "DAVIS346 translating sideways (1 m/s, slightly downwards) along a corridor, facing its far "
        "wall 3 m away, floor 0.7 m below, ceiling 0.9 m above: 5-14 px over the window, growing "
        "towards the image's top and bottom, continuous (no occluding edge); contrast threshold 0.3",
        _corridor,
        # finer than the other presets' 0.6 (the simulator's default is 0.2): at 0.6 the dense flow is
        # 0.60 px off on this window, at 0.3 0.41 px (benchmarks/NOTES.md, "Accuracy on simulated depth
        # scenes")
        config={**_SIM, "contrast_threshold": 0.3},
        window=0.075,
    ),
)
#: depth scenes by name (:func:`depth_scene`, :func:`simulate_depth`)
DEPTH_PRESETS: dict[str, DepthPreset] = {p.name: p for p in _PRESET_LIST}


def depth_scene(name: str, sensor_size: tuple[int, int] | None = None, scale: float = 1.0) -> Scene:
    """The scene of depth preset ``name`` (:data:`DEPTH_PRESETS`).

    Parameters
    ----------
    name : str
    sensor_size : (int, int), optional
        Default: the preset's, times ``scale``.
    scale : float
        The sensor, the focal length and the textures are scaled by it (the same scene, the flow in px
        scaled by it too).
    """
    if name not in DEPTH_PRESETS:
        raise ValueError(f"unknown depth scene {name!r}; valid depth scenes: {', '.join(DEPTH_PRESETS)}")
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and 0.05 <= scale <= 10.0):
        raise ValueError(f"scale must be in [0.05, 10], got {scale!r}")
    p = DEPTH_PRESETS[name]
    W, H = sensor_size or (round(p.sensor_size[0] * scale), round(p.sensor_size[1] * scale))
    W, H = int(W), int(H)
    base = default_camera(p.sensor_size)
    k = W / p.sensor_size[0]
    camera = Camera(base.fx * k, base.fy * k, (W - 1) / 2.0, (H - 1) / 2.0)
    return Scene((W, H), p.build(camera, k), camera=camera, name=name)


def simulate_depth(
    name: str,
    duration: float | None = None,
    seed: int = 0,
    sensor_size: tuple[int, int] | None = None,
    scale: float = 1.0,
    progress: bool = False,
    **overrides,
) -> SimulatedRecording:
    """Simulate depth preset ``name`` for ``duration`` s (default the preset's), seeded by ``seed``;
    keyword arguments override the preset's :class:`~cmax_taichi.sim.SimulatorConfig` fields.

    Returns
    -------
    SimulatedRecording
        With the exact dense ground truth: ``flow(t_a, t_b)`` (px), ``velocity(t)`` (px/s),
        ``depth(t)`` (m), ``label_map(t)``, ``warp_events(t_ref)``.
    """
    from cmax_taichi.sim.simulator import run_preset

    scene = depth_scene(name, sensor_size, scale)
    return run_preset(scene, DEPTH_PRESETS[name], seed, duration, progress, overrides)


@dataclass
class DepthExample:
    """One window of a depth preset with its exact ground truth (:func:`depth_example`).

    Attributes
    ----------
    name : str
    recording : SimulatedRecording
        The whole simulation (ground truth at any time: ``flow``, ``velocity``, ``depth``).
    t0, t1 : float
        The window, s: ``[0.02, 0.02 + preset.window]`` (the sensor has settled from its start at rest).
    events : Events
        The events of ``[t0, t1]``.
    flow : numpy.ndarray
        (2, H, W) px: the exact displacement over the window of the point seen at each pixel at ``t0``
        (MVSEC's convention), NaN where no surface is seen.
    camera : Camera
    """

    name: str
    recording: SimulatedRecording
    t0: float
    t1: float
    events: Events
    flow: np.ndarray
    camera: Camera

    @property
    def labels(self) -> np.ndarray:
        """The surface of each event of :attr:`events` (-1: noise)."""
        return self.recording.label_slice(self.t0, float(np.nextafter(self.t1, np.inf)))


def depth_example(name: str = "planes", seed: int = 0, **overrides) -> DepthExample:
    """Simulate depth preset ``name`` (seeded) over its first window and return the window's events
    with the exact displacement: the out-of-the-box test case of dense flow (``"planes"``: 346x260,
    5-15 px over the window, the flow varying by a factor of 2.4 across the image). Keyword arguments
    override :class:`~cmax_taichi.sim.SimulatorConfig` fields."""
    if name not in DEPTH_PRESETS:
        raise ValueError(f"unknown depth scene {name!r}; valid depth scenes: {', '.join(DEPTH_PRESETS)}")
    t0 = 0.02
    t1 = t0 + DEPTH_PRESETS[name].window
    rec = simulate_depth(name, duration=t1 + 0.01, seed=seed, **overrides)
    events = rec.events(t0, float(np.nextafter(t1, np.inf)))
    return DepthExample(name, rec, t0, t1, events, rec.flow(t0, t1), rec.camera)
