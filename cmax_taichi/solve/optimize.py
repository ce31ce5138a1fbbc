"""Maximizing a CMax problem: global initialisation, then local gradient ascent.

:func:`maximize` drives ``prob.value`` (forward only) for the global search and ``prob.value_and_grad``
for the local refinement. Three local methods:

* ``"adam"``: Adam gradient ascent with a plateau schedule (the step halves when the value has not
  improved for ``patience`` iterations, restarting from the best point), keeping the best iterate;
* ``"armijo"``: gradient ascent with a backtracking (Armijo) line search;
* ``"lbfgs"``: SciPy's L-BFGS-B on ``-J`` (needs SciPy);
* ``"bfgs"``: a dependency-free quasi-Newton ascent (BFGS updates of the inverse Hessian from the exact
  gradients, backtracking line search): the warm-start refinement of a sequence, which converges from
  a good start in about 5-20 evaluations.

Internal units
--------------
Parameters differ in scale by orders of magnitude (px/s, 1/s, rad/s, and all of them with the window
duration T). The optimizer works on ``u = theta * s`` where ``s`` (:func:`parameter_scales`) makes one
unit of ``u`` about **one pixel of displacement over the window**:

==============================================  =====================  ===========================
parameter                                        scale ``s`` (px per     default search range
                                                 unit of theta)          (:func:`search_bounds`)
==============================================  =====================  ===========================
velocity, px/s (``v_x``, ``v_y``, ``h_x``, ...)  ``T``                  ``|theta T| <= max(W, H)/2``
rate, 1/s (``h_z``, ``s``)                       ``T r``                ``|theta T| <= 1``
in-plane angular velocity, rad/s (``w``,         ``T r``                ``|theta T| <= 1`` rad
``theta``, rotation3 ``w_z``)
out-of-plane angular velocity, rad/s             ``T sqrt(f_x f_y)``    ``f |theta| T <= max(W, H)/2``
(rotation3 ``w_x``, ``w_y``)
==============================================  =====================  ===========================

``r`` is the RMS distance (px) of the pixel grid from the warp's centre (principal point or image
centre). Velocities are searched up to half the image per window. Rates are searched up to
``|h_z| T = 1``: at ``h_z T = 1`` the zoom sends the window's last events into the centre (time to
contact = T), and beyond it the events pass through the centre (a non-physical, mirrored warp).
The kind of each parameter comes from the model's registry entry (``WarpModel.parameter_kinds``: its
units px/s, 1/s, rad/s, unless it declares ``scale_kinds``, as rotation3 does for ``w_x, w_y``). A
model with another unit gets its scales numerically (the RMS over the pixel grid of the flow a unit
parameter causes, times T) and the velocity range for every parameter.

Learning rates, tolerances and grid spacings below are in these units (px over the window).
"""

from __future__ import annotations

import math
import numbers
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from cmax_taichi.core import checks
from cmax_taichi.models.warps import WarpModel
from cmax_taichi.pipeline.parameters import NonFiniteResultError
from cmax_taichi.pipeline.parameters import check_theta as _check_theta
from cmax_taichi.pipeline.problem import ContrastMaximization
from cmax_taichi.solve.search import distinct_top, grid_search, random_search, tpe_search

__all__ = [
    "METHODS",
    "INITS",
    "History",
    "OptimizeResult",
    "maximize",
    "parameter_scales",
    "search_bounds",
]

METHODS = ("adam", "armijo", "lbfgs", "bfgs")
INITS = ("auto", "grid", "random", "tpe", "local", "warm", "none")

#: default evaluation budget of the global search, per init
_DEFAULT_N_INIT = {"grid": 1000, "random": 1000, "tpe": 200, "local": 300}


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


# --- scales and ranges ---------------------------------------------------------------------------
def _rms_radius(prob: ContrastMaximization) -> float:
    """RMS distance (px) of the pixel centres from the warp's centre."""
    W, H = prob.width, prob.height
    cx, cy = prob.center
    var_x = (W * W - 1) / 12.0 + (cx - (W - 1) / 2.0) ** 2
    var_y = (H * H - 1) / 12.0 + (cy - (H - 1) / 2.0) ** 2
    return math.sqrt(var_x + var_y)


