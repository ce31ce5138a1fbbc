"""The event passes of the fused CMax kernel (``fused.py``): what one event contributes to the votes
(stage 2, the splat) and to dJ/dtheta (stage 8, the gather), from the warp model's closed-form terms.

``warp_terms(p, dt, theta, ctx) -> (warp, det, jx, ddet, ddiv)`` is the model's joint evaluation (or
one composed from its ``warp``, ``det`` and ``param_jac``, :func:`composed_warp_terms`); each pass uses
only what it needs of it (the rest is dead code to the compiler). Where the model stores its terms
(``store_terms``), :func:`EventPasses.put_terms` writes each event's position, voted quantities and
Jacobians into a ``(rows, n)`` array once per call, and the splat and the gather read them.
"""

import taichi as ti

from . import blocks as _b
from . import fused_common as _c
from . import tiles as _t


def composed_warp_terms(warp_fn, det_fn, param_jac):
    """``warp_terms`` of a model that declares none: its ``warp``, ``det`` and ``param_jac`` side by side."""

    has_det = det_fn is not None

    @ti.func
    def warp_terms(p, dt, th, ctx):
        jx, ddet, ddiv = param_jac(p, dt, th, ctx)
        d = 1.0 + 0.0 * dt
        if ti.static(has_det):
            d = det_fn(p, dt, th, ctx)
        return warp_fn(p, dt, th, ctx), d, jx, ddet, ddiv

    return warp_terms


def terms_width(n_params: int, n_voted: int) -> int:
    """Rows of the stored event terms per event: the warped position (2), the voted quantities
    (``n_voted``), the parameter Jacobian of the position (``2 n_params``, row-major) and of each voted
    quantity (``n_voted n_params``)."""
    return 2 + n_voted + 2 * n_params + n_voted * n_params


