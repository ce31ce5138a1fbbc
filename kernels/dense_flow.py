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

One kernel ``run(n, ev, n_nodes, grad, out, gout)`` holds every stage as its own task:

1. splat: per event, u and Du from its four nodes, then for every reference its warped position votes
   bilinearly into the IWE channels, the count ``C`` and the map numerators of ``acc[s, y, x, k]`` (CPU:
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

from dataclasses import astuple

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


class DenseFlowFields:
    """The fields of one dense-flow pipeline shape.

    Parameters
    ----------
    layout : fused_common.ImageLayout
        Sensor, IWE channels per reference, blur radius, event-pass slices, objective slots, Sobel images.
    n_refs, n_regs : int
        Reference times, and regularizers (each votes a map at every reference).
    max_nodes : int
        Node capacity (the finest grid of a coarse-to-fine run).
    atomic : bool
        The event passes add atomically into one copy of the node gradients (GPU); else each CPU thread
        has :data:`NODE_COPIES` copies of its own.
    """

    def __init__(
        self, layout: _c.ImageLayout, *, n_refs: int, n_regs: int, max_nodes: int, atomic: bool = False
    ) -> None:
        self.layout, self.n_refs = layout, n_refs
        real, W, H, C, R = layout.real, layout.width, layout.height, layout.n_channels, n_refs
        radius, n_slices, sobel = layout.radius, layout.n_slices, layout.sobel
        self.block = channel_layout(C, n_regs, layout.shared_count)[2]
        K, IC = R * self.block, R * C
        self.acc = ti.field(real, shape=(n_slices, H, W, K))  # votes; zero between calls
        self.tmp = ti.field(real, shape=(H, W, IC))  # blur-x output; then the blur-y adjoint
        self.img = ti.field(real, shape=(H, W, IC))  # the blurred IWEs
        self.adj = ti.field(real, shape=(H, W, K))  # adjoints of the acc channels
        self.sobel = ti.field(real, shape=(H, W, 2 * IC) if sobel else (1, 1, 1))
        self.ibar = ti.field(real, shape=(H, W, IC) if sobel else (1, 1, 1))
        self.taps = ti.field(real, shape=2 * radius + 1)
        self.nodes = ti.Vector.field(2, real, shape=max_nodes)  # node flow, px/s
        self.grid = ti.Vector.field(6, real, shape=())  # nx, ny, 1 / sx, 1 / sy, origin x, origin y
        self.ref_off = ti.field(real, shape=R)  # offsets o_r of the reference times, s
        self.ref_w = ti.field(real, shape=R)  # weights omega_r (sum 1)
        self.lam = ti.Vector.field(max(n_regs * (1 + R), 1), real, shape=())  # lambda_q, then s_qr
        self.g0 = ti.field(real, shape=())
        n_slots = n_reduction_slots(R, C, layout.objective_slots, n_regs)
        self.rowred = ti.field(real, shape=(H, n_slots))  # per-row partial sums
        self.red = ti.field(real, shape=n_slots)
        self.graw = ti.field(real, shape=R)  # G_r
        self.coef = ti.field(real, shape=R)  # dJ/dG_r
        self.rw = ti.field(real, shape=max(n_regs * R, 1))  # lambda_q omega_r dR_qr / d ratio
        # node gradients (float64 in every precision) in a field tree of their own: Taichi's SPIR-V
        # backends misalign an f64 placed among f32 fields (docs/GPU.md, kernels/fused.py)
        self.gnode = ti.Vector.field(2, ti.f64)
        tree = ti.FieldsBuilder()
        copies = 1 if atomic else n_slices * NODE_COPIES
        tree.dense(ti.ij, (copies, max_nodes)).place(self.gnode)
        self.f64_tree = tree.finalize()
        self.max_nodes = max_nodes

    def nbytes(self) -> int:
        """Bytes held by the image fields."""
        return _c.field_bytes((self.acc, self.tmp, self.img, self.adj, self.sobel, self.ibar, self.rowred))


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
def interpolate(nodes: ti.template(), n00, stride, a, b, gp):
    """``(u, du/dx, du/dy)`` at local coordinates ``(a, b)`` of the cell at node ``n00``: the bilinear
    interpolant of the node flow (px/s) and its derivatives (1/s), each a 2-vector (x, y components)."""
    u00 = nodes[n00]
    u10 = nodes[n00 + 1]
    u01 = nodes[n00 + stride]
    u11 = nodes[n00 + stride + 1]
    u = (1.0 - a) * (1.0 - b) * u00 + a * (1.0 - b) * u10 + (1.0 - a) * b * u01 + a * b * u11
    du_dx = ((1.0 - b) * (u10 - u00) + b * (u11 - u01)) * gp[2]
    du_dy = ((1.0 - a) * (u01 - u00) + a * (u11 - u10)) * gp[3]
    return u, du_dx, du_dy


@ti.func
def warp_det(du_dx, du_dy, dt):
    """``det(I - dt Du)`` with ``Du = [[du_x/dx, du_x/dy], [du_y/dx, du_y/dy]]``."""
    return (1.0 - dt * du_dx[0]) * (1.0 - dt * du_dy[1]) - dt * dt * du_dy[0] * du_dx[1]


def make_dense_flow_kernels(
    fields: DenseFlowFields,
    quantity_kinds: tuple,
    penalty_fns: tuple,
    penalty_grads: tuple,
    one_sided: tuple,
    *,
    objective,
    events: _c.EventLayout,
):
    """The dense-flow kernel ``run`` over ``fields`` (see the module docstring; the image shape is
    ``fields.layout``'s) with ``fields.ref_off``'s reference times.

    ``ev`` is an ndarray of per-event vectors ``(x, y, t - t_first[, w][, channel])`` (px, px, s) as
    ``events`` lays them out; ``out`` (float64) receives ``J, H, G_0..G_{R-1}, R_q (Q values), R_qr (Q x
    R values)``, ``gout`` (float64) ``dJ/dU`` as ``(n_nodes, 2)`` row-major (per node px/s, x then y).
    The objective comes as its blocks (``pixel``, ``finalize``, ``adjoint``; see ``kernels/fused.py``),
    each regularizer as its quantity kind ("div" or "absdet"), pixel penalty, its derivative and its
    hinge.
    """
    f, R = fields, fields.n_refs
    real, W, H, C, r_, S, shared_count, SL, sobel = astuple(f.layout)
    weighted, split_polarity, atomic_scatter = astuple(events)
    pixel_fn, finalize_fn, adjoint_fn = _c.objective_blocks(objective, sobel)
    Q = len(quantity_kinds)
    if any(k not in QUANTITY_KINDS for k in quantity_kinds):
        raise ValueError(f"quantity_kinds must name each quantity one of {QUANTITY_KINDS}")
    if not (len(penalty_fns) == len(penalty_grads) == len(one_sided) == Q):
        raise ValueError("one penalty, penalty derivative and hinge flag per regularizer")
    if shared_count and (weighted or split_polarity or Q == 0):
        raise ValueError("the count shares the IWE channel only with unit weights and one channel")
    IC = R * C
    i_cnt, i_num, KR = channel_layout(C, Q, shared_count)
    n_pix = float(W * H)
    n_slots = n_reduction_slots(R, C, SL, Q)
    MB = R * C * SL  # first map slot
    # rows of a task: about H / (2 threads), a power of two (the per-row sums make J independent of it)
    row_block = None if atomic_scatter else 1 << max(0, (H // (2 * S)).bit_length() - 1)
    ev_type, out_type = events.ndarray_type(real), _c.F64_ARRAY
    slice_events = events.slices(S)  # the events [lo, hi) of thread slice s
    event = events.reader()  # (p, dt, b, ch) of an event vector
    vote = events.vote(f.acc)  # slice s of the votes += v
    tap_x_votes = _b.make_tap_sum(_read_slice0, r_, 1, W, H)
    tap_x = _b.make_tap_sum(_b.read_hwc, r_, 1, W, H)
    tap_y = _b.make_tap_sum(_b.read_hwc, r_, 0, W, H)
    sobel_fn = _b.make_sobel(_b.read_hwc, W, H)
    sobel_t = _b.make_sobel_transpose(_c.read_gx, _c.read_gy, W, H)

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
        return ti.Vector([f.red[r * C * SL + k] for k in ti.static(range(C * SL))])

    @ti.func
    def splat_event(s, e, gp, maps):
        p, dt, b, ch = event(e)
        n00, stride, a, bb = grid_cell(p, gp)
        u, du_dx, du_dy = interpolate(f.nodes, n00, stride, a, bb, gp)
        div = du_dx[0] + du_dy[1]
        ab = ti.abs(b)
        for r in range(R):  # a runtime loop: unrolled, every reference multiplied the code to compile
            dtr = dt - f.ref_off[r]
            q = p - dtr * u
            if _b.in_window(q, W, H):
                vals, _ = quantities(div, du_dx, du_dy, dtr)
                ix, iy, ax, ay = _b.bilinear_footprint(q)
                for dy in ti.static(range(2)):
                    for dx in ti.static(range(2)):
                        wx, wy = _b.corner_weights(ax, ay, dx, dy)
                        if _b.corner_in_image(ix, iy, dx, dy, W, H):
                            w = wx * wy
                            vote(s, iy + dy, ix + dx, r * KR + ch, b * w)
                            if ti.static(Q > 0):  # noqa: SIM102 - compile-time if
                                if maps != 0:
                                    if ti.static(not shared_count):
                                        vote(s, iy + dy, ix + dx, r * KR + i_cnt, ab * w)
                                    for v in ti.static(range(Q)):
                                        vote(s, iy + dy, ix + dx, r * KR + i_num + v, ab * w * vals[v])

    @ti.func
    def corner_terms(iy, ix, r, ch, b, vals):
        """The adjoint gathered at one pixel for reference r: ``(b adj_ch + |b| adj_C + |b| sum_q q adj_q,
        |b| adj_q)``."""
        ab = ti.abs(b)
        a = b * f.adj[iy, ix, r * KR + ch]
        nr = ti.Vector([0.0 for _ in ti.static(range(max(Q, 1)))])
        if ti.static(Q > 0):
            if ti.static(not shared_count):
                a += ab * f.adj[iy, ix, r * KR + i_cnt]
            for v in ti.static(range(Q)):
                nr[v] = ab * f.adj[iy, ix, r * KR + i_num + v]
                a += vals[v] * nr[v]
        return a, nr

    @ti.func
    def add_node(s, nd, g):
        if ti.static(atomic_scatter):
            f.gnode[0, nd] += g
        else:
            f.gnode[s, nd] = f.gnode[s, nd] + g

    @ti.func
    def event_grad(s, e, gp):
        """dJ/dU of one event, scattered into its four nodes."""
        p, dt, b, ch = event(e)
        n00, stride, a, bb = grid_cell(p, gp)
        u, du_dx, du_dy = interpolate(f.nodes, n00, stride, a, bb, gp)
        div = du_dx[0] + du_dy[1]
        gu = ti.Vector([0.0, 0.0])  # dJ/du
        gdx = ti.Vector([0.0, 0.0])  # dJ/d(du/dx)
        gdy = ti.Vector([0.0, 0.0])  # dJ/d(du/dy)
        for r in range(R):
            dtr = dt - f.ref_off[r]
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
        add_node(s, n00, ti.cast(w00 * gu - (1.0 - bb) * ix_ * gdx - (1.0 - a) * iy_ * gdy, ti.f64))
        add_node(s, n00 + 1, ti.cast(w10 * gu + (1.0 - bb) * ix_ * gdx - a * iy_ * gdy, ti.f64))
        add_node(s, n00 + stride, ti.cast(w01 * gu - bb * ix_ * gdx + (1.0 - a) * iy_ * gdy, ti.f64))
        add_node(s, n00 + stride + 1, ti.cast(w11 * gu + bb * ix_ * gdx + a * iy_ * gdy, ti.f64))

    @ti.func
    def blur_x_row(tap: ti.template(), read: ti.template(), src: ti.template(), c, dst: ti.template(), k, y):
        """``dst[y, :, k]`` = the blur along x (zero padding) of channel ``c`` of row ``y`` of ``src``, read
        by ``read`` (its tap sum ``tap``). The Gaussian is symmetric: the same pass is its own transpose."""
        for x in range(W):
            acc = 0.0
            if ti.static(r_ == 0):
                acc = read(src, c, y, x)
            elif x >= r_ and x < W - r_:
                acc = tap(src, f.taps, c, y, x, False)
            else:
                acc = tap(src, f.taps, c, y, x, True)
            dst[y, x, k] = acc

    @ti.func
    def blur_y_at(src: ti.template(), c, y, x, interior):
        acc = 0.0
        if ti.static(r_ > 0):
            if interior:
                acc = tap_y(src, f.taps, c, y, x, False)
            else:
                acc = tap_y(src, f.taps, c, y, x, True)
        else:
            acc = src[y, x, c]
        return acc

    @ti.func
    def assemble(out: ti.template(), maps):
        """J from the reduced sums (serial): H, dJ/dG_r, the regularizers and their slopes; into out."""
        g0 = f.g0[None]
        inv_sum = 0.0
        ok = 1
        for r in ti.static(range(R)):
            slots = ref_slots(r)
            g = 0.0
            for c in ti.static(range(C)):
                g += finalize_fn(slots, c, n_pix)
            f.graw[r] = g
            out[2 + r] = ti.cast(g, ti.f64)
            if g > 0.0:
                inv_sum += f.ref_w[r] * g0 / g
            else:
                ok = 0
        hval = 0.0
        if ok == 1 and inv_sum > 0.0:
            hval = 1.0 / inv_sum
        for r in ti.static(range(R)):
            f.coef[r] = 0.0
            if ok == 1 and inv_sum > 0.0:  # dH/dG_r = omega_r G0 / (G_r sum)^2
                f.coef[r] = f.ref_w[r] * g0 / (f.graw[r] * f.graw[r] * inv_sum * inv_sum)
        jval = hval
        for v in ti.static(range(Q)):
            rv = 0.0
            for r in ti.static(range(R)):
                base = MB + r * (1 + Q)
                ratio = _b.support_ratio(f.red[base + 1 + v], f.red[base])
                s_vr = f.lam[None][Q + v * R + r]
                rr = 0.0
                slope = 0.0
                if maps != 0:  # else the flow is constant: div = 0, det = 1, every map its neutral value
                    rr = _b.scaled_penalty(ratio, s_vr, ti.static(one_sided[v]))
                    slope = _b.scaled_penalty_slope(ratio, s_vr, ti.static(one_sided[v]))
                f.rw[v * R + r] = f.lam[None][v] * f.ref_w[r] * slope
                rv += f.ref_w[r] * rr
                out[2 + R + Q + v * R + r] = ti.cast(rr, ti.f64)
            jval -= f.lam[None][v] * rv
            out[2 + R + v] = ti.cast(rv, ti.f64)
        out[0] = ti.cast(jval, ti.f64)
        out[1] = ti.cast(hval, ti.f64)

    @ti.kernel
    def run(
        n: ti.i32, ev: ev_type, n_nodes: ti.i32, grad: ti.i32, maps: ti.i32, out: out_type, gout: out_type
    ):
        # --- 1. splat -------------------------------------------------------------------------------
        if ti.static(atomic_scatter):
            for i in range(n):
                splat_event(0, ev[i], f.grid[None], maps)
        else:
            ti.loop_config(block_dim=1)  # one slice per thread (backend.per_thread_loops)
            for s in range(S):
                lo, hi = slice_events(s, n)
                gp_s = f.grid[None]
                for i in range(lo, hi):
                    splat_event(s, ev[i], gp_s, maps)
        # --- 2. rows: sum the slices, blur along x, per-row map sums ---------------------------------
        # (references and channels are runtime loops: unrolled, each multiplied the code to compile)
        ti.loop_config(block_dim=row_block)
        for y in range(H):
            if ti.static(S > 1):
                for k in range(R * KR):
                    for x in range(W):
                        v = f.acc[0, y, x, k]
                        for s in ti.static(range(1, S)):
                            v += f.acc[s, y, x, k]
                            f.acc[s, y, x, k] = 0.0
                        f.acc[0, y, x, k] = v
            for ic in range(IC):  # the IWE channels of the summed votes, blurred along x into tmp
                blur_x_row(tap_x_votes, _read_slice0, f.acc, (ic // C) * KR + ic % C, f.tmp, ic, y)
            if ti.static(Q > 0):
                for r in range(R):
                    msum = 0.0
                    psum = ti.Vector([0.0 for _ in ti.static(range(Q))])
                    for x in range(W):
                        cnt = f.acc[0, y, x, r * KR + i_cnt]
                        if cnt > 0.0 and maps != 0:
                            m = _b.support_weight(cnt)
                            msum += m
                            inv_cnt = 1.0 / cnt
                            for v in ti.static(range(Q)):
                                psum[v] += m * penalty_fns[v](f.acc[0, y, x, r * KR + i_num + v] * inv_cnt)
                    f.rowred[y, MB + r * (1 + Q)] = msum
                    for v in ti.static(range(Q)):
                        f.rowred[y, MB + r * (1 + Q) + 1 + v] = psum[v]
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
                    for x in range(W):
                        f.acc[0, y, x, k] = 0.0
        # --- 3. rows: blur along y, per-row objective sums ----------------------------------------------
        ti.loop_config(block_dim=row_block)
        for y in range(H):
            interior = y >= r_ and y < H - r_
            for ic in range(IC):
                rsum = ti.Vector([0.0 for _ in ti.static(range(SL))])
                for x in range(W):
                    v = blur_y_at(f.tmp, ic, y, x, interior)
                    f.img[y, x, ic] = v
                    if ti.static(not sobel):
                        rsum += pixel_fn(v, 0.0, 0.0)
                if ti.static(not sobel):
                    for k in ti.static(range(SL)):
                        f.rowred[y, SL * ic + k] = rsum[k]
        if ti.static(sobel):
            ti.loop_config(block_dim=row_block)
            for y in range(H):
                for ic in range(IC):
                    rsum = ti.Vector([0.0 for _ in ti.static(range(SL))])
                    for x in range(W):
                        gx, gy = sobel_fn(f.img, ic, y, x)
                        f.sobel[y, x, 2 * ic] = gx
                        f.sobel[y, x, 2 * ic + 1] = gy
                        rsum += pixel_fn(f.img[y, x, ic], gx, gy)
                    for k in ti.static(range(SL)):
                        f.rowred[y, SL * ic + k] = rsum[k]
        # --- 4. the row sums in row order, then J ----------------------------------------------------------
        for j in range(n_slots):
            total = 0.0
            for y in range(H):
                total += f.rowred[y, j]
            f.red[j] = total
        assemble(out, maps)
        # --- 5. rows (grad): adjoint images -------------------------------------------------------------
        if ti.static(sobel):
            ti.loop_config(block_dim=row_block)
            for y in range(H):
                if grad != 0:
                    for ic in range(IC):
                        for x in range(W):
                            f.ibar[y, x, ic] = sobel_t(f.sobel, ic, y, x)
        ti.loop_config(block_dim=row_block)
        for y in range(H):
            if grad != 0:
                # transposed blur along y of dJ/dI = coef_r (scale L(I) + offset): by linearity
                # coef_r (scale blur(L(I)) + offset * sum of the in-image taps)
                interior = y >= r_ and y < H - r_
                tapsum = 0.0
                for k in ti.static(range(-r_, r_ + 1)):
                    if 0 <= y + k < H:
                        tapsum += f.taps[k + r_] if ti.static(r_ > 0) else 1.0
                for r in range(R):
                    slots = ref_slots(r)
                    for c in ti.static(range(C)):
                        ic = r * C + c
                        scale, offset = adjoint_fn(slots, c, n_pix)
                        c1 = f.coef[r] * scale
                        c0 = f.coef[r] * offset * tapsum
                        for x in range(W):
                            acc = 0.0
                            if ti.static(sobel):
                                acc = blur_y_at(f.ibar, ic, y, x, interior)
                            else:
                                acc = blur_y_at(f.img, ic, y, x, interior)
                            f.tmp[y, x, ic] = c1 * acc + c0
                for ic in range(IC):  # the transposed blur along x of tmp into the IWE channels of adj
                    blur_x_row(tap_x, _b.read_hwc, f.tmp, ic, f.adj, (ic // C) * KR + ic % C, y)
                if ti.static(Q > 0):
                    for r in range(R):
                        base = MB + r * (1 + Q)
                        msum = f.red[base]
                        inv_msum = 0.0
                        if msum > 0.0:
                            inv_msum = 1.0 / msum
                        # per regularizer, loaded once per row: lambda omega slope / sum m and the ratio
                        wrs = ti.Vector([f.rw[v * R + r] * inv_msum for v in ti.static(range(Q))])
                        ratios = ti.Vector([f.red[base + 1 + v] * inv_msum for v in ti.static(range(Q))])
                        for x in range(W):
                            cnt = f.acc[0, y, x, r * KR + i_cnt]
                            dc = 0.0
                            for v in ti.static(range(Q)):
                                f.adj[y, x, r * KR + i_num + v] = 0.0
                            if cnt > 0.0 and msum > 0.0:
                                m = _b.support_weight(cnt)
                                dm = _b.support_weight_grad(cnt)
                                inv_cnt = 1.0 / cnt
                                for v in ti.static(range(Q)):
                                    avg = f.acc[0, y, x, r * KR + i_num + v] * inv_cnt
                                    pen = penalty_fns[v](avg)
                                    dpen = penalty_grads[v](avg)
                                    # d(sum m P / sum m)/dC = (dm P + m P' d(avg)/dC - ratio dm) / sum m
                                    dc -= wrs[v] * (dm * pen - m * dpen * avg * inv_cnt - ratios[v] * dm)
                                    f.adj[y, x, r * KR + i_num + v] = -wrs[v] * m * dpen * inv_cnt
                            if ti.static(shared_count):
                                f.adj[y, x, r * KR + i_cnt] += dc
                            else:
                                f.adj[y, x, r * KR + i_cnt] = dc
                            for k in ti.static(range(i_cnt, KR)):
                                f.acc[0, y, x, r * KR + k] = 0.0
        # --- 6. events (grad): gather the adjoints, scatter into the nodes ------------------------------
        if ti.static(atomic_scatter):
            for i in range(n):
                if grad != 0:
                    event_grad(0, ev[i], f.grid[None])
        else:
            ti.loop_config(block_dim=1)  # one slice per thread (backend.per_thread_loops)
            for s in range(S):
                if grad != 0:
                    lo, hi = slice_events(s, n)
                    gp_s = f.grid[None]
                    for i in range(lo, hi):
                        event_grad(s * NODE_COPIES + ((i - lo) & (NODE_COPIES - 1)), ev[i], gp_s)
        # --- 7. nodes (grad): the slices in slice order -----------------------------------------------------
        for nd in range(n_nodes):
            if grad != 0:
                g = f.gnode[0, nd]
                f.gnode[0, nd] = ti.Vector([0.0, 0.0], dt=ti.f64)
                for s in ti.static(range(1, 1 if atomic_scatter else S * NODE_COPIES)):
                    g += f.gnode[s, nd]
                    f.gnode[s, nd] = ti.Vector([0.0, 0.0], dt=ti.f64)
                gout[2 * nd] = g[0]
                gout[2 * nd + 1] = g[1]

    return run
