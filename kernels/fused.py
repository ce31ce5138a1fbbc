"""The fused CMax pipeline: value and gradient in one kernel launch, with a hand-written backward.

Why: the chain of small kernels of ``iwe.py`` / ``objectives.py`` / ``maps.py`` differentiated by
Taichi's reverse mode spends its time in atomics (compare-and-swap loops for float adds on the CPU,
~15 ns each: every scatter, every transposed blur, every reduction) and in kernel launches (~10-40 us
each from Python). Here one kernel ``run(n, ev, terms, params, grad, out, width, height, votes, images,
rows, state, words, rowpx)`` holds every stage as its own task (Taichi runs the top-level loops of a
kernel one after the other, each in parallel). It reads no Taichi field: the image, row and mask
arrays are its arguments, sized for the sensor by the driver (:meth:`FusedShape.array_sizes`), and
the sensor's ``width`` and ``height`` are arguments too, so one compiled kernel serves every sensor
(``fused_common``), or compiled-in constants (``sizes``: the optimized kernel of one sensor, whose
image indices fold). Its stages:

1. splat: each event is warped and votes bilinearly into the IWE channels, the count ``C`` and the
   map numerators of the votes (``votes``: per slice ``s``, planes ``k`` of ``H x W``), and marks the
   segments it touches (``tiles.py``). On the CPU the events are split into one chunk per thread ``s``,
   each voting with plain loads and stores into its own slice; on a GPU one slice takes atomic adds.
   Without weights and per-polarity channels the IWE votes equal the count votes, and one channel
   serves both. Where the model declares ``store_event_terms`` (CPU, ``store_terms=True``), a loop of
   its own first writes each event's warped position, voted quantities and (when the gradient is
   asked) parameter Jacobians into ``terms`` (:func:`~cmax_taichi.kernels.fused_events.terms_width`
   rows, one column per event), and the splat reads them: an event's costly warp is evaluated once per
   call, not again in stage 8, and the loop that evaluates it carries no scattered votes. A value-only
   launch leaves the Jacobians out (dead code): fast math then compiles the position's arithmetic
   differently, and its value may differ from that of ``value_and_grad`` in the last bits (a few ulps);
2. rows: the touched segments ``F0`` of the row and their x-dilations; at the touched pixels, sum the
   slices and reduce the maps (``sum m``, ``sum m P_r``) into the row's partial sums (``rows``); clear
   what the previous call left in ``tmp`` outside the new ``Rx`` (``F0`` and ``r`` columns); blur along
   x into ``tmp`` over ``Rx``;
3. rows: the regions of the row with y-dilation; where the image is kept (a Sobel objective, or
   ``FusedPipeline.image``) blur along y into ``img`` over ``Rxy`` (``Rx`` and ``r`` rows), after clearing
   what the previous kept image left outside it. Without Sobel the objective's terms are quadratic in
   the image (its adjoint is affine in it), so their sum over the image needs only ``sum I`` and ``sum
   I^2`` of each channel: with ``u = tmp`` and ``I = B_y u``, ``sum I = sum u tapsum_y`` and ``sum I^2 =
   ||B_y u||^2 = sum u w``, ``w = B_y^T B_y u`` (``4 r + 1`` taps at ``Rx``'s pixels, into ``tmp2``, where
   the backward reads it): the row's moments into its partial sums, over ``Rx`` rather than ``Rxy``.
   The touched votes cleared;
4. rows (Sobel): the Sobel images over ``Rs`` (one more pixel around ``Rxy``), kept for the backward, and
   the objective's per-pixel terms into the row's partial sums;
5. serial: the partial sums in row order (a fixed order: the same input gives the same J to the last
   bit); the terms of the pixels no pass visited in closed form (``pixel(0, 0, 0)`` times their number),
   or without Sobel every pixel's terms from the moments (``N t(0) + c1 sum I + c2 sum I^2``, the
   quadratic's coefficients from ``pixel`` at 0, 1 and -1); J, into ``state`` for the passes after;
6. rows (``grad``): the pixel adjoint dJ/dI (affine in the image or in its transposed Sobel, as the
   objective declares) and its transposed blurs (the Gaussian is symmetric, so its transpose with
   zero padding is the same correlation): along y over ``Rx`` (without Sobel by linearity from stage
   3's ``w``: ``(scale w + offset tapsum_y) / G0``), along x over ``F0``, with the map adjoints dJ/dC,
   dJ/dN_r, into ``adj`` at the touched pixels, the only ones the gather reads;
7. events (``grad``): dJ/dtheta as a *gather* (``fused_events.py``):
   ``dJ/dtheta = sum_k sum_corners d/dtheta [beta_k (b_k adj_ch + |b_k| adj_C + |b_k| sum_r q_rk adj_r)]``
   with ``adj`` held fixed, using the closed-form parameter Jacobians each model declares; on the CPU
   each slice's sum goes into its own slot of ``out``, added in slice order. The gather has no branch,
   so that LLVM vectorizes its loops (the loops of the other stages store, and stay scalar);
8. serial: ``out = (J, G_raw, dJ/dtheta, J with G0 = G_raw)`` (the last: at the identity, the
   normalised J of every later evaluation there).

The image passes are row loops over the set bits of the row's region words: their work follows the
pixels the events reach, not ``W x H``. The votes are cleared by the passes that consume them at the
touched pixels; ``tmp`` and ``img`` are zero outside the regions the last call wrote (stages 2 and 3
clear what the call before left outside the new regions), so that every read outside a region reads
0; ``tmp2``, ``sobel``, ``ibar`` and ``adj`` are read only inside the regions written in the same call.
No call launches a fill, and nothing is allocated per call (the driver allocates the arrays zeroed
once per sensor).

Warps without closed-form parameter Jacobians (user models) take the generic chain of ``problem.py``.
The formulas (bilinear weights, blur taps, support weight, objectives, loss) are the blocks of
``blocks.py`` shared with the generic chain; nothing here branches on an objective's name.
Formulas: docs/FORMULAS.md; derivatives of the map penalties: ``maps.py``.
"""

