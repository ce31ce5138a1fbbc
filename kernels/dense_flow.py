"""Dense optical flow on a grid of nodes: value and gradient of J in one kernel launch, hand-written
backward that scatters each event's adjoint into its four nodes.

The model (docs/flow.md, docs/FORMULAS.md "Dense flow model"): the flow ``u`` (px/s) lives on the nodes
of a regular grid of ``nx x ny`` cells spanning the sensor (node ``(i, j)`` at ``(i sx, j sy)``,
``sx = (W - 1) / nx``, ``sy = (H - 1) / ny``) and is interpolated bilinearly to the event's own
(unwarped) position ``p``: with the event's cell ``(i, j)`` and local coordinates ``(a, b)`` in [0, 1],
``u(p) = (1-a)(1-b) U00 + a(1-b) U10 + (1-a) b U01 + a b U11``. Both are fixed by ``p``, so the warp

    x'_r = p - (t - t_r) u(p)

is linear in the node values. Its Jacobian ``dx'/dp = I - dt_r Du`` comes in closed form from the
interpolant (``du/dx = ((1-b)(U10 - U00) + b (U11 - U01)) / sx``, likewise ``du/dy``), hence the
per-event quantities of the event-collapse regularizers: ``div u = du_x/dx + du_y/dy`` (1/s) and
``|det(I - dt_r Du)|``.

Several reference times ``t_r = t_first + o_r`` (the multi-reference objective) each get their own
IWE and regularizer maps; ``refs`` holds the offsets ``o_r`` (s) and the normalised weights
``omega_r`` (sum 1). The data term is the weighted harmonic mean of the normalised objectives,

    H = 1 / sum_r omega_r G0 / G_r        (one reference: H = G / G0),

the maximisation form of the multi-focal loss of tub-rip/event_based_optical_flow
(``src/costs/multi_focal_normalized_gradient_magnitude.py``: ``sum_r w_r G0 / G_r``, minimised). Each
regularizer ``q`` enters as ``-lambda_q sum_r omega_r R_qr``, ``R_qr`` the paper's penalty of its map at
reference r (support-weighted mean, scale and one-sided hinge as declared by the registry entry).

One kernel ``run(n, ev, n_nodes, grad, maps, out, gout, params, width, height, ...)`` holds every stage
as its own task; like ``fused.py`` it reads no field (its image, row and node arrays are arguments,
``DenseFlowShape``), so one compiled kernel serves every sensor and grid:

1. splat: per event, u and Du from its four nodes, then for every reference its warped position votes
   bilinearly into the IWE channels, the count ``C`` and the map numerators of the votes (CPU:
   one slice per thread, plain stores; GPU: atomics into slice 0);
2. rows: sum the slices, blur along x, per-row sums of the maps (``sum m``, ``sum m P``);
3. rows: blur along y (and the Sobel images where the objective reads them), per-row sums of the
   objective's pixel terms;
4. the per-row sums are added in row order (the same J from run to run, whatever the threads did),
   then J, dJ/dG_r and the regularizers' slopes;
5. rows (grad): the pixel adjoints, transposed blurs and map adjoints into ``adj``;
6. events (grad): each event gathers dJ/dx'_r from ``adj`` at its footprints (and the map terms
   through div and det), forms dJ/du and dJ/dDu, and scatters them into its four nodes: per-thread
   node-gradient slices on the CPU, atomics on a GPU (no dense Jacobian);
7. nodes (grad): the slices summed in slice order into ``gout`` (float64).

The row passes loop over whole rows here; each stage reads and writes only the rows and channels it
owns, so that they can move to the touched-pixel tiles of ``kernels/fused.py`` without changing the
event passes. Formulas shared with the other pipelines come from ``blocks.py``; nothing here branches on
an objective's or a regularizer's name.
"""

from dataclasses import astuple, dataclass

import taichi as ti

from . import blocks as _b
from . import fused_common as _c

QUANTITY_KINDS = ("div", "absdet")
#: node-gradient copies per CPU thread: consecutive events add into different copies, so that events of
#: one cell (all of them on a coarse grid) do not wait on each other's read-modify-write of the same nodes
NODE_COPIES = 4


def channel_layout(n_channels: int, n_regs: int, shared_count: bool) -> tuple[int, int, int]:
    """``(i_count, i_numer, channels)`` of one reference's block of ``acc`` / ``adj``: where the count and
    the first map numerator live, and how many channels the block has (IWE channels first)."""
    if n_regs == 0:
        return -1, -1, n_channels
    i_count = 0 if shared_count else n_channels
    return i_count, i_count + 1, i_count + 1 + n_regs


