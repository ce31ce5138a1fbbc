"""The local ascents of :func:`cmax_taichi.maximize` and the objective they climb.

:class:`ScaledObjective` is J and dJ/du in the optimizer's internal units (``u = theta * s``, px of
displacement over the window, :mod:`cmax_taichi.solve.scales`), counting evaluations. The methods:

* :func:`adam`: Adam gradient ascent with a plateau schedule (the step halves when the value has not
  improved for ``patience`` iterations, restarting from the best point), keeping the best iterate;
* :func:`armijo`: gradient ascent with a backtracking (Armijo) line search;
* :func:`lbfgs`: SciPy's L-BFGS-B on ``-J`` (needs SciPy);
* :func:`bfgs`: a dependency-free quasi-Newton ascent (BFGS updates of the inverse Hessian from the
  exact gradients, backtracking line search): converges from a good start in about 5-20 evaluations.

Each takes the objective, a start ``u0`` and the box ``lo, hi`` (px) and returns a :class:`LocalRun`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cmax_taichi.pipeline.parameters import NonFiniteResultError
from cmax_taichi.pipeline.problem import ContrastMaximization

__all__ = [
    "AdamStepper",
    "LocalRun",
    "Recorder",
    "ScaledObjective",
    "adam",
    "armijo",
    "bfgs",
    "compass_probe",
    "lbfgs",
    "positive_definite",
]


# --- the objective in internal units --------------------------------------------------------------
class ScaledObjective:
    """J and dJ/du in internal units, counting evaluations; non-finite values read as -inf.

    The last few results are remembered by point, so that a start point whose value and gradient the
    search already computed (a warm start) is not evaluated again.
    """

    _MEMO_SIZE = 8

    def __init__(self, prob: ContrastMaximization, scales: np.ndarray) -> None:
        self.prob = prob
        self.scales = scales
        self.n_evaluations = 0
        #: evaluations allowed (None: no limit); past it a point reads as -inf without being evaluated,
        #: which ends every local method's run at its best iterate, and ``exhausted`` turns True
        self.limit: int | None = None
        self.exhausted = False
        self._memo: dict[bytes, tuple[float, np.ndarray | None]] = {}

    def _spent(self) -> bool:
        if self.limit is not None and self.n_evaluations >= self.limit:
            self.exhausted = True
            return True
        return False

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
        if self._spent():
            return -math.inf
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
        if self._spent():
            return -math.inf, np.zeros(len(self.scales))
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
class LocalRun:
    """The outcome of one local run: its best point ``u`` (px) and ``value``, the iterates (``us``,
    ``values``, gradient norms ``gnorms`` in 1/px), whether a stopping rule ended it and why, and the
    BFGS inverse Hessian (px^2) where the method has one. ``failed``: the method stopped without a
    stopping rule or a limit (its line search found no ascent step along its direction, L-BFGS-B's
    "ABNORMAL", a start where J is not finite): at a kink of J, where the gradient of one side points
    across it, this happens away from any maximum (:func:`compass_probe` checks)."""

    u: np.ndarray
    value: float
    us: list
    values: list
    gnorms: list
    converged: bool
    message: str
    hess_inv: np.ndarray | None = None
    failed: bool = False

    @property
    def n_iterations(self) -> int:
        return max(0, len(self.values) - 1)


class Recorder:
    """The iterates of one local run, and the user's callback after each."""

    def __init__(self, callback, obj: ScaledObjective) -> None:
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


def adam(obj, u0, lo, hi, *, lr, max_iter, gtol, xtol, patience, rec) -> LocalRun:
    """Adam ascent with steps of ``lr`` px, halved after ``patience`` iterations without improvement
    (restarting from the best point); stops at ``gtol``, a step below ``xtol`` or ``max_iter``."""
    u = np.clip(np.array(u0, dtype=np.float64), lo, hi)
    stepper = AdamStepper(u.size)
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
            stepper.reset()
            val, g = obj.value_and_grad(u)
        u = np.clip(u + step * stepper.direction(g), lo, hi)
    return LocalRun(best_u, best_val, rec.us, rec.values, rec.gnorms, converged, message)