from dataclasses import astuple, dataclass

import taichi as ti

from . import blocks as _b
from . import fused_common as _c
from . import tiles as _t
from .fused_events import EventPasses, composed_warp_terms, terms_width
from .fused_rows import SegmentPasses

__all__ = ["MAX_PARAMS", "FusedShape", "channel_layout", "make_fused_kernels", "params_layout", "terms_width"]

MAX_PARAMS = 8  # theta's slots in ``params``
QUANTITY_KINDS = ("div", "absdet")  # per-event quantities the hand-written backward differentiates


def params_layout(n_regs: int, radius: int = 0) -> dict:
    """Where each value sits in the kernel's float64 ``params`` array (a NumPy array the driver fills:
    one argument in place of a launch per value): ``theta`` (``MAX_PARAMS`` slots), ``ctx`` (``cx, cy,
    fx, fy, T``), ``g0``, ``lam`` (``lambda_r`` then ``s_r``), ``taps`` (``2 radius + 1``); ``size`` the
    length."""
    n_lam = max(2 * n_regs, 1)
    taps = MAX_PARAMS + 6 + n_lam
    return {"theta": 0, "ctx": MAX_PARAMS, "g0": MAX_PARAMS + 5, "lam": MAX_PARAMS + 6,
            "n_lam": n_lam, "taps": taps, "size": taps + 2 * int(radius) + 1}  # fmt: skip


def channel_layout(n_channels: int, n_regs: int, n_voted: int, shared_count: bool) -> tuple[int, int, int]:
    """``(i_count, i_numer, n_acc)``: where the count and the first voted numerator live, and the
    channel count of the votes / their adjoints (IWE channels first)."""
    if n_regs == 0:
        return -1, -1, n_channels
    i_count = 0 if shared_count else n_channels
    return i_count, i_count + 1, i_count + 1 + n_voted


@dataclass(frozen=True)
class FusedShape:
    """The compile-time shape of one fused pipeline (its kernels' key, with the model and the entries),
    and the arrays a sensor needs.

    Parameters
    ----------
    layout : fused_common.ImageLayout
        Channels, blur radius, splat slices, objective slots, Sobel images.
    n_regs, n_voted, n_params : int
        Regularizers, regularizer quantities voted into maps (the others are the same for every event),
        warp parameters.
    """

    layout: _c.ImageLayout
    n_regs: int
    n_voted: int
    n_params: int

    @property
    def n_acc(self) -> int:
        """Vote planes per slice (IWE channels, count, numerators)."""
        return channel_layout(self.layout.n_channels, self.n_regs, self.n_voted, self.layout.shared_count)[2]

    @property
    def image_planes(self) -> tuple[int, ...]:
        """Plane counts of the ``images`` array: ``tmp``, ``tmp2``, ``img``, ``adj`` and, with Sobel,
        the Sobel images and ``ibar``."""
        C = self.layout.n_channels
        return (C, C, C, self.n_acc) + ((2 * C, C) if self.layout.sobel else ())

    @property
    def row_slots(self) -> tuple[int, int, int]:
        """Per-row partial sums: the objective's slots (Sobel), the moments (without), the maps."""
        C = self.layout.n_channels
        return self.layout.objective_slots * C, 2 * C, 1 + self.n_voted

    @property
    def state_size(self) -> int:
        """Length of ``state``: the objective's slots, ``sum m`` and ``sum m P_v``, then per regularizer
        its slope weight and its ``R_r``, then J and G."""
        slots, _, maps = self.row_slots
        return slots + maps + 2 * max(self.n_regs, 1) + 2

    def tile_layout(self) -> _t.TileLayout:
        """The mask regions of the passes: ``F0``, ``Rx`` (blur x), ``Rxy`` (blur y), ``Rs`` (Sobel);
        ``tmp`` (written over ``Rx``) and ``img`` (over ``Rxy``) keep the previous call's regions for the
        clears of stages 2 and 3."""
        radius, sobel = self.layout.radius, self.layout.sobel
        kx = _t.reach(radius)
        regions = [(0, 0), (kx, 0), (kx, radius)] + ([(kx + 1, radius + 1)] if sobel else [])
        return _t.TileLayout(tuple(regions), history=(1, 2))

    def array_sizes(self, width: int, height: int) -> dict:
        """``{name: (kind, length)}`` of the kernel's arrays for a ``width x height`` sensor; ``kind`` is
        ``"real"``, ``"u32"`` or ``"i32"``. All start zeroed."""
        plane = int(width) * int(height)
        tiles = self.tile_layout()
        return {
            "votes": ("real", self.layout.n_slices * self.n_acc * plane),
            "images": ("real", sum(self.image_planes) * plane),
            "rows": ("real", int(height) * sum(self.row_slots)),
            "state": ("real", self.state_size),
            "words": ("u32", tiles.n_words_total(width, height)),
            "rowpx": ("i32", tiles.n_rowpx(height)),
        }

    def out_size(self) -> int:
        """Length of the float64 ``out``: J, G, dJ/dtheta, J at G0 = G, then the slices' gradients."""
        return 3 + self.n_params + self.layout.n_slices * self.n_params


