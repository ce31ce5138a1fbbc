"""The default global search of :func:`cmax_taichi.maximize`: coarse to fine over an image pyramid.

Why: J over the search box is a sharp peak (its width is the blur, about a pixel of displacement over
the window) on a wide, nearly flat plain, so a grid must step by about a pixel to find it (the
thorough grid: 1,000-2,000 evaluations). Seen through a coarser image, the peak is as wide as the
coarse pixels: a few points and a few gradient steps find it, and each finer image moves the estimate
by less than its pixel.

A *coarse view* of a problem (:func:`coarse_view`) is the same problem, with the same warp model,
objective, regularizers and blur (in coarse pixels), on the events scaled by ``1 / k`` about the
centre of the image (a ``k x k`` block of pixels becomes one): its IWE is the ``k``-times coarser IWE
of the original events, in the middle of the same sensor, so it runs on the same pooled fields and
compiled kernels (nothing is compiled for it). Events that a large motion warps off the coarse image
stay on the sensor, so no side of the box loses events first. A parameter keeps its value under the
scaling, except a velocity (px/s), which scales by ``1 / k``; in the optimizer's internal units (px of
displacement over the window, :mod:`cmax_taichi.solve.scales`) every parameter scales by ``1 / k``.
The coarse views hold a subsample of the events (evenly spread in time, the first and last included,
so the window keeps its duration): at ``k x k`` pixels per coarse pixel, fewer events give the same
image.

The search (:func:`pyramid_search`): on the coarsest view (where the box's largest half-range is about
8 coarse px) a design of points (a grid, or a central composite design from 4 parameters on), then a
short BFGS ascent from the best few; on each finer view (pixels 2-4 times smaller), a short BFGS
ascent from the best results of the level before (on the finest view of a collapse-enabled model,
from the identity too); at full resolution, the best result (and a runner-up that gains at least half
as much) starts ``maximize``'s local run. Every evaluation of every view is counted.
"""

from __future__ import annotations

import math

import numpy as np

from cmax_taichi.core.events import Camera, Events
from cmax_taichi.pipeline.problem import ContrastMaximization
from cmax_taichi.solve.local import Recorder, ScaledObjective, bfgs
from cmax_taichi.solve.search import distinct_top

__all__ = ["PYRAMID_BUDGET", "PYRAMID_MAX_STEP", "coarse_factors", "coarse_view", "pyramid_search"]

#: the coarsest view makes the largest half-range of the box about this many coarse px
COARSEST_HALF_RANGE = 8.0
#: at most this many coarse levels (the factors between them then grow beyond 2)
MAX_LEVELS = 4
#: events of the coarsest view (each finer view twice as many, up to all of them)
COARSEST_EVENTS = 4096
#: points of the coarsest design (a grid of this many or fewer; a central composite design beyond)
DESIGN_POINTS = 27
#: local ascents per level, coarsest first (the last entry serves the finer levels)
STARTS_PER_LEVEL = (3, 2)
#: a runner-up of the finest view needs this share of the best's gain over the identity for a local run
RUNNER_UP_GAIN = 0.5
#: evaluations of a ``maximize(init="pyramid")`` call (the search and the local runs at full resolution;
#: its ``max_evaluations`` default): the local runs stop there with their best iterate (not converged).
#: Search and local run took 49-129 evaluations on the cases of benchmarks/NOTES.md, and reached it on one
PYRAMID_BUDGET = 150
#: the longest step (px) of a BFGS run from a result of the search at full resolution (a few finest
#: coarse pixels: the search leaves its results within about one)
PYRAMID_MAX_STEP = 4.0
#: BFGS iterations per ascent at a coarse level
LEVEL_ITERATIONS = 5


def coarse_factors(prob: ContrastMaximization, half_range_u: np.ndarray) -> list[int]:
    """The pyramid's factors ``k`` (px per coarse px), coarsest first, all > 1; empty for a model whose
    parameters have no declared kinds (a velocity scales with ``k``, the others do not: without the
    kinds, nothing says how to scale them) or a box already under :data:`COARSEST_HALF_RANGE` px."""
    if prob.model.parameter_kinds is None:
        return []
    largest = float(np.max(half_range_u))
    top = int(math.floor(math.log2(max(largest / COARSEST_HALF_RANGE, 1.0))))
    if top < 1:
        return []
    exponents = list(range(top, 0, -1))
    if len(exponents) > MAX_LEVELS:  # spread MAX_LEVELS levels over the exponents, coarsest and finest kept
        picks = np.unique(np.round(np.linspace(top, 1, MAX_LEVELS)).astype(int))[::-1]
        exponents = [int(e) for e in picks]
    return [2**e for e in exponents]


