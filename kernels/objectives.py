"""Objectives (maximised) as reductions of the blurred IWE into a 0-D accumulator vector.

An objective is a per-pixel term ``pixel(v, gx, gy)`` (a vector of its slots, ``blocks.py``) summed
over the image, and ``finalize(acc, c, n_pixels)`` turning channel ``c``'s slots into its value.
:func:`make_pixel_reduce` builds the generic chain's reduce kernel ``reduce(img, acc)`` of any such
objective over the whole image; it carries its pixel terms (``reduce.pixel_terms``), from which
:func:`make_tiled_reduce` builds the reduce over the pixels the events reach: per segment of a region's
list a partial sum, the partial sums added in list order (a fixed order: the same input gives the same
value to the last bit), and the untouched pixels in closed form (``pixel(0, 0, 0)`` times their number:
their image and Sobel responses are 0). Formulas: docs/FORMULAS.md, "Objectives".
"""

import taichi as ti

from . import blocks as _b
from . import tiles as _t


def _make_pixel_terms(pixel_fn, sobel: bool, width: int, height: int):
    """``terms_at(img, c, y, x)``: ``pixel(I_c(y, x), gx, gy)`` of the ``(C, H, W)`` image, with the Sobel
    responses of ``I_c`` where ``sobel`` (static; else 0)."""
    sobel_fn = _b.make_sobel(_b.read_chw, _b.Size(width, height))

    @ti.func
    def terms_at(img: ti.template(), c: ti.template(), y, x):
        gx = 0.0
        gy = 0.0
        if ti.static(sobel):
            gx, gy = sobel_fn(img, c, y, x)
        return pixel_fn(img[c, y, x], gx, gy)

    return terms_at


def make_pixel_reduce(pixel_fn, slots: int, sobel: bool, width: int, height: int, n_channels: int):
    """Kernel ``reduce(img, acc)``: ``acc[None][slots c + s] += sum_x pixel(I_c(x), gx, gy)[s]`` over
    the ``(C, H, W)`` image, with the Sobel responses ``gx, gy`` of ``I_c`` where ``sobel`` (else 0).
    ``reduce.pixel_terms = (pixel_fn, slots, sobel)`` lets the chains build :func:`make_tiled_reduce`."""
    terms_at = _make_pixel_terms(pixel_fn, sobel, width, height)

    @ti.kernel
    def reduce(img: ti.template(), acc: ti.template()):
        for y, x in ti.ndrange(height, width):
            for c in ti.static(range(n_channels)):
                terms = terms_at(img, c, y, x)
                for s in ti.static(range(slots)):
                    acc[None][slots * c + s] += terms[s]

    reduce.pixel_terms = (pixel_fn, slots, sobel)
    return reduce


def make_tiled_reduce(
    pixel_fn, slots: int, sobel: bool, width: int, height: int, n_channels: int, region: int
):
    """Kernel ``reduce(img, acc, tiles, part)``: :func:`make_pixel_reduce`'s sums over the pixels of list
    ``region`` of ``tiles`` (the blurred IWE's support, one pixel more with ``sobel``), through the
    per-segment partial sums ``part[k, slots c + s]`` (zero before), and the other pixels' terms
    ``pixel(0, 0, 0)`` in closed form."""
    terms_at = _make_pixel_terms(pixel_fn, sobel, width, height)
    entry = _t.entry
    n_pixels = width * height

    @ti.kernel
    def reduce(img: ti.template(), acc: ti.template(), tiles: ti.template(), part: ti.template()):
        for k in range(tiles.count[region]):
            y, x0 = entry(tiles, region, k)
            for p in ti.static(range(_t.SEG)):
                x = x0 + p
                if x < width:
                    for c in ti.static(range(n_channels)):
                        terms = terms_at(img, c, y, x)
                        for s in ti.static(range(slots)):
                            part[k, slots * c + s] += terms[s]
        ti.loop_config(serialize=True)  # the partial sums in list order
        for k in range(tiles.count[region]):
            for j in ti.static(range(slots * n_channels)):
                acc[None][j] += part[k, j]
        for _ in range(1):  # a loop: Taichi's autodiff takes no statements between the loops
            untouched = 1.0 * (n_pixels - tiles.pixels[region])
            terms0 = pixel_fn(0.0, 0.0, 0.0)
            for c in ti.static(range(n_channels)):
                for s in ti.static(range(slots)):
                    acc[None][slots * c + s] += untouched * terms0[s]

    return reduce
