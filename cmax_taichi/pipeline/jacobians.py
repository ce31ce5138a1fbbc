"""Per-event Jacobian determinant and divergence, by closed form or by Taichi autodiff.

``event_jacobians(problem_or_model, ...)`` returns ``det dx'/dx`` and ``div v`` at every event, either
from the model's closed forms (``method="closed"``) or from reverse-mode autodiff of the model's warp
and flow functions with respect to the event position (``method="autodiff"``, kernels of
``kernels/jacobian_ad.py``). The autodiff path works for any registered model and checks the closed
forms.
"""

from __future__ import annotations

import numpy as np
import taichi as ti

from cmax_taichi.core import backend, workspace
from cmax_taichi.kernels import events as kevents
from cmax_taichi.kernels import jacobian_ad as kad
from cmax_taichi.pipeline.parameters import check_theta as _check_theta
from cmax_taichi.pipeline.parameters import require_finite as _require_finite
from cmax_taichi.pipeline.problem import ContrastMaximization
from cmax_taichi.pipeline.setup import cached_kernel as _cached

__all__ = ["event_jacobians"]

METHODS = ("closed", "autodiff")


def event_jacobians(problem: ContrastMaximization, theta, method: str = "closed") -> dict:
    """Per-event deformation and divergence of ``problem``'s warp at ``theta``.

    Parameters
    ----------
    problem : ContrastMaximization
        Supplies the events (positions, ``dt``), the model and its context (centre, focal, T).
    theta : array_like
        Parameters, physical units.
    method : {"closed", "autodiff"}
        Closed forms of the model, or autodiff of its warp (for det) and flow (for div).

    Returns
    -------
    dict
        ``"det"``: ``det dx'/dx`` per event (signed, unitless); ``"div"``: ``div v`` per event (1/s);
        with ``"autodiff"`` also ``"jacobian"``: (N, 2, 2) ``dx'/dx``.

    Raises
    ------
    NonFiniteResultError
        (a ValueError) when the parameters overflow the float type (e.g. ``zoom1`` at 1e308).
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; valid: {', '.join(METHODS)}")
    if not isinstance(problem, ContrastMaximization):
        raise TypeError("problem must be a ContrastMaximization")
    problem._check_alive()
    model = problem.model
    theta = _check_theta(theta, model.n_params, model.name)
    real = backend.real()
    n = problem.n_events
    problem._load()
    problem._th[None] = theta.tolist()
    events = kevents.WarpInputs(problem._ex, problem._ey, problem._edt, problem._th, problem._ctx)
    cap = workspace.capacity_for(n)

    def build(ws):  # pooled by capacity: fields are never freed, so none is made per call
        ws.out = ti.field(real, shape=cap)
        ws.pos = [ti.field(real, shape=cap, needs_grad=True) for _ in range(4)]

    fields = workspace.acquire(("event_jacobians", backend.info().generation, cap), build)
    if method == "closed":
        out = fields.out
        result = {}
        for name, fn in (("det", model.det_fn), ("div", model.quantity("div"))):
            k = _cached(
                ("quantity", name, model.name, id(model)),
                lambda fn=fn: kad.make_quantity_kernel(fn),
            )
            k(n, events, (out,))
            result[name] = out.to_numpy()[:n].astype(np.float64)
        _require_finite(model, theta, "a per-event det or div", *result.values())
        return result

    warp_k, flow_k = _cached(
        ("positions", model.name, id(model)),
        lambda: kad.make_position_kernels(model.warp, model.flow),
    )
    px, py, ox, oy = fields.pos
    for f, values in ((px, problem.events.x), (py, problem.events.y)):
        padded = np.zeros(cap, dtype=backend.numpy_real())
        padded[:n] = values
        f.from_numpy(padded)
    rows = {}
    for label, kernel in (("warp", warp_k), ("flow", flow_k)):
        kargs = (n, events._replace(ex=px, ey=py), (ox, oy))
        kernel(*kargs)
        jac = np.empty((n, 2, 2))
        for row, (sx, sy) in enumerate(((1.0, 0.0), (0.0, 1.0))):
            for f in (px, py, ox, oy):
                f.grad.fill(0)
            ox.grad.fill(sx)
            oy.grad.fill(sy)
            kernel.grad(*kargs)
            jac[:, row, 0] = px.grad.to_numpy()[:n]
            jac[:, row, 1] = py.grad.to_numpy()[:n]
        rows[label] = jac
    jw = rows["warp"]
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is reported below, naming theta
        det = jw[:, 0, 0] * jw[:, 1, 1] - jw[:, 0, 1] * jw[:, 1, 0]
        div = rows["flow"][:, 0, 0] + rows["flow"][:, 1, 1]
    _require_finite(model, theta, "a per-event det or div", det, div, jw)
    return {"det": det, "div": div, "jacobian": jw}