_NUMERIC_SCALES: dict = {}


def _kinds(model: WarpModel) -> tuple[str, ...] | None:
    """Per parameter "velocity" (range: half the image), "rate" (range: |theta T| <= 1) or "focal", as
    the model declares them (``WarpModel.parameter_kinds``: from its units unless declared); None:
    numeric scales."""
    return model.parameter_kinds


def _numeric_scales_per_second(prob: ContrastMaximization) -> np.ndarray:
    """RMS flow (px/s) over the pixel grid per unit of each parameter, at theta = 0 (cached)."""
    from cmax_taichi.pipeline.flow_field import dense_flow

    model = prob.model
    key = (model.name, id(model), prob.width, prob.height, prob.camera, prob.center)
    if key not in _NUMERIC_SCALES:
        out = np.empty(model.n_params)
        for i in range(model.n_params):
            # two passes: a unit step, then one sized to move pixels by about 1 px per second
            step = 1.0
            for _ in range(2):
                theta = np.zeros(model.n_params)
                theta[i] = step
                flow = dense_flow(model, theta, (prob.width, prob.height), camera=prob.camera, duration=1.0)
                rms = float(np.sqrt(np.nanmean(flow[0] ** 2 + flow[1] ** 2))) / step
                if not (math.isfinite(rms) and rms > 0):
                    rms = 1.0
                step = 1.0 / rms
            out[i] = rms
        _NUMERIC_SCALES[key] = out
    return _NUMERIC_SCALES[key]


def parameter_scales(prob: ContrastMaximization) -> np.ndarray:
    """Scale ``s`` of each parameter: px of displacement over the window per unit of theta.

    See the module docstring for the rule per parameter kind. ``u = theta * s`` are the optimizer's
    internal units.
    """
    T = prob.duration
    kinds = _kinds(prob.model)
    if kinds is None:
        return _numeric_scales_per_second(prob) * T
    r = _rms_radius(prob)
    f = math.sqrt(prob.camera.fx * prob.camera.fy) if prob.camera is not None else 1.0
    per_kind = {"velocity": T, "rate": T * r, "focal": T * f}
    return np.array([per_kind[k] for k in kinds])


def _half_ranges_u(prob: ContrastMaximization) -> np.ndarray:
    """Half-width of the default search box in internal units (px)."""
    half_image = 0.5 * max(prob.width, prob.height)
    kinds = _kinds(prob.model)
    if kinds is None:
        return np.full(prob.model.n_params, half_image)
    r = _rms_radius(prob)
    return np.array([r if k == "rate" else half_image for k in kinds])


def search_bounds(prob: ContrastMaximization) -> tuple[np.ndarray, np.ndarray]:
    """Default global search box ``(lo, hi)`` in physical units (see the module docstring)."""
    half = _half_ranges_u(prob) / parameter_scales(prob)
    return -half, half


# --- the objective in internal units --------------------------------------------------------------
class _Objective:
    """J and dJ/du in internal units, counting evaluations; non-finite values read as -inf.

    The last few results are remembered by point, so that a start point whose value and gradient the
    search already computed (a warm start) is not evaluated again.
    """

    _MEMO_SIZE = 8

    def __init__(self, prob: ContrastMaximization, scales: np.ndarray) -> None:
        self.prob = prob
        self.scales = scales
        self.n_evaluations = 0
        self._memo: dict[bytes, tuple[float, np.ndarray | None]] = {}

    def theta(self, u: np.ndarray) -> np.ndarray:
        return np.asarray(u, dtype=np.float64) / self.scales

    def _remember(self, u: np.ndarray, value: float, grad: np.ndarray | None) -> None:
        if len(self._memo) >= self._MEMO_SIZE:
            self._memo.pop(next(iter(self._memo)))
        self._memo[np.asarray(u, dtype=np.float64).tobytes()] = (value, grad)

    def value(self, u: np.ndarray) -> float:
        known = self._memo.get(np.asarray(u, dtype=np.float64).tobytes())
        if known is not None:
            return known[0]
        self.n_evaluations += 1
        try:
            v = self.prob.value(self.theta(u))
        except NonFiniteResultError:  # the parameters overflow the float type: outside the usable range
            v = -math.inf
        v = v if math.isfinite(v) else -math.inf
        self._remember(u, v, None)
        return v

    def value_and_grad(self, u: np.ndarray) -> tuple[float, np.ndarray]:
        known = self._memo.get(np.asarray(u, dtype=np.float64).tobytes())
        if known is not None and known[1] is not None:
            return known[0], known[1].copy()
        self.n_evaluations += 1
        try:
            v, g = self.prob.value_and_grad(self.theta(u))
        except NonFiniteResultError:
            return -math.inf, np.zeros(len(self.scales))
        g = np.asarray(g, dtype=np.float64) / self.scales
        if not (math.isfinite(v) and np.all(np.isfinite(g))):
            v, g = -math.inf, np.zeros_like(g)
        self._remember(u, v, g)
        return v, g.copy()


