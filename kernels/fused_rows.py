"""The per-segment image operations of the fused kernels' row passes (``fused.py``): the separable blur's
two 1-D passes, the blur along y applied twice (the backward's ``B_y^T B_y``), stores and clears, at
the :data:`~cmax_taichi.kernels.tiles.SEG` pixels ``x0 .. x0 + SEG - 1`` of row ``y`` of a
:class:`~cmax_taichi.kernels.fused_common.Planes` view, with zero padding at the image's borders.

Away from the borders the taps read whole segments without bounds checks (vector loads). The image's
width and height come through the view (run-time or compiled-in values); the blur radius is compiled
in, the taps themselves are read from the kernel's parameters. The interior passes unroll the taps up
to :data:`UNROLLED_RADIUS` (the default blur's footprint and a little more: 10-15% less time per call
for a small window); wider footprints, and the border paths, loop over them, which keeps the compile
of the optimized kernels to a few hundred MB (unrolled, a 3 px blur took 1.5 GB).
"""

import taichi as ti

from . import fused_common as _c
from .tiles import SEG, in_image

#: the widest blur footprint (radius, px) whose interior taps are unrolled (sigma 1.5 px)
UNROLLED_RADIUS = 5


@ti.func
def whole(x0, width):
    """All pixels of the segment at ``x0`` are in the image (always, when the width is a multiple of the
    segment)."""
    return x0 + SEG <= width


