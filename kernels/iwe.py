"""Image of warped events: warp + atomic bilinear voting, and the separable Gaussian blur.

Kernels are built by factories closed over the warp model and the static sizes, so each footprint is
unrolled with ``ti.static`` (a dynamic inner loop inside a parallel loop gave silently wrong gradients
in Taichi 1.7) and every write into an image is an atomic add (reverse-mode safe). A forward-only pass
marks the segments the votes touch (``tiles.py``) and the blurs run over the lists of the regions they
need.
Formulas: docs/FORMULAS.md, "Image of warped events".
"""

import taichi as ti

from . import blocks as _b
from . import events as _ev
from . import tiles as _t
from . import whitening as _whitening


def make_warp_vote(
    warp_fn, quantity_fns: tuple, *, width: int, height: int, do_iwe: bool, whiten: bool, with_count: bool
):
    """The votes of one event under one warp, shared by the splat kernels of one warp and of K clusters.

    Returns the ``ti.func`` ``vote(p, dt, theta, c, b, ch, base, wmom, img, count, numer)``: warp the
    event at ``p`` (px), time ``dt`` (s) with the parameters ``theta`` and context ``c``, vote ``b``
    into channel ``ch`` of ``img`` (``do_iwe``; at the whitened position with ``whiten``, moments in the
    0-D field ``wmom``) and ``|b|`` with the per-event quantities into the map numerators
    ``numer[base + r]`` (and into ``count`` with ``with_count``). All flags are static.
    """
    n_q = len(quantity_fns)
    vote_at, vote_maps, _ = _b.make_bilinear(_b.Size(width, height))

    @ti.func
    def vote(
        p,
        dt,
        theta,
        c,
        b,
        ch,
        base,
        wmom: ti.template(),
        img: ti.template(),
        count: ti.template(),
        numer: ti.template(),
    ):
        q = warp_fn(p, dt, theta, c)
        if ti.static(do_iwe):
            if ti.static(whiten):
                vote_at(img, ch, _whitening.apply(q, wmom[None], c), b)
            else:
                vote_at(img, ch, q, b)
        if ti.static(n_q > 0):
            vals = ti.Vector([quantity_fns[r](p, dt, theta, c) for r in ti.static(range(n_q))])
            vote_maps(count, numer, base, q, ti.abs(b), vals, with_count)

    return vote


def make_splat_kernel(
    warp_fn,
    quantity_fns: tuple,
    *,
    width: int,
    height: int,
    n_channels: int,
    split_polarity: bool,
    weighted: bool,
    do_iwe: bool,
    whiten: bool,
):
    """Build the fused per-event kernel: warp, vote into the IWE and into the regularizer maps.

    Parameters
    ----------
    warp_fn : ti.func
        ``warp(p, dt, th, ctx) -> vec2`` of the model.
    quantity_fns : tuple of ti.func
        Per-event quantities ``q(p, dt, th, ctx) -> scalar`` voted into the map numerators
        (divergence, deformation, ...). Empty: no maps, no count image.
    width, height : int
        Image size (px).
    n_channels : int
        IWE channels (1, or 2 for per-polarity images).
    split_polarity : bool
        Route each event to channel ``ech[i]`` (0 positive, 1 negative).
    weighted : bool
        Read per-event vote weights ``ew`` (signed polarity and/or user weights); else weight 1.
    do_iwe : bool
        Vote into the IWE (False when the IWE is built from whitened positions by another kernel).
    whiten : bool
        Vote the IWE at the whitened positions (moments in ``wmom``; see ``whitening.py``).

    The kernel signature is ``(n, ev, ew, ech, wmom, vote, count, numer)`` with ``ev`` the
    ``events.WarpInputs``; :func:`make_mark_kernel` marks the segments its votes touch.
    """
    vote_event = make_warp_vote(
        warp_fn, quantity_fns, width=width, height=height, do_iwe=do_iwe, whiten=whiten, with_count=True
    )

    @ti.kernel
    def splat(
        n: ti.i32,
        ev: ti.template(),
        ew: ti.template(),
        ech: ti.template(),
        wmom: ti.template(),
        vote: ti.template(),
        count: ti.template(),
        numer: ti.template(),
    ):
        for i in range(n):
            p, dt = _ev.event_point(ev, i)
            b = 1.0
            if ti.static(weighted):
                b = ew[i]
            ch = 0
            if ti.static(split_polarity):
                ch = ti.cast(ech[i], ti.i32)
            vote_event(p, dt, ev.th[None], ev.ctx[None], b, ch, 0, wmom, vote, count, numer)

    _ = n_channels  # the channel count is carried by the field shapes
    return splat


def make_mark_kernel(warp_fn, *, width: int, height: int, iwe: bool, maps: bool, whiten: bool):
    """Forward only: mark in ``tiles`` (a ``tiles.TileFields``) the footprints that the splat kernels
    vote: the IWE's (at the whitened positions with ``whiten``) and the maps' (at the warped ones).

    A kernel of its own (one more pass over the events) because Taichi 1.7.4's reverse mode failed to
    compile the splat with the marks inside for some options (per-polarity images without maps).
    Signature ``(n, ev, wmom, tiles)``.
    """
    mark = _t.mark_position

    @ti.kernel
    def mark_events(n: ti.i32, ev: ti.template(), wmom: ti.template(), tiles: ti.template()):
        for i in range(n):
            q = _ev.warped_point(warp_fn, ev, i)
            if ti.static(iwe and whiten):
                mark(tiles, _whitening.apply(q, wmom[None], ev.ctx[None]))
            if ti.static(maps or (iwe and not whiten)):
                mark(tiles, q)

    return mark_events


def make_blur_kernel(radius: int, axis: int, width: int, height: int, n_channels: int):
    """Correlate each channel with a 1-D kernel of ``2 radius + 1`` taps along ``axis`` (1 = x, 0 = y),
    zero padding, adding into ``dst`` at the pixels of list ``region`` of ``tiles`` (a
    ``tiles.TileFields``). ``g`` holds the taps; the footprint is unrolled at compile time. The taps
    are symmetric, so ``blur(dst.grad, src.grad, g, tiles, r)`` is the kernel's own adjoint (into the
    region ``r`` where the adjoint is needed)."""
    tap_sum = _b.make_tap_sum(_b.read_chw, radius, axis, _b.Size(width, height))
    entry = _t.entry
    SEG = _t.SEG

    @ti.kernel
    def blur(
        src: ti.template(), dst: ti.template(), g: ti.template(), tiles: ti.template(), region: ti.template()
    ):
        for i in range(tiles.count[region] * SEG):
            y, x0 = entry(tiles, region, i // SEG)
            x = x0 + i % SEG
            if x < width:
                for c in ti.static(range(n_channels)):
                    dst[c, y, x] += tap_sum(src, g, c, y, x, True)

    return blur