@dataclass
class _Run:
    u: np.ndarray
    value: float
    us: list
    values: list
    gnorms: list
    converged: bool
    message: str
    hess_inv: np.ndarray | None = None

    @property
    def n_iterations(self) -> int:
        return max(0, len(self.values) - 1)


class _Recorder:
    def __init__(self, callback, obj: _Objective) -> None:
        self.callback = callback
        self.obj = obj
        self.us: list = []
        self.values: list = []
        self.gnorms: list = []

    def add(self, u: np.ndarray, value: float, gnorm: float = math.nan) -> bool:
        """Record an iterate; True when the user's callback asks to stop."""
        self.us.append(np.array(u, dtype=np.float64))
        self.values.append(float(value))
        self.gnorms.append(float(gnorm))
        if self.callback is not None:
            return bool(self.callback(len(self.values) - 1, self.obj.theta(u), float(value)))
        return False


# --- local methods ---------------------------------------------------------------------------------
class AdamStepper:
    """The Adam direction of gradient *ascent* (Kingma & Ba 2015): exponential moments of the gradient
    and of its square, bias-corrected.

    Parameters
    ----------
    n : int
        Number of parameters.
    beta1, beta2 : float
        Decay of the first and second moments.
    eps : float
        Guard of the denominator (in the units of the gradient).
    """

    def __init__(self, n: int, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-12) -> None:
        self.beta1, self.beta2, self.eps = beta1, beta2, eps
        self.m = np.zeros(n)
        self.v = np.zeros(n)
        self.k = 0

    def reset(self) -> None:
        """Forget the moments (restart)."""
        self.m = np.zeros_like(self.m)
        self.v = np.zeros_like(self.v)
        self.k = 0

    def direction(self, g: np.ndarray) -> np.ndarray:
        """Take the gradient ``g`` into the moments; return ``mhat / (sqrt(vhat) + eps)`` (each entry
        about +-1: multiply by the step length)."""
        self.k += 1
        self.m = self.beta1 * self.m + (1 - self.beta1) * g
        self.v = self.beta2 * self.v + (1 - self.beta2) * g * g
        mhat = self.m / (1 - self.beta1**self.k)
        vhat = self.v / (1 - self.beta2**self.k)
        return mhat / (np.sqrt(vhat) + self.eps)


def _adam(obj, u0, lo, hi, *, lr, max_iter, gtol, xtol, patience, rec) -> _Run:
    u = np.clip(np.array(u0, dtype=np.float64), lo, hi)
    adam = AdamStepper(u.size)
    best_u, best_val = u.copy(), -math.inf
    stall = 0
    step = float(lr)
    converged, message = False, f"reached max_iter={max_iter}"
    for k in range(max_iter + 1):
        val, g = obj.value_and_grad(u)
        gnorm = float(np.linalg.norm(g))
        if rec.add(u, val, gnorm):
            converged, message = False, "stopped by callback"
            break
        if val > best_val + 1e-12 * max(1.0, abs(val)):
            best_u, best_val, stall = u.copy(), val, 0
        else:
            stall += 1
        if gnorm < gtol:
            converged, message = True, f"gradient norm {gnorm:.3g} < gtol={gtol:g}"
            break
        if k == max_iter:
            break
        if stall >= patience:
            # plateau: halve the step and restart the moments from the best point
            step *= 0.5
            if step < xtol:
                converged, message = True, f"step {step:.3g} px < xtol={xtol:g} px"
                break
            u, stall = best_u.copy(), 0
            adam.reset()
            val, g = obj.value_and_grad(u)
        u = np.clip(u + step * adam.direction(g), lo, hi)
    return _Run(best_u, best_val, rec.us, rec.values, rec.gnorms, converged, message)