def recorded_start(obj, u0, lo, hi, rec):
    """``(u, value, gradient, gradient norm, stop)`` at the start point ``u0`` clipped to the bounds (px),
    recorded in ``rec``; ``stop`` is True when the callback asked to stop."""
    u = np.clip(np.array(u0, dtype=np.float64), lo, hi)
    val, g = obj.value_and_grad(u)
    gnorm = float(np.linalg.norm(g))
    return u, val, g, gnorm, rec.add(u, val, gnorm)


def backtrack(evaluate, u, val, g, direction, alpha, lo, hi, c1, xtol, max_backtracks, interpolate=False):
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


def armijo(obj, u0, lo, hi, *, lr, max_iter, gtol, xtol, rtol, rec) -> LocalRun:
    """Gradient ascent with a backtracking Armijo line search (first trial step ``lr`` px)."""
    c1, max_backtracks = 1e-4, 40
    u, val, g, gnorm, stop = recorded_start(obj, u0, lo, hi, rec)
    alpha = lr / max(gnorm, 1e-300)  # the first trial step moves lr px
    converged, message, failed = False, f"reached max_iter={max_iter}", False
    for _ in range(max_iter):
        if stop:
            converged, message = False, "stopped by callback"
            break
        if gnorm < gtol:
            converged, message = True, f"gradient norm {gnorm:.3g} < gtol={gtol:g}"
            break
        trial = backtrack(
            lambda u_trial: (obj.value(u_trial), None), u, val, g, g, alpha, lo, hi, c1, xtol, max_backtracks
        )
        if trial is None:
            converged, message = False, f"no ascent step longer than xtol={xtol:g} px along the gradient"
            failed = True
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
    return LocalRun(
        rec.us[best], rec.values[best], rec.us, rec.values, rec.gnorms, converged, message, failed=failed
    )


def lbfgs(obj, u0, lo, hi, *, max_iter, gtol, rtol, rec) -> LocalRun:
    """SciPy's L-BFGS-B on ``-J`` inside the box."""
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
        failed = res.status not in (0, 1)  # 1: the iteration or evaluation limit
    except _StopRequestError:
        converged, message, failed = False, "stopped by callback", False
    best = int(np.argmax(rec.values))
    return LocalRun(
        rec.us[best], rec.values[best], rec.us, rec.values, rec.gnorms, converged, message, failed=failed
    )


