"""Estimating a dense flow: coarse to fine, L-BFGS-B on the exact gradient, deterministic.

:class:`DenseFlowEstimator` holds the problems of a run (one per image resolution, each a
:class:`~cmax_taichi.flow.problem.DenseFlowProblem` whose fields and compiled kernel serve every window
of a recording) and solves one window with :meth:`DenseFlowEstimator.estimate`:

1. the start: a global search over constant flows (``init="search"``: the best translation of a
   coarse-to-fine grid of displacements, on the coarsest image), zero, given node values, or the
   previous window's flow (``warm=``: its field fitted to the coarsest grid by least squares);
2. the levels, coarsest grid first: SciPy's L-BFGS-B maximises J in the node displacements over the
   window (px), each level started from the exact prolongation of the last (``FlowGrid.prolong``:
   the same interpolant on the refined grid). A level may run on a downsampled image (``scales``):
   the events' coordinates are scaled so that the grid's nodes keep their places, and the divergence,
   the determinant and the strain of the smoothness terms are the same at every scale.

Everything is deterministic on one machine at a given number of CPU threads: the kernels add their
per-thread partial sums in a fixed order and L-BFGS-B is a deterministic algorithm, so the same window
gives the same flow to the last bit. Another thread count groups the sums differently, and the flow moves
by up to about 0.02 px with the defaults (docs/flow.md, "Deterministic at a given thread count"). The
levels maximise J with the regularizers' kinks rounded (:data:`KINK_WIDTH`) and report what their
optimizer did (:class:`LevelReport`); a level that L-BFGS-B leaves where it started gets a fallback.
:func:`estimate_flow` is the one-call form.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from cmax_taichi.core.checks import OptimizerStallWarning
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.flow.grid import FlowGrid, auto_padding
from cmax_taichi.flow.problem import DenseEvaluation, DenseFlowProblem, resolve_references

__all__ = [
    "DEFAULT_OPTIONS",
    "DEFAULT_REGULARIZERS",
    "DenseFlowEstimator",
    "FlowResult",
    "KINK_WIDTH",
    "LEVEL_STATUSES",
    "LevelReport",
    "auto_iterations",
    "auto_scales",
    "estimate_flow",
]

#: the weights of :class:`DenseFlowEstimator` unless given (docs/flow.md, "What each regularizer does",
#: the ablation of ``python -m benchmarks.flow_ablation``): the curvature prior against local collapse
#: and for accuracy, the paper's two penalties as the guard when the reference time or the weights move
DEFAULT_REGULARIZERS = {"divergence": 1.0, "deformation": 1.0, "curvature": 0.1}
#: the width of the regularizers' rounded kinks in the optimizer's objective by default (``kink_width``;
#: docs/flow.md, "Kinks of the penalties"): the divergence's hinge at R = 0 and the deformation's
#: ``max(D, 1/D)`` at D = 1, where every event of a constant flow sits
KINK_WIDTH = 0.001
#: the share of the larger sensor side that pads the IWEs by default (``padding=None``)
AUTO_PADDING = 0.03
#: the options of :class:`DenseFlowEstimator` that are not its grid and levels, as it defaults them
DEFAULT_OPTIONS = {
    "objective": "gradient_magnitude",
    "references": "middle",
    "regularizers": DEFAULT_REGULARIZERS,
    "blur_sigma": 1.0,
    "padding": None,
    "dither": True,
    "kink_width": KINK_WIDTH,
}
#: the seed of the sub-pixel dither of integer event coordinates (``dither=True``): fixed, so the same
#: window gives the same flow to the last bit
DITHER_SEED = 0


def auto_iterations(levels: int) -> tuple[int, ...]:
    """L-BFGS-B iterations per level when not given: 15 on the coarse levels (they converge in about
    10-20 evaluations on the MVSEC cut), 20 on the level before the finest, 30 on the finest."""
    return tuple(30 if k == levels - 1 else 20 if k == levels - 2 else 15 for k in range(levels))


def auto_scales(levels: int) -> tuple[int, ...]:
    """The image downsampling of each level (coarsest first) when not given: ``min(4, 2^(levels - 1 - k))``,
    e.g. (4, 4, 2, 1) for 4 levels: the coarse grids do not need the full image, whose cost per
    evaluation is 4 to 16 times theirs."""
    return tuple(2 ** min(2, levels - 1 - k) for k in range(levels))  # no 2^levels: levels may be huge


#: what a level's optimizer did (:attr:`LevelReport.status`): L-BFGS-B converged; it used its
#: iterations or evaluations (``max_iter``); it failed or did not move and the fallback moved the flow;
#: neither moved it (the level's flow is its start, and the run warns)
LEVEL_STATUSES = ("converged", "limit", "fallback", "stalled")
#: the fallback of a level whose L-BFGS-B failed or did not move: gradient ascent with an Armijo line
#: search (:func:`cmax_taichi.solve.local.armijo`) from the best point, its first trial step this many px
#: of node displacement, stopping at a step below FALLBACK_XTOL px or after the level's ``max_iter``
FALLBACK_STEP = 0.5
FALLBACK_XTOL = 1e-3


@dataclass(frozen=True)
class LevelReport:
    """One level of a coarse-to-fine run.

    Attributes
    ----------
    grid : FlowGrid
        The level's grid.
    scale : int
        Image downsampling of the level (1 = full resolution).
    iterations, evaluations : int
        Iterations (L-BFGS-B's, plus the fallback's) and J evaluations.
    value_start, value : float
        J at the level's start and end (on the level's image, with the regularizers' rounded kinks:
        the value the optimizer maximises).
    seconds : float
        Wall time of the level.
    message : str
        Why L-BFGS-B stopped (and the fallback, where it ran).
    status : str
        One of :data:`LEVEL_STATUSES`.
    change : float
        The largest change of a node's displacement over the window that the level made, px of the
        full-resolution image (0: the level ended at its start).
    """

    grid: FlowGrid
    scale: int
    iterations: int
    evaluations: int
    value_start: float
    value: float
    seconds: float
    message: str
    status: str = "converged"
    change: float = 0.0

    def summary(self) -> str:
        """``"16x16 limit 30 it 1.52 px"``: cells, status, iterations and change, for tables."""
        return f"{self.grid.nx}x{self.grid.ny} {self.status} {self.iterations} it {self.change:.3g} px"


@dataclass
class FlowResult:
    """A window's dense flow.

    Attributes
    ----------
    grid : FlowGrid
        The finest grid.
    nodes : ndarray, shape ``grid.shape``
        Node flow, px/s.
    t_start, t_end : float
        Time of the window's first and last event, s.
    n_events : int
        Events of the window (after undistortion, those on the sensor).
    value : float
        J at the result (full resolution).
    evaluation : DenseEvaluation
        Its terms.
    levels : list of LevelReport
    n_evaluations : int
        J evaluations of the whole run (search and levels).
    seconds : float
        Wall time of the run.
    init : str
        How the run started: ``"search"``, ``"zero"``, ``"given"`` or ``"warm"``.
    """

    grid: FlowGrid
    nodes: np.ndarray
    t_start: float
    t_end: float
    n_events: int
    value: float
    evaluation: DenseEvaluation
    levels: list[LevelReport] = field(default_factory=list)
    n_evaluations: int = 0
    seconds: float = 0.0
    init: str = ""

    @property
    def duration(self) -> float:
        """Window duration, s."""
        return self.t_end - self.t_start

    @property
    def stalled_levels(self) -> list[int]:
        """Indices (coarsest first) of the levels whose optimizer and fallback did not move the flow."""
        return [k for k, lv in enumerate(self.levels) if lv.status == "stalled"]

    @property
    def status(self) -> str:
        """``"ok"``, or ``"stalled"`` when a level did not move (:attr:`stalled_levels`)."""
        return "stalled" if self.stalled_levels else "ok"

    @property
    def sensor_size(self) -> tuple[int, int]:
        return (self.grid.width, self.grid.height)

    def flow(self, dt: float | None = None, layout: str = "chw", trajectories: bool = True) -> np.ndarray:
        """The flow on every pixel: px/s, or with ``dt`` (s) the displacement over ``dt`` (px) of the
        point seen at each pixel at the start: its path under the flow integrated
        (:meth:`FlowGrid.trajectories`), or with ``trajectories=False`` the straight line ``dt u(x)``.
        ``layout="chw"``: ``(2, H, W)`` (the library's layout: writers, metrics); ``"hwc"``:
        ``(H, W, 2)``."""
        if dt is None:
            out = self.grid.dense(self.nodes)
        else:
            if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt)):
                raise ValueError(f"dt must be a finite number of seconds, got {dt!r}")
            if trajectories:
                out = self.grid.trajectories(self.nodes, float(dt))
            else:
                out = self.grid.dense(self.nodes) * float(dt)
        if layout == "hwc":
            return np.moveaxis(out, 0, -1)
        if layout != "chw":
            raise ValueError(f"layout must be 'chw' or 'hwc', got {layout!r}")
        return out

    def displacement(self, layout: str = "chw", trajectories: bool = True) -> np.ndarray:
        """The displacement over the window (px): :meth:`flow` with ``dt = duration``."""
        return self.flow(self.duration, layout, trajectories)

    def as_dict(self) -> dict:
        """A JSON-friendly summary (no node values)."""
        return {
            "t_start": self.t_start,
            "t_end": self.t_end,
            "n_events": self.n_events,
            "grid": [self.grid.nx, self.grid.ny],
            "value": self.value,
            "value_rounded": self.evaluation.J_rounded,
            "status": self.status,
            "data": self.evaluation.data,
            "penalties": self.evaluation.penalties,
            "smoothness": self.evaluation.smoothness,
            "n_evaluations": self.n_evaluations,
            "seconds": self.seconds,
            "init": self.init,
            "levels": [
                {
                    "cells": [lv.grid.nx, lv.grid.ny],
                    "scale": lv.scale,
                    "iterations": lv.iterations,
                    "evaluations": lv.evaluations,
                    "value_start": lv.value_start,
                    "value": lv.value,
                    "seconds": lv.seconds,
                    "status": lv.status,
                    "change_px": lv.change,
                    "message": lv.message,
                }
                for lv in self.levels
            ],
        }


def _scale_factors(sensor_size: tuple[int, int], scale: int) -> tuple[int, int, float, float]:
    """``(W', H', kx, ky)``: the sensor ``scale`` times smaller and the coordinate factors
    ``k = (W' - 1) / (W - 1)`` (x), likewise y, that keep the grid's nodes in their places."""
    W, H = sensor_size
    if scale == 1:
        return W, H, 1.0, 1.0
    Ws, Hs = max(2, math.ceil(W / scale)), max(2, math.ceil(H / scale))
    return Ws, Hs, (Ws - 1) / (W - 1), (Hs - 1) / (H - 1)


def on_pixel_grid(events: Events) -> bool:
    """Whether every coordinate of ``events`` is a whole number of px (as sensors record them)."""
    x, y = events.x, events.y
    return len(events) > 0 and np.array_equal(x, np.floor(x)) and np.array_equal(y, np.floor(y))


def dithered(events: Events, seed: int = DITHER_SEED, grid: bool | None = None) -> Events:
    """``events`` with their pixel coordinates spread uniformly over their pixel (+-0.5 px, seeded,
    kept on the sensor). ``grid``: whether they lie on a pixel grid; None: when
    :func:`on_pixel_grid` (other events, e.g. undistorted ones, are returned unchanged); True for
    events undistorted from whole pixels (their grid is locally the pixel grid, shifted).

    Events on the integer grid vote, unwarped, into single pixels, and every warp that moves them
    less than a pixel splits their votes: the IWE's contrast then has a spurious maximum at zero
    displacement along each axis, which pulls small flow components towards 0 (docs/flow.md,
    "The solver"). Spread over their pixel (where the event happened, as far as the sensor knows)
    they have no preferred sub-pixel position.
    """
    if len(events) == 0 or not (on_pixel_grid(events) if grid is None else grid):
        return events
    x, y = events.x, events.y
    W, H = events.sensor_size
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(-0.5, 0.5, (2, len(events)))
    return Events(
        np.clip(x + offsets[0], 0.0, W - 1.0),
        np.clip(y + offsets[1], 0.0, H - 1.0),
        events.t,
        events.p,
        events.sensor_size,
        undistorted=events.undistorted,
        _validated=True,  # clipped into the sensor: nothing to check or drop
    )


def _scaled_events(events: Events, scale: int, stride: int = 1) -> Events:
    """Every ``stride``-th event, on the sensor ``scale`` times smaller (:func:`_scale_factors`)."""
    if stride > 1 and len(events) >= 2 * stride:
        events = events[::stride]
    if scale == 1:
        return events
    Ws, Hs, kx, ky = _scale_factors(events.sensor_size, scale)
    return Events(
        np.clip(events.x * kx, 0.0, Ws - 1.0),
        np.clip(events.y * ky, 0.0, Hs - 1.0),
        events.t,
        events.p,
        (Ws, Hs),
        undistorted=True,
        _validated=True,  # clipped into the sensor: nothing to check or drop
    )


class DenseFlowEstimator:
    """Coarse-to-fine dense flow estimation of windows of one sensor (see the module docstring).

    Parameters
    ----------
    grid : FlowGrid or (int, int)
        The finest grid, or its cell counts (x, y); default 16 x 16 cells (the finest level of the
        reference's released MVSEC configuration: 2 x 2 to 16 x 16 patches).
    levels : int
        Grids of the run: the cells halve ``levels - 1`` times from the finest (default 4).
    scales : sequence of int, optional
        Image downsampling per level (coarsest first, each >= 1); default :func:`auto_scales`. The global
        search runs at the first level's scale.
    objective : str
        A registered objective with a fused declaration (default ``"gradient_magnitude"``; as for
        ``DenseFlowProblem``).
    references : str, float or sequence
        Reference times of the IWEs (default ``"middle"``; ``"multi"``: the multi-reference objective).
    reference_weights : sequence of float, optional
        One positive weight per reference.
    blur_sigma : float
        Gaussian blur of the IWEs, px (default 1; 0 = none).
    normalize : bool
        Divide each objective by that of the unwarped events (default True).
    polarity : {"ignore", "signed", "split"}
        How polarities vote (default ``"ignore"``).
    regularizers : mapping, optional
        ``{name: lambda}``, event-collapse regularizers and smoothness terms; default
        :data:`DEFAULT_REGULARIZERS`; ``{}`` for none.
    camera : Camera, optional
        Undistorts the events when it has distortion.
    max_iter : int or sequence of int, optional
        L-BFGS-B iterations per level (one number for all levels, or one per level); default
        :func:`auto_iterations`.
    search_range : float
        Half-width of the global search, px of displacement over the window (default a quarter of the
        larger sensor side).
    subsample : bool
        At image downsampling ``s > 1``, use every ``s``-th event (default True).
    padding : int, optional
        Margin of the IWEs around the sensor, px of the full-resolution image (see
        :class:`~cmax_taichi.flow.DenseFlowProblem`); default :data:`AUTO_PADDING` of the larger sensor
        side, less where the padded image would exceed ``max_sensor_pixels`` (``flow.grid.auto_padding``).
    dither : bool
        Spread integer event coordinates over their pixel (:func:`dithered`) on the full-resolution
        level (default True): without it, flow components under about a pixel over the window are
        pulled towards 0. The downsampled levels take the events undithered (their pixels are 2-4 times
        the grid's spacing).
    kink_width : float
        Width of the rounded kinks of the event-map regularizers in the objective the levels maximise
        (:class:`~cmax_taichi.flow.DenseFlowProblem`; default :data:`KINK_WIDTH`, 0: the exact
        penalties, whose kinks stall L-BFGS-B at a constant flow). The result's ``value`` and terms
        are the exact ones.
    """

    def __init__(
        self,
        grid: FlowGrid | tuple[int, int] = (16, 16),
        *,
        levels: int = 4,
        scales: Sequence[int] | None = None,
        objective: str = "gradient_magnitude",
        references="middle",
        reference_weights: Sequence[float] | None = None,
        regularizers: Mapping[str, float] | None = None,
        camera: Camera | None = None,
        blur_sigma: float = 1.0,
        normalize: bool = True,
        polarity: str = "ignore",
        max_iter: int | Sequence[int] | None = None,
        search_range: float | None = None,
        padding: int | None = None,
        subsample: bool = True,
        dither: bool = True,
        kink_width: float = KINK_WIDTH,
    ) -> None:
        self._grid_arg = grid
        self.levels = levels
        if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)) or levels < 1:
            raise ValueError(f"levels must be an integer >= 1, got {levels!r}")
        self.scales = tuple(auto_scales(levels) if scales is None else scales)
        if len(self.scales) != levels or not all(
            isinstance(s, (int, np.integer)) and not isinstance(s, bool) and s >= 1 for s in self.scales
        ):
            raise ValueError(f"scales must be {levels} integers >= 1 (one per level), got {scales!r}")
        if max_iter is None:
            max_iter = auto_iterations(levels)
        iters = [max_iter] * levels if isinstance(max_iter, (int, np.integer)) else list(max_iter)
        if len(iters) != levels or not all(isinstance(i, (int, np.integer)) and i >= 1 for i in iters):
            raise ValueError(
                f"max_iter must be an integer >= 1 or one per level ({levels}), got {max_iter!r}"
            )
        self.max_iter = tuple(int(i) for i in iters)
        resolve_references(references, reference_weights)  # checked now, before any data
        self.problem_options = dict(
            objective=objective,
            references=references,
            reference_weights=reference_weights,
            regularizers=DEFAULT_REGULARIZERS if regularizers is None else dict(regularizers),
            blur_sigma=blur_sigma,
            normalize=normalize,
            polarity=polarity,
            kink_width=kink_width,
        )
        self.camera = camera
        if search_range is not None and not (math.isfinite(search_range) and search_range > 0):
            raise ValueError(f"search_range must be a positive number of px, got {search_range!r}")
        self.search_range = search_range
        if padding is not None and (
            isinstance(padding, bool) or not isinstance(padding, (int, np.integer)) or padding < 0
        ):
            raise ValueError(
                f"padding must be a whole number of px >= 0 (or None: automatic), got {padding!r}"
            )
        self.padding = None if padding is None else int(padding)
        self.subsample = bool(subsample)
        self.dither = bool(dither)
        self._problems: dict[int, DenseFlowProblem] = {}
        self._loaded: dict[int, Events] = {}  # the window each problem holds now
        self._plain: tuple = (None, None)  # (dithered window, the same undithered)
        self._sensor: tuple[int, int] | None = None
        self.pyramid: list[FlowGrid] = []

    # --- problems ---------------------------------------------------------------------------------
    def _finest_for(self, sensor: tuple[int, int]) -> FlowGrid:
        grid = self._grid_arg
        if isinstance(grid, FlowGrid):
            if (grid.width, grid.height) != sensor:
                raise ValueError(f"grid is for a {grid.width}x{grid.height} sensor, the events for {sensor}")
            return grid
        try:
            nx, ny = grid
        except (TypeError, ValueError):
            raise TypeError(f"grid must be a FlowGrid or (cells_x, cells_y), got {grid!r}") from None
        return FlowGrid(sensor[0], sensor[1], nx, ny)

    def _prepare(self, events: Events) -> Events:
        """Dither integer coordinates (:attr:`dither`), undistort once (when the camera has
        distortion) and set up the pyramid for the sensor."""
        if not isinstance(events, Events):
            raise TypeError(f"events must be cmax_taichi.Events, got {type(events).__name__}")
        on_grid = self.dither and on_pixel_grid(events)
        if self.camera is not None and self.camera.has_distortion and not events.undistorted:
            events = events.undistort(self.camera)  # by its per-pixel table: dithered after it
        if on_grid:  # the undistortion is locally a shift: its grid is as sharp as the raw one
            plain, events = events, dithered(events, grid=True)
            self._plain = (events, plain)
        if self._sensor != events.sensor_size:
            finest = self._finest_for(events.sensor_size)
            self.pyramid = finest.pyramid(self.levels)
            self._sensor = events.sensor_size
            self._problems.clear()
            self._loaded.clear()
        return events

    def _grid_at(self, grid: FlowGrid, scale: int) -> FlowGrid:
        if scale == 1:
            return grid
        Ws, Hs = max(2, math.ceil(grid.width / scale)), max(2, math.ceil(grid.height / scale))
        return FlowGrid(Ws, Hs, min(grid.nx, Ws - 1), min(grid.ny, Hs - 1))

    def problem(self, events: Events, scale: int = 1) -> DenseFlowProblem:
        """The problem of ``events`` at image downsampling ``scale`` (built on first use, then given the
        window with ``set_events``), its grid capacity the finest grid used at that scale. At ``scale > 1``
        it holds every ``scale``-th event when :attr:`subsample` (the coarse grids of the first levels
        need neither the whole image nor every event: their evaluations cost a quarter)."""
        if self._loaded.get(scale) is events:
            return self._problems[scale]
        source = events
        if scale > 1 and self._plain[0] is events:
            source = self._plain[1]  # scaled down, the pixel grid is fine enough: the events undithered
        scaled = _scaled_events(source, scale, scale if self.subsample else 1)
        prob = self._problems.get(scale)
        if prob is None:
            finest = max(
                (self._grid_at(g, s) for g, s in zip(self.pyramid, self.scales, strict=True) if s == scale),
                key=lambda g: g.n_nodes,
                default=self._grid_at(self.pyramid[0], scale),
            )
            full = self.padding
            if full is None:
                full = auto_padding(events.sensor_size, AUTO_PADDING)
            pad = math.ceil(full / scale)
            prob = DenseFlowProblem(scaled, finest, camera=None, padding=pad, **self.problem_options)
            self._problems[scale] = prob
        else:
            prob.set_events(scaled)
        self._loaded[scale] = events
        return prob

    # --- one window ---------------------------------------------------------------------------------
    def estimate(
        self,
        events: Events,
        *,
        init: str | np.ndarray = "search",
        warm: FlowResult | None = None,
    ) -> FlowResult:
        """The dense flow of one window.

        Parameters
        ----------
        events : Events
            The window.
        init : {"search", "zero"} or ndarray
            Start of the coarsest level without ``warm``: the global search over constant flows, zero,
            or node values (px/s) of the coarsest grid (``pyramid[0].shape``).
        warm : FlowResult, optional
            The previous window's result: its flow, fitted to the coarsest grid, is the start (no search).
        """
        t_run = time.perf_counter()
        events = self._prepare(events)
        if len(events) < 2:
            raise ValueError(f"a dense flow window needs at least 2 events, got {len(events)}")
        levels: list[LevelReport] = []
        n_eval = 0
        coarsest = self.pyramid[0]
        if warm is not None:
            if not isinstance(warm, FlowResult):
                raise TypeError(f"warm must be a FlowResult, got {type(warm).__name__}")
            if warm.sensor_size != events.sensor_size:
                raise ValueError(
                    f"warm is a flow of a {warm.sensor_size} sensor, the events are {events.sensor_size}"
                )
            U = coarsest.fit(warm.flow())
            how = "warm"
        elif isinstance(init, str):
            if init == "zero":
                U = np.zeros(coarsest.shape)
            elif init == "search":
                U, n_eval = self._search(events, coarsest)
            else:
                raise ValueError(f"init must be 'search', 'zero' or node values, got {init!r}")
            how = init
        else:
            U = coarsest.check_nodes(init, "init")
            how = "given"
        for k, (grid, scale) in enumerate(zip(self.pyramid, self.scales, strict=True)):
            if k > 0:
                U = self.pyramid[k - 1].prolong(U)
            U, report = self._level(events, grid, scale, U, self.max_iter[k])
            levels.append(report)
            n_eval += report.evaluations
        prob = self.problem(events, 1)
        prob.set_grid(self.pyramid[-1])
        evaluation = prob.evaluate(U)
        stalled = [lv for lv in levels if lv.status == "stalled"]
        if stalled:
            warnings.warn(
                OptimizerStallWarning(
                    f"dense flow of the window at t = {float(events.t[0]):.6f} s: "
                    + "; ".join(f"the {lv.grid.nx}x{lv.grid.ny}-cell level ({lv.message})" for lv in stalled)
                    + " ended at its start, and the fallback did not move it either: the flow there is "
                    "the level's start"
                ),
                stacklevel=2,
            )
        return FlowResult(
            grid=self.pyramid[-1],
            nodes=U,
            t_start=float(events.t[0]),
            t_end=float(events.t[-1]),
            n_events=len(events),
            value=evaluation.J,
            evaluation=evaluation,
            levels=levels,
            n_evaluations=n_eval + 1,
            seconds=time.perf_counter() - t_run,
            init=how,
        )

    def _level(self, events: Events, grid: FlowGrid, scale: int, U: np.ndarray, max_iter: int):
        """One level: L-BFGS-B from ``U`` (px/s, full-resolution units), the fallback where it failed or
        did not move (:data:`FALLBACK_STEP`); ``(U, LevelReport)``."""
        from scipy.optimize import minimize

        from cmax_taichi.solve.local import Recorder, armijo

        t0 = time.perf_counter()
        prob = self.problem(events, scale)
        sgrid = self._grid_at(grid, scale)
        prob.set_grid(sgrid)
        _, _, kx, ky = _scale_factors(events.sensor_size, scale)
        k = np.array([kx, ky])
        T = prob.duration
        # variables: node displacements over the window in the level's px (about 1 unit = 1 px)
        d0 = (U * k * T).reshape(-1)
        obj = _LevelObjective(prob, sgrid.shape, T, d0)
        j_start = obj.value(d0)

        def fun(d):
            value, g = obj.value_and_grad(d)
            return -value, -g

        res = minimize(
            fun,
            d0,
            jac=True,
            method="L-BFGS-B",
            options={"maxiter": max_iter, "maxfun": 2 * max_iter + 10, "ftol": 1e-10, "gtol": 1e-8},
        )
        message = f"L-BFGS-B: {res.message}"
        iterations = int(res.nit)
        status = "converged" if res.success else "limit" if res.status == 1 else "failed"
        if status == "failed" or (status == "limit" and not obj.best_value > j_start):
            j_before = obj.best_value
            run = armijo(
                obj,
                obj.best_d,
                -math.inf,
                math.inf,
                lr=FALLBACK_STEP,
                max_iter=max_iter,
                gtol=1e-8,
                xtol=FALLBACK_XTOL,
                rtol=1e-10,
                rec=Recorder(None, obj),
            )
            iterations += run.n_iterations
            message += f"; fallback (gradient ascent): {run.message}, {run.n_iterations} iterations"
            status = "fallback" if obj.best_value > j_before else "converged"
        d = obj.best_d  # the best point evaluated (L-BFGS-B returns its last accepted iterate)
        change = float(np.max(np.abs((d - d0).reshape(sgrid.shape) / k), initial=0.0))
        if change == 0.0 and not res.success:  # L-BFGS-B did not certify its start, nothing moved it
            status = "stalled"
        report = LevelReport(
            grid=grid,
            scale=scale,
            iterations=iterations,
            evaluations=obj.n_evaluations,
            value_start=float(j_start),
            value=float(obj.best_value),
            seconds=time.perf_counter() - t0,
            message=message,
            status=status,
            change=change,
        )
        return d.reshape(sgrid.shape) / (k * T), report

    def _search(self, events: Events, grid: FlowGrid) -> tuple[np.ndarray, int]:
        """The best constant flow (px/s) on a coarse-to-fine grid of displacements over the window:
        ``(nodes of grid, evaluations)``. Runs on the first level's image."""
        scale = self.scales[0]
        prob = self.problem(events, scale)
        sgrid = self._grid_at(grid, scale)
        prob.set_grid(sgrid)
        _, _, kx, ky = _scale_factors(events.sensor_size, scale)
        T = prob.duration
        W, H = events.sensor_size
        reach = self.search_range if self.search_range is not None else max(W, H) / 4.0
        reach_s = reach * max(kx, ky)  # px of the search image
        const = np.zeros(sgrid.shape)
        n = 0

        def value(d: np.ndarray) -> float:
            nonlocal n
            n += 1
            const[...] = d / T
            return prob.value(const, maps=False)  # a constant flow: the map regularizers are 0

        # a 9 x 9 grid over +-reach, then a 5 x 5 grid of a quarter of its step around the best point
        # (the coarsest level's L-BFGS-B refines from there); about 100 evaluations of J, no gradients
        best_d, best_j = np.zeros(2), value(np.zeros(2))
        centre, half = best_d.copy(), reach_s
        for points in (9, 5):
            steps = np.linspace(-half, half, points)
            for dy in steps:
                for dx in steps:
                    if dx == 0.0 and dy == 0.0 and points == 9:
                        continue  # the identity, evaluated above
                    d = centre + (dx, dy)
                    j = value(d)
                    if j > best_j:
                        best_j, best_d = j, d
            centre = best_d.copy()
            half = (steps[1] - steps[0]) / 2.0
        U = np.zeros(grid.shape)
        U[...] = best_d / (np.array([kx, ky]) * T)
        return U, n


class _LevelObjective:
    """J and its gradient of one level in the optimizer's variables (node displacements over the window,
    px of the level's image, flat), keeping the best point evaluated: the interface of the local
    methods of :mod:`cmax_taichi.solve.local` (the fallback)."""

    def __init__(self, prob: DenseFlowProblem, shape: tuple, duration: float, d0: np.ndarray) -> None:
        self.prob, self.shape, self.duration = prob, shape, duration
        self.best_value, self.best_d = -math.inf, d0.copy()
        self.n_evaluations = 0

    def _keep(self, value: float, d: np.ndarray) -> float:
        self.n_evaluations += 1
        value = value if math.isfinite(value) else -math.inf
        if value > self.best_value:
            self.best_value, self.best_d = value, np.array(d, dtype=np.float64)
        return value

    def value(self, d: np.ndarray) -> float:
        return self._keep(self.prob.value(np.reshape(d, self.shape) / self.duration), d)

    def value_and_grad(self, d: np.ndarray) -> tuple[float, np.ndarray]:
        value, g = self.prob.value_and_grad(np.reshape(d, self.shape) / self.duration)
        return self._keep(value, d), g.reshape(-1) / self.duration

    def theta(self, d: np.ndarray) -> np.ndarray:
        return np.asarray(d)


def estimate_flow(
    events: Events,
    *,
    grid: FlowGrid | tuple[int, int] = (16, 16),
    levels: int = 4,
    init: str | np.ndarray = "search",
    warm: FlowResult | None = None,
    **options,
) -> FlowResult:
    """The dense flow of one window of events (see :class:`DenseFlowEstimator` for ``options``).

    Examples
    --------
    >>> result = estimate_flow(events, grid=(16, 16), regularizers={"deformation": 1.0})  # doctest: +SKIP
    >>> result.displacement().shape  # (2, H, W), px over the window  # doctest: +SKIP
    """
    return DenseFlowEstimator(grid, levels=levels, **options).estimate(events, init=init, warm=warm)