def _recorded_start(obj, u0, lo, hi, rec):
    """``(u, value, gradient, gradient norm, stop)`` at the start point ``u0`` clipped to the bounds (px),
    recorded in ``rec``; ``stop`` is True when the callback asked to stop."""
    u = np.clip(np.array(u0, dtype=np.float64), lo, hi)
    val, g = obj.value_and_grad(u)
    gnorm = float(np.linalg.norm(g))
    return u, val, g, gnorm, rec.add(u, val, gnorm)


def _backtrack(evaluate, u, val, g, direction, alpha, lo, hi, c1, xtol, max_backtracks, interpolate=False):
    """Backtracking line search for an ascent step from ``u`` along ``direction`` (Armijo condition).

    Shrinks ``alpha`` from its given value until ``evaluate(u_new)[0] >= val + c1 * g . step`` with
    ``u_new = clip(u + alpha * direction)`` and ``step = u_new - u`` (px). ``evaluate`` returns a tuple
    whose first item is the objective value; the whole tuple is handed back. Each rejected trial halves
    ``alpha``, or with ``interpolate`` moves it to the maximum of the parabola through ``val``, the
    slope ``g . step`` and the trial value, kept within [0.1, 0.5] of the rejected ``alpha``
    (Nocedal & Wright, Numerical Optimization, 2nd ed., sec. 3.5): one or two trials where halving
    needs several. Returns ``(u_new, step, alpha, evaluation)`` of the accepted step, or None when no
    step longer than ``xtol`` px within ``max_backtracks`` trials increases the objective enough.
    """
    for _ in range(max_backtracks):
        u_new = np.clip(u + alpha * direction, lo, hi)
        step = u_new - u
        if float(np.max(np.abs(step))) < xtol:
            return None
        evaluation = evaluate(u_new)
        slope = float(g @ step)
        if evaluation[0] >= val + c1 * slope:
            return u_new, step, alpha, evaluation
        shrink = 0.5
        if interpolate and math.isfinite(evaluation[0]) and slope > 0:
            # parabola q(s) = val + slope s + c s^2 on the step fraction s in [0, 1], q(1) = trial value
            curvature = evaluation[0] - val - slope
            if curvature < 0:
                shrink = min(0.5, max(0.1, -slope / (2.0 * curvature)))
        alpha *= shrink
    return None


def _armijo(obj, u0, lo, hi, *, lr, max_iter, gtol, xtol, rtol, rec) -> _Run:
    c1, max_backtracks = 1e-4, 40
    u, val, g, gnorm, stop = _recorded_start(obj, u0, lo, hi, rec)
    alpha = lr / max(gnorm, 1e-300)  # the first trial step moves lr px
    converged, message = False, f"reached max_iter={max_iter}"
    for _ in range(max_iter):
        if stop:
            converged, message = False, "stopped by callback"
            break
        if gnorm < gtol:
            converged, message = True, f"gradient norm {gnorm:.3g} < gtol={gtol:g}"
            break
        trial = _backtrack(
            lambda u_trial: (obj.value(u_trial), None), u, val, g, g, alpha, lo, hi, c1, xtol, max_backtracks
        )
        if trial is None:
            converged, message = True, f"no ascent step longer than xtol={xtol:g} px (local maximum)"
            break
        u_new, step, alpha, (val_new, _) = trial
        gain = val_new - val
        u = u_new
        val, g = obj.value_and_grad(u)
        gnorm = float(np.linalg.norm(g))
        stop = rec.add(u, val, gnorm)
        if gain < rtol * max(1.0, abs(val)):
            converged, message = True, f"relative change {gain / max(1.0, abs(val)):.3g} < rtol={rtol:g}"
            break
        alpha *= 2.0  # let the step grow again after a successful one
    best = int(np.argmax(rec.values))
    return _Run(rec.us[best], rec.values[best], rec.us, rec.values, rec.gnorms, converged, message)


