"""Image of warped events: warp + atomic bilinear voting, and the separable Gaussian blur.

Kernels are built by factories closed over the warp model and the static sizes, so each footprint is
unrolled with ``ti.static`` (a dynamic inner loop inside a parallel loop gave silently wrong gradients
in Taichi 1.7) and every write into an image is an atomic add (reverse-mode safe).
Formulas: docs/FORMULAS.md, "Image of warped events".
"""

import taichi as ti

from . import blocks as _b
from . import whitening as _whitening


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

    The kernel signature is ``(n, ex, ey, edt, ew, ech, th, ctx, wmom, vote, count, numer)``.
    """
    n_q = len(quantity_fns)
    W, H = width, height

    @ti.func
    def _vote(img: ti.template(), c, q, b):
        if _b.in_window(q, W, H):
            ix, iy, ax, ay = _b.bilinear_footprint(q)
            for dy in ti.static(range(2)):
                for dx in ti.static(range(2)):
                    if _b.corner_in_image(ix, iy, dx, dy, W, H):
                        wx, wy = _b.corner_weights(ax, ay, dx, dy)
                        img[c, iy + dy, ix + dx] += b * wx * wy

    @ti.kernel
    def splat(
        n: ti.i32,
        ex: ti.template(),
        ey: ti.template(),
        edt: ti.template(),
        ew: ti.template(),
        ech: ti.template(),
        th: ti.template(),
        ctx: ti.template(),
        wmom: ti.template(),
        vote: ti.template(),
        count: ti.template(),
        numer: ti.template(),
    ):
        for i in range(n):
            p = ti.Vector([ex[i], ey[i]])
            dt = edt[i]
            theta = th[None]
            c = ctx[None]
            q = warp_fn(p, dt, theta, c)
            b = 1.0
            if ti.static(weighted):
                b = ew[i]
            ch = 0
            if ti.static(split_polarity):
                ch = ti.cast(ech[i], ti.i32)
            if ti.static(do_iwe):
                if ti.static(whiten):
                    _vote(vote, ch, _whitening.apply(q, wmom[None], c), b)
                else:
                    _vote(vote, ch, q, b)
            if ti.static(n_q > 0):
                ab = ti.abs(b)
                if _b.in_window(q, W, H):
                    ix, iy, ax, ay = _b.bilinear_footprint(q)
                    for r in ti.static(range(n_q)):
                        val = quantity_fns[r](p, dt, theta, c)
                        for dy in ti.static(range(2)):
                            for dx in ti.static(range(2)):
                                wx, wy = _b.corner_weights(ax, ay, dx, dy)
                                if _b.corner_in_image(ix, iy, dx, dy, W, H):
                                    if ti.static(r == 0):
                                        count[iy + dy, ix + dx] += ab * wx * wy
                                    numer[r, iy + dy, ix + dx] += ab * wx * wy * val

    _ = n_channels  # the channel count is carried by the field shapes
    return splat


def make_blur_kernel(radius: int, axis: int, width: int, height: int, n_channels: int):
    """Correlate each channel with a 1-D kernel of ``2 radius + 1`` taps along ``axis`` (1 = x, 0 = y),
    zero padding, adding into ``dst``. ``g`` holds the taps; the footprint is unrolled at compile time.
    The taps are symmetric, so ``blur(dst.grad, src.grad, g)`` is the kernel's own adjoint."""
    tap_sum = _b.make_tap_sum(_b.read_chw, radius, axis, width, height)

    @ti.kernel
    def blur(src: ti.template(), dst: ti.template(), g: ti.template()):
        for c, y, x in ti.ndrange(n_channels, height, width):
            dst[c, y, x] += tap_sum(src, g, c, y, x, True)

    return blur
