"""The fused CMax pipeline: value and gradient in one kernel launch, with a hand-written backward.

Why: the chain of small kernels of ``iwe.py`` / ``objectives.py`` / ``maps.py`` differentiated by
Taichi's reverse mode spends its time in atomics (compare-and-swap loops for float adds on the CPU,
~15 ns each: every scatter, every transposed blur, every reduction into a 0-D *vector* field, which
Taichi does not make thread-local) and in kernel launches (~10-40 us each from Python). Here one
kernel ``run(n, ev, terms, params, grad, out)`` holds every stage as its own task (Taichi runs the
top-level loops of a kernel one after the other, each in parallel):

1. serial: theta and the window's constants (``params``, :func:`params_layout`) into 0-D fields,
   reductions cleared;
2. splat: each event is warped and votes bilinearly into the IWE channels, the count ``C`` and the
   map numerators ``N_r`` of ``acc[s, y, x, k]``, and marks the segments it touches (``tiles.py``).
   On the CPU the events are split into one chunk per thread ``s``, each voting with plain loads and
   stores into its own slice ``s``; on a GPU one slice takes atomic adds. Without weights and
   per-polarity channels the IWE votes equal the count votes, and one channel serves both. Where the
   model declares ``store_event_terms`` (CPU, ``make_fused_kernels(store_terms=True)``), a loop of its
   own first writes each event's warped position, voted quantities and (when the gradient is asked)
   parameter Jacobians into ``terms`` (:func:`terms_width` rows, one column per event: each row is read
   and written contiguously), and the splat reads them: an event's costly warp is evaluated once per
   call, not again in stage 8, and the loop that evaluates it carries no scattered votes. A
   value-only launch leaves the Jacobians out (dead code): fast math then compiles the position's
   arithmetic differently, and its value may differ from that of ``value_and_grad`` in the last bits
   (a few ulps; storing them there too cost value-only calls 50-90%, docs/performance.md);
3. rows: the touched segments ``F0`` of the row and their x-dilations; at the touched pixels, sum the
   slices and reduce the maps (``sum m``, ``sum m P_r``) into the row's partial sums; clear what the
   previous call left in ``tmp`` outside the new ``Rx`` (``F0`` and ``r`` columns); blur along x into
   ``tmp`` over ``Rx``;
4. rows: the regions of the row with y-dilation; where the image is kept (a Sobel objective, or
   ``FusedPipeline.image``) blur along y into ``img`` over ``Rxy`` (``Rx`` and ``r`` rows), after clearing
   what the previous kept image left outside it. Without Sobel the objective's terms are quadratic in
   the image (its adjoint is affine in it), so their sum over the image needs only ``sum I`` and ``sum
   I^2`` of each channel: with ``u = tmp`` and ``I = B_y u``, ``sum I = sum u tapsum_y`` and ``sum I^2 =
   ||B_y u||^2 = sum u w``, ``w = B_y^T B_y u`` (``4 r + 1`` taps at ``Rx``'s pixels, into ``tmp2``, where
   the backward reads it): the row's moments into its partial sums, over ``Rx`` rather than ``Rxy``
   (a third of the pixels of a sparse 1280x720 window). The touched votes cleared;
5. rows (Sobel): the Sobel images over ``Rs`` (one more pixel around ``Rxy``), kept for the backward, and
   the objective's per-pixel terms into the row's partial sums;
6. serial: the partial sums in row order (a fixed order: the same input gives the same J to the last
   bit); the terms of the pixels no pass visited in closed form (``pixel(0, 0, 0)`` times their number:
   their image and Sobel responses are 0), or without Sobel every pixel's terms from the moments
   (``N t(0) + c1 sum I + c2 sum I^2``, the quadratic's coefficients from ``pixel`` at 0, 1 and -1); J;
7. rows (``grad``): the pixel adjoint dJ/dI (affine in the image or in its transposed Sobel, as the
   objective declares) and its transposed blurs (the Gaussian is symmetric, so its transpose with
   zero padding is the same correlation): along y over ``Rx`` (without Sobel by linearity from stage 4's
   ``w``: ``(scale w + offset tapsum_y) / G0``), along x over ``F0``, with the map adjoints dJ/dC,
   dJ/dN_r, into ``adj`` (same channel layout as ``acc``) at the touched pixels, the only ones the
   gather reads (the adjoint's uniform ``offset`` term included);
8. events (``grad``): dJ/dtheta as a *gather*:
   ``dJ/dtheta = sum_k sum_corners d/dtheta [beta_k (b_k adj_ch + |b_k| adj_C + |b_k| sum_r q_rk adj_r)]``
   with ``adj`` held fixed, using the closed-form parameter Jacobians each model declares
   (``kernels/warps/``; the trigonometry depends on theta only and leaves the event loop), or the
   stored ``terms`` of stage 2; on the CPU each slice's sum goes into its own field, added in slice
   order. The gather has no branch (clamped reads and selects, ``grad_at``), so that LLVM vectorizes
   its loops, four events a step (the loops of the other stages store, and stay scalar: Taichi reloads
   an array's base pointer after every store, ``benchmarks/vector_probe.py``);
9. serial: ``out = (J, G_raw, dJ/dtheta, J with G0 = G_raw)`` (the last: at the identity, the
   normalised J of every later evaluation there).

The image passes are row loops over the set bits of the row's region words: their work follows the
pixels the events reach, not ``W x H``. ``acc`` is cleared by the passes that consume it at the touched
pixels; ``tmp`` and ``img`` are zero outside the regions the last call wrote (stages 3 and 4 clear what
the call before left outside the new regions), so that every read outside a region reads 0; ``tmp2``,
``sobel``, ``ibar`` and ``adj`` are read only inside the regions written in the same call. No call launches a
fill, and nothing is allocated per call.

Warps without closed-form parameter Jacobians (user models) take the generic chain of ``problem.py``:
Taichi 1.7.4's compiler crashed on the reverse pass of an autodiff stand-in for step 8 inside this
kernel layout.

The formulas (bilinear weights, blur taps, support weight, objectives, loss) are the blocks of
``blocks.py`` shared with the generic chain; nothing here branches on an objective's name.
Formulas: docs/FORMULAS.md; derivatives of the map penalties: ``maps.py``.
"""

