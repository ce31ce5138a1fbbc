"""Out-of-the-box example recordings: generated on the fly by the event simulator, with exact truth.

``cmax-taichi estimate --example NAME`` and ``cmax-taichi segment --example NAME`` run them; so can
Python::

    from cmax_taichi.sim.examples import make_example
    example = make_example("rotation")
    example.events, example.camera, example.truth, example.warp

Every example is seeded, so the same name gives the same events on every machine. Nothing is read from
disk except the photographs that ship with matplotlib (the simulator's textures).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from cmax_taichi.core.events import Camera, Events
from cmax_taichi.sim import (
    Motion,
    SimulatedRecording,
    default_camera,
    multi_object_scene,
    simulate,
    warp_scene,
)
from cmax_taichi.sim.motions import NotExpressedError

__all__ = [
    "Example",
    "ExampleRecording",
    "EXAMPLES",
    "SEGMENT_EXAMPLES",
    "check_example",
    "example_names",
    "get_example",
    "make_example",
]


@dataclass(frozen=True)
class Example:
    """A simulated scene to estimate, with the settings that estimate it.

    Attributes
    ----------
    name : str
    description : str
        One line for listings.
    warp : str
        The warp model of the true motion, estimated with the same model.
    theta : tuple of float
        True parameters of the background motion, physical units.
    duration : float
        Simulated seconds.
    window : float
        Estimation window length, s.
    sensor_size : (int, int)
        ``(W, H)``, px.
    texture : str
        Photograph on the plane (one of the simulator's textures; ``minduka`` has edges in every
        direction, so every parameter is observable).
    simulator : dict
        :class:`~cmax_taichi.SimulatorConfig` overrides.
    n_objects : int
        Independently moving objects over the background (segmentation examples), 0 for one plane.
    object_motions : tuple of (warp, theta)
        Motion of each object (segmentation examples).
    layout_seed : int
        Seed of the objects' positions and sizes (segmentation examples).
    """

    name: str
    description: str
    warp: str
    theta: tuple[float, ...]
    duration: float
    window: float
    sensor_size: tuple[int, int] = (240, 180)
    texture: str = "minduka"
    simulator: dict = field(default_factory=dict)
    n_objects: int = 0
    object_motions: tuple = ()
    layout_seed: int = 0

    def motions(self) -> list[Motion]:
        """The true motion of every layer: the background, then the objects."""
        return [Motion(self.warp, self.theta)] + [Motion(w, th) for w, th in self.object_motions]

    def truth_in(self, warp: str, layer: int = 0) -> np.ndarray:
        """True parameters of ``layer`` at time 0 in the model ``warp`` (physical units): the example's own
        where ``warp`` is its model, else the parameters of ``warp`` that express the same motion over a
        window (ValueError where ``warp`` cannot, naming both models)."""
        motion = self.motions()[layer]
        if warp == motion.warp:
            return np.asarray(motion.theta_at(0.0), dtype=np.float64)
        try:
            theta = motion.theta_at(0.0, warp, duration=self.window, camera=default_camera(self.sensor_size))
            return np.where(np.abs(theta) < 1e-9, 0.0, theta)  # rounding of the solve: exactly 0
        except NotExpressedError as exc:
            raise ValueError(
                f"example {self.name!r}: its truth is a {motion.warp} motion (theta = {list(motion.theta)}), "
                f"which warp {warp!r} cannot express (its best parameters leave {exc.residual_px:.3g} px "
                f"over {exc.span_s * 1e3:g} ms); estimate it with warp {motion.warp!r}"
            ) from None


@dataclass
class ExampleRecording:
    """An example, simulated: its events and its truth.

    Attributes
    ----------
    example : Example
    recording : SimulatedRecording
        Ground truth per layer (``theta_at``, ``flow``) and a label per event.
    events : Events
    camera : Camera
    """

    example: Example
    recording: SimulatedRecording
    events: Events
    camera: Camera

    @property
    def warp(self) -> str:
        return self.example.warp

    @property
    def truth(self) -> np.ndarray:
        """True parameters of the background at time 0, physical units."""
        return np.asarray(self.recording.theta_at(0.0), dtype=np.float64)

    def truth_in(self, warp: str, layer: int = 0) -> np.ndarray:
        """True parameters of ``layer`` at time 0 in the model ``warp`` (:meth:`Example.truth_in`)."""
        return self.example.truth_in(warp, layer)

    @property
    def labels(self) -> np.ndarray:
        """Layer of each event (0 = background, 1.. = objects, -1 = noise)."""
        return self.recording.label_slice()


_SIM = {"contrast_threshold": 0.5, "log_eps": 0.02}

#: ``cmax-taichi estimate --example NAME``
EXAMPLES: dict[str, Example] = {
    e.name: e
    for e in (
        Example(
            "translation",
            "a textured plane translating at (300, -200) px/s (translation2), 80 ms, 240x180",
            "translation2",
            (300.0, -200.0),
            duration=0.08,
            window=0.02,
            simulator=_SIM,
        ),
        Example(
            "rotation",
            "a camera rotating at (1.0, -1.5, 3.0) rad/s in front of a textured plane (rotation3), 80 ms",
            "rotation3",
            (1.0, -1.5, 3.0),
            duration=0.08,
            window=0.02,
            simulator=_SIM,
        ),
        Example(
            "collapse",
            "a lateral camera motion, (150, -80) px/s with no zoom, estimated with the 4-DOF model "
            "(mitrokhin4): it collapses without regularizers and not with --reg divergence=10 "
            "--reg deformation=10",
            "mitrokhin4",
            (150.0, -80.0, 0.0, 0.0),
            duration=0.05,
            window=0.025,
            simulator=_SIM,
        ),
    )
}

#: ``cmax-taichi segment --example NAME``
SEGMENT_EXAMPLES: dict[str, Example] = {
    e.name: e
    for e in (
        Example(
            "two-objects",
            "a textured disk moving at (-220, 150) px/s over a background translating at (120, -80) px/s "
            "(translation2 for both), 40 ms, 240x180",
            "translation2",
            # (80, -40) px/s moved the background 1.6 px along y in the window: below what bilinear
            # voting resolves (J peaked at v_y = 0, where every event stays on its pixel row), so the
            # example printed v_y = 0.4 against -40; at 3.2 px it is estimated to 0.1 px/s.
            (120.0, -80.0),
            duration=0.04,
            window=0.04,
            simulator=_SIM,
            n_objects=1,
            object_motions=(("translation2", (-220.0, 150.0)),),
            layout_seed=1,
        ),
    )
}


def example_names(kind: str = "estimate") -> list[str]:
    """Names of the examples of ``cmax-taichi estimate`` (``kind="estimate"``) or ``segment``."""
    if kind not in ("estimate", "segment"):
        raise ValueError(f"kind must be 'estimate' or 'segment', got {kind!r}")
    return list(EXAMPLES if kind == "estimate" else SEGMENT_EXAMPLES)


def get_example(name: str) -> Example:
    """The example called ``name`` (of :data:`EXAMPLES` or :data:`SEGMENT_EXAMPLES`; ValueError listing
    the valid names otherwise)."""
    example = EXAMPLES.get(name) or SEGMENT_EXAMPLES.get(name)
    if example is None:
        valid = ", ".join(list(EXAMPLES) + list(SEGMENT_EXAMPLES))
        raise ValueError(f"unknown example {name!r}; valid examples: {valid}")
    return example


def check_example(name: str, warps: str | list[str] | None = None) -> Example:
    """The example called ``name``, checked against the models that will estimate it, before anything is
    simulated (milliseconds): every layer's true motion must be expressed by one of ``warps`` (its own
    model, or another that expresses the same motion exactly: the translation of ``collapse`` in an
    affine model); ValueError otherwise, naming the example, its model and the warp."""
    example = get_example(name)
    if warps is None:
        return example
    warps = [warps] if isinstance(warps, str) else list(warps)
    for layer in range(len(example.motions())):
        errors = []
        for warp in warps:
            try:
                example.truth_in(warp, layer)
                break
            except ValueError as exc:
                errors.append(str(exc))
        else:
            raise ValueError(errors[0] if len(errors) == 1 else "; ".join(errors))
    return example


def make_example(name: str, seed: int = 0) -> ExampleRecording:
    """Simulate the example called ``name`` (see :data:`EXAMPLES` and :data:`SEGMENT_EXAMPLES`).

    Parameters
    ----------
    name : str
        Example name.
    seed : int
        Seed of the simulator's random draws (threshold mismatch, noise); the default reproduces the
        documented outputs.
    """
    example = get_example(name)
    camera = default_camera(example.sensor_size)
    if example.n_objects:
        scene = multi_object_scene(
            example.sensor_size,
            n_objects=example.n_objects,
            background_motion=Motion(example.warp, example.theta),
            object_motions=[Motion(w, th) for w, th in example.object_motions],
            seed=example.layout_seed,
        )
    else:
        scene = warp_scene(
            example.warp, example.theta, example.sensor_size, texture=example.texture, camera=camera
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        recording = simulate(scene, example.duration, seed=seed, **example.simulator)
    return ExampleRecording(example, recording, recording.events(), camera)
