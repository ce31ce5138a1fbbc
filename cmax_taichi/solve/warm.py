"""What one window of a pass leaves to the next (:class:`WarmState`), and :class:`WindowSolver`, the
per-window work of a pass: one :class:`~cmax_taichi.ContrastMaximization` for every window (given each
next one with :meth:`~cmax_taichi.ContrastMaximization.set_events`: its pooled fields, buffers and
compiled kernels serve them all), the global search or the warm refinement with its tracking test, and
the FWL of the estimate. :func:`cmax_taichi.solve.sequence.process` (a recording) and
:func:`cmax_taichi.solve.online.run_live` (a live stream) drive it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from cmax_taichi.core.events import Camera, Events
from cmax_taichi.metrics import fwl_problem
from cmax_taichi.pipeline.problem import ContrastMaximization
from cmax_taichi.pipeline.setup import numeric_t_ref
from cmax_taichi.solve.optimize import OptimizeResult, maximize
from cmax_taichi.solve.results import WindowResult

__all__ = ["TRACKING_LOSS_RATIO", "WARM_XTOL", "WarmState", "WindowSolver", "synthetic_window"]

#: a warm-started window whose refined J falls below this fraction of the previous window's J, and whose
#: gain over the identity, J(theta) - J(0), falls below this fraction of the previous window's gain (scaled
#: down by the squared ratio of window durations when this window is shorter: the gain grows with the
#: identity's motion blur, as its square for blurs of a few px) has lost track of the motion (a sudden
#: change): the global search runs too. Windows of varying sizes or small fluctuations are not a loss
TRACKING_LOSS_RATIO = 0.8

#: the warm refinement's ``xtol`` (px over the window): it stops at a quasi-Newton step, or an accepted
#: step, shorter than this, unless ``optimize_options`` gives an ``xtol``. ``maximize``'s default of
#: 0.01 px chased steps that the windows' data do not resolve: on the shared recordings and the simulated
#: streams this rule takes 25-60% fewer warm evaluations, with errors against the truth about the same
#: (benchmarks/NOTES.md, "2026-12-05, evening")
WARM_XTOL = 0.03

#: problem options under which the estimate's own problem measures the FWL (variance, normalised, no
#: weights or whitening): then its J at the estimate is the FWL and no second problem is built
_FWL_COMPATIBLE_OPTIONS = {"blur_sigma", "t_ref", "polarity"}


def check_sequence_t_ref(t_ref, n_windows: int | None) -> None:
    """A numeric ``t_ref`` is one time on the events' clock: every window of a sequence would be warped
    to it, the later ones over far more than their duration. Allowed for a run of one window only (its
    distance to that window is checked with the window, :func:`~cmax_taichi.pipeline.setup.resolve_t_ref`)."""
    if isinstance(t_ref, str):
        return
    numeric_t_ref(t_ref)  # a type or a value that no window takes: that error first
    if n_windows is not None and n_windows <= 1:
        return
    count = "an unknown number of" if n_windows is None else f"{n_windows}"
    raise ValueError(
        f"t_ref {t_ref!r} s is one time on the events' clock, and this run has {count} windows: every "
        "window would be warped to that time, the later ones over many times their duration; use "
        "'first', 'middle' or 'last' (each window's own time), or run one window (max_windows=1)"
    )


@dataclass(frozen=True)
class WarmState:
    """What the warm start of a window takes from the window before it (see :func:`process`).

    Attributes
    ----------
    theta : ndarray
        The previous estimate, physical units.
    value : float
        Its J.
    value_identity : float
        J of the identity warp on that window (NaN: unknown; then the tracking test compares J alone).
    duration : float
        That window's duration, s (NaN: unknown).
    hess_inv : ndarray or None
        The BFGS inverse Hessian of its refinement (internal units, px^2), or None.
    """

    theta: np.ndarray
    value: float
    value_identity: float = math.nan
    duration: float = math.nan
    hess_inv: np.ndarray | None = None

    @classmethod
    def after(cls, row: WindowResult, result: OptimizeResult) -> WarmState:
        """The state a window leaves for the next one: its row and its optimizer result."""
        return cls(
            theta=np.asarray(row.theta, dtype=np.float64),
            value=float(row.value),
            value_identity=float(result.value_identity),
            duration=float(row.t_end - row.t_start),
            hess_inv=None if result.hess_inv is None else np.array(result.hess_inv, dtype=np.float64),
        )

    def as_dict(self) -> dict:
        """JSON-friendly (NaN as None)."""

        def number(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "theta": [float(v) for v in self.theta],
            "value": number(self.value),
            "value_identity": number(self.value_identity),
            "duration": number(self.duration),
            "hess_inv": None if self.hess_inv is None else np.asarray(self.hess_inv).tolist(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> WarmState:
        """The inverse of :meth:`as_dict`."""

        def number(v) -> float:
            return math.nan if v is None else float(v)

        hess = data.get("hess_inv")
        return cls(
            theta=np.asarray(data["theta"], dtype=np.float64),
            value=number(data.get("value")),
            value_identity=number(data.get("value_identity")),
            duration=number(data.get("duration")),
            hess_inv=None if hess is None else np.asarray(hess, dtype=np.float64),
        )

    def lost_track(self, value: float, value_identity: float, duration: float) -> bool:
        """Whether a refined window (``value``, its identity's J, its duration in s) lost track of the
        motion this state describes (see :data:`TRACKING_LOSS_RATIO`): J fell below the ratio times
        the previous J, and, where both identities' J are known, so did the gain over the identity
        (scaled for a shorter window). Either test alone misfires: J alone on windows of varying
        sizes, the gain alone on recordings of weak contrast (gains of a few % that fluctuate)."""
        if not math.isfinite(self.value) or value >= TRACKING_LOSS_RATIO * self.value:
            return False
        if math.isfinite(self.value_identity) and math.isfinite(value_identity):
            gain_before = self.value - self.value_identity
            if not gain_before > 0:
                return False  # the previous window gained nothing over the identity: nothing to lose
            scale = 1.0
            if math.isfinite(self.duration) and self.duration > 0 and duration > 0:
                scale = min(1.0, duration / self.duration) ** 2
            return value - value_identity < TRACKING_LOSS_RATIO * gain_before * scale
        return True


class WindowSolver:
    """Solves the windows of one pass, in order, on one problem, each warm-started from the one before.

    Parameters
    ----------
    model : WarpModel
    objective, regularizers, camera
        As for :class:`~cmax_taichi.ContrastMaximization`.
    problem_options, optimize_options : mapping
        More arguments of the problem (``weights`` among them: per event of the source windows) and of
        :func:`~cmax_taichi.maximize`.
    method, warm_method : str
        The local optimizer after a global search, and the warm refinement's.
    warm_start : bool
        Warm-start each window from :attr:`state` (else the global search in every window).
    compute_fwl : bool
        Also compute each estimate's FWL.
    state : WarmState, optional
        The warm start of the first window (a resumed pass).

    Attributes
    ----------
    prob : ContrastMaximization or None
        The problem, holding the last window solved (None before the first).
    state : WarmState or None
        What the last window left (:meth:`advance`).
    """

    def __init__(
        self,
        model,
        *,
        objective: str = "variance",
        regularizers: Mapping[str, float] | None = None,
        camera: Camera | None = None,
        problem_options: Mapping[str, Any] | None = None,
        optimize_options: Mapping[str, Any] | None = None,
        method: str = "bfgs",
        warm_method: str = "bfgs",
        warm_start: bool = True,
        compute_fwl: bool = True,
        state: WarmState | None = None,
    ) -> None:
        if state is not None and not isinstance(state, WarmState):
            raise TypeError(f"warm_state must be a sequence.WarmState, got {type(state).__name__}")
        self.model, self.objective, self.regularizers, self.camera = model, objective, regularizers, camera
        self.popts = dict(problem_options or {})
        self.oopts = dict(optimize_options or {})
        self.weights = self.popts.pop("weights", None)
        self.method, self.warm_method, self.warm_start = method, warm_method, warm_start
        self.compute_fwl = compute_fwl
        self.state = state
        self.prob: ContrastMaximization | None = None
        self._fprob: ContrastMaximization | None = None
        self.fwl_is_value = (
            objective == "variance"
            and not any(float(w) for w in (regularizers or {}).values())
            and set(self.popts) <= _FWL_COMPATIBLE_OPTIONS
        )

    def solve(
        self, used: Events, kept: np.ndarray | None = None, start: str = "auto"
    ) -> tuple[OptimizeResult, str, float]:
        """Solve the window ``used`` (its events after the drops; ``kept``: which of them undistortion
        kept, to select their weights): ``(result, search, fwl)``, ``search`` as in
        :attr:`WindowResult.search`, ``fwl`` NaN unless computed.

        ``start``: ``"auto"`` (the warm refinement of :attr:`state`, or the global search without one or
        without ``warm_start``), ``"identity"`` (a local ascent from the identity warp: ``search`` is
        ``"identity"``; the global search too when the ascent stays at the identity, as it does on events
        at whole pixels, whose image at the identity is a spike: ``"identity+global"``) or
        ``"global"``."""
        weights = self.weights
        if weights is not None and kept is not None and np.shape(weights) == kept.shape:
            weights = np.asarray(weights)[kept]  # as the problem's own undistortion does
        if self.prob is None:
            self.prob = ContrastMaximization(
                used, warp=self.model, objective=self.objective, regularizers=self.regularizers,
                camera=self.camera, weights=weights, **self.popts,
            )  # fmt: skip
        else:  # the same problem takes the next window: its fields, kernels and buffers stay
            self.prob.set_events(used, weights=weights)
        prob = self.prob
        if start == "identity":  # the local ascent to its own tolerance, as after a global search
            zero = np.zeros(self.model.n_params)
            res = maximize(prob, theta0=zero, method=self.warm_method, init="warm", **self.oopts)
            search = start
            if not np.any(res.theta):  # held at the identity (events on whole pixels: its spike)
                res = maximize(prob, method=self.method, **self.oopts)
                search = "identity+global"
        else:
            state = self.state if self.warm_start and start == "auto" else None
            res, search = _solve_window(prob, state, self.method, self.warm_method, self.oopts)
        value_fwl = math.nan
        if self.compute_fwl:
            if self.fwl_is_value:
                value_fwl = res.value  # the estimate's problem is the FWL problem
            else:
                if self._fprob is None:
                    self._fprob = _fwl_problem(
                        prob, self.model, self.camera, self.popts.get("t_ref", "first")
                    )
                else:
                    self._fprob.set_events(prob.events)
                value_fwl = self._fprob.value(res.theta)
        return res, search, float(value_fwl)

    def warm_up(self, sensor_size: tuple[int, int], n_events: int, seed: int = 0) -> float:
        """Compile (or load from Taichi's offline cache) what the windows of a ``sensor_size`` source
        will run, on synthetic windows of about ``n_events`` events (a pattern translating at 200 px/s;
        its undistortion too): the problem's kernels, the search from the identity and a warm
        refinement. Leaves the problem allocated and no warm state. Returns the seconds it took."""
        from cmax_taichi.solve.adaptive import extreme_speed

        t0 = time.perf_counter()
        events = synthetic_window(sensor_size, n_events, self.camera, seed)
        n = len(events)
        res, _, _ = self.solve(events, None, "identity")
        self.retry_from(res)
        res, _, _ = self.solve(events[: max(8, n // 2)])
        extreme_speed(self.prob, np.full(self.model.n_params, 1e-3))
        self.state = None
        return time.perf_counter() - t0

    def advance(self, row: WindowResult, result: OptimizeResult) -> None:
        """The window of ``row`` is done: the next one warm-starts from it."""
        self.state = WarmState.after(row, result)

    def retry_from(self, result: OptimizeResult) -> None:
        """The window just solved is solved again, longer (an adaptive first window): warm-start from
        this result."""
        prob = self.prob
        self.state = WarmState(
            theta=np.asarray(result.theta, dtype=np.float64), value=float(result.value),
            value_identity=float(result.value_identity), duration=float(prob.duration),
            hess_inv=None if result.hess_inv is None else np.array(result.hess_inv, dtype=np.float64),
        )  # fmt: skip


def synthetic_window(
    sensor_size: tuple[int, int], n_events: int, camera: Camera | None = None, seed: int = 0
) -> Events:
    """A window of about ``n_events`` events (at least 16) of 64 dots moving along x at 200 px/s over
    20 ms, on whole pixels of a ``sensor_size`` sensor, undistorted by ``camera`` when it has
    distortion: what a live run's warm-up compiles its kernels on."""
    W, H = sensor_size
    rng = np.random.default_rng(seed)
    n = max(16, int(n_events))
    t = np.sort(rng.uniform(0.0, 0.02, n))
    x0, y0 = rng.integers(0, W, 64), rng.integers(0, H, 64)
    k = rng.integers(0, 64, n)
    x = np.clip(np.round(x0[k] + 200.0 * t), 0, W - 1)
    events = Events(x, y0[k].astype(np.float64), t, rng.choice([-1.0, 1.0], n), (W, H))
    if camera is not None and camera.has_distortion:
        events = events.undistort(camera)
    return events


def _fwl_problem(prob: ContrastMaximization, model, camera: Camera | None, t_ref) -> ContrastMaximization:
    """The problem whose J is the FWL of ``prob``'s window (the same, already undistorted, events).

    For a variance problem with regularizers on the fused path: the same regularizers at weight 0, so
    that it runs on the estimate's compiled kernel (the weights are data); a problem without them would
    compile a kernel of its own on the first window (about a second of front end and code generation).
    """
    options = dict(camera=camera, blur_sigma=prob.blur_sigma, t_ref=t_ref, polarity=prob.polarity)
    if prob.regularizer_weights and prob.path == "fused" and prob.objective.name == "variance":
        zero = {name: 0.0 for name in prob.regularizer_weights}
        return ContrastMaximization(
            prob.events, warp=model, objective="variance", regularizers=zero, **options
        )
    return fwl_problem(prob.events, model, **options)


def _solve_window(
    prob: ContrastMaximization,
    state: WarmState | None,
    method: str,
    warm_method: str,
    oopts: dict,
) -> tuple[OptimizeResult, str]:
    """Solve one window: the global search, or the warm refinement with its tracking test.

    A BFGS refinement starts with the previous window's inverse Hessian (a quasi-Newton first step):
    consecutive windows of one motion have about the same curvature in the per-window pixel units of
    :func:`~cmax_taichi.maximize`."""
    if state is None:
        return maximize(prob, method=method, **oopts), "global"
    if "init" in oopts:  # the caller's init in every window, from the previous estimate
        return maximize(prob, theta0=state.theta, method=method, **oopts), oopts["init"]
    warm_options = dict(oopts)
    warm_options.setdefault("xtol", WARM_XTOL)
    if warm_method == "bfgs" and state.hess_inv is not None and "hess_inv0" not in warm_options:
        warm_options["hess_inv0"] = state.hess_inv
    res = maximize(prob, theta0=state.theta, method=warm_method, init="warm", **warm_options)
    if not state.lost_track(res.value, res.value_identity, prob.duration):
        return res, "warm"
    full = maximize(prob, method=method, candidates=[state.theta], **oopts)
    best = full if full.value > res.value else res
    return (
        replace(
            best,
            n_evaluations=res.n_evaluations + full.n_evaluations,
            seconds=res.seconds + full.seconds,
        ),
        "warm+global",
    )
