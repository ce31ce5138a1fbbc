"""Maximizing a CMax problem: a global search, then local gradient ascent.

:func:`maximize` drives ``prob.value`` (forward only) for the global search and ``prob.value_and_grad``
for the local refinement. The parts:

* the per-window scales and default box (:mod:`cmax_taichi.solve.scales`: the optimizer works on
  ``u = theta * s``, one unit of ``u`` about one pixel of displacement over the window; learning
  rates, tolerances and spacings are in these units);
* the global searches: coarse to fine over an image pyramid, the default
  (:mod:`cmax_taichi.solve.pyramid`), and grid, random and TPE (:mod:`cmax_taichi.solve.search`);
* the local methods (:mod:`cmax_taichi.solve.local`): ``"bfgs"``, a dependency-free quasi-Newton
  ascent that converges from a good start in about 5-20 evaluations (the default); ``"adam"``
  (plateau schedule, best iterate kept); ``"armijo"`` (backtracking line search); ``"lbfgs"``
  (SciPy's L-BFGS-B);
* the option checks (:mod:`cmax_taichi.solve.options`).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from cmax_taichi.core import checks
from cmax_taichi.pipeline.problem import ContrastMaximization
from cmax_taichi.solve import local, options
from cmax_taichi.solve.local import AdamStepper, ScaledObjective
from cmax_taichi.solve.pyramid import DESIGN_POINTS, PYRAMID_BUDGET, PYRAMID_MAX_STEP, pyramid_search
from cmax_taichi.solve.scales import parameter_scales, search_bounds
from cmax_taichi.solve.search import distinct_top, grid_search, random_search, tpe_search

__all__ = [
    "METHODS",
    "RUN_STATUSES",
    "INITS",
    "AdamStepper",
    "History",
    "OptimizeResult",
    "maximize",
    "parameter_scales",
    "search_bounds",
]

METHODS = ("bfgs", "adam", "armijo", "lbfgs")
INITS = ("auto", "pyramid", "grid", "random", "tpe", "local", "warm", "none")

#: default evaluation budget of the global search, per init
_DEFAULT_N_INIT = {"pyramid": DESIGN_POINTS, "grid": 1000, "random": 1000, "tpe": 200, "local": 300}
#: the largest ``n_init``: each point is an evaluation of J (a millisecond to tens of milliseconds at
#: 30,000 events), so more runs for hours; refused up front
MAX_N_INIT = 100_000

#: the objective in internal units (kept under its old name for callers that import it from here)
_Objective = ScaledObjective
#: what a local run did (:attr:`OptimizeResult.status`), as the dense flow's levels report it
RUN_STATUSES = ("converged", "limit", "fallback", "stalled")
#: the one-sided step, px, of the fallback's check of a run that ended at its start (:func:`_settle`)
KINK_PROBE_STEP = 0.1


def _settle(obj, run, start, method, lo, hi, *, lr, max_iter, gtol, xtol, rtol, callback, warm=False):
    """``(run, status)``: a local run and its status (:data:`RUN_STATUSES`), after the fallback where
    it needs one (docs/estimation.md, "When a local run does not move").

    A run that ended at its start without a stopping rule (its line search found no ascent step, or its
    iterations passed without one) is checked by one-sided steps of :data:`KINK_PROBE_STEP` px along
    each parameter (:func:`~cmax_taichi.solve.local.compass_probe`): at a regularizer's kink the
    gradient is one side's, and the other side may still ascend. The best step that ascends starts a
    BFGS run (which holds parameters at kinks); when none does, the start is a maximum along every
    parameter and the run counts as converged. An L-BFGS-B run that failed after moving (its line
    search, "ABNORMAL") goes on by BFGS from its best point. A BFGS or Armijo run that moved and then
    found no ascent step longer than ``xtol`` has converged (a maximum to ``xtol`` along its
    directions), and so has one of ``init="warm"`` that found none at its start: that start is the
    previous window's maximum, where a sequence's warm windows usually stay (probing them cost 8-23%
    more evaluations over the ECD rotation cuts' and the MVSEC cut's 5,000-event windows).
    """
    moved = not np.array_equal(run.u, start)
    if run.converged:
        return run, "converged"
    if obj.exhausted or run.message == "stopped by callback" or max_iter == 0:
        return run, "limit"
    if moved and not run.failed:
        return run, "limit"
    if (moved or warm) and method != "lbfgs":
        run.converged = True
        return run, "converged"
    restart = run.u
    if not moved:
        found = local.compass_probe(obj, run.u, run.value, lo, hi, KINK_PROBE_STEP)
        if found is None:
            if obj.exhausted:
                return run, "stalled"
            run.converged = True
            run.message += (
                f"; fallback: no one-sided step of {KINK_PROBE_STEP:g} px along any parameter ascends "
                "(a maximum, at a kink of J)"
            )
            return run, "converged"
        restart = found[0]
    rec = local.Recorder(callback, obj)
    again = local.bfgs(
        obj, restart, lo, hi, lr=lr, max_iter=max_iter, gtol=gtol, xtol=xtol, rtol=rtol, rec=rec
    )
    if not again.value > run.value:
        run.converged = not obj.exhausted
        run.message += f"; fallback BFGS from the best point: {again.message}"
        return run, "converged" if run.converged else "limit"
    merged = local.LocalRun(
        again.u,
        again.value,
        run.us + again.us,
        run.values + again.values,
        run.gnorms + again.gnorms,
        again.converged or again.failed,  # BFGS that moved and then found no ascent step: a maximum
        f"{run.message}; fallback ({'one-sided steps, then ' if not moved else ''}BFGS): {again.message}",
        again.hess_inv if method == "bfgs" else None,  # the result's hess_inv is BFGS's own
    )
    return merged, "fallback"


@dataclass(frozen=True)
class History:
    """Iterates of the local run that gave the result (iteration 0 = its start point).

    Attributes
    ----------
    theta : ndarray, shape (K, P)
        Parameters, physical units.
    value : ndarray, shape (K,)
        J at each iterate.
    grad_norm : ndarray, shape (K,)
        Norm of dJ/du in internal units (1/px); NaN where no gradient was computed.
    """

    theta: np.ndarray
    value: np.ndarray
    grad_norm: np.ndarray

    def __len__(self) -> int:
        return len(self.value)


@dataclass
class OptimizeResult:
    """The outcome of :func:`maximize`.

    Attributes
    ----------
    theta : ndarray
        Best parameters found, physical units (see ``param_names`` / ``units``).
    value : float
        J at ``theta``.
    history : History
        Iterates of the winning local run.
    n_iterations : int
        Iterations of the winning local run.
    n_evaluations : int
        All objective evaluations (global search and every local run).
    seconds : float
        Wall time of the whole call.
    converged : bool
        The winning local run met a stopping rule (not just ``max_iter``).
    message : str
        Why it stopped.
    method, init : str
        Local method and global initialisation used.
    theta_init : ndarray
        Start of the winning local run (physical units).
    value_init : float
        J at ``theta_init``.
    scales : ndarray
        ``s`` of ``u = theta * s`` (px of displacement over the window per unit of theta).
    param_names, units : tuple of str
        Names and units of the parameters.
    value_identity : float
        J at the identity warp (theta = 0), NaN when the search did not evaluate it (the identity
        outside a user-given box).
    hess_inv : ndarray or None
        ``method="bfgs"``: the final BFGS estimate of the inverse Hessian of ``-J`` in internal units
        (px^2, shape (P, P)); hand it to the next window's ``maximize(..., hess_inv0=)`` so that its
        first step is a quasi-Newton step (:func:`cmax_taichi.solve.sequence.process` does). None for
        the other methods.
    status : str
        What the winning local run did (:data:`RUN_STATUSES`): ``"converged"`` (a stopping rule, or a
        maximum along every parameter checked by the fallback), ``"limit"`` (``max_iter``, the
        evaluation budget or the callback), ``"fallback"`` (it failed or ended at its start, and the
        fallback moved it), ``"stalled"`` (neither moved it: an :class:`OptimizerStallWarning` says so).
    """

    theta: np.ndarray
    value: float
    history: History
    n_iterations: int
    n_evaluations: int
    seconds: float
    converged: bool
    message: str
    method: str
    init: str
    theta_init: np.ndarray
    value_init: float
    scales: np.ndarray
    param_names: tuple[str, ...] = field(default=())
    units: tuple[str, ...] = field(default=())
    value_identity: float = math.nan
    hess_inv: np.ndarray | None = None
    status: str = "converged"

    def as_dict(self) -> dict:
        """A JSON-friendly summary (no history)."""
        return {
            "theta": {n: float(v) for n, v in zip(self.param_names, self.theta, strict=True)},
            "units": dict(zip(self.param_names, self.units, strict=True)),
            "value": float(self.value),
            "n_iterations": int(self.n_iterations),
            "n_evaluations": int(self.n_evaluations),
            "seconds": float(self.seconds),
            "converged": bool(self.converged),
            "status": self.status,
            "message": self.message,
            "method": self.method,
            "init": self.init,
        }

    def __repr__(self) -> str:
        params = ", ".join(
            f"{n}={v:.6g} {u}" for n, v, u in zip(self.param_names, self.theta, self.units, strict=True)
        )
        return (
            f"OptimizeResult({params}; J={self.value:.6g}, {self.n_iterations} it, "
            f"{self.n_evaluations} evals, {self.seconds:.2f} s, converged={self.converged})"
        )


def maximize(
    prob: ContrastMaximization,
    theta0: Sequence[float] | np.ndarray | None = None,
    method: str = "bfgs",
    *,
    init: str = "auto",
    bounds: tuple[Sequence[float], Sequence[float]] | None = None,
    n_init: int | None = None,
    n_starts: int = 3,
    max_iter: int | None = None,
    lr: float = 1.0,
    gtol: float = 1e-7,
    rtol: float = 1e-9,
    xtol: float = 0.01,
    patience: int = 5,
    min_spacing: float = 1.0,
    candidates: Sequence[Sequence[float]] | None = None,
    seed: int = 0,
    callback: Callable[[int, np.ndarray, float], bool | None] | None = None,
    hess_inv0: np.ndarray | None = None,
    max_evaluations: int | None = None,
) -> OptimizeResult:
    """Maximize ``J`` of a CMax problem: a global search over a box, then local ascent from the best
    few candidates.

    Parameters
    ----------
    prob : ContrastMaximization
        The problem (its warp, objective and regularizers define J).
    theta0 : array_like, optional
        Start or warm start (physical units), e.g. the previous window's estimate.
    method : {"bfgs", "adam", "armijo", "lbfgs"}
        Local ascent (see the module docstring). ``"lbfgs"`` needs SciPy.
    init : {"auto", "pyramid", "grid", "random", "tpe", "local", "warm", "none"}
        Global initialisation. ``"pyramid"``: coarse to fine over an image pyramid
        (:mod:`cmax_taichi.solve.pyramid`: a design of ``n_init`` points and short BFGS ascents on
        views of the events 8-64 times coarser, then on views twice as fine each; 49-129 evaluations
        with the local run on the cases of docs/estimation.md); ``"grid"``: a coarse grid over the
        box (``n_init`` points) refined by a beam of zooming grids down to ``min_spacing`` px;
        ``"random"``: ``n_init`` uniform samples; ``"tpe"``: ``n_init`` trials of optuna's TPE
        sampler (needs optuna); ``"local"``: a grid search in a box around ``theta0`` of half-width
        ``0.5 |u0| + 5`` px per parameter (inside the global box); ``"warm"``: no search, one local
        run from the best of ``theta0``, ``candidates`` and the identity (the refinement of a
        sequence's warm start); ``"none"``: start at ``theta0`` (or 0). ``"auto"`` is ``"pyramid"``
        without ``theta0`` and ``"local"`` with it. ``theta0`` (when given), ``candidates`` and the
        identity are always evaluated; a result below the identity's J is never reported as converged.
    bounds : (lo, hi), optional
        Global search box in physical units; default :func:`search_bounds`. Local runs stay inside it.
        Finite, ``lo < hi`` per parameter, and within 1e290 px of displacement over the window (the
        searches step through differences of the box); a ValueError names the parameter otherwise.
        Points where J overflows the float type (:class:`~cmax_taichi.NonFiniteResultError`) count
        as -inf.
    n_init : int, optional
        Evaluation budget of the global search, 1 to :data:`MAX_N_INIT` (default 1000 for grid / random,
        200 for TPE, 300 for local); for the pyramid, the points of its coarsest design (default 27).
    n_starts : int
        Local runs, from the best distinct candidates of the global search (the pyramid hands on at
        most two, and a runner-up only when it gains at least half as much over the identity).
    max_iter : int, optional
        Iterations per local run, >= 0 (0: the global search alone; default 150 for Adam, 50 for
        BFGS, 100 otherwise).
    lr : float
        Adam step / first Armijo trial step, px of displacement over the window.
    gtol : float
        Stop when ``|dJ/du|`` (1/px) is below it (finite, >= 0).
    rtol : float
        Armijo / L-BFGS-B: stop when J improves by less than ``rtol * max(1, |J|)``.
    xtol : float
        Stop when the step (px) falls below it (Adam's halved step, Armijo's backtracked step).
    patience : int
        Adam: iterations without improvement before the step halves.
    min_spacing : float
        Grid search: finest spacing, px.
    candidates : sequence of array_like, optional
        More starting points (physical units) evaluated with the search, e.g. earlier estimates.
    seed : int
        Seed of random and TPE searches.
    callback : callable, optional
        ``callback(iteration, theta, value)`` after each iterate of each local run; return True to
        stop that run.
    hess_inv0 : ndarray, optional
        ``method="bfgs"``: the initial inverse Hessian of ``-J`` in internal units (px^2, symmetric
        positive definite, shape (P, P)), typically the previous window's ``result.hess_inv``: the
        first step is then a quasi-Newton step instead of a gradient step of ``lr`` px.

    max_evaluations : int, optional
        Evaluations of the whole call, >= 1: the local runs stop there with their best iterate,
        ``converged=False`` (default with ``init="pyramid"``: 150, the budget of a first window, plus
        the points of an ``n_init`` above the default 27; otherwise no limit).

    Returns
    -------
    OptimizeResult
        ``.theta`` in physical units, ``.value``, ``.history``, ``.n_iterations``, ``.seconds``,
        ``.converged``, ``.message``.
    """
    t_start = time.perf_counter()
    if not isinstance(prob, ContrastMaximization):
        raise TypeError(f"prob must be a ContrastMaximization, got {type(prob).__name__}")
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; valid: {', '.join(METHODS)}")
    if init not in INITS:
        raise ValueError(f"unknown init {init!r}; valid: {', '.join(INITS)}")
    lr = options.positive_number("lr", lr, "px")
    xtol = options.positive_number("xtol", xtol, "px")
    min_spacing = options.positive_number("min_spacing", min_spacing, "px")
    gtol = options.non_negative_number("gtol", gtol, "1/px")
    rtol = options.non_negative_number("rtol", rtol, "relative")
    n_starts = checks.whole_number("n_starts", n_starts, minimum=1)
    patience = checks.whole_number("patience", patience, minimum=1)
    if n_init is not None:
        n_init = checks.whole_number("n_init", n_init, minimum=1)
        if n_init > MAX_N_INIT:
            raise ValueError(
                f"n_init = {n_init:,} evaluations of the global search is above {MAX_N_INIT:,} (each is an "
                "evaluation of J: that many would run for hours or days); a narrower box (bounds=) or a "
                "warm start (theta0=) needs fewer"
            )
    if max_iter is not None:
        max_iter = checks.whole_number("max_iter", max_iter, minimum=0)
    if max_evaluations is not None:
        max_evaluations = checks.whole_number("max_evaluations", max_evaluations, minimum=1)
    model = prob.model
    P = model.n_params
    if hess_inv0 is not None:
        if method != "bfgs":
            raise ValueError(f"hess_inv0 is the initial inverse Hessian of method='bfgs', not {method!r}")
        checked = local.positive_definite(hess_inv0, P)
        if checked is None:
            raise ValueError(
                f"hess_inv0 must be a finite symmetric positive definite {P}x{P} matrix (px^2), "
                f"got {np.asarray(hess_inv0)!r}"
            )
        hess_inv0 = checked
    scales = parameter_scales(prob)
    obj = ScaledObjective(prob, scales)

    if bounds is None:
        lo_t, hi_t = search_bounds(prob)
    else:
        lo_t, hi_t = options.check_bounds(bounds, model)
    lo, hi = lo_t * scales, hi_t * scales
    options.check_searchable("bounds", np.stack([lo_t, hi_t]), scales, model)

    u0 = None
    if theta0 is not None:
        arr = options.parameter_vector("theta0", theta0, model)
        options.check_searchable("theta0", arr[None, :], scales, model)
        u0 = arr * scales
        lo, hi = np.minimum(lo, u0), np.maximum(hi, u0)  # a warm start outside the box widens it
    if init == "auto":
        init = "pyramid" if u0 is None else "local"
    if max_iter is None:
        max_iter = {"adam": 150, "bfgs": 50}.get(method, 100)
    rng = np.random.default_rng(seed)

    extra = [np.zeros(P)] if np.all((lo <= 0) & (hi >= 0)) else []
    if u0 is not None:
        extra.append(u0)
    for i, c in enumerate(candidates or ()):
        arr = options.parameter_vector(f"candidates[{i}]", c, model)
        extra.append(np.clip(arr * scales, lo, hi))
    if init == "warm" and u0 is None:
        raise ValueError("init='warm' refines a warm start: pass theta0")
    budget = int(n_init) if n_init is not None else _DEFAULT_N_INIT.get(init, 0)
    min_dist = np.maximum(min_spacing, 1e-9 * (hi - lo))  # two starts closer than this are one
    if init == "pyramid":
        found, pyramid_starts = pyramid_search(
            obj, lo, hi, extra=extra, n_final=int(n_starts), min_dist=min_dist, n_design=budget
        )
    elif init == "grid":
        found = grid_search(obj, lo, hi, budget=budget, beam=n_starts, min_spacing=min_spacing, extra=extra)
    elif init == "local":
        centre = u0 if u0 is not None else np.zeros(P)
        half = 0.5 * np.abs(centre) + 5.0
        llo, lhi = np.maximum(lo, centre - half), np.minimum(hi, centre + half)
        found = grid_search(obj, llo, lhi, budget=budget, beam=n_starts, min_spacing=min_spacing, extra=[])
        # the identity and theta0 may lie outside the local box: evaluate them where they are
        found += [(obj.value(u), np.array(u)) for u in extra]
    elif init == "warm":
        # the warm start with its gradient: it usually starts the local run, which then reuses both
        found = [(obj.value(u) if not np.any(u) else obj.value_and_grad(u)[0], np.array(u)) for u in extra]
        n_starts = 1
    elif init == "random":
        found = random_search(obj, lo, hi, budget=budget, rng=rng, extra=extra)
    elif init == "tpe":
        found = tpe_search(obj, lo, hi, budget=budget, seed=seed, extra=extra)
    else:  # "none"
        start = u0 if u0 is not None else np.zeros(P)
        found = [(obj.value(np.clip(start, lo, hi)), np.clip(start, lo, hi))]
    identity_value = next((v for v, u in found if not np.any(u)), None)
    starts = pyramid_starts if init == "pyramid" else distinct_top(found, int(n_starts), min_dist)
    if not starts:
        raise ValueError("the objective is not finite anywhere in the search box")

    if max_evaluations is None and init == "pyramid":  # a larger design than the default widens it
        max_evaluations = PYRAMID_BUDGET + max(0, budget - DESIGN_POINTS)
    obj.limit = max_evaluations
    runs: list[tuple[local.LocalRun, float, np.ndarray, str]] = []
    for val0, start in starts:
        if obj.exhausted and runs:
            break
        rec = local.Recorder(callback, obj)
        if method == "adam":
            run = local.adam(
                obj, start, lo, hi, lr=lr, max_iter=max_iter, gtol=gtol, xtol=xtol, patience=patience, rec=rec
            )
        elif method == "armijo":
            run = local.armijo(
                obj, start, lo, hi, lr=lr, max_iter=max_iter, gtol=gtol, xtol=xtol, rtol=rtol, rec=rec
            )
        elif method == "bfgs":
            run = local.bfgs(
                obj,
                start,
                lo,
                hi,
                lr=lr,
                max_iter=max_iter,
                gtol=gtol,
                xtol=xtol,
                rtol=rtol,
                rec=rec,
                hess_inv0=hess_inv0,
                max_step=PYRAMID_MAX_STEP if init == "pyramid" else None,
            )
        else:
            run = local.lbfgs(obj, start, lo, hi, max_iter=max_iter, gtol=gtol, rtol=rtol, rec=rec)
        if run.value < val0:  # never return worse than the start
            run.u, run.value = start.copy(), val0
        run, status = _settle(
            obj,
            run,
            start,
            method,
            lo,
            hi,
            lr=lr,
            max_iter=max_iter,
            gtol=gtol,
            xtol=xtol,
            rtol=rtol,
            callback=callback,
            warm=init == "warm",
        )
        if obj.exhausted:
            run.converged = False
            run.message = f"stopped at the evaluation budget (max_evaluations={max_evaluations})"
        runs.append((run, val0, start, status))
    best, best_val0, best_start, best_status = max(runs, key=lambda r: r[0].value)
    if best_status == "stalled":
        warnings.warn(
            checks.OptimizerStallWarning(
                f"maximize: the local run ended at its start ({best.message}), and the fallback did not "
                "move it either: theta is the global search's best point"
            ),
            stacklevel=2,
        )
    if identity_value is not None and best.value < identity_value:
        # only possible when a start was clipped into a box that excludes the identity's neighbourhood
        best.converged = False
        best.message = f"J = {best.value:.6g} is below the identity's {identity_value:.6g}: not converged"
    us = np.array(best.us) if best.us else best_start[None, :]
    history = History(
        theta=us / scales,
        value=np.array(best.values, dtype=np.float64),
        grad_norm=np.array(best.gnorms, dtype=np.float64),
    )
    return OptimizeResult(
        theta=obj.theta(best.u),
        value=float(best.value),
        history=history,
        n_iterations=best.n_iterations,
        n_evaluations=obj.n_evaluations,
        seconds=time.perf_counter() - t_start,
        converged=best.converged,
        message=best.message,
        status=best_status,
        method=method,
        init=init,
        theta_init=obj.theta(best_start),
        value_init=float(best_val0),
        scales=scales,
        param_names=tuple(model.params),
        units=tuple(model.units),
        value_identity=math.nan if identity_value is None else float(identity_value),
        hess_inv=best.hess_inv,
    )