def n_reduction_slots(n_refs: int, n_channels: int, objective_slots: int, n_regs: int) -> int:
    """Per-row reduction slots: the objective's slots of every (reference, channel), then per reference
    ``sum m`` and ``sum m P_q`` of each regularizer."""
    return n_refs * n_channels * objective_slots + (n_refs * (1 + n_regs) if n_regs else 0)


@dataclass(frozen=True)
class DenseFlowShape:
    """The compile-time shape of one dense-flow pipeline, and the arrays a sensor and a grid need.

    Parameters
    ----------
    layout : fused_common.ImageLayout
        IWE channels per reference, blur radius, event-pass slices, objective slots, Sobel images.
    n_refs, n_regs : int
        Reference times, and regularizers (each votes a map at every reference).
    atomic : bool
        The event passes add atomically into one copy of the node gradients (GPU); else each CPU thread
        has :data:`NODE_COPIES` copies of its own.
    """

    layout: _c.ImageLayout
    n_refs: int
    n_regs: int
    atomic: bool = False

    @property
    def block(self) -> int:
        """Vote planes per reference (IWE channels, count, numerators)."""
        return channel_layout(self.layout.n_channels, self.n_regs, self.layout.shared_count)[2]

    @property
    def image_planes(self) -> tuple[int, ...]:
        """Plane counts of ``images``: ``tmp``, ``img``, ``adj`` and, with Sobel, the Sobel images and
        ``ibar``."""
        IC = self.n_refs * self.layout.n_channels
        return (IC, IC, self.n_refs * self.block) + ((2 * IC, IC) if self.layout.sobel else ())

    @property
    def n_slots(self) -> int:
        layout = self.layout
        return n_reduction_slots(self.n_refs, layout.n_channels, layout.objective_slots, self.n_regs)

    @property
    def node_copies(self) -> int:
        """Copies of the node gradients (per thread, or one with atomics)."""
        return 1 if self.atomic else self.layout.n_slices * NODE_COPIES

    def state_size(self) -> int:
        """Length of ``state``: the reduced sums, ``G_r``, ``dJ/dG_r``, the regularizers' slopes."""
        return self.n_slots + 2 * self.n_refs + max(self.n_regs * self.n_refs, 1)

    def params_layout(self) -> dict:
        """Where each value sits in the float64 ``params``: ``grid`` (``nx, ny, 1/sx, 1/sy``, origin x, y),
        ``ref_off`` and ``ref_w`` (per reference), ``lam`` (``lambda_q`` then ``s_qr``), ``g0``, ``taps``."""
        R, Q = self.n_refs, self.n_regs
        lam = 6 + 2 * R
        g0 = lam + max(Q * (1 + R), 1)
        taps = g0 + 1
        return {"grid": 0, "ref_off": 6, "ref_w": 6 + R, "lam": lam, "g0": g0, "taps": taps,
                "size": taps + 2 * self.layout.radius + 1}  # fmt: skip

    def array_sizes(self, width: int, height: int) -> dict:
        """``{name: (kind, length)}`` of the image-side arrays for a ``width x height`` image (``kind``
        ``"real"``); all start zeroed."""
        plane = int(width) * int(height)
        return {
            "votes": ("real", self.layout.n_slices * self.n_refs * self.block * plane),
            "images": ("real", sum(self.image_planes) * plane),
            "rows": ("real", int(height) * self.n_slots),
            "state": ("real", self.state_size()),
        }

    def node_sizes(self, capacity: int) -> dict:
        """``{name: (kind, length)}`` of the node arrays for ``capacity`` nodes: the flow (``"real"``,
        x and y per node) and the per-copy gradients (``"f64"``)."""
        return {"nodes": ("real", 2 * capacity), "gnode": ("f64", 2 * capacity * self.node_copies)}


@ti.func
def _read_slice0(src: ti.template(), c, y, x):
    """Pixel of slice 0 of the ``(S, H, W, K)`` vote field."""
    return src[0, y, x, c]


