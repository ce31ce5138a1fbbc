"""Objectives (maximised) as reductions of the blurred IWE into a 0-D accumulator vector.

An objective is a per-pixel term ``pixel(v, gx, gy)`` (a vector of its slots, ``blocks.py``) summed
over the image, and ``finalize(acc, c, n_pixels)`` turning channel ``c``'s slots into its value.
:func:`make_pixel_reduce` builds the generic chain's reduce kernel ``reduce(img, acc)`` of any such
objective; it atomically adds into ``acc[None]`` (a 0-D field: Taichi accumulates thread-locally).
Formulas: docs/FORMULAS.md, "Objectives".
"""

import taichi as ti

from . import blocks as _b


def make_pixel_reduce(pixel_fn, slots: int, sobel: bool, width: int, height: int, n_channels: int):
    """Kernel ``reduce(img, acc)``: ``acc[None][slots c + s] += sum_x pixel(I_c(x), gx, gy)[s]`` over
    the ``(C, H, W)`` image, with the Sobel responses ``gx, gy`` of ``I_c`` where ``sobel`` (else 0)."""
    sobel_fn = _b.make_sobel(_b.read_chw, width, height)

    @ti.kernel
    def reduce(img: ti.template(), acc: ti.template()):
        for y, x in ti.ndrange(height, width):
            for c in ti.static(range(n_channels)):
                gx = 0.0
                gy = 0.0
                if ti.static(sobel):
                    gx, gy = sobel_fn(img, c, y, x)
                terms = pixel_fn(img[c, y, x], gx, gy)
                for s in ti.static(range(slots)):
                    acc[None][slots * c + s] += terms[s]

    return reduce