def _lbfgs(obj, u0, lo, hi, *, max_iter, gtol, rtol, rec) -> _Run:
    try:
        from scipy.optimize import minimize as scipy_minimize
    except ImportError:
        raise ImportError(
            "method='lbfgs' needs SciPy: pip install scipy (or 'cmax-taichi[scipy]'), "
            "or use method='adam' / 'armijo'"
        ) from None
    last: dict = {}

    def fun(u):
        val, g = obj.value_and_grad(u)
        last["u"], last["val"], last["g"] = np.array(u), val, g
        if not math.isfinite(val):
            return 1e30, np.zeros_like(g)
        return -val, -g

    class _StopRequestError(Exception):
        pass

    def callback(u):
        val = last["val"] if "u" in last and np.array_equal(last["u"], u) else obj.value(u)
        g = last.get("g")
        if rec.add(u, val, float(np.linalg.norm(g)) if g is not None else math.nan):
            raise _StopRequestError

    u0 = np.clip(np.array(u0, dtype=np.float64), lo, hi)
    rec.add(u0, obj.value(u0))
    try:
        res = scipy_minimize(
            fun,
            u0,
            jac=True,
            method="L-BFGS-B",
            bounds=list(zip(lo, hi, strict=True)),
            callback=callback,
            options={"maxiter": max_iter, "gtol": gtol, "ftol": rtol},
        )
        converged, message = bool(res.success), f"L-BFGS-B: {res.message}"
    except _StopRequestError:
        converged, message = False, "stopped by callback"
    best = int(np.argmax(rec.values))
    return _Run(rec.us[best], rec.values[best], rec.us, rec.values, rec.gnorms, converged, message)


def _bfgs(obj, u0, lo, hi, *, lr, max_iter, gtol, xtol, rtol, rec, hess_inv0=None) -> _Run:
    """Quasi-Newton ascent: BFGS updates of the inverse Hessian of -J from exact gradients, a
    backtracking line search with parabolic interpolation, projection onto the box.

    The first step is a quasi-Newton step with ``hess_inv0`` (a previous window's estimate, px^2) when
    it is given and positive definite, else a gradient step of ``lr`` px. The run stops, without
    another evaluation, when the quasi-Newton step itself is shorter than ``xtol`` px (the estimate is
    already resolved to that precision).
    """
    c1, max_backtracks = 1e-4, 30
    u, val, g, gnorm, stop = _recorded_start(obj, u0, lo, hi, rec)
    n = u.size
    H = _positive_definite(hess_inv0, n)
    warm_curvature = H is not None
    if H is None:
        H = np.eye(n) * (lr / max(gnorm, 1e-300))  # inverse curvature guess: the first step moves lr px
    frozen = np.zeros(n, dtype=bool)  # parameters held at a kink of J (see below)
    converged, message = False, f"reached max_iter={max_iter}"
    for _ in range(max_iter):
        if stop:
            converged, message = False, "stopped by callback"
            break
        if not math.isfinite(val):
            message = "the objective is not finite at the start"
            break
        if gnorm < gtol:
            converged, message = True, f"gradient norm {gnorm:.3g} < gtol={gtol:g}"
            break
        direction = _free_direction(H, g, frozen, lr)
        if direction is None:  # lost positive definiteness: restart from a gradient step
            H = np.eye(n) * (lr / max(gnorm, 1e-300))
            direction = _free_direction(H, g, frozen, lr)
            warm_curvature = False
        newton = float(np.max(np.abs(np.clip(u + direction, lo, hi) - u)))
        if warm_curvature and newton < xtol:
            converged, message = True, f"quasi-Newton step {newton:.3g} px < xtol={xtol:g} px"
            break
        trial = _backtrack(
            obj.value_and_grad, u, val, g, direction, 1.0, lo, hi, c1, xtol, max_backtracks, interpolate=True
        )
        while trial is None and np.count_nonzero(~frozen) > 1:
            # A kink of J (a regularizer's one-sided hinge, e.g. the divergence penalty at h_z = 0) has
            # different slopes on its two sides: the gradient of one side can point across it, and then
            # every step along the direction descends although the gradient is not small. Hold the
            # parameter that carries most of the predicted gain where it is and search the others.
            gain_share = np.where(frozen, -np.inf, direction * g)
            frozen[int(np.argmax(gain_share))] = True
            direction = _free_direction(H, g, frozen, lr)
            if direction is None:
                break
            trial = _backtrack(
                obj.value_and_grad, u, val, g, direction, 1.0, lo, hi, c1, xtol, max_backtracks, True
            )
        if trial is None:
            converged, message = True, f"no ascent step longer than xtol={xtol:g} px (local maximum)"
            break
        u_new, step, _, (val_new, g_new) = trial
        gain = val_new - val
        y = g - g_new  # gradient change of -J
        sy = float(step @ y)
        if sy > 1e-12 * float(np.linalg.norm(step) * np.linalg.norm(y)):
            if not warm_curvature:  # first curvature pair: rescale the guess (Nocedal & Wright 6.20)
                H = np.eye(n) * (sy / float(y @ y))
            rho = 1.0 / sy
            V = np.eye(n) - rho * np.outer(step, y)
            H = V @ H @ V.T + rho * np.outer(step, step)
            warm_curvature = True
        u, val, g = u_new, val_new, g_new
        gnorm = float(np.linalg.norm(g))
        stop = rec.add(u, val, gnorm)
        if gain < rtol * max(1.0, abs(val)):
            converged, message = True, f"relative change {gain / max(1.0, abs(val)):.3g} < rtol={rtol:g}"
            break
        if float(np.max(np.abs(step))) < xtol:
            converged, message = True, f"step {float(np.max(np.abs(step))):.3g} px < xtol={xtol:g} px"
            break
    best = int(np.argmax(rec.values))
    hess_inv = H.copy() if warm_curvature else None
    return _Run(rec.us[best], rec.values[best], rec.us, rec.values, rec.gnorms, converged, message, hess_inv)