class SegmentPasses:
    """Blurs, stores and clears of one segment for a blur of ``radius`` px (0: no blur, one tap of 1).

    Parameters
    ----------
    real : Taichi float type
        The kernels' float type.
    radius : int
        Blur footprint radius, px.
    taps_at : int
        Where the ``2 radius + 1`` taps start in the kernel's float64 parameters (``args.params``).
    args : fused_common.KernelArgs
        The kernel's bound arguments (``params``).
    """

    def __init__(self, real, radius: int, taps_at: int, args: _c.KernelArgs) -> None:
        r_ = int(radius)
        T = int(taps_at)
        # the tap loops in loops where the codegen takes them (less to compile), unrolled elsewhere
        static_taps = not _c.loops_over_local_vectors()
        unrolled = r_ <= UNROLLED_RADIUS or static_taps

        @ti.func
        def load_taps():
            """The blur taps as a local vector (an array is loaded again after every store: LLVM cannot
            tell the arrays apart)."""
            tv = ti.Vector([1.0 for _ in ti.static(range(2 * r_ + 1))])
            if ti.static(r_ > 0):
                for k in ti.static(range(2 * r_ + 1)):
                    tv[k] = ti.cast(args.params[T + k], real)
            return tv

        @ti.func
        def blur_x(src: ti.template(), c: ti.template(), y, x0, tv):
            """``sum_k taps_k src[c, y, x + k]`` at the segment's pixels (plane ``c`` of ``src``; the
            votes' slice 0 holds their channels in its first planes). Away from the borders the taps run over
            whole segments (unrolled up to :data:`UNROLLED_RADIUS`); at a border each tap is checked."""
            W = src.width
            o = _c.at(src, c, y, x0)  # the segment's first pixel
            v = ti.Vector([0.0 for _ in ti.static(range(SEG))])
            if whole(x0, W) and x0 >= r_ and x0 + SEG - 1 + r_ < W:
                if ti.static(unrolled):
                    for k in ti.static(range(-r_, r_ + 1)):
                        for p in ti.static(range(SEG)):
                            v[p] += tv[k + r_] * src.array[o + p + k]
                else:
                    for k in range(-r_, r_ + 1):
                        for p in ti.static(range(SEG)):
                            v[p] += tv[k + r_] * src.array[o + p + k]
            else:
                if ti.static(static_taps):
                    for k in ti.static(range(-r_, r_ + 1)):
                        for p in ti.static(range(SEG)):
                            if 0 <= x0 + p + k < W and in_image(x0 + p, W):
                                v[p] += tv[k + r_] * src.array[o + p + k]
                else:
                    for k in range(-r_, r_ + 1):
                        for p in ti.static(range(SEG)):
                            if 0 <= x0 + p + k < W and in_image(x0 + p, W):
                                v[p] += tv[k + r_] * src.array[o + p + k]
            return v

        @ti.func
        def blur_y(src: ti.template(), c: ti.template(), y, x0, tv):
            """``sum_k taps_k src[c, y + k, x]`` at the segment's pixels."""
            W, H = src.width, src.height
            o = _c.at(src, c, y, x0)
            v = ti.Vector([0.0 for _ in ti.static(range(SEG))])
            if whole(x0, W) and y >= r_ and y < H - r_:
                if ti.static(unrolled):
                    for k in ti.static(range(-r_, r_ + 1)):
                        for p in ti.static(range(SEG)):
                            v[p] += tv[k + r_] * src.array[o + k * W + p]
                else:
                    for k in range(-r_, r_ + 1):
                        for p in ti.static(range(SEG)):
                            v[p] += tv[k + r_] * src.array[o + k * W + p]
            else:
                if ti.static(static_taps):
                    for k in ti.static(range(-r_, r_ + 1)):
                        if 0 <= y + k < H:
                            for p in ti.static(range(SEG)):
                                if in_image(x0 + p, W):
                                    v[p] += tv[k + r_] * src.array[o + k * W + p]
                else:
                    for k in range(-r_, r_ + 1):
                        if 0 <= y + k < H:
                            for p in ti.static(range(SEG)):
                                if in_image(x0 + p, W):
                                    v[p] += tv[k + r_] * src.array[o + k * W + p]
            return v

        @ti.func
        def store(dst: ti.template(), c: ti.template(), y, x0, v):
            W = dst.width
            o = _c.at(dst, c, y, x0)
            if whole(x0, W):
                for p in ti.static(range(SEG)):
                    dst.array[o + p] = v[p]
            else:
                for p in ti.static(range(SEG)):
                    if in_image(x0 + p, W):
                        dst.array[o + p] = v[p]

        @ti.func
        def twice_taps(y, tv, height):
            """The taps of ``B_y^T B_y`` at row ``y`` (offsets ``-2 r .. 2 r``): the Gaussian convolved
            with itself, less the products of the first blur's taps that fall outside the image."""
            wide = ti.Vector([0.0 for _ in ti.static(range(4 * r_ + 1))])
            if ti.static(r_ > 0):
                if ti.static(static_taps):
                    for k1 in ti.static(range(-r_, r_ + 1)):
                        if 0 <= y + k1 < height:
                            for k2 in ti.static(range(-r_, r_ + 1)):
                                wide[k1 + k2 + 2 * r_] += tv[k1 + r_] * tv[k2 + r_]
                else:
                    for k1 in range(-r_, r_ + 1):
                        if 0 <= y + k1 < height:
                            for k2 in range(-r_, r_ + 1):
                                wide[k1 + k2 + 2 * r_] += tv[k1 + r_] * tv[k2 + r_]
            else:
                wide[0] = 1.0
            return wide

        @ti.func
        def twice_blur_y(src: ti.template(), wide, c: ti.template(), y, x0):
            """``(B_y^T B_y src)[c, y, x]`` at the segment's pixels, with the taps of :func:`twice_taps`."""
            W, H = src.width, src.height
            o = _c.at(src, c, y, x0)
            v = ti.Vector([0.0 for _ in ti.static(range(SEG))])
            if whole(x0, W) and y >= 2 * r_ and y < H - 2 * r_:
                if ti.static(unrolled):
                    for k in ti.static(range(-2 * r_, 2 * r_ + 1)):
                        for p in ti.static(range(SEG)):
                            v[p] += wide[k + 2 * r_] * src.array[o + k * W + p]
                else:
                    for k in range(-2 * r_, 2 * r_ + 1):
                        for p in ti.static(range(SEG)):
                            v[p] += wide[k + 2 * r_] * src.array[o + k * W + p]
            else:
                if ti.static(static_taps):
                    for k in ti.static(range(-2 * r_, 2 * r_ + 1)):
                        if 0 <= y + k < H:
                            for p in ti.static(range(SEG)):
                                if in_image(x0 + p, W):
                                    v[p] += wide[k + 2 * r_] * src.array[o + k * W + p]
                else:
                    for k in range(-2 * r_, 2 * r_ + 1):
                        if 0 <= y + k < H:
                            for p in ti.static(range(SEG)):
                                if in_image(x0 + p, W):
                                    v[p] += wide[k + 2 * r_] * src.array[o + k * W + p]
            return v

        @ti.func
        def clear(y, x0, dst: ti.template()):
            """Every plane of ``dst`` zeroed at the segment (the argument order of a
            ``TileOps.each_segment`` body)."""
            o = _c.at(dst, 0, y, x0)
            HW = _c.plane_size(dst)
            for p in ti.static(range(SEG)):
                if in_image(x0 + p, dst.width):
                    for c in ti.static(range(dst.count)):
                        dst.array[o + c * HW + p] = 0.0

        @ti.func
        def y_tap_sum(y, tv, height):
            """``B_y^T 1`` at row ``y``: the sum of the y taps that fall inside the image."""
            tapsum = 0.0
            if ti.static(static_taps):
                for k in ti.static(range(-r_, r_ + 1)):
                    if 0 <= y + k < height:
                        tapsum += tv[k + r_]
            else:
                for k in range(-r_, r_ + 1):
                    if 0 <= y + k < height:
                        tapsum += tv[k + r_]
            return tapsum

        @ti.func
        def x_tap_sums(x0, tv, width):
            """``B_x^T 1`` at the segment's pixels: the sum of the x taps that fall inside the image (away
            from the borders every tap does: their sum, added in the same order)."""
            s = ti.Vector([0.0 for _ in ti.static(range(SEG))])
            if whole(x0, width) and x0 >= r_ and x0 + SEG - 1 + r_ < width:
                total = 0.0
                for k in ti.static(range(2 * r_ + 1)):
                    total += tv[k]
                for p in ti.static(range(SEG)):
                    s[p] = total
            else:
                if ti.static(static_taps):
                    for k in ti.static(range(-r_, r_ + 1)):
                        for p in ti.static(range(SEG)):
                            if 0 <= x0 + p + k < width:
                                s[p] += tv[k + r_]
                else:
                    for k in range(-r_, r_ + 1):
                        for p in ti.static(range(SEG)):
                            if 0 <= x0 + p + k < width:
                                s[p] += tv[k + r_]
            return s

        self.load_taps, self.blur_x, self.blur_y, self.store = load_taps, blur_x, blur_y, store
        self.twice_taps, self.twice_blur_y, self.clear = twice_taps, twice_blur_y, clear
        self.y_tap_sum, self.x_tap_sums = y_tap_sum, x_tap_sums
