"""Per-event Jacobians of any warp with respect to the event position, by Taichi reverse-mode autodiff.

``dx'/dx`` of ``warp(p, dt, th, ctx)`` and ``dv/dx`` of ``flow(p, th, ctx)`` at every event: the
determinant of the first is the deformation ``det dx'/dx``, the trace of the second the divergence.
Each output depends on its own event only, so seeding every output's adjoint with a unit vector gives a
whole row of every event's Jacobian in one reverse pass. These kernels check the closed forms of
``kernels/warps/`` and serve user-registered warps; they differentiate with respect to positions held in
their own fields (``px, py`` with ``needs_grad``), never the problem's event arrays.
"""

import taichi as ti


def _per_event_vector_kernel(vector_fn):
    """A kernel writing ``out_x[i], out_y[i] = vector_fn(p_i, dt_i, th, ctx)`` for the first ``n`` events."""

    @ti.kernel
    def per_event(
        n: ti.i32,
        px: ti.template(),
        py: ti.template(),
        pdt: ti.template(),
        th: ti.template(),
        ctx: ti.template(),
        out_x: ti.template(),
        out_y: ti.template(),
    ):
        for i in range(n):
            v = vector_fn(ti.Vector([px[i], py[i]]), pdt[i], th[None], ctx[None])
            out_x[i] = v[0]
            out_y[i] = v[1]

    return per_event


def make_position_kernels(warp_fn, flow_fn):
    """Return ``(warp_positions, flow_positions)`` kernels writing ``out_x, out_y`` for the first ``n``
    events."""

    @ti.func
    def flow_at(p, dt, th, ctx):  # the flow does not depend on the event time
        return flow_fn(p, th, ctx)

    return _per_event_vector_kernel(warp_fn), _per_event_vector_kernel(flow_at)


def make_quantity_kernel(quantity_fn):
    """Forward-only: ``out[i] = quantity(p_i, dt_i, th, ctx)`` (closed-form det or div per event)."""

    @ti.kernel
    def per_event(
        n: ti.i32,
        px: ti.template(),
        py: ti.template(),
        pdt: ti.template(),
        th: ti.template(),
        ctx: ti.template(),
        out: ti.template(),
    ):
        for i in range(n):
            out[i] = quantity_fn(ti.Vector([px[i], py[i]]), pdt[i], th[None], ctx[None])

    return per_event