def coarse_view(
    prob: ContrastMaximization, factor: int, max_events: int | None = None
) -> ContrastMaximization:
    """The problem seen through ``factor x factor`` pixel blocks (see the module docstring).

    Parameters
    ----------
    prob : ContrastMaximization
        The problem (its undistorted events, warp, objective, regularizers, options).
    factor : int
        Pixels per coarse pixel, >= 1.
    max_events : int, optional
        Keep at most this many events, evenly spread over the window (first and last included).

    Returns
    -------
    ContrastMaximization
        On the same sensor size (its pooled fields and kernels): the events at
        ``c + (x - c_image) / factor`` about the image centre ``c_image``, the warp's centre and focal
        lengths scaled alike. Its parameters: the original ones with velocities (px/s) divided by
        ``factor`` (:func:`view_parameter_factors`).
    """
    setup = prob.setup
    ev = setup.events
    n = len(ev)
    keep = slice(None)
    if max_events is not None and max_events < n:
        keep = np.unique(np.linspace(0, n - 1, max(2, int(max_events))).round().astype(np.int64))
    k = float(factor)
    W, H = ev.sensor_size
    # the scaling about the image centre keeps the coarse image in the middle of the sensor
    ox, oy = 0.5 * (W - 1) * (1.0 - 1.0 / k), 0.5 * (H - 1) * (1.0 - 1.0 / k)
    events = Events(
        ev.x[keep] / k + ox,
        ev.y[keep] / k + oy,
        ev.t[keep],
        ev.p[keep],
        ev.sensor_size,
        undistorted=True,
        _validated=True,
    )
    (cx, cy), (fx, fy) = setup.center, setup.focal
    camera = Camera(fx=fx / k, fy=fy / k, cx=cx / k + ox, cy=cy / k + oy)
    weights = None if setup.vote_weights is None else setup.vote_weights[keep]
    # signed polarity is already in the vote weights
    polarity = "ignore" if setup.polarity == "signed" else setup.polarity
    return ContrastMaximization(
        events,
        warp=prob.model,
        objective=setup.objective.name,
        regularizers=setup.regularizer_weights,
        camera=camera,
        t_ref=setup.t_ref,
        blur_sigma=setup.blur_sigma,
        polarity=polarity,
        weights=weights,
        normalize=setup.normalize,
        whitening=prob.whitening,
    )


def view_parameter_factors(prob: ContrastMaximization, factor: int) -> np.ndarray:
    """Per parameter, the view's value over the original's: ``1 / factor`` for a velocity, else 1."""
    kinds = prob.model.parameter_kinds or ("velocity",) * prob.model.n_params
    return np.array([1.0 / factor if kind == "velocity" else 1.0 for kind in kinds])


def design(lo: np.ndarray, hi: np.ndarray, n_points: int = DESIGN_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """``(points, spacing)``: the coarsest level's design over the box ``[lo, hi]`` (px) and the
    distance (px, per parameter) within which two results count as one start.

    A grid of ``n`` points per parameter where ``n >= 3`` fits ``n_points`` (odd ``n``, so the box's
    centre is on it); else a central composite design: the centre, the 2P points half a box away
    along each axis and the ``2^P`` corners of the half-size box.
    """
    P = len(lo)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    n = int(math.floor(n_points ** (1.0 / P) + 1e-9))
    n = n if n % 2 else n - 1
    if n >= 3:
        axes = [np.linspace(lo[i], hi[i], n) for i in range(P)]
        points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, P)
        return points, (hi - lo) / (n - 1)
    axial = np.concatenate([np.eye(P), -np.eye(P)]) * 0.5
    corners = np.stack(np.meshgrid(*([np.array([-0.5, 0.5])] * P), indexing="ij"), -1).reshape(-1, P)
    unit = np.concatenate([np.zeros((1, P)), axial, corners])
    return centre + unit * half, half * 0.5


