"""Per-event Jacobians of any warp with respect to the event position, by Taichi reverse-mode autodiff.

``dx'/dx`` of ``warp(p, dt, th, ctx)`` and ``dv/dx`` of ``flow(p, th, ctx)`` at every event: the
determinant of the first is the deformation ``det dx'/dx``, the trace of the second the divergence.
Each output depends on its own event only, so seeding every output's adjoint with a unit vector gives a
whole row of every event's Jacobian in one reverse pass. These kernels check the closed forms of
``kernels/warps/`` and serve user-registered warps; they differentiate with respect to positions held in
their own fields (``px, py`` with ``needs_grad``), never the problem's event arrays.
"""

import taichi as ti

from . import events as _ev


def _per_event_kernel(vector_fn):
    """Kernel ``per_event(n, ev, outs)``: ``outs[k][i] = vector_fn(p_i, dt_i, th, ctx)[k]`` for the first
    ``n`` events, ``ev`` the ``events.WarpInputs`` (its own position fields here), ``outs`` a tuple of
    fields, one per component."""

    @ti.kernel
    def per_event(n: ti.i32, ev: ti.template(), outs: ti.template()):
        for i in range(n):
            v = _ev.warped_point(vector_fn, ev, i)
            for k in ti.static(range(len(outs))):
                outs[k][i] = v[k]

    return per_event


def make_position_kernels(warp_fn, flow_fn):
    """Return ``(warp_positions, flow_positions)`` kernels ``(n, ev, (out_x, out_y))`` writing the warped
    position and the flow of the first ``n`` events."""

    @ti.func
    def flow_at(p, dt, th, ctx):  # the flow does not depend on the event time
        return flow_fn(p, th, ctx)

    return _per_event_kernel(warp_fn), _per_event_kernel(flow_at)


def make_quantity_kernel(quantity_fn):
    """Forward-only kernel ``(n, ev, (out,))``: ``out[i] = quantity(p_i, dt_i, th, ctx)`` (closed-form
    det or div per event)."""

    @ti.func
    def as_vector(p, dt, th, ctx):
        return ti.Vector([quantity_fn(p, dt, th, ctx)])

    return _per_event_kernel(as_vector)
