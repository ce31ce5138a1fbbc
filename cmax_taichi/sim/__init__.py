"""The event simulator with exact ground truth: textured planes from real photographs under the exact motion
of every warp model of the core, independently moving objects, and presets that stand in for MVSEC.

How it works (ESIM-like; kernels in ``kernels/simulator.py``). Modules: ``textures`` (photographs,
cameras), ``motions`` (exact motion per warp model), ``scenes`` (layers, scenes, presets),
``simulator`` (:class:`Simulator`, :func:`simulate`, :func:`simulate_preset`), ``recording``
(:class:`SimulatedRecording`, its MVSEC-like files and :func:`read_simulation`).

* A :class:`Scene` is a stack of textured :class:`Layer` s (photographs shipped with matplotlib, so
  nothing is downloaded). Layer 0 is an infinite background plane (the texture repeats mirrored); the
  others are objects with a coverage mask. Each layer moves with its own :class:`Motion`.
* A motion is the exact image motion that the core's warp with the same parameters undoes:
  ``W(x_t, t - t_ref; theta(t_ref)) = x_{t_ref}`` for every point of the layer (docs/FORMULAS.md).
  It is stored as a homography ``G(t)`` that moves image points at time 0 to time ``t``, so that
  ``W(x, t - t_ref) = G(t_ref) G(t)^-1 x``.
* The :class:`Simulator` renders the scene at an adaptive rate and emits an event each time a
  pixel's log intensity crosses one of its contrast thresholds, with sensor effects (module docstring
  of ``simulator``).

* Depth scenes (``depth``, ``rigid``): textured 3-D planes seen by a moving camera, each under its own
  rigid motion (:class:`PlaneMotion`, :func:`plane_layer`); the renderer draws the nearest surface at
  every pixel. Presets :data:`DEPTH_PRESETS` (``planes``, ``room``, ``object``,
  ``corridor``), :func:`simulate_depth`.

Ground truth of a :class:`SimulatedRecording`: ``theta_at(t)`` per layer, the dense flow ``flow(t_a, t_b)``
between any two times (px, indexed at the start positions, the front-most layer at each pixel), and a
label per event (layer index; -1 for noise and hot-pixel events); for every scene ``velocity(t)`` (the
dense instantaneous flow, px/s), ``label_map(t)`` and ``warp_events(t_ref)`` (each event moved exactly
to ``t_ref``), and for depth scenes ``depth(t)``. :meth:`SimulatedRecording.write` saves it in
the MVSEC-like layout read by :func:`read_simulation` (and by the dataset readers).
"""

from cmax_taichi.sim import depth as _depth
from cmax_taichi.sim.depth import *  # noqa: F403 - the depth scenes' API, named once in depth.__all__
from cmax_taichi.sim.motions import DEFAULT_THETAS, Motion
from cmax_taichi.sim.recording import SimulatedRecording, SimulationData, read_simulation
from cmax_taichi.sim.rigid import PlaneMotion, RigidMotion
from cmax_taichi.sim.scenes import PRESETS, Layer, Preset, Scene, multi_object_scene, preset_scene, warp_scene
from cmax_taichi.sim.simulator import Simulator, SimulatorConfig, simulate, simulate_preset
from cmax_taichi.sim.textures import SENSORS, TEXTURES, default_camera, load_texture

__all__ = [
    "DEFAULT_THETAS",
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
    "RigidMotion",
    "PlaneMotion",
    # the depth scenes' API (cmax_taichi.sim.depth) but its texture-coverage helper
    *(name for name in _depth.__all__ if name != "rectangle_alpha"),
]