def _free_direction(H: np.ndarray, g: np.ndarray, frozen: np.ndarray, lr: float) -> np.ndarray | None:
    """The quasi-Newton ascent direction ``H g`` over the parameters not ``frozen`` (frozen ones do not
    move); the gradient step of ``lr`` px over them when ``H g`` does not ascend; None when neither
    does (no gradient left on the free parameters)."""
    free = ~frozen
    direction = np.zeros_like(g)
    if np.any(frozen):
        sub = H[np.ix_(free, free)]
        direction[free] = sub @ g[free]
    else:
        direction = H @ g
    if float(direction @ g) > 0:
        return direction
    g_free = np.where(free, g, 0.0)
    norm = float(np.linalg.norm(g_free))
    if not norm > 0:
        return None
    return g_free * (lr / norm)


def _positive_definite(matrix, n: int) -> np.ndarray | None:
    """``matrix`` as an (n, n) float64 array when it is a finite, symmetric positive definite matrix
    (a usable inverse Hessian), else None."""
    if matrix is None:
        return None
    H = np.asarray(matrix, dtype=np.float64)
    if H.shape != (n, n) or not np.all(np.isfinite(H)):
        return None
    H = 0.5 * (H + H.T)
    try:
        np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        return None
    return H


# --- the driver --------------------------------------------------------------------------------------
def _real_number(name: str, value, unit: str) -> float:
    if not isinstance(value, numbers.Real) or isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be a number ({unit}), got {value!r} ({type(value).__name__})")
    try:
        number = float(value)
    except OverflowError:
        raise ValueError(f"{name} must be a finite number ({unit}), got an int beyond float64") from None
    if not math.isfinite(number):
        raise ValueError(f"{name} must be a finite number ({unit}), got {number}")
    return number


def _positive_number(name: str, value, unit: str) -> float:
    number = _real_number(name, value, unit)
    if not number > 0:
        raise ValueError(f"{name} must be a positive number ({unit}), got {number}")
    return number


def _non_negative_number(name: str, value, unit: str) -> float:
    number = _real_number(name, value, unit)
    if not number >= 0:
        raise ValueError(f"{name} must be a finite number >= 0 ({unit}), got {number}")
    return number