def pyramid_search(
    obj: ScaledObjective,
    lo: np.ndarray,
    hi: np.ndarray,
    *,
    extra: list[np.ndarray],
    n_final: int,
    min_dist: np.ndarray,
    n_design: int | None = None,
) -> tuple[list[tuple[float, np.ndarray]], list[tuple[float, np.ndarray]]]:
    """Coarse-to-fine search of J over the box ``[lo, hi]`` (internal units, px).

    Parameters
    ----------
    obj : ScaledObjective
        J of the problem in internal units; the views' evaluations are added to its count.
    lo, hi : ndarray
        The box, px.
    extra : list of ndarray
        Points evaluated at full resolution and on the coarsest view (the identity, a warm start, the
        caller's candidates).
    n_final : int
        Results handed to the local runs at full resolution.
    min_dist : ndarray
        Two points closer than this (px, per parameter) are one start.
    n_design : int, optional
        Points of the coarsest design (default :data:`DESIGN_POINTS`).

    Returns
    -------
    found : list of (value, u)
        Every full-resolution J the search computed: ``extra`` and the best ``n_final`` results of the
        finest view (those with their gradient, which the local run that starts there reuses).
    starts : list of (value, u)
        The starts of the local runs, best first: the finest view's results, and a point of
        ``extra`` whose full-resolution J beats them all (the search compared the others with its
        design on the coarsest view already; a local run from each would cost up to a few tens of
        evaluations at a regularizer's kink, such as the identity's).
    """
    prob = obj.prob
    half_range = 0.5 * (hi - lo)
    factors = coarse_factors(prob, half_range)
    found_full = [(obj.value(u), np.array(u)) for u in extra]
    candidates: list[tuple[float, np.ndarray]] = []
    finest = 0
    for level, k in enumerate(factors):
        n_events = COARSEST_EVENTS * 2**level
        try:
            view = coarse_view(prob, k, n_events)
        except ValueError:  # e.g. a flat image at this scale: search from the next level
            obj.n_evaluations += 1
            continue
        obj.n_evaluations += 1  # the view's identity evaluation (its G0)
        vobj = ScaledObjective(view, obj.scales / (k * view_parameter_factors(prob, k)))
        vlo, vhi = lo / k, hi / k
        if not candidates:  # the coarsest view: the design and the extra points
            points, spacing = design(vlo, vhi, n_design or DESIGN_POINTS)
            evaluated = [(vobj.value(u), u) for u in list(points) + [u / k for u in extra]]
            starts = distinct_top(evaluated, STARTS_PER_LEVEL[0], 0.5 * spacing)
        else:
            scale = finest / k  # previous level's coarse px per this level's
            previous = [(v, u * scale) for v, u in candidates]
            n_level = STARTS_PER_LEVEL[min(level, len(STARTS_PER_LEVEL) - 1)]
            starts = distinct_top(previous, n_level, np.maximum(min_dist / k, 1e-9))
            starts = [(v, np.clip(u, vlo, vhi)) for v, u in starts]
            if level == len(factors) - 1 and prob.model.collapse_enabled:
                # the finest view also climbs from the extra points (the identity first): a moderate
                # motion's peak can be invisible on the coarser views, where a collapse of the events
                # (a warp that gathers them towards a point, sharp at every scale) outshines it
                near = np.maximum(min_dist / k, 1e-9)
                for u in extra:
                    u = np.clip(u / k, vlo, vhi)
                    if all(np.any(np.abs(u - w) > near) for _, w in starts):
                        starts.append((math.nan, u))
        results = []
        for _, start in starts:
            # (the previous level's inverse Hessian is no help: taken across a regularizer's kink it
            # stops the next level's run at its first, tiny quasi-Newton step)
            run = bfgs(
                vobj,
                start,
                vlo,
                vhi,
                lr=1.0,
                max_iter=LEVEL_ITERATIONS,
                gtol=0.0,
                xtol=0.05,
                rtol=1e-6,
                rec=Recorder(None, vobj),
            )
            results.append((run.value, run.u))
        candidates = results
        finest = k
        obj.n_evaluations += vobj.n_evaluations
    candidates = distinct_top(candidates, n_final, np.maximum(min_dist / finest, 1e-9)) if finest else []
    if not candidates:  # no view, or J nowhere finite on them: the local runs start from extra
        return found_full, distinct_top(found_full, n_final, min_dist)
    if len(candidates) > 1 and np.all((lo <= 0) & (hi >= 0)):
        # a runner-up that gains less than RUNNER_UP_GAIN of the best's gain over the identity (on the
        # finest view) does not get a local run of its own at full resolution
        n0 = vobj.n_evaluations
        identity = vobj.value(np.zeros(len(lo)))
        obj.n_evaluations += vobj.n_evaluations - n0
        best_gain = candidates[0][0] - identity
        candidates = candidates[:1] + [
            (v, u) for v, u in candidates[1:] if v - identity >= RUNNER_UP_GAIN * best_gain
        ]
    finals = []
    for _, u in [(v, u * finest) for v, u in candidates]:
        u = np.clip(u, lo, hi)
        finals.append((obj.value_and_grad(u)[0], u))
    best_final = max(v for v, _ in finals)
    better = [(v, u) for v, u in found_full if v > best_final]
    return found_full + finals, distinct_top(better + finals, n_final, min_dist)