from dataclasses import astuple

import taichi as ti

from . import blocks as _b
from . import fused_common as _c
from . import tiles as _t

MAX_PARAMS = 8  # theta's slots in ``params``


def terms_width(n_params: int, n_voted: int) -> int:
    """Rows of the stored event terms (``store_terms``) per event: the warped position (2), the voted
    quantities (``n_voted``), the parameter Jacobian of the position (``2 n_params``, row-major) and of
    each voted quantity (``n_voted n_params``)."""
    return 2 + n_voted + 2 * n_params + n_voted * n_params


def params_layout(n_regs: int) -> dict:
    """Where each value sits in the kernel's float64 ``params`` array (a NumPy array the driver fills:
    one argument in place of a launch per field write): ``theta`` (``MAX_PARAMS`` slots), ``ctx``
    (``cx, cy, fx, fy, T``), ``g0``, ``lam`` (``lambda_r`` then ``s_r``); ``size`` the length."""
    n_lam = max(2 * n_regs, 1)
    return {"theta": 0, "ctx": MAX_PARAMS, "g0": MAX_PARAMS + 5, "lam": MAX_PARAMS + 6,
            "n_lam": n_lam, "size": MAX_PARAMS + 6 + n_lam}  # fmt: skip


QUANTITY_KINDS = ("div", "absdet")  # per-event quantities the hand-written backward differentiates


def channel_layout(n_channels: int, n_regs: int, n_voted: int, shared_count: bool) -> tuple[int, int, int]:
    """``(i_count, i_numer, n_acc)``: where the count and the first voted numerator live, and the
    channel count of ``acc`` / ``adj`` (IWE channels first)."""
    if n_regs == 0:
        return -1, -1, n_channels
    i_count = 0 if shared_count else n_channels
    return i_count, i_count + 1, i_count + 1 + n_voted


def _planes(builder, real, outer: tuple, height: int, width: int, channels: int):
    """A ``(*outer, H, W, channels)`` field stored as row-major ``H x W`` planes, one per channel (and
    outer index): the pixels of a segment (``tiles.SEG`` of one row) are contiguous in every channel, so
    a segment's blur taps are vector loads."""
    field = ti.field(real)
    n = len(outer)
    builder.dense(ti.axes(*range(n), n + 2), outer + (channels,)).dense(
        ti.axes(n, n + 1), (height, width)
    ).place(field)
    return field


class FusedFields:
    """The fields of one fused pipeline shape.

    Parameters
    ----------
    layout : fused_common.ImageLayout
        Sensor, channels, blur radius, splat slices, objective slots, Sobel images.
    n_regs, n_params : int
        Regularizers, warp parameters.
    n_voted : int
        Regularizer quantities voted into maps (the others are the same for every event).
    """

    def __init__(self, layout: _c.ImageLayout, *, n_regs: int, n_voted: int, n_params: int) -> None:
        self.layout, self.n_params = layout, n_params
        real, W, H, C = layout.real, layout.width, layout.height, layout.n_channels
        radius, n_slices, sobel = layout.radius, layout.n_slices, layout.sobel
        objective_slots = layout.objective_slots
        self.n_acc = channel_layout(C, n_regs, n_voted, layout.shared_count)[2]
        images = ti.FieldsBuilder()
        self.acc = _planes(images, real, (n_slices,), H, W, self.n_acc)  # votes; zero between calls
        self.tmp = _planes(images, real, (), H, W, C)  # blur-x output
        self.tmp2 = _planes(images, real, (), H, W, C)  # the blur-y adjoint
        self.img = _planes(images, real, (), H, W, C)  # the blurred IWE
        self.adj = _planes(images, real, (), H, W, self.n_acc)  # adjoints of the acc channels
        self.sobel = _planes(images, real, (), H, W, 2 * C) if sobel else ti.field(real, shape=(1, 1, 1))
        self.ibar = _planes(images, real, (), H, W, C) if sobel else ti.field(real, shape=(1, 1, 1))
        self.images_tree = images.finalize()
        # the regions of the image passes (tiles.py): F0, Rx (blur x), Rxy (blur y), Rs (Sobel);
        # tmp (written over Rx) and img (over Rxy) keep the previous call's regions for stage 4's clears
        kx = _t.reach(radius)
        regions = [(0, 0), (kx, 0), (kx, radius)] + ([(kx + 1, radius + 1)] if sobel else [])
        self.tiles = _t.TileFields(W, H, regions, history=(1, 2))
        # per-row partial sums (summed in row order: a fixed order whatever the threads do)
        self.part_obj = ti.field(real, shape=(H, objective_slots * C))
        self.part_mom = ti.field(real, shape=(H, 2 * C))  # without Sobel: the row's sum I, sum I^2
        self.part_map = ti.field(real, shape=(H, 1 + n_voted))
        self.taps = ti.field(real, shape=2 * radius + 1)
        self.ctx = ti.Vector.field(5, real, shape=())
        self.lam = ti.Vector.field(max(2 * n_regs, 1), real, shape=())  # lambda_r, then scales s_r
        self.g0 = ti.field(real, shape=())
        # 0-D scalars (Taichi accumulates them thread-locally): objective slots, sum m, sum m P_r
        self.red = [ti.field(real, shape=()) for _ in range(objective_slots * C + 1 + n_voted)]
        self.mom = [ti.field(real, shape=()) for _ in range(2 * C)]  # sum I, sum I^2 of each channel
        # dJ/dtheta accumulators (f64 also in f32 runs) in a field tree of their own: Taichi 1.7.4's SPIR-V
        # backends (Vulkan, Metal) pack a tree's fields without alignment padding but address an f64 at
        # byte offset o as element o >> 3, so an f64 placed at 4 mod 8 among the f32 fields reads and
        # writes 4 bytes too low, over its neighbour (it zeroed lambda's s_r; taichi-dev/taichi#8803,
        # docs/GPU.md). Alone in their tree, every f64 sits at a multiple of 8.
        self.gsum = [ti.field(ti.f64) for _ in range(n_params)]
        self.gpart = ti.field(ti.f64)  # per-slice dJ/dtheta sums of the gather (added in slice order)
        f64_tree = ti.FieldsBuilder()
        for g in self.gsum:
            f64_tree.place(g)
        f64_tree.dense(ti.ij, (n_slices, n_params)).place(self.gpart)
        self.f64_tree = f64_tree.finalize()
        # theta as a 0-D vector: Taichi keeps its loads outside the event loop (not so for 0-D scalars,
        # whose loads it moves into the loop, where they block hoisting the trigonometry)
        self.thv = ti.Vector.field(n_params, real, shape=())
        self.loss = ti.field(real, shape=())
        self.graw = ti.field(real, shape=())
        self.rvals = ti.field(real, shape=max(n_regs, 1))  # R_r as in J
        self.rw = ti.field(real, shape=max(n_regs, 1))  # weight of sum m P_r / sum m in -J (0: flat hinge)

    def nbytes(self) -> int:
        """Bytes held by the image fields."""
        images = (self.acc, self.tmp, self.tmp2, self.img, self.adj, self.sobel, self.ibar)
        return self.tiles.nbytes() + _c.field_bytes(images + (self.part_obj, self.part_mom, self.part_map))