def _parameter_vector(name: str, value, model: WarpModel) -> np.ndarray:
    """A parameter vector of ``model`` given by the user (``theta0``, a candidate, a bound), checked as
    the problem checks theta, with ``name`` in the message."""
    return _check_theta(value, model.n_params, model.name, label=name)


#: the largest |u| (px over the window) the searches step through: they take differences and
#: midpoints of the box and round points to 1e-9 px to skip repeats (u * 1e9 overflows float64 from
#: 1.8e299)
_SEARCHABLE_U = 1e290


def _check_searchable(name: str, thetas: np.ndarray, scales: np.ndarray, model: WarpModel) -> None:
    """Refuse parameter values whose internal units (``theta * scale``, px) the searches cannot step
    through (differences of the box overflow float64), naming the parameter and the limit."""
    with np.errstate(over="ignore", invalid="ignore"):
        u = np.abs(thetas * scales)
    bad = np.argwhere(~(u <= _SEARCHABLE_U))
    if bad.size:
        i = int(bad[0][1])
        limit = _SEARCHABLE_U / scales[i]
        raise ValueError(
            f"{name}: {model.params[i]} = {thetas[tuple(bad[0])]:.6g} {model.units[i]} is beyond what the "
            f"search can step through for this problem: |{model.params[i]}| <= {limit:.3g} {model.units[i]}"
        )


