"""The per-event inputs of the warp kernels, shared by the generic chain (``iwe.py``, ``whitening.py``),
the multi-cluster kernels (``clusters.py``) and the autodiff Jacobians (``jacobian_ad.py``).

Every per-event kernel reads the event positions, their times and the warp's parameters and context.
They travel as one ``ti.template()`` argument, a :class:`WarpInputs`: a named tuple, so Taichi keys a
compiled kernel by the fields it holds (a new bundle of the same fields compiles nothing) and the
kernels read them by name (``ev.ex[i]``, ``ev.th[None]``).
"""

from typing import Any, NamedTuple

import taichi as ti


class WarpInputs(NamedTuple):
    """The fields a per-event warp kernel reads (``capacity`` slots, the first ``n`` events used).

    Attributes
    ----------
    ex, ey : ti.field, shape (capacity,)
        Event position (px).
    edt : ti.field, shape (capacity,)
        Event time relative to the reference time (s).
    th : ti.Vector.field, 0-D
        Warp parameters (physical units; all clusters' parameters, one after the other, for K clusters).
    ctx : ti.Vector.field, 0-D
        The model's context (centre, focal length, time span; ``warps/common.py``).
    """

    ex: Any
    ey: Any
    edt: Any
    th: Any
    ctx: Any


@ti.func
def event_point(ev: ti.template(), i):
    """Position ``p`` (px, a 2-vector) and time ``dt`` (s) of event ``i``."""
    return ti.Vector([ev.ex[i], ev.ey[i]]), ev.edt[i]


@ti.func
def warped_point(warp_fn: ti.template(), ev: ti.template(), i):
    """Event ``i``'s position warped by ``warp_fn`` with the parameters and context of ``ev`` (px)."""
    p, dt = event_point(ev, i)
    return warp_fn(p, dt, ev.th[None], ev.ctx[None])


def make_cluster_theta(offsets: tuple, n_params: tuple):
    """``theta(thv, j)``: cluster ``j``'s parameter vector, ``thv[offsets[j] : offsets[j] + n_params[j]]``
    of the vector ``thv`` of all parameters (``j`` static)."""

    @ti.func
    def theta(thv, j: ti.template()):
        return ti.Vector([thv[offsets[j] + a] for a in ti.static(range(n_params[j]))])

    return theta


def make_cluster_warp(warp_fns: tuple, offsets: tuple, n_params: tuple):
    """``warp_of(ev, i, j)``: event ``i``'s position warped by cluster ``j``'s model and parameters (px;
    ``j`` static), the clusters' parameters laid out as in :func:`make_cluster_theta`."""
    theta = make_cluster_theta(offsets, n_params)

    @ti.func
    def warp_of(ev: ti.template(), i, j: ti.template()):
        p, dt = event_point(ev, i)
        return warp_fns[j](p, dt, theta(ev.th[None], j), ev.ctx[None])

    return warp_of
