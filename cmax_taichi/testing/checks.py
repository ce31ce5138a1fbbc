"""The library's own checks of a warp model, an objective or a regularizer.

:func:`check_model`, :func:`check_objective` and :func:`check_regularizer` (``cm.check_model`` and so
on) hold every closed form that an entry declares against central differences of what it is the
derivative of, and its values against the float64 NumPy reference where one exists, on several
parameter vectors and in both precisions. Each returns a :class:`CheckReport` that names what is wrong
(the column of ``param_jac``, the quantity, the precision and the parameter vector); the project's own
tests run them on every registered entry, so a new built-in is tested by being registered.

What is checked:

* a warp model, per event (``kernels/model_checks.py``): ``warp`` at ``dt = 0`` is the identity; the
  flow is ``-dW/d(dt)`` at ``dt = 0``; the closed ``det`` is ``det dx'/dx`` and ``div`` the trace of
  ``dv/dx`` (central differences in x and y); every column of ``param_jac`` (``dx'/dtheta``,
  ``d det/dtheta``, ``d div/dtheta``) against central differences in that parameter; a ``warp_terms``
  returns what ``warp``, ``det`` and ``param_jac`` do; ``constant_quantities`` are constant over the
  events; ``positive_det`` holds; position, det, div and flow against the model's NumPy twin
  (:mod:`cmax_taichi.testing.reference_warps`) when one is registered. Then a problem (variance with
  both regularizers): J against the reference and dJ/dtheta against central differences (of the
  reference where there is a twin, else of J itself).
* an objective: J (with both built-in regularizers) against a NumPy formula of the objective (the
  reference's for the built-ins, or ``reference=``) and dJ/dtheta against central differences, on two
  warps; with a fused declaration on both paths (the declared ``adjoint`` on the fused one, Taichi's
  autodiff of the pixel terms and finalize on the chain).
* a regularizer: ``penalty_grad`` against central differences of ``penalty`` over a range of map values;
  J with the regularizer against the reference (the built-ins, or a NumPy ``reference_penalty``) and its
  gradient against central differences, on two warps.

Switching precision re-initialises Taichi (problems built before are invalidated); the precision in use
is restored at the end.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from cmax_taichi.testing import samples

__all__ = ["CheckError", "CheckReport", "check_model", "check_objective", "check_regularizer"]

#: central-difference steps (px of displacement, px, fraction of the window) and tolerances per precision
_STEPS = {"f64": dict(theta=1e-3, pos=1e-3, time=1e-4), "f32": dict(theta=3e-2, pos=5e-2, time=1e-2)}
_TOL = {
    "f64": dict(diff=1e-6, ref=1e-9, value=1e-10, grad=2e-6, identity=1e-9),
    "f32": dict(diff=2e-2, ref=1e-4, value=2e-4, grad=2e-2, identity=1e-3),
}
#: map values where a penalty is sampled, per quantity kind (a user quantity: the divergence's)
_PENALTY_SAMPLES = {
    "absdet": np.geomspace(0.05, 5.0, 41) * 1.0137,
    "div": np.linspace(-30.0, 30.0, 41) + 0.0137,
}
_BOTH = {"divergence": 0.7, "deformation": 1.3}


class CheckError(AssertionError):
    """A check of :mod:`cmax_taichi.testing.checks` failed; the message is the report."""


@dataclass
class CheckReport:
    """What a check found.

    Attributes
    ----------
    subject : str
        What was checked, e.g. ``"warp 'affine6'"``.
    passed : list of str
        The checks that held.
    failures : list of str
        One line per check that did not hold, naming the quantity (the column of ``param_jac``, ...),
        the precision and the parameter vector.
    notes : list of str
        What could not be checked and why (no NumPy twin, no fused declaration, ...).
    """

    subject: str
    passed: list[str] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failures

    def __str__(self) -> str:
        head = f"{self.subject}: " + (
            f"{len(self.passed)} checks passed" if self.ok else f"{len(self.failures)} check(s) FAILED"
        )
        lines = [head]
        lines += [f"  FAILED {f}" for f in self.failures]
        lines += [f"  note: {n}" for n in self.notes]
        if self.ok:
            lines += [f"  ok: {p}" for p in self.passed]
        return "\n".join(lines)

    __repr__ = __str__

    def raise_if_failed(self) -> CheckReport:
        """Raise :class:`CheckError` (an AssertionError) with the report when a check failed."""
        if not self.ok:
            raise CheckError(str(self))
        return self

    def _compare(
        self,
        label: str,
        context: str,
        got,
        want,
        tol: float,
        *,
        scale: float | None = None,
        floor: float = 1e-12,
    ) -> None:
        """Record ``label`` as passed, or as failed in ``context``: ``max |got - want| <= tol * scale``
        (``scale``: the largest magnitude of ``want`` unless given, at least ``floor``: the size below
        which a difference is rounding, in the quantity's unit)."""
        got = np.asarray(got, dtype=np.float64)
        want = np.asarray(want, dtype=np.float64)
        if scale is None:
            finite = want[np.isfinite(want)]
            scale = float(np.max(np.abs(finite))) if finite.size else 0.0
        scale = max(scale, floor)
        err = np.abs(got - want).reshape(-1)
        err = np.where(np.isfinite(err), err, np.inf)
        worst = int(np.argmax(err)) if err.size else 0
        value = float(err[worst]) if err.size else 0.0
        if value > tol * scale:
            where = f" at entry {worst % max(got.shape[-1], 1)}" if got.ndim else ""
            self.failures.append(
                f"{label} {context}: max error {value:.3g}{where}, {value / scale:.3g} of its scale "
                f"{scale:.3g} (tolerance {tol:g})"
            )
        elif label not in self.passed:
            self.passed.append(label)

    def _require(self, label: str, context: str, holds: bool, detail: str) -> None:
        """Record ``label`` as passed, or as failed in ``context`` with ``detail``."""
        if not holds:
            self.failures.append(f"{label} {context}: {detail}")
        elif label not in self.passed:
            self.passed.append(label)


# ---------------------------------------------------------------------------------------------------
# shared set-up
# ---------------------------------------------------------------------------------------------------
def _precisions(precisions: Sequence[str] | None) -> tuple[str, ...]:
    from cmax_taichi.core import backend

    if precisions is not None:
        out = tuple(precisions)
        bad = [p for p in out if p not in backend.PRECISIONS]
        if bad or not out:
            raise ValueError(f"precisions must be among {backend.PRECISIONS}, got {precisions!r}")
        return out
    arch = backend.info().requested_arch if backend.is_initialized() else "cpu"
    return ("f32",) if arch in ("vulkan", "metal") else ("f64", "f32")


@contextlib.contextmanager
def _backend_precisions(precisions: tuple[str, ...]) -> Iterator[Callable[[str], None]]:
    """Yield ``use(precision)``, which re-initialises Taichi on the same arch when the precision
    changes; the precision in use before is restored at the end."""
    from cmax_taichi.core import backend

    before = backend.ensure_initialized()

    def use(precision: str) -> None:
        if backend.info().precision != precision:
            backend.init(arch=before.requested_arch, precision=precision)

    try:
        yield use
    finally:
        if backend.info().precision != before.precision:
            backend.init(arch=before.requested_arch, precision=before.precision)


def _events(n: int = 400, seed: int = 0):
    import cmax_taichi as cm

    x, y, t, p = samples.edge_events(n=n, seed=seed)
    return cm.Events(x, y, t, p, samples.SENSOR), (x, y, t, p)


def _ref_kwargs(warp: str, **extra) -> dict:
    cam = samples.CAMERA
    kwargs = dict(warp=warp, sensor_size=samples.SENSOR, center=(cam.cx, cam.cy), focal=(cam.fx, cam.fy))
    kwargs.update(extra)
    return kwargs


def _fd_grad(fn: Callable[[np.ndarray], float], theta: np.ndarray, rel_step: float = 1e-6) -> np.ndarray:
    """Central differences of ``fn`` (the reference's, with the step ``rel_step * max(1, |theta_i|)``)."""
    from cmax_taichi.testing.reference import central_differences

    return central_differences(fn, theta, rel_step=rel_step)


def _problem(events, warp, *, chain: bool = False, **options):
    import cmax_taichi as cm
    from cmax_taichi.pipeline.fused import FusedPipeline

    saved = FusedPipeline.enabled
    FusedPipeline.enabled = not chain
    try:
        return cm.ContrastMaximization(events, warp=warp, camera=samples.CAMERA, **options)
    finally:
        FusedPipeline.enabled = saved


def _check_j(report: CheckReport, prob, thetas, reference_j, precision: str, what: str, tag: str) -> None:
    """J of ``prob`` against ``reference_j(theta)`` (when given) and dJ/dtheta against its central
    differences (of the reference, else of J itself in f64; in f32 without a reference: skipped)."""
    tol = _TOL[precision]
    for k, theta in enumerate(thetas):
        value, grad = prob.value_and_grad(theta)
        context = f"[{precision}, {tag}, theta #{k} = {np.array2string(theta, precision=4)}]"
        if reference_j is not None:
            report._compare(
                "J against the float64 reference", context, value, reference_j(theta), tol["value"]
            )
            fd = _fd_grad(reference_j, theta)
        elif precision == "f64":
            fd = _fd_grad(prob.value, theta)
        else:
            continue
        report._compare(f"dJ/dtheta {what} against central differences", context, grad, fd, tol["grad"])


# ---------------------------------------------------------------------------------------------------
# warp models
# ---------------------------------------------------------------------------------------------------
def _default_thetas(model, rng) -> list[np.ndarray]:
    """Several parameter vectors from the model's declarations: tiny (the series branches), moderate,
    reversed and large, the last two with unequal random factors."""
    base = samples.moderate_theta(model)
    jitter = rng.uniform(0.7, 1.3, base.size)
    return [base * 1e-6, base, -0.6 * base * jitter, 2.5 * base * jitter[::-1]]


def _point_blocks(model, x, y, dt, theta, steps, scales):
    """The points of one parameter vector: the events, then the events with theta -/+ h e_j, x -/+ h,
    y -/+ h, dt -/+ tau, and at dt = 0 (``(points, thetas, h_theta)``)."""
    n, P = x.size, model.n_params
    h_theta = steps["theta"] / scales
    tau = steps["time"] * samples.DURATION
    pos = np.stack([x, y, dt], axis=1)
    blocks_p, blocks_th = [pos], [np.tile(theta, (n, 1))]
    for j in range(P):
        for sign in (-1.0, 1.0):
            shifted = theta.copy()
            shifted[j] += sign * h_theta[j]
            blocks_p.append(pos)
            blocks_th.append(np.tile(shifted, (n, 1)))
    for axis, h in ((0, steps["pos"]), (1, steps["pos"]), (2, None)):
        for sign in (-1.0, 1.0):
            moved = pos.copy()
            if h is None:
                moved[:, 2] = sign * tau
            else:
                moved[:, axis] += sign * h
            blocks_p.append(moved)
            blocks_th.append(np.tile(theta, (n, 1)))
    at_zero = pos.copy()
    at_zero[:, 2] = 0.0
    blocks_p.append(at_zero)
    blocks_th.append(np.tile(theta, (n, 1)))
    return np.concatenate(blocks_p), np.concatenate(blocks_th), h_theta, tau


class _ModelKernel:
    """The model's per-point kernel (``kernels/model_checks.py``) with its pooled fields."""

    def __init__(self, model, n_points: int) -> None:
        import taichi as ti

        from cmax_taichi.core import backend, workspace
        from cmax_taichi.kernels import model_checks as kmc
        from cmax_taichi.pipeline.setup import cached_kernel

        self.model = model
        P = model.n_params
        real = backend.real()
        self.cap = cap = workspace.capacity_for(n_points)

        def build(ws):
            ws.points = ti.Vector.field(3, real, shape=cap)
            ws.th = ti.Vector.field(P, real, shape=cap)
            ws.ctx = ti.Vector.field(5, real, shape=())
            ws.out = ti.field(real, shape=(len(kmc.VALUE_ROWS), cap))
            ws.jac = ti.field(real, shape=(4, cap, P))
            ws.terms = ti.field(real, shape=(3, cap))
            ws.terms_jac = ti.field(real, shape=(4, cap, P))

        self.ws = workspace.acquire(("model_check", backend.info().generation, cap, P), build)
        self.kernel = cached_kernel(
            ("model_check", model.name, id(model)),
            lambda: kmc.make_model_kernel(
                model.warp, model.det_fn, model.div_fn, model.flow, model.param_jac, P, model.warp_terms
            ),
        )

    def __call__(self, points: np.ndarray, thetas: np.ndarray, ctx) -> tuple[np.ndarray, np.ndarray | None]:
        from cmax_taichi.core import backend

        ws, n = self.ws, points.shape[0]
        real = backend.numpy_real()
        for f, values in ((ws.points, points), (ws.th, thetas)):
            padded = np.zeros((self.cap, values.shape[1]), dtype=real)
            padded[:n] = values
            f.from_numpy(padded)
        ws.ctx[None] = list(ctx)
        self.kernel(n, ws.points, ws.th, ws.ctx, ws.out, ws.jac, ws.terms, ws.terms_jac)
        out = ws.out.to_numpy()[:, :n].astype(np.float64)
        jac = ws.jac.to_numpy()[:, :n].astype(np.float64) if self.model.param_jac is not None else None
        return out, jac

    def terms(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """What ``warp_terms`` returned at the points of the last call: ``x', y', det`` and the
        derivatives (as ``jac``)."""
        terms = self.ws.terms.to_numpy()[:, :n].astype(np.float64)
        return terms, self.ws.terms_jac.to_numpy()[:, :n].astype(np.float64)


def _check_closed_forms(report, model, raw, thetas, precision, twin) -> None:
    """The per-event checks of :func:`check_model` in the running precision."""
    x, y, t, _ = raw
    n, P = x.size, model.n_params
    dt = t - 0.4 * samples.DURATION  # negative and positive offsets
    cam = samples.CAMERA
    ctx = (cam.cx, cam.cy, cam.fx, cam.fy, samples.DURATION)
    steps, tol = _STEPS[precision], _TOL[precision]
    scales = samples.parameter_scales(model)
    kernel = None
    for k, theta in enumerate(thetas):
        points, point_thetas, h_theta, tau = _point_blocks(model, x, y, dt, theta, steps, scales)
        if kernel is None:
            kernel = _ModelKernel(model, points.shape[0])
        out, jac = kernel(points, point_thetas, ctx)
        blocks = out.reshape(out.shape[0], -1, n)  # (row, block, event)
        base = blocks[:, 0]
        by_theta = blocks[:, 1 : 1 + 2 * P]
        bx_m, bx_p, by_m, by_p, bt_m, bt_p, at_zero = (blocks[:, 1 + 2 * P + i] for i in range(7))
        at = f"[{precision}, theta #{k} = {np.array2string(theta, precision=4)}]"
        # the warp at dt = 0, the flow as -dW/d(dt) there
        report._compare("warp(p, dt=0) is p", at, at_zero[:2], np.stack([x, y]), tol["identity"], scale=1.0)
        dw_dt = (bt_p[:2] - bt_m[:2]) / (2.0 * tau)
        rate = 1.0 / samples.DURATION  # one px (flow) or one unit of area (div) per window: the floors
        report._compare("flow is -dW/d(dt) at dt = 0", at, base[4:6], -dw_dt, tol["diff"], floor=rate)
        # det and div against central differences in x and y
        h = steps["pos"]
        jxx, jyx = (bx_p[0] - bx_m[0]) / (2 * h), (bx_p[1] - bx_m[1]) / (2 * h)
        jxy, jyy = (by_p[0] - by_m[0]) / (2 * h), (by_p[1] - by_m[1]) / (2 * h)
        if model.det is not None:
            report._compare("det is det dx'/dx", at, base[2], jxx * jyy - jxy * jyx, tol["diff"], floor=1.0)
        if model.div is not None:
            trace = (bx_p[4] - bx_m[4]) / (2 * h) + (by_p[5] - by_m[5]) / (2 * h)
            report._compare("div is the trace of dv/dx", at, base[3], trace, tol["diff"], floor=rate)
        if jac is not None:
            closed = jac.reshape(4, -1, n, P)[:, 0]
            _check_param_jac(report, model, closed, by_theta, h_theta, scales, tol["diff"], at)
        if model.warp_terms is not None:  # the fused kernels' joint function is the separate ones
            terms, terms_jac = kernel.terms(points.shape[0])
            terms, terms_jac = terms[:, :n], terms_jac.reshape(4, -1, n, P)[:, 0]
            for r, name in enumerate(("x'", "y'", "det")):
                report._compare(
                    f"warp_terms: its {name} is the model's", at, terms[r], base[r], tol["ref"], floor=1.0
                )
            rows = ("dx'/dtheta (row x')", "dx'/dtheta (row y')", "d det/dtheta", "d div/dtheta")
            for r, name in enumerate(rows):  # per px of displacement, as the param_jac checks
                got, want = terms_jac[r] / scales, closed[r] / scales
                label = f"warp_terms: its {name} is param_jac's"
                report._compare(label, at, got, want, tol["ref"], floor=1.0)
        for kind in model.constant_quantities:  # declared constants
            values = base[3] if kind == "div" else np.abs(base[2])
            report._compare(
                f"constant_quantities: {kind} is the same at every event",
                at,
                values,
                np.full(n, values[0]),
                tol["diff"],
                scale=max(abs(values[0]), 1.0),
            )
        if model.positive_det:
            worst = float(np.min(base[2]))
            report._require("positive_det", at, worst > 0.0, f"declared, but det = {worst:.4g} at an event")
        if twin is not None:
            _check_against_twin(report, twin, theta, (x, y, dt), base, tol["ref"], at)


def _check_param_jac(report, model, closed, by_theta, h_theta, scales, tol: float, at: str) -> None:
    """Each column of ``param_jac`` (``closed``: row, event, parameter) against central differences in
    that parameter (``by_theta``: row, 2 P shifted blocks, event)."""
    P = model.n_params
    fd = np.stack(
        [(by_theta[:4, 2 * j + 1] - by_theta[:4, 2 * j]) / (2.0 * h_theta[j]) for j in range(P)], -1
    )
    rows = ("dx'/dtheta (row x')", "dx'/dtheta (row y')", "d det/dtheta", "d div/dtheta")
    for r, row in enumerate(rows):
        # per px of displacement, so that the columns of one row are comparable
        cn, fn = closed[r] / scales, fd[r] / scales
        row_scale = float(np.max(np.abs(fn)))
        for j in range(P):
            report._compare(
                f"param_jac: column {j} ({model.params[j]}) of {row} against central differences",
                at,
                cn[:, j],
                fn[:, j],
                tol,
                scale=max(row_scale, 1e-3),
            )


def _check_against_twin(report, twin, theta, events, base, tol: float, at: str) -> None:
    """Position, det, div and flow of every event against the model's float64 NumPy twin."""
    x, y, dt = events
    cam = samples.CAMERA
    context = dict(focal=(cam.fx, cam.fy), duration=samples.DURATION)
    xw, yw, det, div = twin.warp(theta, x, y, dt, center=(cam.cx, cam.cy), **context)
    vx, vy = twin.flow(theta, x - cam.cx, y - cam.cy, **context)
    ref = [np.broadcast_to(np.asarray(v, dtype=np.float64), x.shape) for v in (xw, yw, det, div, vx, vy)]
    rate = 1.0 / samples.DURATION
    for r, (name, floor) in enumerate((("x'", 1.0), ("y'", 1.0), ("det", 1.0), ("div", rate))):
        report._compare(f"{name} against the float64 reference", at, base[r], ref[r], tol, floor=floor)
    report._compare("flow against the float64 reference", at, base[4:6], np.stack(ref[4:]), tol, floor=rate)


def check_model(
    model,
    *,
    thetas: Sequence | None = None,
    precisions: Sequence[str] | None = None,
    problem: bool = True,
    seed: int = 0,
) -> CheckReport:
    """Check a warp model's declarations against what they declare (see the module docstring).

    Parameters
    ----------
    model : str or WarpModel
        A registered name or a model (registered or not).
    thetas : sequence of array_like, optional
        Parameter vectors to check at (physical units). Default: four derived from the declarations
        (:func:`cmax_taichi.testing.samples.moderate_theta`, scaled by 1e-6, 1, -0.6 and 2.5).
    precisions : sequence of {"f64", "f32"}, optional
        Default both (f32 only on Vulkan and Metal). Switching re-initialises Taichi.
    problem : bool
        Also check a problem's J and dJ/dtheta (variance with both regularizers, on the fused path when
        the model declares ``param_jac``).
    seed : int
        Seed of the synthetic events and of the random factors of the default parameter vectors.

    Returns
    -------
    CheckReport
        ``report.ok``; ``str(report)`` lists what failed; ``report.raise_if_failed()``.
    """
    from cmax_taichi.models.warps import get_warp, warp_names
    from cmax_taichi.testing import reference, reference_warps

    model = get_warp(model)
    report = CheckReport(f"warp {model.name!r}")
    rng = np.random.default_rng(seed)
    if thetas is None:
        theta_list = _default_thetas(model, rng)
    else:
        theta_list = [np.asarray(th, dtype=np.float64).reshape(-1) for th in thetas]
        for th in theta_list:
            if th.size != model.n_params:
                raise ValueError(f"warp {model.name!r} takes {model.n_params} parameter(s), got {th.size}")
    twin = reference_warps.REFERENCE_WARPS.get(model.name)
    if twin is not None and twin.n_params != model.n_params:
        report.failures.append(
            f"the float64 reference warp {model.name!r} takes {twin.n_params} parameters, "
            f"the model {model.n_params}"
        )
        twin = None
    if twin is None:
        unclaimed = [  # a twin registered under another name than its model's (a typo, a renamed model)
            n
            for n, w in reference_warps.REFERENCE_WARPS.items()
            if w.n_params == model.n_params and n not in warp_names()
        ]
        hint = f" (unclaimed twins of {model.n_params} parameters: {', '.join(unclaimed)})" * bool(unclaimed)
        report.notes.append(
            f"no float64 NumPy twin named {model.name!r} is registered (testing.reference."
            f"register_reference_warp, under the model's name){hint}: values are checked for consistency "
            "only, not against the reference"
        )
    if model.param_jac is None:
        report.notes.append("no param_jac: problems with this model run on the generic autodiff chain")
    if model.det is None or model.div is None:
        report.notes.append("det / div not declared: central differences of warp / flow stand in")
    events, raw = _events(seed=seed)
    with _backend_precisions(_precisions(precisions)) as use:
        for precision in _precisions(precisions):
            use(precision)
            _check_closed_forms(report, model, raw, theta_list, precision, twin)
            if not problem:
                continue
            prob = _problem(events, model, objective="variance", regularizers=_BOTH)
            reference_j = None
            if twin is not None:
                kwargs = _ref_kwargs(
                    model.name, lambda_div=_BOTH["divergence"], lambda_def=_BOTH["deformation"]
                )

                def reference_j(theta, kwargs=kwargs):
                    return reference.evaluate(*raw, theta, **kwargs)["J"]

            moderate = [th for th in theta_list if np.max(np.abs(th)) > 0][1:3] or theta_list[:1]
            _check_j(
                report,
                prob,
                moderate,
                reference_j,
                precision,
                f"({prob.path} path)",
                "variance + both regularizers",
            )
    return report


# ---------------------------------------------------------------------------------------------------
# objectives and regularizers
# ---------------------------------------------------------------------------------------------------
@contextlib.contextmanager
def _registered(entry, registry, register, unregister) -> Iterator[str]:
    """The entry's name, registered for the duration of the block if it was not."""
    if isinstance(entry, str):
        registry.get(entry)
        yield entry
        return
    if entry.name in registry and registry.get(entry.name) is entry:
        yield entry.name
        return
    register(entry, replace=False)
    try:
        yield entry.name
    finally:
        unregister(entry.name)


def _warp_thetas(warp: str) -> list[np.ndarray]:
    base = samples.moderate_theta(warp)
    return [base, 2.0 * base * np.linspace(0.8, 1.2, base.size)]


def check_objective(
    objective,
    *,
    reference: Callable[[np.ndarray], float] | None = None,
    warps: Sequence[str] = ("translation2", "mitrokhin4"),
    precisions: Sequence[str] | None = None,
) -> CheckReport:
    """Check an objective: value against a NumPy formula, gradient against central differences.

    Parameters
    ----------
    objective : str or Objective
        A registered name, or an objective (registered for the duration of the check if it is not).
    reference : callable, optional
        ``reference(images) -> G``: the objective in NumPy of the blurred IWE ``images`` (C, H, W);
        default the float64 reference's formula for the built-in names. Without one, only the gradient
        is checked (against central differences of J, in f64).
    warps : sequence of str
        The warp models of the problems (with their moderate parameters).
    precisions : sequence of {"f64", "f32"}, optional
        Default both (f32 only on Vulkan and Metal).
    """
    from cmax_taichi.models.objectives import OBJECTIVES, register_objective, unregister_objective
    from cmax_taichi.testing import reference as oracle

    name = objective if isinstance(objective, str) else objective.name
    report = CheckReport(f"objective {name!r}")
    if reference is None and name in oracle.OBJECTIVE_NAMES:

        def reference(images, name=name):
            return oracle.objective_value(name, images)

    if reference is None:
        report.notes.append("no NumPy reference given: the value is not checked, the gradient is")
    events, raw = _events(seed=2)
    with _registered(objective, OBJECTIVES, register_objective, unregister_objective) as name:
        entry = OBJECTIVES.get(name)
        if entry.fused is None:
            report.notes.append("no fused declaration: problems with it run on the generic autodiff chain")
        with _backend_precisions(_precisions(precisions)) as use:
            for precision in _precisions(precisions):
                use(precision)
                # the fused path where declared, and the chain (in f64 only when the fused path is
                # checked: the chain runs the same kernels in both precisions)
                paths = [False] if entry.fused is not None else []
                if entry.fused is None or precision == "f64":
                    paths.append(True)
                for warp in warps:
                    reference_j = None
                    if reference is not None:
                        kwargs = _ref_kwargs(
                            warp, lambda_div=_BOTH["divergence"], lambda_def=_BOTH["deformation"]
                        )

                        def reference_j(theta, kwargs=kwargs):
                            out = oracle.evaluate(*raw, theta, **kwargs)
                            g = reference(out["iwe"]) / reference(
                                oracle.evaluate(*raw, 0 * theta, **kwargs)["iwe"]
                            )
                            return (
                                g - kwargs["lambda_div"] * out["R_div"] - kwargs["lambda_def"] * out["R_def"]
                            )

                    for chain in paths:
                        prob = _problem(events, warp, chain=chain, objective=name, regularizers=_BOTH)
                        what = (
                            "(generic chain: autodiff of pixel and finalize)"
                            if chain
                            else "(fused path: adjoint)"
                        )
                        _check_j(report, prob, _warp_thetas(warp), reference_j, precision, what, warp)
    return report


def _penalty_values(reg, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``penalty`` and ``penalty_grad`` of ``reg`` at ``values``, by a Taichi kernel."""
    import taichi as ti

    from cmax_taichi.core import backend, workspace
    from cmax_taichi.kernels import model_checks as kmc
    from cmax_taichi.pipeline.setup import cached_kernel

    real = backend.real()
    cap = workspace.capacity_for(values.size)

    def build(ws):
        ws.values = ti.field(real, shape=cap)
        ws.out = ti.field(real, shape=(2, cap))

    ws = workspace.acquire(("penalty_check", backend.info().generation, cap), build)
    kernel = cached_kernel(
        ("penalty_check", reg.name, id(reg)), lambda: kmc.make_penalty_kernel(reg.penalty, reg.penalty_grad)
    )
    padded = np.zeros(cap, dtype=backend.numpy_real())
    padded[: values.size] = values
    ws.values.from_numpy(padded)
    kernel(values.size, ws.values, ws.out)
    result = ws.out.to_numpy()[:, : values.size].astype(np.float64)
    return result[0], result[1]


def check_regularizer(
    regularizer,
    *,
    reference_penalty: Callable[[np.ndarray], np.ndarray] | None = None,
    warps: Sequence[str] = ("zoom1", "mitrokhin4"),
    weight: float = 1.3,
    precisions: Sequence[str] | None = None,
) -> CheckReport:
    """Check a regularizer: ``penalty_grad`` against central differences of ``penalty``; J with it
    against the reference and dJ/dtheta against central differences.

    Parameters
    ----------
    regularizer : str or Regularizer
        A registered name, or a regularizer (registered for the duration of the check if it is not).
    reference_penalty : callable, optional
        ``reference_penalty(map_values) -> penalties`` in NumPy (vectorised), for a regularizer with a
        declared quantity kind: R is then computed by the float64 reference as the library defines it
        (``s_r sum m P / sum m``, one-sided if declared). The built-ins use the reference's own R.
    warps : sequence of str
        The warp models of the problems (with their moderate parameters).
    weight : float
        lambda of the regularizer in J.
    precisions : sequence of {"f64", "f32"}, optional
        Default both (f32 only on Vulkan and Metal).
    """
    from cmax_taichi.models.regularizers import REGULARIZERS, register_regularizer, unregister_regularizer
    from cmax_taichi.testing import reference as oracle

    name = regularizer if isinstance(regularizer, str) else regularizer.name
    report = CheckReport(f"regularizer {name!r}")
    events, raw = _events(seed=0)
    builtin_r = {"divergence": "R_div", "deformation": "R_def"}
    with _registered(regularizer, REGULARIZERS, register_regularizer, unregister_regularizer) as name:
        reg = REGULARIZERS.get(name)
        if reg.penalty_grad is None:
            report.notes.append("no penalty_grad: problems with it run on the generic autodiff chain")
        if reg.kind is None:
            report.notes.append("a quantity function, not a kind: it runs on the chain and has no reference")
        has_reference = name in builtin_r or (reference_penalty is not None and reg.kind is not None)
        if not has_reference:
            report.notes.append("no NumPy reference_penalty: J is not checked against the reference")
        with _backend_precisions(_precisions(precisions)) as use:
            for precision in _precisions(precisions):
                use(precision)
                _check_penalty_grad(report, reg, precision)
                for warp in warps:
                    reference_j = None
                    if has_reference:
                        kwargs = _ref_kwargs(warp)

                        def reference_j(theta, kwargs=kwargs):
                            out = oracle.evaluate(*raw, theta, **kwargs)
                            if name in builtin_r:
                                r = out[builtin_r[name]]
                            else:
                                r = _reference_r(reg, reference_penalty, out, raw)
                            return out["G"] - weight * r

                    prob = _problem(events, warp, objective="variance", regularizers={name: weight})
                    _check_j(
                        report, prob, _warp_thetas(warp), reference_j, precision, f"({prob.path} path)", warp
                    )
    return report


def _reference_r(reg, reference_penalty, out: dict, raw) -> float:
    """R of a regularizer with a declared kind, from the reference's maps: ``s sum m P / sum m``."""
    from cmax_taichi.testing import reference as oracle

    t = raw[2]
    support = out["count"] > 0
    values = out["div_map"] if reg.kind == "div" else out["def_map"]
    penalty = np.where(support, reference_penalty(np.where(support, values, reg.neutral)), 0.0)
    m = out["count"] / (out["count"] + oracle.KAPPA)
    duration = float(t.max() - t.min())
    orientation = 1.0 if float(t.min()) <= float(np.mean(t)) else -1.0
    mean = float(np.sum(m * penalty) / np.sum(m)) if np.sum(m) > 0 else 0.0
    value = reg.scale(duration, orientation) * mean
    return max(0.0, value) if reg.one_sided else value


def _check_penalty_grad(report: CheckReport, reg, precision: str) -> None:
    """``penalty_grad`` against central and one-sided differences of ``penalty`` at sample map values
    (at a kink, either side's derivative is accepted: the one Taichi's autodiff takes)."""
    if reg.penalty_grad is None:
        return
    values = _PENALTY_SAMPLES.get(reg.kind or "div")
    rel = 1e-6 if precision == "f64" else 1e-2
    h = rel * np.maximum(np.abs(values), 1e-2)
    points = np.concatenate([values, values - h, values + h])
    penalty, grad = _penalty_values(reg, points)
    n = values.size
    p0, pm, pp = penalty[:n], penalty[n : 2 * n], penalty[2 * n :]
    central, left, right = (pp - pm) / (2 * h), (p0 - pm) / h, (pp - p0) / h
    declared = grad[:n]
    tol = _TOL[precision]["diff"] * 10 * np.maximum(1.0, np.abs(declared))
    ok = np.zeros(n, dtype=bool)
    for diff in (central, left, right):
        ok |= np.abs(declared - diff) <= tol
    i = int(np.flatnonzero(~ok)[0]) if not np.all(ok) else 0
    report._require(
        "penalty_grad is d penalty / d map value",
        f"[{precision}]",
        bool(np.all(ok)),
        f"at map value {values[i]:.4g} it is {declared[i]:.6g}, but the differences of penalty are "
        f"{left[i]:.6g} (left), {central[i]:.6g} (central) and {right[i]:.6g} (right)",
    )
