"""Per-point values of a warp model's functions, for the model checker (``cmax_taichi/testing/checks.py``).

:func:`make_model_kernel` evaluates, at every point, the six quantities that a model declares as
functions: the warped position ``x', y'`` (``warp``), ``det`` and ``div`` (closed forms or their
stand-ins) and the flow ``v_x, v_y``, and, for a model with ``param_jac``, its closed-form derivatives
with respect to the parameters, and for a model with ``warp_terms`` what that joint function returns
(the fused kernels use it instead of ``warp``, ``det`` and ``param_jac``). Every point has its own
position, time and parameters, so that one launch evaluates the events and all the shifted copies whose
central differences (in each parameter, in x, in y and in the time) the checker holds the closed forms
against. :func:`make_penalty_kernel` evaluates a regularizer's pixel penalty and its declared
derivative at given map values.
"""

import taichi as ti

#: the rows of ``out``: position, deformation, divergence, flow
VALUE_ROWS = ("x'", "y'", "det", "div", "v_x", "v_y")


def make_model_kernel(
    warp_fn, det_fn, div_fn, flow_fn, param_jac_fn=None, n_params: int = 0, warp_terms_fn=None
):
    """``evaluate(n, points, th, ctx, out, jac, terms, terms_jac)`` over points ``i < n``, with
    ``points[i] = (x, y, dt)`` (px, px, s) and parameters ``th[i]``: ``out[r, i]`` for the rows of
    :data:`VALUE_ROWS`, and, with ``param_jac_fn``, ``jac[r, i, j]`` its derivative of row ``r``
    (``x', y', det, div``) with respect to parameter ``j`` (``jac`` is not touched without it). With
    ``warp_terms_fn``, ``terms[r, i]`` its ``x', y', det`` and ``terms_jac`` its derivatives, as ``jac``."""
    with_jac = param_jac_fn is not None
    with_terms = warp_terms_fn is not None

    @ti.kernel
    def evaluate(
        n: ti.i32,
        points: ti.template(),
        th: ti.template(),
        ctx: ti.template(),
        out: ti.template(),
        jac: ti.template(),
        terms: ti.template(),
        terms_jac: ti.template(),
    ):
        for i in range(n):
            p = ti.Vector([points[i][0], points[i][1]])
            dt = points[i][2]
            moved = warp_fn(p, dt, th[i], ctx[None])
            v = flow_fn(p, th[i], ctx[None])
            out[0, i] = moved[0]
            out[1, i] = moved[1]
            out[2, i] = det_fn(p, dt, th[i], ctx[None])
            out[3, i] = div_fn(p, th[i], ctx[None])
            out[4, i] = v[0]
            out[5, i] = v[1]
            if ti.static(with_jac):
                jx, ddet, ddiv = param_jac_fn(p, dt, th[i], ctx[None])
                for j in ti.static(range(n_params)):
                    jac[0, i, j] = jx[0, j]
                    jac[1, i, j] = jx[1, j]
                    jac[2, i, j] = ddet[j]
                    jac[3, i, j] = ddiv[j]
            if ti.static(with_terms):
                w, d, tjx, tddet, tddiv = warp_terms_fn(p, dt, th[i], ctx[None])
                terms[0, i] = w[0]
                terms[1, i] = w[1]
                terms[2, i] = d
                for j in ti.static(range(n_params)):
                    terms_jac[0, i, j] = tjx[0, j]
                    terms_jac[1, i, j] = tjx[1, j]
                    terms_jac[2, i, j] = tddet[j]
                    terms_jac[3, i, j] = tddiv[j]

    return evaluate


def make_penalty_kernel(penalty_fn, penalty_grad_fn=None):
    """``evaluate(n, values, out)``: ``out[0, i] = penalty(values[i])`` and, with ``penalty_grad_fn``,
    ``out[1, i] = penalty_grad(values[i])``."""
    with_grad = penalty_grad_fn is not None

    @ti.kernel
    def evaluate(n: ti.i32, values: ti.template(), out: ti.template()):
        for i in range(n):
            out[0, i] = penalty_fn(values[i])
            if ti.static(with_grad):
                out[1, i] = penalty_grad_fn(values[i])

    return evaluate