def make_fused_kernels(
    shape: FusedShape,
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
    sizes: tuple[int, int] | None = None,
):
    """The kernel ``run`` of the fused pipeline of ``shape`` (see the module docstring).

    ``ev`` is an ndarray of per-event vectors as ``events`` lays them out (``fused_common.EventLayout``,
    which also says whether the event passes add atomically). The ``objective`` comes as its blocks
    (``blocks.py``; ``models.objectives.FusedObjective``): ``objective.pixel(v, gx, gy)``
    (``objective_slots`` terms per channel, Sobel responses where ``sobel``), ``objective.finalize(a,
    c, n_pixels)`` and ``objective.adjoint(a, c, n_pixels) -> (scale, offset)`` with ``dG_c/dI = scale
    * L(I) + offset`` (``L``: identity, or the transposed Sobel of the Sobel images where ``sobel``).
    Regularizer ``r`` enters J as ``-lambda_r R_r`` with ``R_r = s_r sum m P_r / sum m``
    (``max(0, R_r)`` where ``one_sided[r]``); ``params`` holds ``lambda_r`` then ``s_r``
    (:func:`params_layout`). ``param_jac`` is the model's closed-form parameter Jacobian
    (``WarpModel.param_jac``, e.g. in ``kernels/warps/zoom1.py``) and ``quantity_kinds`` names each
    quantity "div" or "absdet". ``constant[r]`` says quantity ``r`` is the same for every event: its
    map is that value wherever ``C > 0``, so ``R_r = s_r P_r(q_r)`` (``sum m > 0``) and nothing is voted
    for it. ``det_fn`` is the model's ``det`` (the "absdet" quantities are its absolute value, and where
    ``positive_det`` is False ``d|det|/dtheta = sign(det) ddet``). ``warp_terms(p, dt, th, ctx) -> (warp,
    det, jx, ddet, ddiv)`` is the model's optional joint evaluation (e.g. ``kernels/warps/rotation3.py``);
    without it the kernels compose it from ``warp_fn``, ``det_fn`` and ``param_jac``.
    ``store_terms`` (the model's ``store_event_terms``; ignored with atomic adds) evaluates it once per
    event and call into the ``terms`` argument (a ``(terms_width(P, n_voted), n)`` array of the kernel's
    float type; otherwise any ``(1, 1)`` one). ``serial`` runs every loop on the calling thread (CPU).
    ``sizes``: the sensor ``(width, height)`` compiled in as constants (the kernel of one sensor: the
    image indices fold into constants), or None (the kernel reads them from
    its ``width`` and ``height`` arguments: one compiled kernel serves every sensor). The arguments are
    the same either way.
    """
    P, RV = shape.n_params, shape.n_voted
    real, C, r_, S, shared_count, SL, sobel = astuple(shape.layout)
    weighted, split_polarity, atomic_scatter = astuple(events)
    pixel_fn, finalize_fn, adjoint_fn = _c.objective_blocks(objective, sobel)
    if P > MAX_PARAMS:
        raise ValueError(f"the fused pipeline takes at most {MAX_PARAMS} parameters")
    if shared_count and (weighted or split_polarity or not quantity_fns):
        raise ValueError("the count shares the IWE channel only with unit weights and one channel")
    R = len(quantity_fns)
    if shape.n_regs != R:
        raise ValueError(f"{R} regularizer quantities for a shape of {shape.n_regs} regularizers")
    if param_jac is None:
        raise ValueError("the fused pipeline needs the model's closed-form parameter Jacobian")
    if len(quantity_kinds) != R or any(k not in QUANTITY_KINDS for k in quantity_kinds):
        raise ValueError(f"quantity_kinds must name each quantity one of {QUANTITY_KINDS}")
    constant = tuple(bool(c) for c in constant) if constant else (False,) * R
    if len(constant) != R:
        raise ValueError("constant needs one flag per quantity")
    voted = tuple(r for r in range(R) if not constant[r])  # voted quantity -> its regularizer
    if len(voted) != RV:
        raise ValueError(f"{len(voted)} voted quantities for a shape of {RV}")
    if det_fn is None and any(quantity_kinds[r] == "absdet" for r in voted):
        raise ValueError("a voted 'absdet' quantity needs the model's det (det_fn)")
    if warp_terms is None:
        warp_terms = composed_warp_terms(warp_fn, det_fn, param_jac)
    if sizes is not None:
        sizes = (int(sizes[0]), int(sizes[1]))

    def bind_sizes(w_, h_):
        """Bind the sensor the passes index with: the compiled-in ``sizes``, or the run-time sizes as the
        loop body's own locals (kept in registers: an argument is reloaded after every store to an
        array, which may alias it)."""
        if sizes is None:
            return args.bind(width=w_, height=h_)
        return args.bind(width=sizes[0], height=sizes[1])

    # row passes: a few rows per task on the CPU (their partial sums are per row, so the threads'
    # scheduling cannot change J); a GPU keeps its default
    row_block = None if atomic_scatter else 4
    vpos = tuple(voted.index(r) if r in voted else -1 for r in range(R))  # regularizer -> voted slot
    i_cnt, i_num, K = channel_layout(C, R, RV, shared_count)
    real_type, ev_type, f64 = _c.real_array(real), events.ndarray_type(real), _c.F64_ARRAY
    terms_type = _c.real_array(real, ndim=2)
    store = bool(store_terms) and not atomic_scatter
    slots_at = params_layout(R, r_)
    p_theta, p_ctx, p_g0, p_lam = slots_at["theta"], slots_at["ctx"], slots_at["g0"], slots_at["lam"]
    SLC = SL * C
    ROW = sum(shape.row_slots)
    ROW_MOM, ROW_MAP = SLC, SLC + 2 * C  # the row's moments, its map sums
    ST_MAP = SLC  # state: slots [0, SLC), sum m, sum m P_v, then rw_r, R_r, J, G
    Rm = max(R, 1)
    ST_RW, ST_RV = ST_MAP + 1 + RV, ST_MAP + 1 + RV + Rm
    ST_LOSS, ST_GRAW = ST_RV + Rm, ST_RV + Rm + 1
    G_SLICES = 3 + P  # out: the slices' gradients from here

    args = _c.KernelArgs()  # the kernel's arrays and sizes (bound at the top of its body)
    base = 0
    views = []
    for count in shape.image_planes:
        views.append(_c.Planes(args, "images", base, count))
        base += count
    tmp, tmp2, img, adj = views[:4]
    sob, ibar = views[4:] if sobel else (None, None)
    acc = _c.Planes(args, "votes", 0, S * K)
    sobel_fn = _b.make_sobel(_c.read_plane, args)
    sobel_t = _b.make_sobel_transpose(_c.read_gx, _c.read_gy, args)
    slice_events = events.slices(S)  # the events [lo, hi) of thread slice s
    row = events.row()  # event i of ev as a vector
    ops = EventPasses(
        args, warp_terms, quantity_fns, quantity_kinds, voted, positive_det,
        real=real, n_params=P, channels=(i_cnt, i_num, shared_count), events=events, acc=acc, adj=adj,
        per_slice=K,
    )  # fmt: skip
    tiles = _t.ops_for(shape.tile_layout())
    SEG = _t.SEG
    F0, RX, RXY = 0, 1, 2
    R_OBJ = 3 if sobel else RXY  # the region of the objective's pixel terms
    seg = SegmentPasses(real, r_, slots_at["taps"], args)  # blurs, stores and clears of one segment
    load_taps, blur_x_segment, blur_y_segment = seg.load_taps, seg.blur_x, seg.blur_y
    store_segment, clear_segment, twice_taps = seg.store, seg.clear, seg.twice_taps

    @ti.func
    def param(k):
        return ti.cast(args.params[k], real)

    @ti.func
    def theta_vec():
        return ti.Vector([param(p_theta + j) for j in ti.static(range(P))])

    @ti.func
    def ctx_vec():
        return ti.Vector([param(p_ctx + j) for j in ti.static(range(5))])

    @ti.func
    def state_at(k):
        return args.state[k]

    @ti.func
    def objective_slots_vec():
        return ti.Vector([state_at(j) for j in ti.static(range(SLC))])

    @ti.func
    def n_pixels():
        return ti.cast(args.width * args.height, real)

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
        """Stage 2 at a touched pixel: the slices summed into slice 0; ``sums`` += (m, m P_v)."""
        if ti.static(S > 1):
            for k in ti.static(range(K)):
                v = _c.load(acc, k, y, x)
                for s in ti.static(range(1, S)):
                    v += _c.load(acc, s * K + k, y, x)
                    _c.store(acc, s * K + k, y, x, 0.0)
                _c.store(acc, k, y, x, v)
        if ti.static(R > 0):
            cnt = _c.load(acc, i_cnt, y, x)
            if cnt > 0.0:
                m = _b.support_weight(cnt)
                sums[0] += m
                for v in ti.static(range(RV)):
                    sums[1 + v] += m * penalty_fns[voted[v]](_c.load(acc, i_num + v, y, x) / cnt)

    @ti.func
    def blur_x_votes(y, x0, tv):
        """Stage 2 over Rx: the IWE channels of the votes (slice 0) blurred along x into ``tmp``."""
        for c in ti.static(range(C)):
            store_segment(tmp, c, y, x0, blur_x_segment(acc, c, y, x0, tv))

    @ti.func
    def blur_y_image(y, x0, tv):
        """Stage 3 over Rxy where the image is kept: ``tmp`` blurred along y into ``img``."""
        for c in ti.static(range(C)):
            store_segment(img, c, y, x0, blur_y_segment(tmp, c, y, x0, tv))

    @ti.func
    def image_moments(y, x0, st: ti.template()):
        """Stage 3 over Rx without Sobel, ``st = (B_y^T B_y taps, in-image y taps, moments)``: ``w = B_y^T
        B_y u`` of the blur-x output ``u = tmp`` into ``tmp2`` (the adjoint's image), and the row's ``sum
        I = sum u tapsum_y`` and ``sum I^2 = ||B_y u||^2 = sum u w`` of each channel into the moments."""
        for c in ti.static(range(C)):
            w = seg.twice_blur_y(tmp, st[0], c, y, x0)
            store_segment(tmp2, c, y, x0, w)
            for p in ti.static(range(SEG)):
                if _t.in_image(x0 + p, args.width):
                    u = _c.load(tmp, c, y, x0 + p)
                    st[2][2 * c] += u * st[1]
                    st[2][2 * c + 1] += u * w[p]

    @ti.func
    def adjoint_coefficients(y, tv):
        """Per channel, ``(scale / G0, offset / G0 * B_y^T 1 at row y)`` of dJ/dI = (scale L + offset) / G0
        (``adjoint_fn``): the two terms of the transposed blur along y of the adjoint at row ``y``."""
        tapsum = seg.y_tap_sum(y, tv, args.height)
        slots = objective_slots_vec()
        g0 = param(p_g0)
        c1 = ti.Vector([0.0 for _ in ti.static(range(C))])
        c0 = ti.Vector([0.0 for _ in ti.static(range(C))])
        for c in ti.static(range(C)):
            scale, offset = adjoint_fn(slots, c, n_pixels())
            c1[c] = scale / g0
            c0[c] = offset / g0 * tapsum
        return c1, c0

    @ti.func
    def clear_votes(y, x, grad):
        """Stage 3 at a touched pixel: the votes stage 2's blur read, cleared: the IWE channels now, the
        maps (and a shared count) after the backward where it runs (it reads them and clears them)."""
        if ti.static(R > 0):  # noqa: SIM102 - compile-time if
            if grad & 1 == 0:
                for k in ti.static(range(i_cnt, K)):
                    _c.store(acc, k, y, x, 0.0)
        for c in ti.static(range(C)):
            if ti.static(shared_count and c == i_cnt):
                if grad & 1 == 0:
                    _c.store(acc, c, y, x, 0.0)
            else:
                _c.store(acc, c, y, x, 0.0)

    @ti.func
    def sobel_and_terms(y, x, sums: ti.template()):
        """Stage 4 over Rs: the Sobel images (kept for the backward), the objective's terms into ``sums``."""
        for c in ti.static(range(C)):
            gx, gy = sobel_fn(img, c, y, x)
            _c.store(sob, 2 * c, y, x, gx)
            _c.store(sob, 2 * c + 1, y, x, gy)
            terms = pixel_fn(_c.load(img, c, y, x), gx, gy)
            for k in ti.static(range(SL)):
                sums[SL * c + k] += terms[k]

    @ti.func
    def transposed_sobel(y, x, _unused):
        """Stage 6 over Rxy: ``L(I)``, the transposed Sobel of the Sobel images, into ``ibar``."""
        for c in ti.static(range(C)):
            _c.store(ibar, c, y, x, sobel_t(sob, c, y, x))

    @ti.func
    def blur_y_adjoint(y, x0, st: ti.template()):
        """Stage 6 over Rx with Sobel, ``st = (taps, scale / G0, offset tap sum / G0)`` per channel: the
        transposed blur along y of dJ/dI = (scale L(I) + offset) / G0 into ``tmp2``."""
        for c in ti.static(range(C)):
            v = blur_y_segment(ibar, c, y, x0, st[0])
            store_segment(tmp2, c, y, x0, st[1][c] * v + st[2][c])

    @ti.func
    def map_adjoints(y, x, msum):
        """dJ/dC and dJ/dN_r at pixel ``(y, x)`` into ``adj``; the maps' votes cleared."""
        cnt = _c.load(acc, i_cnt, y, x)
        dc = 0.0
        for v in ti.static(range(RV)):
            _c.store(adj, i_num + v, y, x, 0.0)
        if cnt > 0.0 and msum > 0.0:
            m = _b.support_weight(cnt)
            dm = _b.support_weight_grad(cnt)
            for v in ti.static(range(RV)):
                wr = state_at(ST_RW + voted[v])
                avg = _c.load(acc, i_num + v, y, x) / cnt
                pen = penalty_fns[voted[v]](avg)
                dpen = penalty_grads[voted[v]](avg)
                ratio = state_at(ST_MAP + 1 + v) / msum
                # d(sum m P / sum m)/dC = (dm P + m P' d(avg)/dC - ratio dm) / sum m
                dc -= wr * (dm * pen - m * dpen * avg / cnt - ratio * dm) / msum
                _c.store(adj, i_num + v, y, x, -wr * m * dpen / (cnt * msum))
        if ti.static(shared_count):
            _c.store(adj, i_cnt, y, x, _c.load(adj, i_cnt, y, x) + dc)
        else:
            _c.store(adj, i_cnt, y, x, dc)
        for k in ti.static(range(i_cnt, K)):
            _c.store(acc, k, y, x, 0.0)

    @ti.func
    def blur_x_adjoint(y, x0, st: ti.template()):
        """Stage 6 over F0, ``st = (taps, sum m, scale / G0, offset tap sum / G0)``: the transposed blur
        along x into ``adj`` of ``tmp2`` (with Sobel: the blur-y adjoint; without: ``w = B_y^T B_y u``,
        of which dJ/du = scale w + offset tapsum_y), the map adjoints (and the maps cleared)."""
        for c in ti.static(range(C)):
            v = blur_x_segment(tmp2, c, y, x0, st[0])
            if ti.static(not sobel):
                v = st[2][c] * v + st[3][c] * seg.x_tap_sums(x0, st[0], args.width)
            store_segment(adj, c, y, x0, v)
        if ti.static(R > 0):
            for p in ti.static(range(SEG)):
                if _t.in_image(x0 + p, args.width):
                    map_adjoints(y, x0 + p, st[1])

    @ti.func
    def finish_value(grad):
        """Stage 5 (serial): the rows' sums in row order, J, and the regularizers' terms into ``state``;
        returns the gradient of the constant quantities' penalties."""
        H = args.height
        slots = ti.Vector([0.0 for _ in ti.static(range(SLC))])
        mom = ti.Vector([0.0 for _ in ti.static(range(2 * C))])
        maps = ti.Vector([0.0 for _ in ti.static(range(1 + RV))])
        touched = 0  # pixels of the objective's region
        for y in range(H):
            if ti.static(sobel):
                for k in ti.static(range(SLC)):
                    slots[k] += args.rows[y * ROW + k]
                touched += tiles.row_pixel_count(args, R_OBJ, y)
            else:
                for k in ti.static(range(2 * C)):
                    mom[k] += args.rows[y * ROW + ROW_MOM + k]
            if ti.static(R > 0):
                for k in ti.static(range(1 + RV)):
                    maps[k] += args.rows[y * ROW + ROW_MAP + k]
        n_pix = n_pixels()
        terms0 = pixel_fn(0.0, 0.0, 0.0)  # an untouched pixel: I = 0, zero Sobel responses
        if ti.static(sobel):
            untouched = n_pix - ti.cast(touched, real)
            for k in ti.static(range(SLC)):
                slots[k] += untouched * terms0[k % SL]
        else:
            # terms(v) = t0 + c1 v + c2 v^2 (exact for a quadratic: from its values at 0, 1, -1), summed
            # over every pixel: N t0 + c1 sum I + c2 sum I^2
            terms1 = pixel_fn(1.0, 0.0, 0.0)
            terms_1 = pixel_fn(-1.0, 0.0, 0.0)
            for c in ti.static(range(C)):
                for k in ti.static(range(SL)):
                    c1 = 0.5 * (terms1[k] - terms_1[k])
                    c2 = 0.5 * (terms1[k] + terms_1[k]) - terms0[k]
                    slots[SL * c + k] = n_pix * terms0[k] + c1 * mom[2 * c] + c2 * mom[2 * c + 1]
        for k in ti.static(range(SLC)):
            args.state[k] = slots[k]
        for k in ti.static(range(1 + RV)):
            args.state[ST_MAP + k] = maps[k]
        g = 0.0
        for c in ti.static(range(C)):
            g += finalize_fn(slots, c, n_pix)
        jval = g / param(p_g0)
        gconst = ti.Vector([0.0 for _ in ti.static(range(P))], dt=ti.f64)
        if ti.static(R > 0):
            msum = maps[0]
            theta = theta_vec()
            c = ctx_vec()
            centre = ti.Vector([c[0], c[1]])
            for r in ti.static(range(R)):
                ratio = 0.0  # sum m P_r / sum m
                qc = 0.0
                if ti.static(constant[r]):
                    qc = quantity_fns[r](centre, 0.0, theta, c)
                    if msum > 0.0:
                        ratio = penalty_fns[r](qc)
                else:
                    ratio = _b.support_ratio(maps[1 + ti.static(vpos[r])], msum)
                lam_r, s_r = param(p_lam + r), param(p_lam + R + r)
                rr = _b.scaled_penalty(ratio, s_r, ti.static(one_sided[r]))
                wr = lam_r * _b.scaled_penalty_slope(ratio, s_r, ti.static(one_sided[r]))
                jval -= lam_r * rr
                args.state[ST_RV + r] = rr
                args.state[ST_RW + r] = wr
                if ti.static(constant[r]):  # noqa: SIM102 - compile-time if
                    if grad & 1 != 0 and msum > 0.0:
                        # R_r = s_r P_r(q_r): dJ/dtheta = -w_r P_r'(q_r) dq_r/dtheta
                        _, ddet, ddiv = param_jac(centre, 0.0, theta, c)
                        dpen = penalty_grads[r](qc)
                        for j in ti.static(range(P)):
                            dq = ddiv[j] if ti.static(quantity_kinds[r] == "div") else ddet[j]
                            gconst[j] += ti.cast(-wr * dpen * dq, ti.f64)
        args.state[ST_LOSS] = jval
        args.state[ST_GRAW] = g
        return gconst

    @ti.kernel
    def run(
        n: ti.i32,
        ev: ev_type,
        terms: terms_type,
        params: f64,
        grad: ti.i32,
        out: f64,
        width: ti.i32,
        height: ti.i32,
        votes: real_type,
        images: real_type,
        rows: real_type,
        state: real_type,
        words: _c.U32_ARRAY,
        rowpx: _c.I32_ARRAY,
    ):
        ti.static(args.bind(params=params, votes=votes, images=images, rows=rows, state=state, words=words,
                            rowpx=rowpx))  # fmt: skip
        ti.static(bind_sizes(width, height))
        gconst = ti.Vector([0.0 for _ in ti.static(range(P))], dt=ti.f64)  # constant quantities' penalties
        gatomic = ti.Vector([0.0 for _ in ti.static(range(P))], dt=ti.f64)  # the GPU's event gradients
        # --- 1. splat ----------------------------------------------------------------------------
        if ti.static(atomic_scatter):
            for i in range(n):
                w_, h_ = width, height
                ti.static(bind_sizes(w_, h_))
                ops.splat_event(0, row(ev, i), theta_vec(), ctx_vec())
        else:
            ti.loop_config(block_dim=1, serialize=serial)  # one slice per thread (backend.per_thread_loops)
            for s in range(S):
                w_, h_ = width, height
                ti.static(bind_sizes(w_, h_))
                lo, hi = slice_events(s, n)
                theta = theta_vec()
                c = ctx_vec()
                if ti.static(store):
                    # the warps in a loop without scattered votes, then the votes from the stored terms
                    # (value-only: no Jacobians, at the price of the last bits of the positions, see above)
                    if grad & 1 != 0:
                        for i in range(lo, hi):
                            ops.put_terms(terms, i, row(ev, i), theta, c, True)
                    else:
                        for i in range(lo, hi):
                            ops.put_terms(terms, i, row(ev, i), theta, c, False)
                    for i in range(lo, hi):
                        ops.splat_stored(s, terms, i, row(ev, i))
                else:
                    for i in range(lo, hi):
                        ops.splat_event(s, row(ev, i), theta, c)
        # --- 2. rows (each row by itself): F0 and its x-dilations; at the touched pixels the slice sums
        #        and the map reductions; tmp: what the previous call left outside Rx cleared, blur along x
        ti.loop_config(block_dim=row_block, serialize=serial)
        for y in range(height):
            w_, h_ = width, height
            ti.static(bind_sizes(w_, h_))
            tiles.build_x(args, y)
            sums = ti.Vector([0.0 for _ in ti.static(range(1 + RV))])  # sum m, sum m P_v
            tiles.each_pixel(args, F0, y, sum_slices_and_maps, sums)
            for k in ti.static(range(1 + RV)):
                rows[y * ROW + ROW_MAP + k] = sums[k]
            tiles.each_stale_segment(args, 0, y, clear_segment, tmp)  # in the previous Rx, not in this one
            tiles.each_segment(args, RX, y, blur_x_votes, load_taps())
        # --- 3. rows: Rxy (and Rs); the kept image over Rxy; without Sobel the image's moments; votes cleared
        ti.loop_config(block_dim=row_block, serialize=serial)
        for y in range(height):
            w_, h_ = width, height
            ti.static(bind_sizes(w_, h_))
            tiles.build_y(args, y)
            keep = keep_image(grad)
            if keep:  # img: in the previous kept image's Rxy, not in this one's
                tiles.each_stale_segment(args, 1, y, clear_segment, img)
            tv = load_taps()
            if keep:  # (always with Sobel: its pass reads the image)
                tiles.each_segment(args, RXY, y, blur_y_image, tv)
            if ti.static(not sobel):
                # the objective's terms are quadratic in I (its adjoint is affine in I): from the
                # image's moments, over Rx (B_y^T B_y on u: 4 r + 1 taps) rather than the image over Rxy
                mom = ti.Vector([0.0 for _ in ti.static(range(2 * C))])
                tiles.each_segment(
                    args, RX, y, image_moments, (twice_taps(y, tv, height), seg.y_tap_sum(y, tv, height), mom)
                )
                for k in ti.static(range(2 * C)):
                    rows[y * ROW + ROW_MOM + k] = mom[k]
            tiles.each_pixel(args, F0, y, clear_votes, grad)
        if ti.static(sobel):
            # --- 4. rows: Sobel images (kept for the backward) and the pixel terms that read them, over Rs
            ti.loop_config(block_dim=row_block, serialize=serial)
            for y in range(height):
                w_, h_ = width, height
                ti.static(bind_sizes(w_, h_))
                rsum = ti.Vector([0.0 for _ in ti.static(range(SLC))])
                tiles.each_pixel(args, R_OBJ, y, sobel_and_terms, rsum)
                for k in ti.static(range(SLC)):
                    rows[y * ROW + k] = rsum[k]
        # --- 5. serial: the row sums in row order, the untouched pixels in closed form, J ------------------
        ti.loop_config(serialize=True)
        for _ in range(1):
            w_, h_ = width, height
            ti.static(bind_sizes(w_, h_))
            gconst = finish_value(grad)
        # --- 6. rows (grad): adjoint images ------------------------------------------------------------
        if ti.static(sobel):
            # L(I): transposed Sobel of the Sobel images, over Rxy (where the transposed blur reads it)
            ti.loop_config(block_dim=row_block, serialize=serial)
            for y in range(height):
                w_, h_ = width, height
                ti.static(bind_sizes(w_, h_))
                if grad & 1 != 0:
                    tiles.each_pixel(args, RXY, y, transposed_sobel, 0)
            ti.loop_config(block_dim=row_block, serialize=serial)
            for y in range(height):
                w_, h_ = width, height
                ti.static(bind_sizes(w_, h_))
                if grad & 1 != 0:
                    # transposed blur along y of dJ/dI = (scale L(I) + offset) / G0 into tmp2 over Rx
                    tv = load_taps()
                    c1, c0 = adjoint_coefficients(y, tv)
                    tiles.each_segment(args, RX, y, blur_y_adjoint, (tv, c1, c0))
        ti.loop_config(block_dim=row_block, serialize=serial)
        for y in range(height):
            w_, h_ = width, height
            ti.static(bind_sizes(w_, h_))
            if grad & 1 != 0:
                # transposed blur along x into adj at the touched pixels; map adjoints; clear the maps.
                # Without Sobel, dJ/dI = (scale I + offset) / G0 and tmp2 = B_y^T B_y u (stage 3): the
                # transposed blur along y of dJ/dI is (scale tmp2 + offset tapsum_y) / G0, by linearity
                msum = state_at(ST_MAP) if ti.static(R > 0) else 0.0
                tv = load_taps()
                c1 = ti.Vector([0.0 for _ in ti.static(range(C))])
                c0 = ti.Vector([0.0 for _ in ti.static(range(C))])
                if ti.static(not sobel):
                    c1, c0 = adjoint_coefficients(y, tv)
                tiles.each_segment(args, F0, y, blur_x_adjoint, (tv, msum, c1, c0))
        # --- 7. events (grad, closed-form Jacobians): dJ/dtheta ---------------------------------------
        if ti.static(atomic_scatter):
            for i in range(n):
                w_, h_ = width, height
                ti.static(bind_sizes(w_, h_))
                if grad & 1 != 0:
                    gatomic += ops.event_grad(row(ev, i), theta_vec(), ctx_vec())
        else:
            ti.loop_config(block_dim=1, serialize=serial)  # one slice per thread (backend.per_thread_loops)
            for s in range(S):
                w_, h_ = width, height
                ti.static(bind_sizes(w_, h_))
                if grad & 1 != 0:
                    lo, hi = slice_events(s, n)
                    theta = theta_vec()
                    c = ctx_vec()
                    gacc = ti.Vector([0.0 for _ in ti.static(range(P))], dt=ti.f64)
                    if ti.static(store):
                        for i in range(lo, hi):
                            gacc += ops.stored_event_grad(terms, i, row(ev, i))
                    else:
                        for i in range(lo, hi):
                            gacc += ops.event_grad(row(ev, i), theta, c)
                    for j in ti.static(range(P)):
                        out[G_SLICES + s * P + j] = gacc[j]
        # --- 8. serial: results (the slices' sums in slice order) ------------------------------------------
        ti.loop_config(serialize=True)
        for _ in range(1):
            w_, h_ = width, height
            ti.static(bind_sizes(w_, h_))
            out[0] = ti.cast(state_at(ST_LOSS), ti.f64)
            graw = state_at(ST_GRAW)
            out[1] = ti.cast(graw, ti.f64)
            for j in ti.static(range(P)):
                gj = gconst[j]
                if ti.static(atomic_scatter):
                    gj += gatomic[j]
                elif grad & 1 != 0:
                    for s in ti.static(range(S)):
                        gj += out[G_SLICES + s * P + j]
                out[2 + j] = gj
            # J as if G0 were this G: at the identity, the J of every later evaluation there (the same
            # operations as stage 5, in the same order), so that the driver need not evaluate it again
            jself = graw / graw
            if ti.static(R > 0):
                for r in ti.static(range(R)):
                    jself -= param(p_lam + r) * state_at(ST_RV + r)
            out[2 + P] = ti.cast(jself, ti.f64)

    return run
