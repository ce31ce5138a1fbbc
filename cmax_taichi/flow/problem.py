"""A dense-flow CMax problem: J and its exact gradient in the node values of a flow grid.

:class:`DenseFlowProblem` validates its inputs with the same :class:`~cmax_taichi.pipeline.setup.ProblemSetup`
as :class:`~cmax_taichi.ContrastMaximization` (undistortion, polarity, weights, blur, regularizer
weights), then drives the fused kernel of ``kernels/dense_flow.py``: one launch per value and gradient,
no allocation per call, fields pooled per shape (``core/workspace.py``) so that the levels of a
coarse-to-fine run and the windows of a recording share one compiled kernel. The grid of the current
level is a runtime setting (:meth:`DenseFlowProblem.set_grid`); the fields hold the finest grid's nodes.

J (maximised) = ``H - sum_q lambda_q sum_r omega_r R_qr - sum_s lambda_s S_s``: the data term ``H`` (the
weighted harmonic mean of ``G_r / G0`` over the reference times, ``G / G0`` for one), the event-collapse
regularizers of the registry at every reference (``divergence``, ``deformation``, ...), and the
smoothness terms of ``flow/smoothness.py`` (host, float64). Formulas: docs/FORMULAS.md, "Dense flow".
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from cmax_taichi.core import backend, limits, workspace
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.flow.grid import FlowGrid
from cmax_taichi.flow.smoothness import SMOOTHNESS
from cmax_taichi.kernels import dense_flow as kdense
from cmax_taichi.kernels import fused_common as kcommon
from cmax_taichi.models.regularizers import REGULARIZERS
from cmax_taichi.pipeline import tiers
from cmax_taichi.pipeline.footprint import image_layout, kernels_key
from cmax_taichi.pipeline.launch import HostArray, array_bytes, kernel_arrays
from cmax_taichi.pipeline.setup import POLARITY_MODES, ProblemSetup, SetupOptions, check_regularizers

__all__ = ["DenseEvaluation", "DenseFlowProblem", "MULTI_REFERENCE", "resolve_references"]

#: the references of the multi-reference objective of tub-rip/event_based_optical_flow (the
#: "multi-focal" loss: IWEs warped to the first, middle and last event, the middle counted twice)
MULTI_REFERENCE = (("first", "middle", "last"), (1.0, 2.0, 1.0))
_NAMED_REFERENCES = {"first": 0.0, "middle": 0.5, "last": 1.0}
#: images from this many pixels on get their events in pixel-row order (CPU)
SORT_MIN_PIXELS = 65536


def resolve_references(references, weights=None) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``(fractions, weights)``: the reference times as fractions of the window (0 = first event,
    1 = last) and their weights normalised to sum 1.

    ``references`` is ``"multi"`` (:data:`MULTI_REFERENCE`), one of ``"first"``, ``"middle"``,
    ``"last"``, a fraction in [0, 1], or a sequence of those; ``weights`` one positive number per
    reference (default equal, or those of ``"multi"``).
    """
    if isinstance(references, str) and references == "multi":
        references, default = MULTI_REFERENCE
        weights = default if weights is None else weights
    if isinstance(references, (str, numbers.Real)) and not isinstance(references, bool):
        references = (references,)
    try:
        refs = list(references)
    except TypeError:
        raise TypeError(
            f"references must be 'multi', a name, a fraction or a sequence, got {references!r}"
        ) from None
    if not refs:
        raise ValueError("references must name at least one reference time")
    fractions = []
    for ref in refs:
        if isinstance(ref, str):
            if ref not in _NAMED_REFERENCES:
                raise ValueError(
                    f"unknown reference {ref!r}; use 'first', 'middle', 'last' or a fraction of the "
                    "window in [0, 1]"
                )
            fractions.append(_NAMED_REFERENCES[ref])
        elif isinstance(ref, numbers.Real) and not isinstance(ref, bool) and 0.0 <= float(ref) <= 1.0:
            fractions.append(float(ref))
        else:
            raise ValueError(
                f"a reference time must be a name or a fraction of the window in [0, 1], got {ref!r}"
            )
    if weights is None:
        w = np.ones(len(fractions))
    else:
        try:
            w = np.asarray(weights, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise TypeError(f"reference_weights must be numbers, got {weights!r}") from None
        if w.size != len(fractions):
            raise ValueError(f"{w.size} reference weight(s) for {len(fractions)} reference(s)")
        if not np.all(np.isfinite(w)) or np.any(w <= 0):
            raise ValueError(f"reference weights must be finite and > 0, got {w.tolist()}")
    w = w / w.sum()
    return tuple(fractions), tuple(float(v) for v in w)


def split_regularizers(regularizers) -> tuple[dict[str, float], dict[str, float]]:
    """``(event_map_regularizers, smoothness)``: the weights of ``regularizers`` split between the
    registry of ``cmax_taichi.models.regularizers`` and that of ``flow/smoothness.py``."""
    if regularizers is None:
        return {}, {}
    if not isinstance(regularizers, Mapping):
        raise TypeError("regularizers must be a mapping name -> weight, e.g. {'deformation': 1.0}")
    maps, smooth = {}, {}
    for name, weight in regularizers.items():
        if name in SMOOTHNESS:
            smooth[name] = weight
        elif name in REGULARIZERS:
            maps[name] = weight
        else:
            raise ValueError(
                f"unknown regularizer {name!r}; valid: {', '.join(REGULARIZERS.names() + SMOOTHNESS.names())}"
            )
    return check_regularizers(maps), {name: _weight(name, w) for name, w in smooth.items()}


def _weight(name: str, weight) -> float:
    """A regularizer weight: a finite number >= 0 (the checks of ``check_regularizers``)."""
    if not isinstance(weight, numbers.Real) or isinstance(weight, (bool, np.bool_)):
        raise TypeError(f"weight of regularizer {name!r} must be a number, got {weight!r}")
    try:
        w = float(weight)
    except OverflowError:  # an int such as 10**400
        w = math.inf
    if not (math.isfinite(w) and w >= 0):
        raise ValueError(f"weight of regularizer {name!r} must be finite and >= 0, got {w}")
    return w


@dataclass(frozen=True)
class DenseEvaluation:
    """J of a dense flow and its terms.

    Attributes
    ----------
    J : float
        The augmented objective (maximised).
    data : float
        ``H``: the weighted harmonic mean of ``G_r / G0`` (``G_r`` raw where ``normalize=False``).
    G : tuple of float
        Raw objective of each reference's IWE.
    penalties : dict
        Each event-map regularizer's ``sum_r omega_r R_qr`` (dimensionless).
    penalties_per_reference : dict
        Each event-map regularizer's ``R_qr`` per reference.
    smoothness : dict
        Each smoothness term's value (before its weight).
    """

    J: float
    data: float
    G: tuple[float, ...]
    penalties: dict = field(default_factory=dict)
    penalties_per_reference: dict = field(default_factory=dict)
    smoothness: dict = field(default_factory=dict)


def _row_keys(y: np.ndarray, height: int) -> np.ndarray:
    dtype = np.int16 if height < np.iinfo(np.int16).max else np.int32
    return np.clip(y, 0, height - 1).astype(dtype)


def _node_capacity(n_nodes: int) -> int:
    cap = 64
    while cap < n_nodes:
        cap *= 2
    return cap


class DenseFlowProblem:
    """J and dJ/dU of a dense flow ``U`` (node values, px/s) on one window of events.

    Parameters
    ----------
    events : Events
        The window (at least 2 events spanning a positive time).
    grid : FlowGrid or (int, int)
        The finest grid of the run (cells along x and y): the capacity of the fields. Coarser grids of
        the same sensor are set with :meth:`set_grid`.
    objective : str
        A registered objective with a fused declaration (``variance``, ``gradient_magnitude``,
        ``mean_square``).
    references : str, float or sequence
        Reference times of the IWEs, as for :func:`resolve_references`: ``"first"`` (default), or
        ``"multi"`` for the multi-reference objective.
    reference_weights : sequence of float, optional
        One positive weight per reference (normalised to sum 1).
    regularizers : mapping, optional
        ``{name: lambda}``: event-collapse regularizers of ``cmax_taichi.REGULARIZERS`` declaring a
        quantity kind and ``penalty_grad``, and smoothness terms of ``cmax_taichi.flow.SMOOTHNESS``.
    camera : Camera, optional
        Undistorts the events when it has distortion coefficients.
    blur_sigma : float
        Gaussian blur of the IWEs, px (0 = none).
    normalize : bool
        Divide each ``G_r`` by ``G0``, the objective of the unwarped events (the identity).
    polarity : {"ignore", "signed", "split"}
    weights : array_like, optional
        Per-event vote weights.
    padding : int
        Margin of the IWEs around the sensor, px: events warped up to this far outside the sensor still
        vote. Without it, an expanding flow that carries texture out of the image loses those events
        from the IWE, which biases the estimate near the borders towards less motion (0 = the sensor's
        image, as :class:`~cmax_taichi.ContrastMaximization`).
    """

    def __init__(
        self,
        events: Events,
        grid: FlowGrid | tuple[int, int] = (16, 16),
        *,
        objective: str = "gradient_magnitude",
        references="first",
        reference_weights: Sequence[float] | None = None,
        regularizers: Mapping[str, float] | None = None,
        camera: Camera | None = None,
        blur_sigma: float = 1.0,
        normalize: bool = True,
        polarity: str = "ignore",
        weights: Sequence[float] | np.ndarray | None = None,
        padding: int = 0,
    ) -> None:
        if not isinstance(events, Events):
            raise TypeError(f"events must be cmax_taichi.Events, got {type(events).__name__}")
        if polarity not in POLARITY_MODES:
            raise ValueError(f"unknown polarity mode {polarity!r}; valid: {', '.join(POLARITY_MODES)}")
        if isinstance(padding, bool) or not isinstance(padding, (int, np.integer)) or padding < 0:
            raise ValueError(f"padding must be a whole number of px >= 0, got {padding!r}")
        self.padding = int(padding)
        backend.ensure_initialized()
        self.fractions, self.reference_weights = resolve_references(references, reference_weights)
        map_regs, self.smoothness_weights = split_regularizers(regularizers)
        # the IWEs' reference times are self.fractions; the set-up keeps t_ref "first"
        self._options = SetupOptions(objective, map_regs, camera, "first", blur_sigma, normalize, polarity)
        setup = self._setup_for(events, weights)
        self.objective = setup.objective
        if self.objective.fused is None:
            raise ValueError(
                f"objective {self.objective.name!r} has no fused declaration (FusedObjective): the dense "
                "flow kernels compute only such objectives"
            )
        self.regularizers = setup.regularizers
        for reg in self.regularizers:
            if reg.kind is None or reg.penalty_grad is None:
                raise ValueError(
                    f"regularizer {reg.name!r} does not declare a quantity kind ('div' or 'absdet') and a "
                    "penalty_grad: the dense flow kernels need both"
                )
        self.regularizer_weights = dict(setup.regularizer_weights)
        self.width, self.height = setup.width, setup.height
        if not isinstance(grid, FlowGrid):
            try:
                nx, ny = grid
            except (TypeError, ValueError):
                raise TypeError(f"grid must be a FlowGrid or (cells_x, cells_y), got {grid!r}") from None
            grid = FlowGrid(self.width, self.height, nx, ny)
        if (grid.width, grid.height) != (self.width, self.height):
            raise ValueError(
                f"grid is for a {grid.width}x{grid.height} sensor, the events for {self.width}x{self.height}"
            )
        self.finest = grid
        self.n_channels = setup.n_channels
        self._build(setup)
        self.set_grid(grid)
        self._take_window(setup)

    # --- set-up -------------------------------------------------------------------------------------
    def _setup_for(self, events: Events, weights) -> ProblemSetup:
        return self._options.build(events, [], weights)

    def _build(self, setup: ProblemSetup) -> None:
        P = self.padding
        W, H, C = setup.width + 2 * P, setup.height + 2 * P, setup.n_channels  # the image of the kernels
        R, Q = len(self.fractions), len(self.regularizers)
        obj = self.objective.fused
        self._atomic = backend.info().arch != "cpu"
        weighted = setup.vote_weights is not None
        split = setup.polarity == "split"
        layout = image_layout(
            n_channels=C,
            radius=setup.radius,
            shared_count=Q > 0 and not weighted and not split,
            objective_slots=self.objective.slots_per_channel,
            sobel=obj.sobel,
            atomic=self._atomic,
        )
        slices, shared = layout.n_slices, layout.shared_count
        self._weighted, self._split = weighted, split
        cap = _node_capacity(self.finest.n_nodes)
        itemsize = np.dtype(backend.numpy_real()).itemsize
        limits.check_sensor(W, H, "the dense flow problem")
        limits.check_blur_sigma(setup.blur_sigma)
        block = kdense.channel_layout(C, Q, shared)[2]
        per_pixel = (slices + 1) * R * block + (3 + (3 if obj.sobel else 0)) * R * C
        estimate = (
            itemsize * (W * H * per_pixel + 5 * workspace.capacity_for(setup.n_events)) + 16 * slices * cap
        )
        limits.check_bytes(
            estimate,
            "the dense flow problem",
            f"sensor {W}x{H}, {R} reference(s), {Q} regularizer(s), {setup.n_events:,} events",
        )
        shape = self._shape = kdense.DenseFlowShape(layout, R, Q, self._atomic)
        self._image = (W, H)
        # the arrays of this image (shared by the problems of this shape and image) and of this grid capacity
        self._ws = workspace.acquire(
            ("dense_flow", backend.info().generation, shape, W, H),
            lambda ws: setattr(ws, "arrays", kernel_arrays(shape.array_sizes(W, H), self._atomic)),
            f"a {W}x{H} dense flow problem",
        )
        self._node_ws = workspace.acquire(
            ("dense_flow_nodes", backend.info().generation, shape, cap),
            lambda ws: setattr(ws, "arrays", kernel_arrays(shape.node_sizes(cap), self._atomic)),
            f"the nodes of a {cap}-node dense flow problem",
        )
        self.max_nodes = cap
        regs = self.regularizers
        kkey = (
            "dense_flow",
            backend.info().generation,
            shape,
            *kernels_key(self.objective.name, obj, regs, weighted, split, self._atomic),
        )
        # one Taichi kernel per tier (Taichi compiles a kernel object once, with the options of then)
        self._kernels_key = kkey
        self._build_kernel = lambda: kdense.make_dense_flow_kernels(
            shape,
            tuple(r.kind for r in regs),
            tuple(r.penalty for r in regs),
            tuple(r.penalty_grad for r in regs),
            tuple(bool(r.one_sided) for r in regs),
            objective=obj,
            events=kcommon.EventLayout(weighted, split, self._atomic),
        )
        self.kernel_config = tiers.dense_config(self, setup, weighted, slices, self._atomic)
        self.tier = "full"  # the compiled tier of the current window's kernel (_take_window)
        self._params_at = shape.params_layout()
        self._params = np.zeros(self._params_at["size"])
        self._out = np.zeros(2 + R + Q + Q * R)
        self._gout = np.zeros(2 * cap)
        self._nodes_buf = np.zeros(2 * cap, dtype=backend.numpy_real())
        self._event_buffer = None
        self._generation = backend.info().generation

    def _take_window(self, setup: ProblemSetup) -> None:
        """Load a window: its events, constants and G0."""
        self.setup = setup
        self.tier = tiers.current_tier(self.kernel_config)  # (the optimized kernel from when it is ready)
        self.events = setup.events
        self.n_events = setup.n_events
        self.duration = setup.duration
        self.t_first = float(setup.events.t[0])
        t_refs = [self.t_first + fr * self.duration for fr in self.fractions]
        mean_t = float(np.mean(setup.events.t))
        self.orientations = tuple(1.0 if t <= mean_t else -1.0 for t in t_refs)
        regs = self.regularizers
        self._lam = [self.regularizer_weights[r.name] for r in regs] + [
            r.scale(self.duration, o) for r in regs for o in self.orientations
        ]
        at, params = self._params_at, self._params
        R = len(self.fractions)
        params[at["ref_off"] : at["ref_off"] + R] = [fr * self.duration for fr in self.fractions]
        params[at["ref_w"] : at["ref_w"] + R] = self.reference_weights
        params[at["lam"] : at["lam"] + len(self._lam)] = self._lam
        if setup.taps is not None:  # (without blur the kernel's one tap is 1)
            params[at["taps"] : at["taps"] + len(setup.taps)] = setup.taps
        ev = setup.events
        cols = [ev.x + self.padding, ev.y + self.padding, ev.t - self.t_first]
        if self._weighted:
            cols.append(setup.vote_weights)
        if self._split:
            cols.append((ev.p < 0).astype(np.float64))
        cap = workspace.capacity_for(self.n_events)
        if self._event_buffer is None or self._event_buffer.capacity != cap:
            self._event_buffer = workspace.event_buffer(backend.real(), len(cols), self.n_events)
            self._packed = np.zeros((cap, len(cols)), dtype=backend.numpy_real())
        else:
            self._packed[self.n_events :] = 0.0
        # CPU, large images: events in pixel-row order (a stable sort: time order within a row), so that
        # consecutive events touch the same rows of the images, which stay in cache (pipeline/fused.py).
        # Small images stay in cache anyway, and there the sorted events would add into the same pixels
        # one after the other, each waiting on the last one's store (measured 3x slower at 87 x 65 px
        # with 30,000 events); a GPU takes them as they come
        sort = not self._atomic and self.width * self.height >= SORT_MIN_PIXELS
        order = np.argsort(_row_keys(ev.y, self.height), kind="stable") if sort else slice(None)
        for j, col in enumerate(cols):
            self._packed[: self.n_events, j] = col[order]
        self._event_buffer.release()
        self._g0 = 1.0
        if setup.normalize:
            g0 = self._raw_identity()
            if not g0 > 0.0:
                raise ValueError(
                    "G0 = 0: the objective of the unwarped events is 0, so it cannot normalise (too few "
                    "events, or all of them outside the sensor)"
                )
            self._g0 = g0

    def _raw_identity(self) -> float:
        """Raw G of the unwarped events (any reference: they coincide)."""
        saved = self._g0
        self._g0 = 1.0
        out = self._launch(np.zeros(self.grid.shape), grad=0, maps=False)
        self._g0 = saved
        return float(out[2])

    def set_events(self, events: Events, weights: Sequence[float] | np.ndarray | None = None) -> None:
        """Take the next window (same sensor and options): the fields and compiled kernel are reused."""
        self._check_alive()
        if not isinstance(events, Events):
            raise TypeError(f"events must be cmax_taichi.Events, got {type(events).__name__}")
        if events.sensor_size != (self.width, self.height):
            raise ValueError(
                f"events are for a {events.sensor_size} sensor, the problem for {(self.width, self.height)}"
            )
        setup = self._setup_for(events, weights)
        if (setup.vote_weights is not None) != self._weighted:
            raise ValueError(
                "set_events cannot switch between weighted and unweighted votes: build a new problem"
            )
        self._take_window(setup)

    def set_grid(self, grid: FlowGrid) -> None:
        """Evaluate on ``grid`` from now on (a grid of this sensor with at most the finest grid's nodes)."""
        if not isinstance(grid, FlowGrid):
            raise TypeError(f"grid must be a FlowGrid, got {type(grid).__name__}")
        if (grid.width, grid.height) != (self.width, self.height):
            raise ValueError(
                f"grid is for a {grid.width}x{grid.height} sensor, the problem for {self.width}x{self.height}"
            )
        if grid.n_nodes > self.max_nodes:
            raise ValueError(
                f"a {grid.nx}x{grid.ny}-cell grid has {grid.n_nodes} nodes; this problem holds "
                f"{self.max_nodes} "
                "(build it with the finest grid of the run)"
            )
        self.grid = grid
        sx, sy = grid.spacing
        at = self._params_at["grid"]
        self._params[at : at + 6] = [grid.nx, grid.ny, 1.0 / sx, 1.0 / sy, self.padding, self.padding]

    def _check_alive(self) -> None:
        if backend.info().generation != self._generation:
            raise RuntimeError(
                "the Taichi backend was re-initialised since this problem was built: build it again"
            )

    # --- evaluation ------------------------------------------------------------------------------------
    def _load(self, U: np.ndarray) -> None:
        self._event_buffer.load(self, self._packed)
        self._nodes_buf[: 2 * self.grid.n_nodes] = U.reshape(-1)
        self._nodes_buf[2 * self.grid.n_nodes :] = 0.0
        self._params[self._params_at["g0"]] = self._g0
        nodes = self._node_ws.arrays["nodes"]
        if not isinstance(nodes, HostArray):  # a GPU's node array: uploaded
            nodes.from_numpy(self._nodes_buf)
        else:
            nodes.array[:] = self._nodes_buf

    def _launch(self, U: np.ndarray, grad: int, maps: bool = True) -> np.ndarray:
        self._check_alive()
        self._load(U)
        arrays = {**self._ws.arrays, **self._node_ws.arrays}
        kernel = workspace.compiled((*self._kernels_key, self.tier), self._build_kernel)
        with backend.hand_written_gradient_kernels(self.tier):  # one slice per thread; the tier
            kernel(
                self.n_events,
                self._event_buffer.array,
                self.grid.n_nodes,
                grad,
                int(maps),
                self._out,
                self._gout,
                self._params,
                *self._image,
                *(a.array if isinstance(a, HostArray) else a for a in arrays.values()),
            )
        return self._out

    def _smoothness(self, U: np.ndarray, grad: bool):
        """``(sum_s lambda_s S_s, d/dU, {name: S_s})`` of the smoothness terms at node flow ``U``."""
        total, values = 0.0, {}
        g = np.zeros(U.shape) if grad else None
        D = U * self.duration
        for name, lam in self.smoothness_weights.items():
            value, dvalue = SMOOTHNESS.get(name).value_and_grad(D, self.grid)
            values[name] = float(value)
            total += lam * value
            if grad:
                g += lam * self.duration * dvalue
        return total, g, values

    def value(self, nodes, maps: bool = True) -> float:
        """J at node flow ``nodes`` (px/s, shape ``grid.shape`` or flat). ``maps=False`` leaves out the
        event-map regularizers (exact for a constant flow, whose divergence is 0 and determinant 1 at every
        event, so that every map has its neutral value; the global search evaluates such flows)."""
        U = self.grid.check_nodes(nodes)
        out = self._launch(U, 0, maps)
        penalty, _, _ = self._smoothness(U, False)
        return float(out[0]) - penalty

    def value_and_grad(self, nodes) -> tuple[float, np.ndarray]:
        """``(J, dJ/dU)`` at node flow ``nodes``; the gradient has the shape ``grid.shape`` (1/(px/s))."""
        U = self.grid.check_nodes(nodes)
        out = self._launch(U, 1)
        g = self._gout[: self.grid.n_params].reshape(self.grid.shape).copy()
        penalty, gs, _ = self._smoothness(U, True)
        return float(out[0]) - penalty, g - gs

    def evaluate(self, nodes) -> DenseEvaluation:
        """J and its terms at node flow ``nodes``."""
        U = self.grid.check_nodes(nodes)
        out = self._launch(U, 0).copy()
        penalty, _, smooth = self._smoothness(U, False)
        R, Q = len(self.fractions), len(self.regularizers)
        names = [r.name for r in self.regularizers]
        return DenseEvaluation(
            J=float(out[0]) - penalty,
            data=float(out[1]),
            G=tuple(float(v) for v in out[2 : 2 + R]),
            penalties={n: float(out[2 + R + q]) for q, n in enumerate(names)},
            penalties_per_reference={
                n: tuple(float(out[2 + R + Q + q * R + r]) for r in range(R)) for q, n in enumerate(names)
            },
            smoothness=smooth,
        )

    @property
    def g0(self) -> float:
        """``G0``: the raw objective of the unwarped events (1 where ``normalize=False``)."""
        return self._g0

    def iwe(self, nodes, reference: int = 0, padded: bool = False) -> np.ndarray:
        """The blurred IWE of reference ``reference`` at node flow ``nodes``: (H, W), (2, H, W) split; with
        ``padded`` the whole image of the kernels (``padding`` px more on every side)."""
        if not (isinstance(reference, (int, np.integer)) and 0 <= reference < len(self.fractions)):
            raise ValueError(f"reference must be an index in 0..{len(self.fractions) - 1}, got {reference!r}")
        U = self.grid.check_nodes(nodes)
        self._launch(U, 0)
        C, P = self.n_channels, self.padding
        W, H = self._image
        images = self._ws.arrays["images"]
        flat = images.array if isinstance(images, HostArray) else images.to_numpy()
        # the planes tmp, then img (DenseFlowShape.image_planes)
        first = len(self.fractions) * C + reference * C
        img = flat[first * W * H : (first + C) * W * H].reshape(C, H, W).astype(np.float64)
        if not padded and P:
            img = img[:, P : P + self.height, P : P + self.width]
        return img[0] if C == 1 else img

    def flow(self, nodes, dt: float | None = None) -> np.ndarray:
        """The flow on every pixel, ``(2, H, W)``: px/s, or with ``dt`` (s) the displacement ``dt u(x)``
        over ``dt`` (px)."""
        U = self.grid.check_nodes(nodes)
        out = self.grid.dense(U)
        if dt is not None:
            if not (isinstance(dt, numbers.Real) and math.isfinite(dt)):
                raise ValueError(f"dt must be a finite number of seconds, got {dt!r}")
            out = out * float(dt)
        return out

    def event_quantities(self, nodes, reference: int = 0) -> dict[str, np.ndarray]:
        """Per event at node flow ``nodes`` (float64, the window's event order): the warped position
        ``xw, yw`` (px) to reference ``reference``, ``div`` (1/s) and ``det`` (``det(I - dt Du)``)."""
        U = self.grid.check_nodes(nodes)
        ev = self.events
        dt = ev.t - (self.t_first + self.fractions[reference] * self.duration)
        u = self.grid.interpolate(U, ev.x, ev.y)
        du_dx, du_dy = self.grid.derivatives(U, ev.x, ev.y)
        det = (1 - dt * du_dx[0]) * (1 - dt * du_dy[1]) - dt * dt * du_dy[0] * du_dx[1]
        return {"xw": ev.x - dt * u[0], "yw": ev.y - dt * u[1], "div": du_dx[0] + du_dy[1], "det": det}

    def maps(self, nodes, reference: int = 0) -> dict[str, np.ndarray]:
        """The regularizer maps at reference ``reference`` (for figures): ``count`` C(x) (H, W), ``div``
        DIV(x) (1/s) and ``def`` DEF(x), NaN where no event landed (docs/FORMULAS.md)."""
        q = self.event_quantities(nodes, reference)
        W, H = self.width, self.height
        count = np.zeros((H, W))
        num_div = np.zeros((H, W))
        num_def = np.zeros((H, W))
        w = np.ones(self.n_events) if self.setup.vote_weights is None else np.abs(self.setup.vote_weights)
        xw, yw = q["xw"], q["yw"]
        ok = np.isfinite(xw) & np.isfinite(yw) & (xw > -1) & (xw < W) & (yw > -1) & (yw < H)
        x0, y0 = np.floor(xw[ok]).astype(np.int64), np.floor(yw[ok]).astype(np.int64)
        ax, ay = xw[ok] - x0, yw[ok] - y0
        for dx, dy, share in (
            (0, 0, (1 - ax) * (1 - ay)),
            (1, 0, ax * (1 - ay)),
            (0, 1, (1 - ax) * ay),
            (1, 1, ax * ay),
        ):
            cx, cy = x0 + dx, y0 + dy
            inside = (cx >= 0) & (cx < W) & (cy >= 0) & (cy < H)
            vote = (w[ok] * share)[inside]
            np.add.at(count, (cy[inside], cx[inside]), vote)
            np.add.at(num_div, (cy[inside], cx[inside]), vote * q["div"][ok][inside])
            np.add.at(num_def, (cy[inside], cx[inside]), vote * np.abs(q["det"][ok][inside]))
        with np.errstate(invalid="ignore", divide="ignore"):
            div_map = np.where(count > 0, num_div / count, np.nan)
            def_map = np.where(count > 0, num_def / count, np.nan)
        return {"count": count, "div": div_map, "def": def_map}

    def nbytes(self) -> int:
        """Bytes of the shared image fields plus this problem's event array."""
        return array_bytes(self._ws.arrays) + array_bytes(self._node_ws.arrays) + self._packed.nbytes

    def __repr__(self) -> str:
        regs = {**self.regularizer_weights, **self.smoothness_weights}
        return (
            f"DenseFlowProblem({self.n_events} events, {self.width}x{self.height}, grid "
            f"{self.grid.nx}x{self.grid.ny} "
            f"cells, objective {self.objective.name!r}, references {self.fractions}, regularizers {regs})"
        )