def _composed_warp_terms(warp_fn, det_fn, param_jac):
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


def make_fused_kernels(
    fields: FusedFields,
    warp_fn,
    quantity_fns: tuple,
    penalty_fns: tuple,
    penalty_grads: tuple,
    one_sided: tuple,
    *,
    objective,
    events: _c.EventLayout,
    param_jac=None,
    quantity_kinds: tuple = (),
    constant: tuple = (),
    det_fn=None,
    warp_terms=None,
    positive_det: bool = True,
    serial: bool = False,
    store_terms: bool = False,
):
    """The kernel ``run`` of the fused pipeline over ``fields`` (see the module docstring); the shape
    (sensor, channels, blur, slices, objective slots, Sobel) is ``fields.layout``'s.

    ``ev`` is an ndarray of per-event vectors as ``events`` lays them out (``fused_common.EventLayout``,
    which also says whether the event passes add atomically). The ``objective`` comes as its blocks
    (``blocks.py``; ``models.objectives.FusedObjective``): ``objective.pixel(v, gx, gy)``
    (``objective_slots`` terms per channel, Sobel responses where ``sobel``), ``objective.finalize(a,
    c, n_pixels)`` and ``objective.adjoint(a, c, n_pixels) -> (scale, offset)`` with ``dG_c/dI = scale
    * L(I) + offset`` (``L``: identity, or the transposed Sobel of the Sobel images where ``sobel``).
    Regularizer ``r`` enters J as ``-lambda_r R_r`` with ``R_r = s_r sum m P_r / sum m``
    (``max(0, R_r)`` where ``one_sided[r]``); ``lam`` holds ``lambda_r`` then ``s_r``.
    ``param_jac`` is the model's closed-form parameter Jacobian (``WarpModel.param_jac``, e.g. in
    ``kernels/warps/zoom1.py``) and
    ``quantity_kinds`` names each quantity "div" or "absdet". ``constant[r]`` says quantity ``r``
    is the same for every event: its map is that value
    wherever ``C > 0``, so ``R_r = s_r P_r(q_r)`` (``sum m > 0``) and nothing is voted for it.
    ``det_fn`` is the model's ``det`` (the "absdet" quantities are its absolute value, and where
    ``positive_det`` is False ``d|det|/dtheta = sign(det) ddet``). ``warp_terms(p, dt, th, ctx) ->
    (warp, det, jx, ddet, ddiv)`` is the model's optional joint evaluation (e.g.
    ``kernels/warps/rotation3.py``: one rotation of the ray serves all five); without it the kernels
    compose it from ``warp_fn``, ``det_fn`` and ``param_jac``. The event loops use only what they need
    of it (the rest is dead code to the compiler). ``store_terms`` (the model's ``store_event_terms``;
    ignored with atomic adds) evaluates it once per event and call into the ``terms`` argument (a
    ``(terms_width(P, n_voted), n)`` array of the kernel's float type; otherwise any ``(1, 1)`` one),
    which the splat and the gather read: the same sums of the same terms, so value and gradient agree
    with the unstored kernel to rounding (about 1e-14 relative in f64: the compiler contracts the
    products differently when a loop stores them).
    """
    f, P = fields, fields.n_params
    real, W, H, C, r_, S, shared_count, SL, sobel = astuple(f.layout)
    weighted, split_polarity, atomic_scatter = astuple(events)
    pixel_fn, finalize_fn, adjoint_fn = _c.objective_blocks(objective, sobel)
    if P > MAX_PARAMS:
        raise ValueError(f"the fused pipeline takes at most {MAX_PARAMS} parameters")
    if shared_count and (weighted or split_polarity or not quantity_fns):
        raise ValueError("the count shares the IWE channel only with unit weights and one channel")
    R = len(quantity_fns)
    if param_jac is None:
        raise ValueError("the fused pipeline needs the model's closed-form parameter Jacobian")
    if len(quantity_kinds) != R or any(k not in QUANTITY_KINDS for k in quantity_kinds):
        raise ValueError(f"quantity_kinds must name each quantity one of {QUANTITY_KINDS}")
    constant = tuple(bool(c) for c in constant) if constant else (False,) * R
    if len(constant) != R:
        raise ValueError("constant needs one flag per quantity")
    voted = tuple(r for r in range(R) if not constant[r])  # voted quantity -> its regularizer
    if det_fn is None and any(quantity_kinds[r] == "absdet" for r in voted):
        raise ValueError("a voted 'absdet' quantity needs the model's det (det_fn)")
    if warp_terms is None:
        warp_terms = _composed_warp_terms(warp_fn, det_fn, param_jac)
    # row passes: a few rows per task on the CPU (their partial sums are per row, so the threads'
    # scheduling cannot change J); a GPU keeps its default
    row_block = None if atomic_scatter else 4
    vpos = tuple(voted.index(r) if r in voted else -1 for r in range(R))  # regularizer -> voted slot
    RV = len(voted)
    i_cnt, i_num, K = channel_layout(C, R, RV, shared_count)
    n_pix = float(W * H)
    red, gsum = f.red, f.gsum
    i_m = SL * C  # red[i_m] = sum m, red[i_m + 1 + r] = sum m P_r
    ev_type, out_type = events.ndarray_type(real), _c.F64_ARRAY
    # (a Taichi primitive type of its own: ``real`` may be the default float alias, which ndarray
    # annotations do not take)
    terms_type = ti.types.ndarray(dtype=ti.f64 if real == ti.f64 else ti.f32, ndim=2)
    store = bool(store_terms) and not atomic_scatter
    T_Q, T_V, T_J = 0, 2, 2 + RV  # rows of the stored terms: position, quantities, Jacobians
    T_DQ = T_J + 2 * P
    slots_at = params_layout(R)
    p_theta, p_ctx, p_g0, p_lam = slots_at["theta"], slots_at["ctx"], slots_at["g0"], slots_at["lam"]
    n_lam = slots_at["n_lam"]
    sobel_fn = _b.make_sobel(_b.read_hwc, W, H)
    sobel_t = _b.make_sobel_transpose(_c.read_gx, _c.read_gy, W, H)
    slice_events = events.slices(S)  # the events [lo, hi) of thread slice s
    event = events.reader()  # (p, dt, b, ch) of an event vector
    vote = events.vote(f.acc)  # slice s of the votes += v
    tf = f.tiles
    tiles = _t.ops_for(tf)
    SEG = _t.SEG
    in_image = tiles.in_image  # a column of a segment is in the image
    F0, RX, RXY = 0, 1, 2
    R_OBJ = 3 if sobel else RXY  # the region of the objective's pixel terms

    @ti.func
    def theta_vec():
        return f.thv[None]

    @ti.func
    def objective_slots_vec():
        return ti.Vector([red[j][None] for j in ti.static(range(SL * C))])

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
        """d q_v / d theta of the voted quantities, a ``RV x P`` matrix, from ``warp_terms``' output (the
        "absdet" rows signed where the model's det may be negative: d|det| = -d det where det < 0)."""
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
        if _b.in_window(q, W, H):
            ix, iy, ax, ay = _b.bilinear_footprint(q)
            tiles.mark(tf, ix, iy)
            ab = ti.abs(b)
            for dy in ti.static(range(2)):
                for dx in ti.static(range(2)):
                    wx, wy = _b.corner_weights(ax, ay, dx, dy)
                    if _b.corner_in_image(ix, iy, dx, dy, W, H):
                        w = wx * wy
                        vote(s, iy + dy, ix + dx, ch, b * w)
                        if ti.static(R > 0):
                            if ti.static(not shared_count):
                                vote(s, iy + dy, ix + dx, i_cnt, ab * w)
                            for v in ti.static(range(RV)):
                                vote(s, iy + dy, ix + dx, i_num + v, ab * w * vals[v])

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
    def corner_terms(iy, ix, ch, b, vals):
        """The adjoint gathered at one pixel: (b adj_ch + |b| adj_C + |b| sum_r q_r adj_r, adj_r)."""
        ab = ti.abs(b)
        a = b * f.adj[iy, ix, ch]
        nr = ti.Vector([0.0 for _ in ti.static(range(max(RV, 1)))])
        if ti.static(R > 0):
            if ti.static(not shared_count):
                a += ab * f.adj[iy, ix, i_cnt]
            for v in ti.static(range(RV)):
                nr[v] = ab * f.adj[iy, ix, i_num + v]
                a += vals[v] * nr[v]
        return a, nr

    @ti.func
    def grad_at(q, vals, jx, dq, b, ch):
        """dJ/dtheta of an event warped to ``q`` (quantities ``vals``; Jacobians ``jx`` of the position,
        ``dq`` of the quantities), hand-written, float64.

        Without branches, so that LLVM vectorizes the gather loops (a branch per corner kept them
        scalar): every corner is read at an index clamped into the image and a corner outside it, or an
        event outside the window, is dropped by a select (a select, not a product with 0: an adjoint
        that overflowed to inf stays out as before); the conditions are bitwise (``blocks.in_window``).
        ``q`` outside the window (NaN included) is read at the origin first, so that no index is computed
        from it."""
        inside = _b.in_window(q, W, H)  # (bitwise: no branch)
        qs = ti.Vector([ti.select(inside, q[0], 0.0), ti.select(inside, q[1], 0.0)])
        ix, iy, ax, ay = _b.bilinear_footprint(qs)
        ga = 0.0  # dS/dax
        gb = 0.0  # dS/day
        gv = ti.Vector([0.0 for _ in ti.static(range(max(RV, 1)))])  # dS/dq_v
        for dy in ti.static(range(2)):
            for dx in ti.static(range(2)):
                keep = _b.corner_in_image(ix, iy, dx, dy, W, H)
                cx = ti.min(ti.max(ix + dx, 0), W - 1)
                cy = ti.min(ti.max(iy + dy, 0), H - 1)
                a, nr = corner_terms(cy, cx, ch, b, vals)
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

    seg = _t.SegmentPasses(W, H, r_)  # blurs, stores and clears of one segment
    load_taps, blur_x_segment, blur_y_segment = seg.load_taps, seg.blur_x, seg.blur_y
    store_segment, clear_segment, twice_taps = seg.store, seg.clear, seg.twice_taps

    @ti.func
    def keep_image(grad):
        """Whether this call keeps the blurred IWE in ``img``: for a Sobel objective (its pass reads it)
        or when asked (bit 2 of ``grad``, ``FusedPipeline.image``)."""
        keep = True
        if ti.static(not sobel):
            keep = grad & 2 != 0
        return keep

    # The bodies of the row passes, ``body(y, x0 or x, state)`` of ``tiles.each_segment`` / ``each_pixel``:
    # ``state`` is passed by reference (its vectors accumulate the row's sums), tuples indexed, not unpacked.

    @ti.func
    def sum_slices_and_maps(y, x, sums: ti.template()):
        """Stage 3 at a touched pixel: the slices summed into slice 0; ``sums`` += (m, m P_v)."""
        if ti.static(S > 1):
            for k in ti.static(range(K)):
                v = f.acc[0, y, x, k]
                for s in ti.static(range(1, S)):
                    v += f.acc[s, y, x, k]
                    f.acc[s, y, x, k] = 0.0
                f.acc[0, y, x, k] = v
        if ti.static(R > 0):
            cnt = f.acc[0, y, x, i_cnt]
            if cnt > 0.0:
                m = _b.support_weight(cnt)
                sums[0] += m
                for v in ti.static(range(RV)):
                    sums[1 + v] += m * penalty_fns[voted[v]](f.acc[0, y, x, i_num + v] / cnt)

    @ti.func
    def blur_x_votes(y, x0, tv):
        """Stage 3 over Rx: the IWE channels of the votes blurred along x into ``tmp``."""
        for c in ti.static(range(C)):
            store_segment(f.tmp, c, y, x0, blur_x_segment(f.acc, True, c, y, x0, tv))

    @ti.func
    def blur_y_image(y, x0, tv):
        """Stage 4 over Rxy where the image is kept: ``tmp`` blurred along y into ``img``."""
        for c in ti.static(range(C)):
            store_segment(f.img, c, y, x0, blur_y_segment(f.tmp, c, y, x0, tv))

    @ti.func
    def image_moments(y, x0, st: ti.template()):
        """Stage 4 over Rx without Sobel, ``st = (B_y^T B_y taps, in-image y taps, moments)``: ``w = B_y^T
        B_y u`` of the blur-x output ``u = tmp`` into ``tmp2`` (the adjoint's image), and the row's ``sum
        I = sum u tapsum_y`` and ``sum I^2 = ||B_y u||^2 = sum u w`` of each channel into the moments."""
        for c in ti.static(range(C)):
            w = seg.twice_blur_y(f.tmp, st[0], c, y, x0)
            store_segment(f.tmp2, c, y, x0, w)
            for p in ti.static(range(SEG)):
                if in_image(x0 + p):
                    u = f.tmp[y, x0 + p, c]
                    st[2][2 * c] += u * st[1]
                    st[2][2 * c + 1] += u * w[p]

    @ti.func
    def x_tap_sums(x0, tv):
        """``B_x^T 1`` at the segment's pixels: the sum of the x taps that fall inside the image."""
        s = ti.Vector([0.0 for _ in ti.static(range(SEG))])
        for k in ti.static(range(-r_, r_ + 1)):
            for p in ti.static(range(SEG)):
                if 0 <= x0 + p + k < W:
                    s[p] += tv[k + r_]
        return s

    @ti.func
    def y_tap_sum(y):
        """``B_y^T 1`` at row ``y``: the sum of the y taps that fall inside the image."""
        tapsum = 0.0
        for k in ti.static(range(-r_, r_ + 1)):
            if 0 <= y + k < H:
                tapsum += f.taps[k + r_] if ti.static(r_ > 0) else 1.0
        return tapsum

    @ti.func
    def adjoint_coefficients(y):
        """Per channel, ``(scale / G0, offset / G0 * B_y^T 1 at row y)`` of dJ/dI = (scale L + offset) / G0
        (``adjoint_fn``): the two terms of the transposed blur along y of the adjoint at row ``y``."""
        tapsum = y_tap_sum(y)
        slots = objective_slots_vec()
        c1 = ti.Vector([0.0 for _ in ti.static(range(C))])
        c0 = ti.Vector([0.0 for _ in ti.static(range(C))])
        for c in ti.static(range(C)):
            scale, offset = adjoint_fn(slots, c, n_pix)
            c1[c] = scale / f.g0[None]
            c0[c] = offset / f.g0[None] * tapsum
        return c1, c0

    @ti.func
    def clear_votes(y, x, grad):
        """Stage 4 at a touched pixel: the votes stage 3's blur read, cleared: the IWE channels now, the
        maps (and a shared count) after the backward where it runs (it reads them and clears them)."""
        if ti.static(R > 0):  # noqa: SIM102 - compile-time if
            if grad & 1 == 0:
                for k in ti.static(range(i_cnt, K)):
                    f.acc[0, y, x, k] = 0.0
        for c in ti.static(range(C)):
            if ti.static(shared_count and c == i_cnt):
                if grad & 1 == 0:
                    f.acc[0, y, x, c] = 0.0
            else:
                f.acc[0, y, x, c] = 0.0

    @ti.func
    def sobel_and_terms(y, x, sums: ti.template()):
        """Stage 5 over Rs: the Sobel images (kept for the backward), the objective's terms into ``sums``."""
        for c in ti.static(range(C)):
            gx, gy = sobel_fn(f.img, c, y, x)
            f.sobel[y, x, 2 * c] = gx
            f.sobel[y, x, 2 * c + 1] = gy
            terms = pixel_fn(f.img[y, x, c], gx, gy)
            for k in ti.static(range(SL)):
                sums[SL * c + k] += terms[k]

    @ti.func
    def transposed_sobel(y, x, ibar: ti.template()):
        """Stage 7 over Rxy: ``L(I)``, the transposed Sobel of the Sobel images."""
        for c in ti.static(range(C)):
            ibar[y, x, c] = sobel_t(f.sobel, c, y, x)

    @ti.func
    def blur_y_adjoint(y, x0, st: ti.template()):
        """Stage 7 over Rx with Sobel, ``st = (taps, scale / G0, offset tap sum / G0)`` per channel: the
        transposed blur along y of dJ/dI = (scale L(I) + offset) / G0 into ``tmp2``."""
        for c in ti.static(range(C)):
            v = blur_y_segment(f.ibar, c, y, x0, st[0])
            store_segment(f.tmp2, c, y, x0, st[1][c] * v + st[2][c])

    @ti.func
    def map_adjoints(y, x, msum):
        """dJ/dC and dJ/dN_r at pixel ``(y, x)`` into ``adj``; the maps' votes cleared."""
        cnt = f.acc[0, y, x, i_cnt]
        dc = 0.0
        for v in ti.static(range(RV)):
            f.adj[y, x, i_num + v] = 0.0
        if cnt > 0.0 and msum > 0.0:
            m = _b.support_weight(cnt)
            dm = _b.support_weight_grad(cnt)
            for v in ti.static(range(RV)):
                wr = f.rw[voted[v]]
                avg = f.acc[0, y, x, i_num + v] / cnt
                pen = penalty_fns[voted[v]](avg)
                dpen = penalty_grads[voted[v]](avg)
                ratio = red[i_m + 1 + v][None] / msum
                # d(sum m P / sum m)/dC = (dm P + m P' d(avg)/dC - ratio dm) / sum m
                dc -= wr * (dm * pen - m * dpen * avg / cnt - ratio * dm) / msum
                f.adj[y, x, i_num + v] = -wr * m * dpen / (cnt * msum)
        if ti.static(shared_count):
            f.adj[y, x, i_cnt] += dc
        else:
            f.adj[y, x, i_cnt] = dc
        for k in ti.static(range(i_cnt, K)):
            f.acc[0, y, x, k] = 0.0

    @ti.func
    def blur_x_adjoint(y, x0, st: ti.template()):
        """Stage 7 over F0, ``st = (taps, sum m, scale / G0, offset tap sum / G0)``: the transposed blur
        along x into ``adj`` of ``tmp2`` (with Sobel: the blur-y adjoint; without: ``w = B_y^T B_y u``,
        of which dJ/du = scale w + offset tapsum_y), the map adjoints (and the maps cleared)."""
        for c in ti.static(range(C)):
            v = blur_x_segment(f.tmp2, False, c, y, x0, st[0])
            if ti.static(not sobel):
                v = st[2][c] * v + st[3][c] * x_tap_sums(x0, st[0])
            store_segment(f.adj, c, y, x0, v)
        if ti.static(R > 0):
            for p in ti.static(range(SEG)):
                if in_image(x0 + p):
                    map_adjoints(y, x0 + p, st[1])

    @ti.kernel
    def run(
        n: ti.i32,
        ev: ev_type,
        terms: terms_type,
        params: out_type,
        grad: ti.i32,
        out: out_type,
    ):
        # --- 1. serial: theta, the window's constants, cleared reductions -----------------------------
        for j in ti.static(range(P)):
            f.thv[None][j] = ti.cast(params[p_theta + j], real)
            gsum[j][None] = 0.0
        for j in ti.static(range(5)):
            f.ctx[None][j] = ti.cast(params[p_ctx + j], real)
        for j in ti.static(range(n_lam)):
            f.lam[None][j] = ti.cast(params[p_lam + j], real)
        f.g0[None] = ti.cast(params[p_g0], real)
        for j in ti.static(range(len(red))):
            red[j][None] = 0.0
        for j in ti.static(range(2 * C)):
            f.mom[j][None] = 0.0
        tf.pixels[R_OBJ] = 0
        # --- 2. splat ----------------------------------------------------------------------------
        if ti.static(atomic_scatter):
            for i in range(n):
                splat_event(0, ev[i], theta_vec(), f.ctx[None])
        else:
            ti.loop_config(block_dim=1, serialize=serial)  # one slice per thread (backend.per_thread_loops)
            for s in range(S):
                lo, hi = slice_events(s, n)
                theta = theta_vec()
                c = f.ctx[None]
                if ti.static(store):
                    # the warps in a loop without scattered votes, then the votes from the stored terms
                    # (value-only: no Jacobians, at the price of the last bits of the positions, see above)
                    if grad & 1 != 0:
                        for i in range(lo, hi):
                            put_terms(terms, i, ev[i], theta, c, True)
                    else:
                        for i in range(lo, hi):
                            put_terms(terms, i, ev[i], theta, c, False)
                    for i in range(lo, hi):
                        _, _, b, ch = event(ev[i])
                        q, vals = stored_position(terms, i)
                        splat_at(s, q, vals, b, ch)
                else:
                    for i in range(lo, hi):
                        splat_event(s, ev[i], theta, c)
        # --- 3. rows (each row by itself): F0 and its x-dilations; at the touched pixels the slice sums
        #        and the map reductions; tmp: what the previous call left outside Rx cleared, blur along x
        ti.loop_config(block_dim=row_block, serialize=serial)
        for y in range(H):
            tiles.build_x(tf, y)
            sums = ti.Vector([0.0 for _ in ti.static(range(1 + RV))])  # sum m, sum m P_v
            tiles.each_pixel(tf, F0, y, sum_slices_and_maps, sums)
            for k in ti.static(range(1 + RV)):
                f.part_map[y, k] = sums[k]
            tiles.each_stale_segment(tf, 0, y, clear_segment, f.tmp)  # in the previous Rx, not in this one
            tiles.each_segment(tf, RX, y, blur_x_votes, load_taps(f.taps))
        # --- 4. rows: Rxy (and Rs); the kept image over Rxy; without Sobel the image's moments; votes cleared
        ti.loop_config(block_dim=row_block, serialize=serial)
        for y in range(H):
            tiles.build_y(tf, y)
            keep = keep_image(grad)
            if keep:  # img: in the previous kept image's Rxy, not in this one's
                tiles.each_stale_segment(tf, 1, y, clear_segment, f.img)
            tv = load_taps(f.taps)
            if keep:  # (always with Sobel: its pass reads the image)
                tiles.each_segment(tf, RXY, y, blur_y_image, tv)
            if ti.static(not sobel):
                # the objective's terms are quadratic in I (its adjoint is affine in I): from the
                # image's moments, over Rx (B_y^T B_y on u: 4 r + 1 taps) rather than the image over Rxy
                mom = ti.Vector([0.0 for _ in ti.static(range(2 * C))])
                tiles.each_segment(tf, RX, y, image_moments, (twice_taps(y, tv), y_tap_sum(y), mom))
                for k in ti.static(range(2 * C)):
                    f.part_mom[y, k] = mom[k]
            tiles.each_pixel(tf, F0, y, clear_votes, grad)
        if ti.static(sobel):
            # --- 5. rows: Sobel images (kept for the backward) and the pixel terms that read them, over Rs
            ti.loop_config(block_dim=row_block, serialize=serial)
            for y in range(H):
                rsum = ti.Vector([0.0 for _ in ti.static(range(SL * C))])
                tiles.each_pixel(tf, R_OBJ, y, sobel_and_terms, rsum)
                for k in ti.static(range(SL * C)):
                    f.part_obj[y, k] = rsum[k]
        # --- 6. serial: the row sums in row order, the untouched pixels in closed form, J -------------------
        ti.loop_config(serialize=True)
        for y in range(H):
            if ti.static(sobel):
                for k in ti.static(range(SL * C)):
                    red[k][None] += f.part_obj[y, k]
                tf.pixels[R_OBJ] += tf.rowpx[R_OBJ, y]
            else:
                for k in ti.static(range(2 * C)):
                    f.mom[k][None] += f.part_mom[y, k]
            if ti.static(R > 0):
                for k in ti.static(range(1 + RV)):
                    red[i_m + k][None] += f.part_map[y, k]
        terms0 = pixel_fn(0.0, 0.0, 0.0)  # an untouched pixel: I = 0, zero Sobel responses
        if ti.static(sobel):
            untouched = n_pix - ti.cast(tf.pixels[R_OBJ], real)
            for k in ti.static(range(SL * C)):
                red[k][None] += untouched * terms0[k % SL]
        else:
            # terms(v) = t0 + c1 v + c2 v^2 (exact for a quadratic: from its values at 0, 1, -1), summed
            # over every pixel: N t0 + c1 sum I + c2 sum I^2
            terms1 = pixel_fn(1.0, 0.0, 0.0)
            terms_1 = pixel_fn(-1.0, 0.0, 0.0)
            for c in ti.static(range(C)):
                for k in ti.static(range(SL)):
                    c1 = 0.5 * (terms1[k] - terms_1[k])
                    c2 = 0.5 * (terms1[k] + terms_1[k]) - terms0[k]
                    red[SL * c + k][None] = (
                        n_pix * terms0[k] + c1 * f.mom[2 * c][None] + c2 * f.mom[2 * c + 1][None]
                    )
        slots = objective_slots_vec()
        g = 0.0
        for c in ti.static(range(C)):
            g += finalize_fn(slots, c, n_pix)
        jval = g / f.g0[None]
        f.graw[None] = g
        if ti.static(R > 0):
            msum = red[i_m][None]
            theta = theta_vec()
            c = f.ctx[None]
            centre = ti.Vector([c[0], c[1]])
            for r in ti.static(range(R)):
                ratio = 0.0  # sum m P_r / sum m
                qc = 0.0
                if ti.static(constant[r]):
                    qc = quantity_fns[r](centre, 0.0, theta, c)
                    if msum > 0.0:
                        ratio = penalty_fns[r](qc)
                else:
                    ratio = _b.support_ratio(red[i_m + 1 + ti.static(vpos[r])][None], msum)
                s_r = f.lam[None][R + r]
                rr = _b.scaled_penalty(ratio, s_r, ti.static(one_sided[r]))
                wr = f.lam[None][r] * _b.scaled_penalty_slope(ratio, s_r, ti.static(one_sided[r]))
                jval -= f.lam[None][r] * rr
                f.rvals[r] = rr
                f.rw[r] = wr
                if ti.static(constant[r]):  # noqa: SIM102 - compile-time if
                    if grad & 1 != 0 and msum > 0.0:
                        # R_r = s_r P_r(q_r): dJ/dtheta = -w_r P_r'(q_r) dq_r/dtheta
                        _, ddet, ddiv = param_jac(centre, 0.0, theta, c)
                        dpen = penalty_grads[r](qc)
                        for j in ti.static(range(P)):
                            dq = ddiv[j] if ti.static(quantity_kinds[r] == "div") else ddet[j]
                            gsum[j][None] += ti.cast(-wr * dpen * dq, ti.f64)
        f.loss[None] = jval
        # --- 7. rows (grad): adjoint images ------------------------------------------------------------
        if ti.static(sobel):
            # L(I): transposed Sobel of the Sobel images, over Rxy (where the transposed blur reads it)
            ti.loop_config(block_dim=row_block, serialize=serial)
            for y in range(H):
                if grad & 1 != 0:
                    tiles.each_pixel(tf, RXY, y, transposed_sobel, f.ibar)
        if ti.static(sobel):
            ti.loop_config(block_dim=row_block, serialize=serial)
            for y in range(H):
                if grad & 1 != 0:
                    # transposed blur along y of dJ/dI = (scale L(I) + offset) / G0 into tmp2 over Rx
                    c1, c0 = adjoint_coefficients(y)
                    tiles.each_segment(tf, RX, y, blur_y_adjoint, (load_taps(f.taps), c1, c0))
        ti.loop_config(block_dim=row_block, serialize=serial)
        for y in range(H):
            if grad & 1 != 0:
                # transposed blur along x into adj at the touched pixels; map adjoints; clear the maps.
                # Without Sobel, dJ/dI = (scale I + offset) / G0 and tmp2 = B_y^T B_y u (stage 4): the
                # transposed blur along y of dJ/dI is (scale tmp2 + offset tapsum_y) / G0, by linearity
                msum = red[i_m][None] if ti.static(R > 0) else 0.0
                c1 = ti.Vector([0.0 for _ in ti.static(range(C))])
                c0 = ti.Vector([0.0 for _ in ti.static(range(C))])
                if ti.static(not sobel):
                    c1, c0 = adjoint_coefficients(y)
                tiles.each_segment(tf, F0, y, blur_x_adjoint, (load_taps(f.taps), msum, c1, c0))
        # --- 8. events (grad, closed-form Jacobians): dJ/dtheta ---------------------------------------
        if ti.static(atomic_scatter):
            for i in range(n):
                if grad & 1 != 0:
                    gev = event_grad(ev[i], theta_vec(), f.ctx[None])
                    for j in ti.static(range(P)):
                        gsum[j][None] += gev[j]
        else:
            ti.loop_config(block_dim=1, serialize=serial)  # one slice per thread (backend.per_thread_loops)
            for s in range(S):
                if grad & 1 != 0:
                    lo, hi = slice_events(s, n)
                    theta = theta_vec()
                    c = f.ctx[None]
                    gacc = ti.Vector([0.0 for _ in ti.static(range(P))], dt=ti.f64)
                    if ti.static(store):
                        for i in range(lo, hi):
                            gacc += stored_event_grad(terms, i, ev[i])
                    else:
                        for i in range(lo, hi):
                            gacc += event_grad(ev[i], theta, c)
                    for j in ti.static(range(P)):
                        f.gpart[s, j] = gacc[j]
        # --- 9. serial: results (the slices' sums in slice order) ------------------------------------------
        out[0] = ti.cast(f.loss[None], ti.f64)
        out[1] = ti.cast(f.graw[None], ti.f64)
        for j in ti.static(range(P)):
            gj = gsum[j][None]
            if ti.static(not atomic_scatter):  # noqa: SIM102 - compile-time if
                if grad & 1 != 0:
                    for s in ti.static(range(S)):
                        gj += f.gpart[s, j]
            out[2 + j] = gj
        # J as if G0 were this G: at the identity, the J of every later evaluation there (the same
        # operations as stage 6, in the same order), so that the driver need not evaluate it again
        jself = f.graw[None] / f.graw[None]
        if ti.static(R > 0):
            for r in ti.static(range(R)):
                jself -= f.lam[None][r] * f.rvals[r]
        out[2 + P] = ti.cast(jself, ti.f64)

    return run