@ti.func
def grid_cell(p, gp):
    """``(n00, stride, a, b)``: the index of the cell's top-left node, the node row length and the local
    coordinates of position ``p`` (px of the image) on the grid ``gp = (nx, ny, 1/sx, 1/sy, ox, oy)`` whose
    node (0, 0) sits at ``(ox, oy)``. Positions outside the grid (undistorted events just off the sensor)
    use the nearest border cell (linear extrapolation)."""
    nx = ti.cast(gp[0], ti.i32)
    ny = ti.cast(gp[1], ti.i32)
    fx = (p[0] - gp[4]) * gp[2]
    fy = (p[1] - gp[5]) * gp[3]
    i = ti.min(ti.max(ti.cast(ti.floor(fx), ti.i32), 0), nx - 1)
    j = ti.min(ti.max(ti.cast(ti.floor(fy), ti.i32), 0), ny - 1)
    stride = nx + 1
    return j * stride + i, stride, fx - i, fy - j


@ti.func
def node_flow(nodes: ti.template(), k):
    """The flow (px/s) of node ``k`` in the flat ``(x, y)`` pairs of ``nodes``."""
    return ti.Vector([nodes[2 * k], nodes[2 * k + 1]])


@ti.func
def interpolate(nodes: ti.template(), n00, stride, a, b, gp):
    """``(u, du/dx, du/dy)`` at local coordinates ``(a, b)`` of the cell at node ``n00``: the bilinear
    interpolant of the node flow (px/s, flat ``(x, y)`` pairs) and its derivatives (1/s), each a 2-vector
    (x, y components)."""
    u00 = node_flow(nodes, n00)
    u10 = node_flow(nodes, n00 + 1)
    u01 = node_flow(nodes, n00 + stride)
    u11 = node_flow(nodes, n00 + stride + 1)
    u = (1.0 - a) * (1.0 - b) * u00 + a * (1.0 - b) * u10 + (1.0 - a) * b * u01 + a * b * u11
    du_dx = ((1.0 - b) * (u10 - u00) + b * (u11 - u01)) * gp[2]
    du_dy = ((1.0 - a) * (u01 - u00) + a * (u11 - u10)) * gp[3]
    return u, du_dx, du_dy


@ti.func
def warp_det(du_dx, du_dy, dt):
    """``det(I - dt Du)`` with ``Du = [[du_x/dx, du_x/dy], [du_y/dx, du_y/dy]]``."""
    return (1.0 - dt * du_dx[0]) * (1.0 - dt * du_dy[1]) - dt * dt * du_dy[0] * du_dx[1]