class EventPasses:
    """The per-event ``ti.func``s of one fused kernel.

    Parameters
    ----------
    args : fused_common.KernelArgs
        The kernel's bound arguments (``width``, ``height`` and the mask arrays ``words`` that
        ``tiles.mark`` writes).
    warp_terms, quantity_fns, quantity_kinds, voted, positive_det
        The model's joint terms, the regularizers' per-event quantities and kinds, the voted ones
        (regularizer indices), whether the model's det is positive.
    real : Taichi float type
    n_params : int
    channels : tuple of int
        ``(i_count, i_numer, shared_count)`` of the vote channels (``fused.channel_layout``).
    events : fused_common.EventLayout
    acc, adj : fused_common.Planes
        The votes (slices of ``per_slice`` planes) and their adjoints.
    per_slice : int
        Vote planes per slice.
    """

    def __init__(
        self,
        args: _c.KernelArgs,
        warp_terms,
        quantity_fns: tuple,
        quantity_kinds: tuple,
        voted: tuple,
        positive_det: bool,
        *,
        real,
        n_params: int,
        channels: tuple,
        events: _c.EventLayout,
        acc: _c.Planes,
        adj: _c.Planes,
        per_slice: int,
    ) -> None:
        P, RV, R = n_params, len(voted), len(quantity_fns)
        i_cnt, i_num, shared_count = channels
        T_Q, T_V, T_J = 0, 2, 2 + RV  # rows of the stored terms: position, quantities, Jacobians
        T_DQ = T_J + 2 * P
        event = events.reader()  # (p, dt, b, ch) of an event vector
        vote = events.vote(acc)  # votes[i] += v
        K = int(per_slice)

        @ti.func
        def quantities(p, dt, theta, c, det):
            """The voted quantities of one event (``det``: its determinant, from ``warp_terms``)."""
            vals = ti.Vector([0.0 for _ in ti.static(range(max(RV, 1)))])
            for v in ti.static(range(RV)):
                if ti.static(quantity_kinds[voted[v]] == "absdet"):
                    vals[v] = ti.abs(det)
                else:
                    vals[v] = quantity_fns[voted[v]](p, dt, theta, c)
            return vals

        @ti.func
        def quantity_slopes(terms):
            """d q_v / d theta of the voted quantities, a ``RV x P`` matrix, from ``warp_terms``' output
            (the "absdet" rows signed where the model's det may be negative: d|det| = -d det where
            det < 0)."""
            dq = ti.Matrix.zero(real, max(RV, 1), P)
            ddet = terms[3]
            if ti.static(not positive_det and "absdet" in quantity_kinds):  # noqa: SIM102 - compile-time if
                if terms[1] < 0.0:
                    ddet = -ddet
            for v in ti.static(range(RV)):
                for j in ti.static(range(P)):
                    if ti.static(quantity_kinds[voted[v]] == "div"):
                        dq[v, j] = terms[4][j]
                    else:
                        dq[v, j] = ddet[j]
            return dq

        @ti.func
        def splat_at(s, q, vals, b, ch):
            """The bilinear votes of an event warped to ``q`` with voted quantities ``vals``."""
            W, H = args.width, args.height
            if _b.in_window(q, W, H):
                ix, iy, ax, ay = _b.bilinear_footprint(q)
                _t.mark(args, ix, iy)
                ab = ti.abs(b)
                HW = _c.plane_size(acc)
                o = _c.at(acc, s * K, iy, ix)  # corner (0, 0) of the slice's first plane
                for dy in ti.static(range(2)):
                    for dx in ti.static(range(2)):
                        wx, wy = _b.corner_weights(ax, ay, dx, dy)
                        if _b.corner_in_image(ix, iy, dx, dy, W, H):
                            w = wx * wy
                            i = o + dy * W + dx
                            vote(i + ch * HW, b * w)
                            if ti.static(R > 0):
                                if ti.static(not shared_count):
                                    vote(i + i_cnt * HW, ab * w)
                                for v in ti.static(range(RV)):
                                    vote(i + (i_num + v) * HW, ab * w * vals[v])

        @ti.func
        def splat_event(s, e, theta, c):
            p, dt, b, ch = event(e)
            # everything that depends on theta only (trigonometry) must be computed unconditionally at
            # the top of the event loop, or LLVM cannot hoist it out of the loop
            terms = warp_terms(p, dt, theta, c)  # its Jacobians are dead code here
            splat_at(s, terms[0], quantities(p, dt, theta, c, terms[1]), b, ch)

        @ti.func
        def put_terms(tm: ti.template(), i, e, theta, c, with_jacobians: ti.template()):
            """Stage 2 with stored terms: event ``i``'s position, quantities (and Jacobians) into ``tm``."""
            p, dt, b, ch = event(e)
            terms = warp_terms(p, dt, theta, c)  # unconditionally: see splat_event
            q = terms[0]
            vals = quantities(p, dt, theta, c, terms[1])
            tm[T_Q, i] = q[0]
            tm[T_Q + 1, i] = q[1]
            for v in ti.static(range(RV)):
                tm[T_V + v, i] = vals[v]
            if ti.static(with_jacobians):
                jx = terms[2]
                dq = quantity_slopes(terms)
                for k in ti.static(range(2)):
                    for j in ti.static(range(P)):
                        tm[T_J + P * k + j, i] = jx[k, j]
                for v in ti.static(range(RV)):
                    for j in ti.static(range(P)):
                        tm[T_DQ + P * v + j, i] = dq[v, j]

        @ti.func
        def stored_position(tm: ti.template(), i):
            """Event ``i``'s stored position and voted quantities."""
            vals = ti.Vector([0.0 for _ in ti.static(range(max(RV, 1)))])
            for v in ti.static(range(RV)):
                vals[v] = tm[T_V + v, i]
            return ti.Vector([tm[T_Q, i], tm[T_Q + 1, i]]), vals

        @ti.func
        def splat_stored(s, tm: ti.template(), i, e):
            """Stage 2 from event ``i``'s stored terms."""
            _, _, b, ch = event(e)
            q, vals = stored_position(tm, i)
            splat_at(s, q, vals, b, ch)

        @ti.func
        def stored_jacobians(tm: ti.template(), i):
            """Event ``i``'s stored Jacobians of the position (2 x P) and of the voted quantities (RV x P)."""
            jx = ti.Matrix.zero(real, 2, P)
            dq = ti.Matrix.zero(real, max(RV, 1), P)
            for j in ti.static(range(P)):
                for k in ti.static(range(2)):
                    jx[k, j] = tm[T_J + P * k + j, i]
                for v in ti.static(range(RV)):
                    dq[v, j] = tm[T_DQ + P * v + j, i]
            return jx, dq

        @ti.func
        def corner_terms(i, HW, ch, b, vals):
            """The adjoint gathered at one pixel (index ``i`` in the first plane of ``adj``, ``HW`` pixels
            a plane): (b adj_ch + |b| adj_C + |b| sum_r q_r adj_r, adj_r)."""
            ab = ti.abs(b)
            a = b * adj.array[i + ch * HW]
            nr = ti.Vector([0.0 for _ in ti.static(range(max(RV, 1)))])
            if ti.static(R > 0):
                if ti.static(not shared_count):
                    a += ab * adj.array[i + i_cnt * HW]
                for v in ti.static(range(RV)):
                    nr[v] = ab * adj.array[i + (i_num + v) * HW]
                    a += vals[v] * nr[v]
            return a, nr

        @ti.func
        def grad_at(q, vals, jx, dq, b, ch):
            """dJ/dtheta of an event warped to ``q`` (quantities ``vals``; Jacobians ``jx`` of the
            position, ``dq`` of the quantities), hand-written, float64.

            Without branches, so that LLVM vectorizes the gather loops (a branch per corner kept them
            scalar): every corner is read at an index clamped into the image and a corner outside it, or
            an event outside the window, is dropped by a select (a select, not a product with 0: an
            adjoint that overflowed to inf stays out as before); the conditions are bitwise
            (``blocks.in_window``). ``q`` outside the window (NaN included) is read at the origin first,
            so that no index is computed from it."""
            W, H = args.width, args.height
            inside = _b.in_window(q, W, H)  # (bitwise: no branch)
            qs = ti.Vector([ti.select(inside, q[0], 0.0), ti.select(inside, q[1], 0.0)])
            ix, iy, ax, ay = _b.bilinear_footprint(qs)
            HW = _c.plane_size(adj)
            base = _c.at(adj, 0, 0, 0)
            ga = 0.0  # dS/dax
            gb = 0.0  # dS/day
            gv = ti.Vector([0.0 for _ in ti.static(range(max(RV, 1)))])  # dS/dq_v
            for dy in ti.static(range(2)):
                for dx in ti.static(range(2)):
                    keep = _b.corner_in_image(ix, iy, dx, dy, W, H)
                    cx = ti.min(ti.max(ix + dx, 0), W - 1)
                    cy = ti.min(ti.max(iy + dy, 0), H - 1)
                    a, nr = corner_terms(base + cy * W + cx, HW, ch, b, vals)
                    a = ti.select(keep, a, 0.0)
                    wx, wy = _b.corner_weights(ax, ay, dx, dy)
                    ga += ti.static(1.0 if dx == 1 else -1.0) * wy * a
                    gb += ti.static(1.0 if dy == 1 else -1.0) * wx * a
                    if ti.static(RV > 0):
                        for v in ti.static(range(RV)):
                            gv[v] += ti.select(keep, wx * wy * nr[v], 0.0)
            g = ti.Vector([0.0 for _ in ti.static(range(P))], dt=ti.f64)
            for j in ti.static(range(P)):
                gj = ga * jx[0, j] + gb * jx[1, j]
                for v in ti.static(range(RV)):
                    gj += gv[v] * dq[v, j]
                g[j] = ti.select(inside, ti.cast(gj, ti.f64), 0.0)
            return g

        @ti.func
        def event_grad(e, theta, c):
            """dJ/dtheta contribution of one event, its terms evaluated here."""
            p, dt, b, ch = event(e)
            terms = warp_terms(p, dt, theta, c)  # unconditionally: see splat_event
            vals = quantities(p, dt, theta, c, terms[1])
            return grad_at(terms[0], vals, terms[2], quantity_slopes(terms), b, ch)

        @ti.func
        def stored_event_grad(tm: ti.template(), i, e):
            """dJ/dtheta contribution of event ``i`` from its stored terms."""
            p, dt, b, ch = event(e)
            q, vals = stored_position(tm, i)
            jx, dq = stored_jacobians(tm, i)
            return grad_at(q, vals, jx, dq, b, ch)

        self.splat_event, self.put_terms, self.splat_stored = splat_event, put_terms, splat_stored
        self.event_grad, self.stored_event_grad = event_grad, stored_event_grad
