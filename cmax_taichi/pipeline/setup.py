"""What a CMax problem is made of, validated once, and the runner of a generic kernel chain.

:class:`ProblemSetup` turns the user's arguments (events, warp models, objective, regularizers, camera,
reference time, blur, polarity, weights) into checked, derived values: the undistorted events and
which input events they are, ``t_ref`` and the orientation of the window, its duration, the centre
and focal lengths of the warps, the IWE channels and per-event vote weights, the blur radius and
normalised taps, and the regularizers' weights and scales. :class:`~cmax_taichi.ContrastMaximization`
and :class:`~cmax_taichi.pipeline.clusters.MultiClusterCMax` both build one; their kernel chains run
through :func:`run_chain` and :func:`run_chain_backward`.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import taichi as ti

from cmax_taichi.core import backend, checks, limits, workspace
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.kernels import iwe as kiwe
from cmax_taichi.kernels import objectives as kobjectives
from cmax_taichi.kernels import tiles as ktiles
from cmax_taichi.models.objectives import OBJECTIVES, Objective
from cmax_taichi.models.regularizers import REGULARIZERS, Regularizer
from cmax_taichi.models.warps import WarpModel

__all__ = [
    "POLARITY_MODES",
    "ImageKernels",
    "ProblemSetup",
    "SetupView",
    "cached_kernel",
    "check_limits",
    "run_chain",
    "run_chain_backward",
]

POLARITY_MODES = ("ignore", "signed", "split")

# Compiled kernels, keyed by everything that is static in them; cleared when Taichi is reset.
_KERNELS: dict = {}
backend.on_reset(_KERNELS.clear)


def cached_kernel(key, factory):
    """The kernel compiled for ``key``, built by ``factory()`` on first use."""
    kernel = _KERNELS.get(key)
    if kernel is None:
        kernel = _KERNELS[key] = factory()
    return kernel


def _as_float(value, what: str) -> float:
    """``float(value)``, ``inf`` for an int beyond float64 (such as 10**400); TypeError ``what, got ...``
    for anything that is not a number."""
    try:
        return float(value)
    except OverflowError:
        return math.inf
    except (TypeError, ValueError):
        raise TypeError(f"{what}, got {value!r}") from None


#: the largest regularizer weight: beyond it the data term vanishes in the rounding of the penalty (the
#: objective is the penalty alone), and near 1e308 the weighted penalty overflows to inf
MAX_REGULARIZER_WEIGHT = 1e9


def check_regularizers(regularizers) -> dict[str, float]:
    """The regularizer weights as ``{name: lambda}`` (registered names, weights from 0 to
    :data:`MAX_REGULARIZER_WEIGHT`)."""
    if regularizers is None:
        return {}
    if not isinstance(regularizers, Mapping):
        raise TypeError("regularizers must be a mapping name -> weight, e.g. {'divergence': 1.0}")
    out = {}
    for name, weight in regularizers.items():
        REGULARIZERS.get(name)
        if not isinstance(weight, numbers.Real) or isinstance(weight, (bool, np.bool_)):
            raise TypeError(f"weight of regularizer {name!r} must be a number, got {weight!r}")
        w = _as_float(weight, f"weight of regularizer {name!r} must be a number")
        if not (math.isfinite(w) and w >= 0):
            raise ValueError(f"weight of regularizer {name!r} must be finite and >= 0, got {w}")
        if w > MAX_REGULARIZER_WEIGHT:
            raise ValueError(
                f"weight of regularizer {name!r} is {w:g}, above {MAX_REGULARIZER_WEIGHT:g}: the data term "
                "would vanish in the rounding of the penalty (and the weighted penalty overflows near 1e308)"
            )
        out[name] = w
    return out


def numeric_t_ref(t_ref) -> float:
    """A numeric ``t_ref`` as a float (s): TypeError for a bool or a non-number, ValueError if not
    finite."""
    if isinstance(t_ref, (bool, np.bool_)):  # True is not 1 s
        raise TypeError(f"t_ref must be 'first', 'middle', 'last' or seconds, got {t_ref!r}")
    value = _as_float(t_ref, "t_ref must be a string or a number")
    if not math.isfinite(value):
        raise ValueError(f"t_ref must be finite, got {value}")
    return value


def resolve_t_ref(t_ref, events: Events) -> float:
    """The reference time in seconds on the events' clock from ``"first"``, ``"middle"``, ``"last"``
    or a number.

    A number is a time on the events' own clock (not relative to the window). It must lie within the
    window's span extended by its duration ``T`` on each side, ``[t_first - T, t_last + T]``: further
    away, every event is warped over many times the window's duration and the estimate means nothing
    (a time on another clock, e.g. microseconds or a Unix time, is the usual cause).

    Raises
    ------
    ValueError
        For an unknown name, a value that is not finite, or a number outside that interval (the error
        names the value, the window's span and the allowed interval, all in seconds).
    """
    if isinstance(t_ref, str):
        choices = {
            "first": events.t[0],
            "middle": 0.5 * (events.t[0] + events.t[-1]),
            "last": events.t[-1],
        }
        if t_ref not in choices:
            raise ValueError(f"t_ref must be 'first', 'middle', 'last' or seconds, got {t_ref!r}")
        return float(choices[t_ref])
    value = numeric_t_ref(t_ref)
    first, last = float(events.t[0]), float(events.t[-1])
    margin = last - first
    if not first - margin <= value <= last + margin:
        raise ValueError(
            f"t_ref {value:.9g} s is outside the window: its events span [{first:.9g}, {last:.9g}] s on "
            f"their clock, and a numeric t_ref must lie within that span extended by its duration "
            f"({margin:.3g} s) on each side, [{first - margin:.9g}, {last + margin:.9g}] s; "
            "'first', 'middle' and 'last' follow the window"
        )
    return value


def gaussian_taps(blur_sigma: float) -> tuple[int, np.ndarray | None]:
    """``(radius, taps)``: the footprint radius ``ceil(3 sigma)`` (px) and the normalised Gaussian taps
    (None without blur).

    ValueError for a blur that is not a finite number >= 0 or is above ``max_blur_sigma``, before the
    taps (``6 sigma`` of them) are allocated.
    """
    if not (math.isfinite(blur_sigma) and blur_sigma >= 0):
        raise ValueError(f"blur_sigma must be a finite number >= 0, got {blur_sigma}")
    limits.check_blur_sigma(blur_sigma)
    if blur_sigma == 0:
        return 0, None
    r = int(math.ceil(3 * blur_sigma))
    with np.errstate(over="ignore"):  # (k / sigma)^2 = inf for a tiny sigma: a tap of 0, not 0 / 0 = NaN
        taps = np.exp(-0.5 * (np.arange(-r, r + 1) / blur_sigma) ** 2)
    return r, taps / taps.sum()


@dataclass(frozen=True)
class ProblemSetup:
    """The checked and derived inputs of one CMax window (see the module docstring).

    Attributes
    ----------
    events : Events
        The window, undistorted where the camera has distortion.
    kept : ndarray of bool
        Which input events are in ``events``.
    camera : Camera or None
    objective : Objective
    regularizer_weights : dict
        ``{name: lambda}`` in the user's order.
    regularizers : tuple of Regularizer
        The registry entries, same order.
    t_ref, duration : float
        Reference time and window duration, s.
    orientation : float
        +1 when ``t_ref`` is before the mean event time, else -1 (sign of the divergence scale).
    width, height : int
        Sensor size, px.
    center, focal : tuple of float
        Centre (px) and focal lengths (px) of the warps: the camera's, else the image centre and 1.
    blur_sigma : float
        px; ``radius`` its footprint and ``taps`` the normalised taps (None without blur).
    normalize : bool
    polarity : str
        One of :data:`POLARITY_MODES`; ``n_channels`` IWE channels (2 for ``"split"``).
    vote_weights : ndarray or None
        Per-event vote weights (signed polarity and/or user weights); None where all are 1.
    """

    events: Events
    kept: np.ndarray
    camera: Camera | None
    objective: Objective
    regularizer_weights: dict
    regularizers: tuple
    t_ref: float
    duration: float
    orientation: float
    width: int
    height: int
    center: tuple
    focal: tuple
    blur_sigma: float
    radius: int
    taps: np.ndarray | None
    normalize: bool
    polarity: str
    n_channels: int
    vote_weights: np.ndarray | None

    @classmethod
    def build(
        cls,
        events: Events,
        models: Sequence[WarpModel],
        objective: str,
        regularizers: Mapping[str, float] | None,
        camera: Camera | None,
        t_ref: str | float,
        blur_sigma: float,
        normalize: bool,
        polarity: str = "ignore",
        weights: Sequence[float] | np.ndarray | None = None,
    ) -> ProblemSetup:
        """Check the arguments (one clear error each) and derive the window's values.

        ``models`` are the already resolved warp models (one per cluster); ``events`` must be checked
        to be :class:`Events` by the caller before resolving them.
        """
        objective_entry: Objective = OBJECTIVES.get(objective)
        if camera is not None and not isinstance(camera, Camera):
            raise TypeError(f"camera must be cmax_taichi.Camera, got {type(camera).__name__}")
        for m in models:
            if m.needs_camera and camera is None:
                raise ValueError(f"warp {m.name!r} needs a camera (intrinsics): pass camera=")
        reg_weights = check_regularizers(regularizers)
        checks.flag("normalize", normalize)  # (normalize="no" read as True)
        if polarity not in POLARITY_MODES:
            raise ValueError(f"unknown polarity mode {polarity!r}; valid: {', '.join(POLARITY_MODES)}")
        if not isinstance(blur_sigma, numbers.Real) or isinstance(blur_sigma, (bool, np.bool_)):
            raise TypeError(
                f"blur_sigma must be a number of px >= 0, got {blur_sigma!r} ({type(blur_sigma).__name__})"
            )
        blur_sigma = _as_float(blur_sigma, "blur_sigma must be a number of px >= 0")
        if not (math.isfinite(blur_sigma) and blur_sigma >= 0):
            raise ValueError(f"blur_sigma must be a finite number >= 0, got {blur_sigma}")

        if len(events) < 2:
            raise ValueError(f"a CMax problem needs at least 2 events, got {len(events)}")
        # real, finite, one per event and small enough not to overflow the image (checks.vote_weights)
        user_weights = None if weights is None else checks.vote_weights(weights, len(events))
        kept = np.ones(len(events), dtype=bool)
        if camera is not None and camera.has_distortion and not events.undistorted:
            events, kept = events.undistort(camera, return_mask=True)
            if user_weights is not None:
                user_weights = user_weights[kept]
            if len(events) < 2:
                raise ValueError("fewer than 2 events remain inside the sensor after undistortion")
        duration = events.duration
        if not duration > 0:
            raise ValueError("the events span zero time: a CMax window needs a positive duration")
        t_ref_s = resolve_t_ref(t_ref, events)
        width, height = events.sensor_size
        if camera is not None:
            center, focal = (camera.cx, camera.cy), (camera.fx, camera.fy)
        else:
            center, focal = ((width - 1) / 2.0, (height - 1) / 2.0), (1.0, 1.0)
        vote_weights = None  # only where they are not all 1
        if polarity == "signed" or user_weights is not None:
            vote_weights = np.ones(len(events)) if user_weights is None else user_weights
            if polarity == "signed":
                vote_weights = vote_weights * events.p
        radius, taps = gaussian_taps(blur_sigma)
        return cls(
            events=events,
            kept=kept,
            camera=camera,
            objective=objective_entry,
            regularizer_weights=reg_weights,
            regularizers=tuple(REGULARIZERS.get(name) for name in reg_weights),
            t_ref=t_ref_s,
            duration=duration,
            orientation=1.0 if t_ref_s <= float(np.mean(events.t)) else -1.0,
            width=width,
            height=height,
            center=center,
            focal=focal,
            blur_sigma=blur_sigma,
            radius=radius,
            taps=taps,
            normalize=bool(normalize),
            polarity=polarity,
            n_channels=2 if polarity == "split" else 1,
            vote_weights=vote_weights,
        )

    # --- derived values --------------------------------------------------------------------------------
    @property
    def n_events(self) -> int:
        return len(self.events)

    @property
    def ctx(self) -> list[float]:
        """The warps' context vector ``(cx, cy, fx, fy, T)``."""
        return [self.center[0], self.center[1], self.focal[0], self.focal[1], self.duration]

    @property
    def lam(self) -> list[float]:
        """The weights ``lambda_r`` then the scales ``s_r`` of the regularizers, as the loss kernels read
        them (they apply the one-sided hinges to ``s_r R_r``)."""
        regs: Sequence[Regularizer] = self.regularizers
        return [self.regularizer_weights[r.name] for r in regs] + [
            r.scale(self.duration, self.orientation) for r in regs
        ]

    def one_sided(self) -> tuple[bool, ...]:
        return tuple(bool(r.one_sided) for r in self.regularizers)


@dataclass(frozen=True)
class SetupOptions:
    """The options a problem sets up every window it takes with (:meth:`ProblemSetup.build`), kept so
    that ``set_events`` checks and derives the next window as the first."""

    objective: str
    regularizers: Mapping[str, float] | None
    camera: Camera | None
    t_ref: str | float
    blur_sigma: float
    normalize: bool
    polarity: str = "ignore"

    def build(
        self,
        events: Events,
        models: Sequence[WarpModel],
        weights: Sequence[float] | np.ndarray | None = None,
    ) -> ProblemSetup:
        """The set-up of the window ``events`` for the warp ``models`` (see :meth:`ProblemSetup.build`)."""
        return ProblemSetup.build(
            events,
            models,
            self.objective,
            self.regularizers,
            self.camera,
            self.t_ref,
            self.blur_sigma,
            self.normalize,
            self.polarity,
            weights,
        )


def _from_setup(name: str, doc: str) -> property:
    return property(lambda self: getattr(self.setup, name), doc=doc)


class SetupView:
    """The checked values of a problem's window as its read-only attributes: one list for
    :class:`~cmax_taichi.ContrastMaximization` and :class:`~cmax_taichi.pipeline.clusters.MultiClusterCMax`,
    read from the :class:`ProblemSetup` they hold in ``self.setup`` (a new window is a new setup)."""

    setup: ProblemSetup

    events = _from_setup("events", "The window's events (undistorted where the camera has distortion).")
    kept = _from_setup("kept", "Which input events are in ``events`` (bool array).")
    n_events = _from_setup("n_events", "Number of events of the window.")
    camera = _from_setup("camera", "The camera (intrinsics), or None.")
    objective = _from_setup("objective", "The :class:`~cmax_taichi.Objective` entry.")
    regularizer_weights = _from_setup("regularizer_weights", "``{name: lambda}`` in the user's order.")
    t_ref = _from_setup("t_ref", "Reference time, s (on the events' clock).")
    duration = _from_setup("duration", "Window duration, s.")
    orientation = _from_setup("orientation", "+1 when t_ref is before the mean event time, else -1.")
    width = _from_setup("width", "Sensor width, px.")
    height = _from_setup("height", "Sensor height, px.")
    center = _from_setup("center", "Centre of the warps, px.")
    blur_sigma = _from_setup("blur_sigma", "Gaussian blur of the IWE, px.")
    normalize = _from_setup("normalize", "J uses G / G0.")
    polarity = _from_setup("polarity", "How polarity enters the IWE.")
    n_channels = _from_setup("n_channels", "IWE channels (2 for split polarity).")


def check_limits(setup: ProblemSetup, what: str, *, n_clusters: int = 0, n_slices: int = 1) -> None:
    """Refuse a problem above the limits of ``core/limits.py`` before anything is allocated.

    ValueError for a sensor above ``max_sensor_pixels``, a blur above ``max_blur_sigma`` or more
    clusters than ``max_clusters``, MemoryError for fields estimated above ``max_bytes``.
    ``n_clusters`` > 0: a K-cluster problem; ``n_slices``: the fused pipeline's accumulation slices
    (CPU threads).
    """
    if n_clusters:
        limits.check_clusters(n_clusters)
    W, H = setup.width, setup.height
    limits.check_sensor(W, H, what)
    limits.check_blur_sigma(setup.blur_sigma)
    itemsize = np.dtype(backend.numpy_real()).itemsize
    n_regs = len(setup.regularizers)
    if n_clusters:
        estimate = limits.clusters_bytes(W, H, n_clusters, n_regs, setup.n_events, itemsize)
        parameters = f"sensor {W}x{H}, n_clusters = {n_clusters}"
    else:
        estimate = limits.problem_bytes(W, H, setup.n_channels, n_regs, setup.n_events, itemsize, n_slices)
        parameters = f"sensor {W}x{H}, {setup.n_channels} channel(s)"
    parameters += f", {n_regs} regularizer(s), {setup.n_events:,} events, {itemsize}-byte floats"
    limits.check_bytes(estimate, what, parameters)


# --- fields shared by the generic chains --------------------------------------------------------------
#: the chains' regions (kernels/tiles.py): touched segments, blur along x, blurred image; with a Sobel
#: objective its pixel terms' region and one more pixel, where its adjoint writes
F0, RX, RXY, RS, RC = 0, 1, 2, 3, 4


def objective_terms(setup: ProblemSetup, n_images: int):
    """``(pixel_fn, slots, sobel)`` that the objective's reduce kernel declares (``pixel_terms``,
    ``kernels/objectives.make_pixel_reduce``), or None (a reduce of its own: it runs over the whole
    image)."""
    return getattr(_full_reduce(setup, n_images), "pixel_terms", None)


def images_key(setup: ProblemSetup, n_images: int) -> tuple:
    """What :func:`allocate_images` lays out from besides the shapes (part of a workspace's key):
    whether the objective declares pixel terms, and whether they read the Sobel responses."""
    terms = objective_terms(setup, n_images)
    return (terms is not None, bool(terms and terms[2]))


def _full_reduce(setup: ProblemSetup, n_images: int):
    W, H, obj = setup.width, setup.height, setup.objective
    return cached_kernel(
        ("reduce", obj.name, id(obj), W, H, n_images), lambda: obj.make_reduce(W, H, n_images)
    )


def allocate_images(ws, setup: ProblemSetup, n_images: int) -> None:
    """On a workspace: the ``(n_images, H, W)`` vote image and, with blur, the taps and the blur-x /
    blurred images (all three the vote image itself without blur); the tile masks and lists of the
    regions the passes need (``ws.tiles``; ``ws.region_obj``: the objective's, ``ws.region_clear``:
    everything one evaluation writes) and the objective's per-segment partial sums (``ws.part``)."""
    real = backend.real()
    W, H, r = setup.width, setup.height, setup.radius
    ws.vote = ti.field(real, shape=(n_images, H, W), needs_grad=True)
    if r > 0:
        ws.taps = ti.field(real, shape=2 * r + 1)
        ws.tmp = ti.field(real, shape=(n_images, H, W), needs_grad=True)
        ws.img = ti.field(real, shape=(n_images, H, W), needs_grad=True)
    else:
        ws.taps = workspace.dummy(real)
        ws.tmp = ws.img = ws.vote
    terms = objective_terms(setup, n_images)
    sobel = bool(terms and terms[2])
    kx = ktiles.reach(r)
    regions = [(0, 0), (kx, 0), (kx, r)] + ([(kx + 1, r + 1), (kx + 2, r + 2)] if sobel else [])
    ws.tiles = ktiles.TileFields(W, H, regions, lists=True)
    ws.region_obj = RS if sobel else RXY
    ws.region_clear = RC if sobel else RXY
    n_entries = H * ws.tiles.n_segments
    if terms is None:
        ws.part = workspace.dummy(real, (1, 1))
    else:
        ws.part = ti.field(real, shape=(n_entries, terms[1] * n_images), needs_grad=True)


def upload(ws, setup: ProblemSetup, per_event: Mapping[str, np.ndarray | None]) -> None:
    """Per-event arrays (padded to the fields' capacity; None: not used) and the constants (context,
    taps, regularizer weights) of ``setup`` into a workspace's fields."""
    npr = backend.numpy_real()
    for name, values in per_event.items():
        if values is None:
            continue
        f = getattr(ws, name)
        buf = np.zeros(f.shape, dtype=values.dtype if values.dtype == np.int8 else npr)
        buf[: len(values)] = values
        f.from_numpy(buf)
    ws.ctx[None] = setup.ctx
    if setup.taps is not None:
        ws.taps.from_numpy(setup.taps.astype(npr))
    ws.lam[None] = setup.lam or [0.0]


@dataclass(frozen=True)
class ImageKernels:
    """The (cached) image kernels of a chain over ``(n_images, H, W)`` images (``image_kernels``).

    Attributes
    ----------
    blur_x, blur_y : Taichi kernels or None
        ``blur(src, dst, taps, tiles, region)`` (None without blur).
    reduce : Taichi kernel
        ``reduce(img, acc, tiles, part)`` over the objective's region (``tiled``), or the objective's
        own ``reduce(img, acc)`` over the whole image.
    compact : Taichi kernel
        ``compact(tiles)``: the regions and lists of the marks the splat left (forward only).
    tiled : bool
    """

    blur_x: object
    blur_y: object
    reduce: object
    compact: object
    tiled: bool

    def reduce_args(self, ws, img, acc) -> tuple:
        return (img, acc, ws.tiles, ws.part) if self.tiled else (img, acc)

    def blur_adjoints(self) -> tuple:
        """``(kernel, region of its adjoint's output)`` pairs for :func:`run_chain_backward`: the vote
        gradient is needed at the touched pixels, the blur-x output's along its region."""
        return ((self.blur_x, F0), (self.blur_y, RX)) if self.blur_x is not None else ()


def image_kernels(setup: ProblemSetup, n_images: int, ws) -> ImageKernels:
    """The (cached) image kernels of the ``(n_images, H, W)`` images of workspace ``ws``
    (:func:`allocate_images`)."""
    W, H, r, obj = setup.width, setup.height, setup.radius, setup.objective
    blur_x = blur_y = None
    if r > 0:
        blur_x = cached_kernel(
            ("blur", r, 1, W, H, n_images), lambda: kiwe.make_blur_kernel(r, 1, W, H, n_images)
        )
        blur_y = cached_kernel(
            ("blur", r, 0, W, H, n_images), lambda: kiwe.make_blur_kernel(r, 0, W, H, n_images)
        )
    terms = objective_terms(setup, n_images)
    if terms is None:
        reduce = _full_reduce(setup, n_images)
    else:
        region = ws.region_obj
        reduce = cached_kernel(
            ("tiled_reduce", obj.name, id(obj), W, H, n_images, region),
            lambda: kobjectives.make_tiled_reduce(*terms, W, H, n_images, region),
        )
    return ImageKernels(blur_x, blur_y, reduce, ktiles.ops_for(ws.tiles).compact, terms is not None)


def make_clear(ws, images: tuple, rows: tuple = (), scalars: tuple = ()):
    """The workspace's clear kernel (built once): ``images`` over the region everything is written in,
    the objective's partial sums and ``rows`` (``(field, list)`` pairs), and ``scalars``
    (``kernels/tiles.make_clear_kernel``)."""
    part_rows = ((ws.part, ws.region_obj), (ws.part.grad, ws.region_obj)) if ws.part.grad is not None else ()
    return ktiles.make_clear_kernel(ws.tiles, ws.region_clear, images, part_rows + tuple(rows), scalars)


# --- the runner of a generic kernel chain ---------------------------------------------------------------
def run_chain(chain) -> None:
    """Launch the kernels of ``chain`` (a list of ``(kernel, args)``) in order."""
    for kernel, args in chain:
        kernel(*args)


def run_chain_backward(chain, blurs=(), forward_only=()) -> None:
    """Reverse pass of ``chain``: each kernel's ``.grad`` in reverse order, with the loss adjoint
    seeded by the caller, skipping the kernels in ``forward_only`` (the compaction of the tile lists).
    The kernels of ``blurs`` (pairs ``(blur, region)``, ``blur(src, dst, taps, tiles, region)`` of
    ``kernels/iwe.py``) correlate with symmetric taps, so their adjoint is the same correlation of
    ``dst.grad`` into ``src.grad`` (over ``region``, where it is needed): ~8x cheaper than Taichi's
    scatter-add adjoint."""
    for kernel, args in reversed(chain):
        if any(kernel is k for k in forward_only):
            continue
        adjoint = [region for blur, region in blurs if kernel is blur]
        if adjoint:
            src, dst, taps, tiles, _ = args
            kernel(dst.grad, src.grad, taps, tiles, adjoint[0])
        else:
            kernel.grad(*args)