def make_dense_flow_kernels(
    shape: DenseFlowShape,
    quantity_kinds: tuple,
    penalty_fns: tuple,
    penalty_grads: tuple,
    one_sided: tuple,
    *,
    objective,
    events: _c.EventLayout,
):
    """The dense-flow kernel ``run`` of ``shape`` (see the module docstring).

    ``run(n, ev, n_nodes, grad, maps, out, gout, params, width, height, votes, images, rows, state, nodes,
    gnode)``: ``ev`` is an ndarray of per-event vectors ``(x, y, t - t_first[, w][, channel])`` (px, px,
    s) as ``events`` lays them out; ``params`` (float64) holds the grid, the reference times and weights,
    the regularizers' weights and scales, G0 and the taps (:meth:`DenseFlowShape.params_layout`);
    ``width, height`` are the image's (px) and ``votes`` ... ``gnode`` the arrays of
    :meth:`DenseFlowShape.array_sizes` and :meth:`DenseFlowShape.node_sizes` (the node flow, px/s, in
    ``nodes``); ``out`` (float64) receives ``J, H, G_0..G_{R-1}, R_q (Q values), R_qr (Q x R values)``,
    ``gout`` (float64) ``dJ/dU`` as ``(n_nodes, 2)`` row-major (per node px/s, x then y). The objective
    comes as its blocks (``pixel``, ``finalize``, ``adjoint``; see ``kernels/fused.py``), each regularizer
    as its quantity kind ("div" or "absdet"), pixel penalty, its derivative and its hinge.
    """
    R, atomic_scatter = shape.n_refs, shape.atomic
    real, C, r_, S, shared_count, SL, sobel = astuple(shape.layout)
    weighted, split_polarity, atomic_events = astuple(events)
    if atomic_events != atomic_scatter:
        raise ValueError("the events' accumulation (EventLayout.atomic) is not the shape's")
    pixel_fn, finalize_fn, adjoint_fn = _c.objective_blocks(objective, sobel)
    Q = len(quantity_kinds)
    if shape.n_regs != Q:
        raise ValueError(f"{Q} regularizers for a shape of {shape.n_regs}")
    if any(k not in QUANTITY_KINDS for k in quantity_kinds):
        raise ValueError(f"quantity_kinds must name each quantity one of {QUANTITY_KINDS}")
    if not (len(penalty_fns) == len(penalty_grads) == len(one_sided) == Q):
        raise ValueError("one penalty, penalty derivative and hinge flag per regularizer")
    if shared_count and (weighted or split_polarity or Q == 0):
        raise ValueError("the count shares the IWE channel only with unit weights and one channel")
    IC = R * C
    i_cnt, i_num, KR = channel_layout(C, Q, shared_count)
    n_slots = shape.n_slots
    MB = R * C * SL  # first map slot
    ST_GRAW, ST_COEF, ST_RW = n_slots, n_slots + R, n_slots + 2 * R  # state: sums, G_r, dJ/dG_r, slopes
    COPIES = shape.node_copies
    at = shape.params_layout()
    P_GRID, P_OFF, P_W, P_LAM = at["grid"], at["ref_off"], at["ref_w"], at["lam"]
    P_G0, P_TAPS = at["g0"], at["taps"]
    # rows of a task on the CPU (the per-row sums make J independent of it)
    row_block = None if atomic_scatter else 32
    real_type, ev_type, f64 = _c.real_array(real), events.ndarray_type(real), _c.F64_ARRAY
    slice_events = events.slices(S)  # the events [lo, hi) of thread slice s
    row = events.row()  # event i of ev as a vector
    event = events.reader()  # (p, dt, b, ch) of an event vector

    args = _c.KernelArgs()  # the kernel's arrays and sizes (bound at the top of its body)
    base = 0
    views = []
    for count in shape.image_planes:
        views.append(_c.Planes(args, "images", base, count))
        base += count
    tmp, img, adj = views[:3]
    sob, ibar = views[3:] if sobel else (None, None)
    acc = _c.Planes(args, "votes", 0, S * R * KR)
    vote = events.vote(acc)  # votes[i] += v
    tap_x = _b.make_tap_sum(_c.read_plane, r_, 1, args)
    tap_y = _b.make_tap_sum(_c.read_plane, r_, 0, args)
    sobel_fn = _b.make_sobel(_c.read_plane, args)
    sobel_t = _b.make_sobel_transpose(_c.read_gx, _c.read_gy, args)

    @ti.func
    def param(k):
        return ti.cast(args.params[k], real)

    @ti.func
    def grid_vec():
        return ti.Vector([param(P_GRID + j) for j in ti.static(range(6))])

    @ti.func
    def load_taps():
        tv = ti.Vector([1.0 for _ in ti.static(range(2 * r_ + 1))])
        if ti.static(r_ > 0):
            for k in ti.static(range(2 * r_ + 1)):
                tv[k] = param(P_TAPS + k)
        return tv

    @ti.func
    def quantities(div, du_dx, du_dy, dt):
        """The map quantities of one event at one reference, and ``det(I - dt Du)``."""
        det = warp_det(du_dx, du_dy, dt)
        vals = ti.Vector([0.0 for _ in ti.static(range(max(Q, 1)))])
        for q in ti.static(range(Q)):
            if ti.static(quantity_kinds[q] == "div"):
                vals[q] = div
            else:
                vals[q] = ti.abs(det)
        return vals, det

    @ti.func
    def ref_slots(r):
        return ti.Vector([args.state[r * C * SL + k] for k in ti.static(range(C * SL))])

    @ti.func
    def splat_event(s, e, gp, maps):
        W, H = args.width, args.height
        p, dt, b, ch = event(e)
        n00, stride, a, bb = grid_cell(p, gp)
        u, du_dx, du_dy = interpolate(args.nodes, n00, stride, a, bb, gp)
        div = du_dx[0] + du_dy[1]
        ab = ti.abs(b)
        for r in range(R):  # a runtime loop: unrolled, every reference multiplied the code to compile
            dtr = dt - param(P_OFF + r)
            q = p - dtr * u
            if _b.in_window(q, W, H):
                vals, _ = quantities(div, du_dx, du_dy, dtr)
                ix, iy, ax, ay = _b.bilinear_footprint(q)
                HW = _c.plane_size(acc)
                o = _c.at(acc, s * R * KR + r * KR, iy, ix)  # corner (0, 0) of the reference's first plane
                for dy in ti.static(range(2)):
                    for dx in ti.static(range(2)):
                        wx, wy = _b.corner_weights(ax, ay, dx, dy)
                        if _b.corner_in_image(ix, iy, dx, dy, W, H):
                            w = wx * wy
                            i = o + dy * W + dx
                            vote(i + ch * HW, b * w)
                            if ti.static(Q > 0):  # noqa: SIM102 - compile-time if
                                if maps != 0:
                                    if ti.static(not shared_count):
                                        vote(i + i_cnt * HW, ab * w)
                                    for v in ti.static(range(Q)):
                                        vote(i + (i_num + v) * HW, ab * w * vals[v])

    @ti.func
    def corner_terms(iy, ix, r, ch, b, vals):
        """The adjoint gathered at one pixel for reference r: ``(b adj_ch + |b| adj_C + |b| sum_q q adj_q,
        |b| adj_q)``."""
        ab = ti.abs(b)
        a = b * _c.load(adj, r * KR + ch, iy, ix)
        nr = ti.Vector([0.0 for _ in ti.static(range(max(Q, 1)))])
        if ti.static(Q > 0):
            if ti.static(not shared_count):
                a += ab * _c.load(adj, r * KR + i_cnt, iy, ix)
            for v in ti.static(range(Q)):
                nr[v] = ab * _c.load(adj, r * KR + i_num + v, iy, ix)
                a += vals[v] * nr[v]
        return a, nr

    @ti.func
    def add_node(first, nd, g):
        """Node ``nd``'s gradient in the copy whose first node is ``first`` += ``g`` (float64, x and y)."""
        i = 2 * (first + nd)
        for k in ti.static(range(2)):
            if ti.static(atomic_scatter):
                args.gnode[i + k] += g[k]
            else:
                args.gnode[i + k] = args.gnode[i + k] + g[k]

    @ti.func
    def event_grad(first, e, gp):
        """dJ/dU of one event, scattered into its four nodes (of the gradient copy whose first node is
        ``first``: the copy times the node capacity)."""
        W, H = args.width, args.height
        p, dt, b, ch = event(e)
        n00, stride, a, bb = grid_cell(p, gp)
        u, du_dx, du_dy = interpolate(args.nodes, n00, stride, a, bb, gp)
        div = du_dx[0] + du_dy[1]
        gu = ti.Vector([0.0, 0.0])  # dJ/du
        gdx = ti.Vector([0.0, 0.0])  # dJ/d(du/dx)
        gdy = ti.Vector([0.0, 0.0])  # dJ/d(du/dy)
        for r in range(R):
            dtr = dt - param(P_OFF + r)
            q = p - dtr * u
            if _b.in_window(q, W, H):
                vals, det = quantities(div, du_dx, du_dy, dtr)
                ix, iy, ax, ay = _b.bilinear_footprint(q)
                ga = 0.0  # dS/dq_x
                gb = 0.0  # dS/dq_y
                gv = ti.Vector([0.0 for _ in ti.static(range(max(Q, 1)))])  # dS/d(quantity)
                for dy in ti.static(range(2)):
                    for dx in ti.static(range(2)):
                        if _b.corner_in_image(ix, iy, dx, dy, W, H):
                            ac, nr = corner_terms(iy + dy, ix + dx, r, ch, b, vals)
                            wx, wy = _b.corner_weights(ax, ay, dx, dy)
                            ga += ti.static(1.0 if dx == 1 else -1.0) * wy * ac
                            gb += ti.static(1.0 if dy == 1 else -1.0) * wx * ac
                            if ti.static(Q > 0):
                                gv += wx * wy * nr
                gu += -dtr * ti.Vector([ga, gb])
                for v in ti.static(range(Q)):
                    if ti.static(quantity_kinds[v] == "div"):
                        gdx[0] += gv[v]
                        gdy[1] += gv[v]
                    else:  # d|det| = sign(det) d det (+ at det = 0)
                        gd = gv[v] if det >= 0.0 else -gv[v]
                        gdx += gd * ti.Vector([-dtr * (1.0 - dtr * du_dy[1]), -dtr * dtr * du_dy[0]])
                        gdy += gd * ti.Vector([-dtr * dtr * du_dx[1], -dtr * (1.0 - dtr * du_dx[0])])
        ix_, iy_ = gp[2], gp[3]
        w00 = (1.0 - a) * (1.0 - bb)
        w10 = a * (1.0 - bb)
        w01 = (1.0 - a) * bb
        w11 = a * bb
        add_node(first, n00, ti.cast(w00 * gu - (1.0 - bb) * ix_ * gdx - (1.0 - a) * iy_ * gdy, ti.f64))
        add_node(first, n00 + 1, ti.cast(w10 * gu + (1.0 - bb) * ix_ * gdx - a * iy_ * gdy, ti.f64))
        add_node(first, n00 + stride, ti.cast(w01 * gu - bb * ix_ * gdx + (1.0 - a) * iy_ * gdy, ti.f64))
        add_node(first, n00 + stride + 1, ti.cast(w11 * gu + bb * ix_ * gdx + a * iy_ * gdy, ti.f64))

    @ti.func
    def blur_x_row(src: ti.template(), c, dst: ti.template(), k, y, tv):
        """Plane ``k`` of ``dst`` at row ``y`` = the blur along x (zero padding) of plane ``c`` of ``src``.
        The Gaussian is symmetric: the same pass is its own transpose."""
        W = args.width
        for x in range(W):
            acc_x = 0.0
            if ti.static(r_ == 0):
                acc_x = _c.load(src, c, y, x)
            elif x >= r_ and x < W - r_:
                acc_x = tap_x(src, tv, c, y, x, False)
            else:
                acc_x = tap_x(src, tv, c, y, x, True)
            _c.store(dst, k, y, x, acc_x)

    @ti.func
    def blur_y_at(src: ti.template(), c, y, x, interior, tv):
        acc_y = 0.0
        if ti.static(r_ > 0):
            if interior:
                acc_y = tap_y(src, tv, c, y, x, False)
            else:
                acc_y = tap_y(src, tv, c, y, x, True)
        else:
            acc_y = _c.load(src, c, y, x)
        return acc_y

    @ti.func
    def assemble(out: ti.template(), maps):
        """J from the reduced sums (serial): H, dJ/dG_r, the regularizers and their slopes; into out."""
        n_pix = ti.cast(args.width * args.height, real)
        g0 = param(P_G0)
        inv_sum = 0.0
        ok = 1
        graw = ti.Vector([0.0 for _ in ti.static(range(R))])
        for r in ti.static(range(R)):
            slots = ref_slots(r)
            g = 0.0
            for c in ti.static(range(C)):
                g += finalize_fn(slots, c, n_pix)
            graw[r] = g
            args.state[ST_GRAW + r] = g
            out[2 + r] = ti.cast(g, ti.f64)
            if g > 0.0:
                inv_sum += param(P_W + r) * g0 / g
            else:
                ok = 0
        hval = 0.0
        if ok == 1 and inv_sum > 0.0:
            hval = 1.0 / inv_sum
        for r in ti.static(range(R)):
            coef = 0.0
            if ok == 1 and inv_sum > 0.0:  # dH/dG_r = omega_r G0 / (G_r sum)^2
                coef = param(P_W + r) * g0 / (graw[r] * graw[r] * inv_sum * inv_sum)
            args.state[ST_COEF + r] = coef
        jval = hval
        for v in ti.static(range(Q)):
            rv = 0.0
            for r in ti.static(range(R)):
                base = MB + r * (1 + Q)
                ratio = _b.support_ratio(args.state[base + 1 + v], args.state[base])
                s_vr = param(P_LAM + Q + v * R + r)
                rr = 0.0
                slope = 0.0
                if maps != 0:  # else the flow is constant: div = 0, det = 1, every map its neutral value
                    rr = _b.scaled_penalty(ratio, s_vr, ti.static(one_sided[v]))
                    slope = _b.scaled_penalty_slope(ratio, s_vr, ti.static(one_sided[v]))
                args.state[ST_RW + v * R + r] = param(P_LAM + v) * param(P_W + r) * slope
                rv += param(P_W + r) * rr
                out[2 + R + Q + v * R + r] = ti.cast(rr, ti.f64)
            jval -= param(P_LAM + v) * rv
            out[2 + R + v] = ti.cast(rv, ti.f64)
        out[0] = ti.cast(jval, ti.f64)
        out[1] = ti.cast(hval, ti.f64)

    @ti.kernel
    def run(
        n: ti.i32,
        ev: ev_type,
        n_nodes: ti.i32,
        grad: ti.i32,
        maps: ti.i32,
        out: f64,
        gout: f64,
        params: f64,
        width: ti.i32,
        height: ti.i32,
        votes: real_type,
        images: real_type,
        rows: real_type,
        state: real_type,
        nodes: real_type,
        gnode: f64,
    ):
        ti.static(args.bind(params=params, width=width, height=height, votes=votes, images=images,
                            rows=rows, state=state, nodes=nodes, gnode=gnode))  # fmt: skip
        # --- 1. splat -------------------------------------------------------------------------------
        if ti.static(atomic_scatter):
            for i in range(n):
                splat_event(0, row(ev, i), grid_vec(), maps)
        else:
            ti.loop_config(block_dim=1)  # one slice per thread (backend.per_thread_loops)
            for s in range(S):
                lo, hi = slice_events(s, n)
                gp_s = grid_vec()
                for i in range(lo, hi):
                    splat_event(s, row(ev, i), gp_s, maps)
        # --- 2. rows: sum the slices, blur along x, per-row map sums ---------------------------------
        # (references and channels are runtime loops: unrolled, each multiplied the code to compile)
        ti.loop_config(block_dim=row_block)
        for y in range(height):
            tv = load_taps()
            if ti.static(S > 1):
                for k in range(R * KR):
                    for x in range(width):
                        v = _c.load(acc, k, y, x)
                        for s in ti.static(range(1, S)):
                            v += _c.load(acc, s * R * KR + k, y, x)
                            _c.store(acc, s * R * KR + k, y, x, 0.0)
                        _c.store(acc, k, y, x, v)
            for ic in range(IC):  # the IWE channels of the summed votes (slice 0), blurred along x into tmp
                blur_x_row(acc, (ic // C) * KR + ic % C, tmp, ic, y, tv)
            if ti.static(Q > 0):
                for r in range(R):
                    msum = 0.0
                    psum = ti.Vector([0.0 for _ in ti.static(range(Q))])
                    for x in range(width):
                        cnt = _c.load(acc, r * KR + i_cnt, y, x)
                        if cnt > 0.0 and maps != 0:
                            m = _b.support_weight(cnt)
                            msum += m
                            inv_cnt = 1.0 / cnt
                            for v in ti.static(range(Q)):
                                avg = _c.load(acc, r * KR + i_num + v, y, x) * inv_cnt
                                psum[v] += m * penalty_fns[v](avg)
                    rows[y * n_slots + MB + r * (1 + Q)] = msum
                    for v in ti.static(range(Q)):
                        rows[y * n_slots + MB + r * (1 + Q) + 1 + v] = psum[v]
            # clear what no later pass reads (the backward clears the maps and a shared count)
            for k in range(R * KR):
                c = k % KR
                keep = 0  # maps channels, and the count where it shares IWE channel 0
                if c >= C:
                    keep = 1
                if ti.static(shared_count):  # noqa: SIM102 - compile-time if
                    if c == i_cnt:
                        keep = 1
                if grad == 0 or keep == 0:
                    for x in range(width):
                        _c.store(acc, k, y, x, 0.0)
        # --- 3. rows: blur along y, per-row objective sums ----------------------------------------------
        ti.loop_config(block_dim=row_block)
        for y in range(height):
            tv = load_taps()
            interior = y >= r_ and y < height - r_
            for ic in range(IC):
                rsum = ti.Vector([0.0 for _ in ti.static(range(SL))])
                for x in range(width):
                    v = blur_y_at(tmp, ic, y, x, interior, tv)
                    _c.store(img, ic, y, x, v)
                    if ti.static(not sobel):
                        rsum += pixel_fn(v, 0.0, 0.0)
                if ti.static(not sobel):
                    for k in ti.static(range(SL)):
                        rows[y * n_slots + SL * ic + k] = rsum[k]
        if ti.static(sobel):
            ti.loop_config(block_dim=row_block)
            for y in range(height):
                for ic in range(IC):
                    rsum = ti.Vector([0.0 for _ in ti.static(range(SL))])
                    for x in range(width):
                        gx, gy = sobel_fn(img, ic, y, x)
                        _c.store(sob, 2 * ic, y, x, gx)
                        _c.store(sob, 2 * ic + 1, y, x, gy)
                        rsum += pixel_fn(_c.load(img, ic, y, x), gx, gy)
                    for k in ti.static(range(SL)):
                        rows[y * n_slots + SL * ic + k] = rsum[k]
        # --- 4. the row sums in row order, then J ----------------------------------------------------------
        for j in range(n_slots):
            total = 0.0
            for y in range(height):
                total += rows[y * n_slots + j]
            state[j] = total
        ti.loop_config(serialize=True)
        for _ in range(1):
            assemble(out, maps)
        # --- 5. rows (grad): adjoint images -------------------------------------------------------------
        if ti.static(sobel):
            ti.loop_config(block_dim=row_block)
            for y in range(height):
                if grad != 0:
                    for ic in range(IC):
                        for x in range(width):
                            _c.store(ibar, ic, y, x, sobel_t(sob, ic, y, x))
        ti.loop_config(block_dim=row_block)
        for y in range(height):
            if grad != 0:
                # transposed blur along y of dJ/dI = coef_r (scale L(I) + offset): by linearity
                # coef_r (scale blur(L(I)) + offset * sum of the in-image taps)
                tv = load_taps()
                n_pix = ti.cast(width * height, real)
                interior = y >= r_ and y < height - r_
                tapsum = 0.0
                for k in ti.static(range(-r_, r_ + 1)):
                    if 0 <= y + k < height:
                        tapsum += tv[k + r_]
                for r in range(R):
                    slots = ref_slots(r)
                    coef = state[ST_COEF + r]
                    for c in ti.static(range(C)):
                        ic = r * C + c
                        scale, offset = adjoint_fn(slots, c, n_pix)
                        c1 = coef * scale
                        c0 = coef * offset * tapsum
                        for x in range(width):
                            acc_y = 0.0
                            if ti.static(sobel):
                                acc_y = blur_y_at(ibar, ic, y, x, interior, tv)
                            else:
                                acc_y = blur_y_at(img, ic, y, x, interior, tv)
                            _c.store(tmp, ic, y, x, c1 * acc_y + c0)
                for ic in range(IC):  # the transposed blur along x of tmp into the IWE channels of adj
                    blur_x_row(tmp, ic, adj, (ic // C) * KR + ic % C, y, tv)
                if ti.static(Q > 0):
                    for r in range(R):
                        base = MB + r * (1 + Q)
                        msum = state[base]
                        inv_msum = 0.0
                        if msum > 0.0:
                            inv_msum = 1.0 / msum
                        # per regularizer, loaded once per row: lambda omega slope / sum m and the ratio
                        wrs = ti.Vector([state[ST_RW + v * R + r] * inv_msum for v in ti.static(range(Q))])
                        ratios = ti.Vector([state[base + 1 + v] * inv_msum for v in ti.static(range(Q))])
                        for x in range(width):
                            cnt = _c.load(acc, r * KR + i_cnt, y, x)
                            dc = 0.0
                            for v in ti.static(range(Q)):
                                _c.store(adj, r * KR + i_num + v, y, x, 0.0)
                            if cnt > 0.0 and msum > 0.0:
                                m = _b.support_weight(cnt)
                                dm = _b.support_weight_grad(cnt)
                                inv_cnt = 1.0 / cnt
                                for v in ti.static(range(Q)):
                                    avg = _c.load(acc, r * KR + i_num + v, y, x) * inv_cnt
                                    pen = penalty_fns[v](avg)
                                    dpen = penalty_grads[v](avg)
                                    # d(sum m P / sum m)/dC = (dm P + m P' d(avg)/dC - ratio dm) / sum m
                                    dc -= wrs[v] * (dm * pen - m * dpen * avg * inv_cnt - ratios[v] * dm)
                                    _c.store(adj, r * KR + i_num + v, y, x, -wrs[v] * m * dpen * inv_cnt)
                            if ti.static(shared_count):
                                k_c = r * KR + i_cnt
                                _c.store(adj, k_c, y, x, _c.load(adj, k_c, y, x) + dc)
                            else:
                                _c.store(adj, r * KR + i_cnt, y, x, dc)
                            for k in ti.static(range(i_cnt, KR)):
                                _c.store(acc, r * KR + k, y, x, 0.0)
        # --- 6. events (grad): gather the adjoints, scatter into the nodes ------------------------------
        if ti.static(atomic_scatter):
            for i in range(n):
                if grad != 0:
                    event_grad(0, row(ev, i), grid_vec())
        else:
            ti.loop_config(block_dim=1)  # one slice per thread (backend.per_thread_loops)
            for s in range(S):
                if grad != 0:
                    lo, hi = slice_events(s, n)
                    gp_s = grid_vec()
                    capacity = gnode.shape[0] // (2 * COPIES)  # nodes per copy
                    for i in range(lo, hi):
                        copy = s * NODE_COPIES + ((i - lo) & (NODE_COPIES - 1))
                        event_grad(copy * capacity, row(ev, i), gp_s)
        # --- 7. nodes (grad): the copies in copy order ----------------------------------------------------
        for nd in range(n_nodes):
            if grad != 0:
                stride = gnode.shape[0] // (2 * COPIES)
                for k in ti.static(range(2)):
                    g = gnode[2 * nd + k]
                    gnode[2 * nd + k] = 0.0
                    for copy in ti.static(range(1, COPIES)):
                        i = 2 * (copy * stride + nd) + k
                        g += gnode[i]
                        gnode[i] = 0.0
                    gout[2 * nd + k] = g

    return run