def _check_bounds(bounds, model: WarpModel) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` of a user-given search box: finite parameter vectors with ``lo < hi``."""
    P = model.n_params
    if isinstance(bounds, (str, bytes)) or not hasattr(bounds, "__len__") or len(bounds) != 2:
        raise TypeError(
            f"bounds must be a pair (lo, hi) of {P} numbers each for warp {model.name!r}, got {bounds!r}"
        )
    lo = _parameter_vector("bounds lo", bounds[0], model)
    hi = _parameter_vector("bounds hi", bounds[1], model)
    inverted = np.flatnonzero(~(lo < hi))
    if inverted.size:
        i = int(inverted[0])
        raise ValueError(
            f"bounds: lo[{i}] = {lo[i]:.6g} is not below hi[{i}] = {hi[i]:.6g} "
            f"(parameter {model.params[i]!r} of warp {model.name!r}); bounds are (lo, hi) with lo < hi"
        )
    return lo, hi


def maximize(
    prob: ContrastMaximization,
    theta0: Sequence[float] | np.ndarray | None = None,
    method: str = "adam",
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
) -> OptimizeResult:
    """Maximize ``J`` of a CMax problem: a global search over a box, then local ascent from the best
    few candidates.

    Parameters
    ----------
    prob : ContrastMaximization
        The problem (its warp, objective and regularizers define J).
    theta0 : array_like, optional
        Start or warm start (physical units), e.g. the previous window's estimate.
    method : {"adam", "armijo", "lbfgs", "bfgs"}
        Local ascent (see the module docstring). ``"lbfgs"`` needs SciPy.
    init : {"auto", "grid", "random", "tpe", "local", "warm", "none"}
        Global initialisation. ``"grid"``: a coarse grid over the box (``n_init`` points) refined by a
        beam of zooming grids down to ``min_spacing`` px; ``"random"``: ``n_init`` uniform samples;
        ``"tpe"``: ``n_init`` trials of optuna's TPE sampler (needs optuna); ``"local"``: a grid search
        in a box around ``theta0`` of half-width ``0.5 |u0| + 5`` px per parameter (inside the global
        box); ``"warm"``: no search, one local run from the best of ``theta0``, ``candidates`` and the
        identity (the refinement of a sequence's warm start); ``"none"``: start at ``theta0`` (or 0).
        ``"auto"`` is ``"grid"`` without ``theta0`` and ``"local"`` with it. ``theta0`` (when given),
        ``candidates`` and the identity are always evaluated; a result below the identity's J is never
        reported as converged.
    bounds : (lo, hi), optional
        Global search box in physical units; default :func:`search_bounds`. Local runs stay inside it.
        Finite, ``lo < hi`` per parameter, and within 1e290 px of displacement over the window (the
        searches step through differences of the box); a ValueError names the parameter otherwise.
        Points where J overflows the float type (:class:`~cmax_taichi.NonFiniteResultError`) count
        as -inf.
    n_init : int, optional
        Evaluation budget of the global search, >= 1 (default 1000 for grid / random, 200 for TPE, 300
        for local).
    n_starts : int
        Local runs, from the best distinct candidates of the global search.
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
    lr = _positive_number("lr", lr, "px")
    xtol = _positive_number("xtol", xtol, "px")
    min_spacing = _positive_number("min_spacing", min_spacing, "px")
    gtol = _non_negative_number("gtol", gtol, "1/px")
    rtol = _non_negative_number("rtol", rtol, "relative")
    n_starts = checks.whole_number("n_starts", n_starts, minimum=1)
    patience = checks.whole_number("patience", patience, minimum=1)
    if n_init is not None:
        n_init = checks.whole_number("n_init", n_init, minimum=1)
    if max_iter is not None:
        max_iter = checks.whole_number("max_iter", max_iter, minimum=0)
    model = prob.model
    P = model.n_params
    if hess_inv0 is not None:
        if method != "bfgs":
            raise ValueError(f"hess_inv0 is the initial inverse Hessian of method='bfgs', not {method!r}")
        checked = _positive_definite(hess_inv0, P)
        if checked is None:
            raise ValueError(
                f"hess_inv0 must be a finite symmetric positive definite {P}x{P} matrix (px^2), "
                f"got {np.asarray(hess_inv0)!r}"
            )
        hess_inv0 = checked
    scales = parameter_scales(prob)
    obj = _Objective(prob, scales)

    if bounds is None:
        lo_t, hi_t = search_bounds(prob)
    else:
        lo_t, hi_t = _check_bounds(bounds, model)
    lo, hi = lo_t * scales, hi_t * scales
    _check_searchable("bounds", np.stack([lo_t, hi_t]), scales, model)

    u0 = None
    if theta0 is not None:
        arr = _parameter_vector("theta0", theta0, model)
        _check_searchable("theta0", arr[None, :], scales, model)
        u0 = arr * scales
        lo, hi = np.minimum(lo, u0), np.maximum(hi, u0)  # a warm start outside the box widens it
    if init == "auto":
        init = "grid" if u0 is None else "local"
    if max_iter is None:
        max_iter = {"adam": 150, "bfgs": 50}.get(method, 100)
    rng = np.random.default_rng(seed)

    extra = [np.zeros(P)] if np.all((lo <= 0) & (hi >= 0)) else []
    if u0 is not None:
        extra.append(u0)
    for i, c in enumerate(candidates or ()):
        arr = _parameter_vector(f"candidates[{i}]", c, model)
        extra.append(np.clip(arr * scales, lo, hi))
    if init == "warm" and u0 is None:
        raise ValueError("init='warm' refines a warm start: pass theta0")
    budget = int(n_init) if n_init is not None else _DEFAULT_N_INIT.get(init, 0)
    if init == "grid":
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
    min_dist = np.maximum(min_spacing, 1e-9 * (hi - lo))
    starts = distinct_top(found, int(n_starts), min_dist)
    if not starts:
        raise ValueError("the objective is not finite anywhere in the search box")

    runs: list[tuple[_Run, float, np.ndarray]] = []
    for val0, start in starts:
        rec = _Recorder(callback, obj)
        if method == "adam":
            run = _adam(
                obj, start, lo, hi, lr=lr, max_iter=max_iter, gtol=gtol, xtol=xtol, patience=patience, rec=rec
            )
        elif method == "armijo":
            run = _armijo(
                obj, start, lo, hi, lr=lr, max_iter=max_iter, gtol=gtol, xtol=xtol, rtol=rtol, rec=rec
            )
        elif method == "bfgs":
            run = _bfgs(
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
            )
        else:
            run = _lbfgs(obj, start, lo, hi, max_iter=max_iter, gtol=gtol, rtol=rtol, rec=rec)
        if run.value < val0:  # never return worse than the start
            run.u, run.value = start.copy(), val0
        runs.append((run, val0, start))
    best, best_val0, best_start = max(runs, key=lambda r: r[0].value)
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