def bfgs(obj, u0, lo, hi, *, lr, max_iter, gtol, xtol, rtol, rec, hess_inv0=None, max_step=None) -> LocalRun:
    """Quasi-Newton ascent: BFGS updates of the inverse Hessian of -J from exact gradients, a
    backtracking line search with parabolic interpolation, projection onto the box.

    The first step is a quasi-Newton step with ``hess_inv0`` (a previous window's estimate, px^2) when
    it is given and positive definite, else a gradient step of ``lr`` px. The run stops, without
    another evaluation, when the quasi-Newton step itself is shorter than ``xtol`` px (the estimate is
    already resolved to that precision). ``max_step`` (px, optional) caps every trial step per
    parameter: from a start near a maximum, a quasi-Newton step far longer than the distance to it
    comes from curvature pairs taken across a kink of J, and only costs backtracking.
    """
    c1, max_backtracks = 1e-4, 30
    u, val, g, gnorm, stop = recorded_start(obj, u0, lo, hi, rec)
    n = u.size
    H = positive_definite(hess_inv0, n)
    warm_curvature = H is not None
    if H is None:
        H = np.eye(n) * (lr / max(gnorm, 1e-300))  # inverse curvature guess: the first step moves lr px
    frozen = np.zeros(n, dtype=bool)  # parameters held at a kink of J (see below)
    converged, message, failed = False, f"reached max_iter={max_iter}", False
    for _ in range(max_iter):
        if stop:
            converged, message = False, "stopped by callback"
            break
        if not math.isfinite(val):
            message, failed = "the objective is not finite at the start", True
            break
        if gnorm < gtol:
            converged, message = True, f"gradient norm {gnorm:.3g} < gtol={gtol:g}"
            break
        direction = free_direction(H, g, frozen, lr)
        if direction is None:  # lost positive definiteness: restart from a gradient step
            H = np.eye(n) * (lr / max(gnorm, 1e-300))
            direction = free_direction(H, g, frozen, lr)
            warm_curvature = False
        if direction is None:  # no gradient left on the free parameters
            converged, message = True, "the gradient vanishes on the parameters not held at a kink"
            break
        newton = float(np.max(np.abs(np.clip(u + direction, lo, hi) - u)))
        if warm_curvature and newton < xtol:
            converged, message = True, f"quasi-Newton step {newton:.3g} px < xtol={xtol:g} px"
            break
        direction = _capped(direction, max_step)
        trial = backtrack(
            obj.value_and_grad, u, val, g, direction, 1.0, lo, hi, c1, xtol, max_backtracks, interpolate=True
        )
        while trial is None and np.count_nonzero(~frozen) > 1:
            # A kink of J (a regularizer's one-sided hinge, e.g. the divergence penalty at h_z = 0) has
            # different slopes on its two sides: the gradient of one side can point across it, and then
            # every step along the direction descends although the gradient is not small. Hold the
            # parameter that carries most of the predicted gain where it is and search the others.
            gain_share = np.where(frozen, -np.inf, direction * g)
            frozen[int(np.argmax(gain_share))] = True
            if not warm_curvature:  # the guess was sized by the frozen slope: size it by the free ones
                free_norm = float(np.linalg.norm(np.where(frozen, 0.0, g)))
                H = np.eye(n) * (lr / max(free_norm, 1e-300))
            direction = free_direction(H, g, frozen, lr)
            if direction is None:
                break
            direction = _capped(direction, max_step)
            trial = backtrack(
                obj.value_and_grad, u, val, g, direction, 1.0, lo, hi, c1, xtol, max_backtracks, True
            )
        if trial is None:
            converged, message = (
                False,
                f"no ascent step longer than xtol={xtol:g} px along any direction tried",
            )
            failed = True
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
    return LocalRun(
        rec.us[best], rec.values[best], rec.us, rec.values, rec.gnorms, converged, message, hess_inv, failed
    )


def compass_probe(obj, u: np.ndarray, value: float, lo, hi, step: float):
    """One-sided steps of ``step`` px from ``u`` along each parameter, both ways: ``(u, value)`` of the
    best one that ascends, or None when none does (``u`` is then a maximum along every parameter at
    that step). The check of a run that ended at its start without a stopping rule: at a kink of J
    (a regularizer's hinge, the deformation's ``max(D, 1/D)`` at D = 1) the gradient is one side's,
    and a method that follows it can stop where a step to the other side still ascends."""
    best = None
    for i in range(u.size):
        for sign in (1.0, -1.0):
            trial = np.array(u, dtype=np.float64)
            trial[i] = min(max(trial[i] + sign * step, lo[i]), hi[i])
            if trial[i] == u[i]:
                continue
            v = obj.value(trial)
            if v > value and (best is None or v > best[1]):
                best = (trial, v)
    return best


def _capped(direction: np.ndarray, max_step: float | None) -> np.ndarray:
    """``direction`` shortened so that no parameter moves by more than ``max_step`` px (None: as is)."""
    longest = float(np.max(np.abs(direction)))
    if max_step is None or longest <= max_step:
        return direction
    return direction * (max_step / longest)


def free_direction(H: np.ndarray, g: np.ndarray, frozen: np.ndarray, lr: float) -> np.ndarray | None:
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


def positive_definite(matrix, n: int) -> np.ndarray | None:
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
