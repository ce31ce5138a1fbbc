"""Objectives (maximised) as reductions of the blurred IWE into a 0-D accumulator vector.

Each objective is a pair: ``make_<name>_reduce(W, H, C)`` builds a kernel ``reduce(img, acc)`` that
atomically adds per-pixel terms into ``acc[None]`` (a 0-D field: Taichi accumulates thread-locally), and
``<name>_finalize(acc, c, n_pixels)`` turns channel ``c``'s slots into its objective value.
Formulas: docs/FORMULAS.md, "Objectives".
"""

import taichi as ti

# --- variance: slots per channel (sum I, sum I^2) ------------------------------------------------
VARIANCE_SLOTS = 2


def make_variance_reduce(width: int, height: int, n_channels: int):
    @ti.kernel
    def reduce(img: ti.template(), acc: ti.template()):
        for y, x in ti.ndrange(height, width):
            for c in ti.static(range(n_channels)):
                v = img[c, y, x]
                acc[None][2 * c] += v
                acc[None][2 * c + 1] += v * v

    return reduce


@ti.func
def variance_finalize(a, c: ti.template(), n_pixels):
    mean = a[2 * c] / n_pixels
    return a[2 * c + 1] / n_pixels - mean * mean


# --- mean square: slots per channel (sum I^2) -----------------------------------------------------
MEAN_SQUARE_SLOTS = 1


def make_mean_square_reduce(width: int, height: int, n_channels: int):
    @ti.kernel
    def reduce(img: ti.template(), acc: ti.template()):
        for y, x in ti.ndrange(height, width):
            for c in ti.static(range(n_channels)):
                v = img[c, y, x]
                acc[None][c] += v * v

    return reduce


@ti.func
def mean_square_finalize(a, c: ti.template(), n_pixels):
    return a[c] / n_pixels


# --- gradient magnitude: slots per channel (sum |Sobel I / 8|^2) -----------------------------------
GRADIENT_MAGNITUDE_SLOTS = 1
_SOBEL_X = ((-1.0, 0.0, 1.0), (-2.0, 0.0, 2.0), (-1.0, 0.0, 1.0))  # [row dy][col dx]


def make_gradient_magnitude_reduce(width: int, height: int, n_channels: int):
    W, H = width, height

    @ti.kernel
    def reduce(img: ti.template(), acc: ti.template()):
        for y, x in ti.ndrange(H, W):
            for c in ti.static(range(n_channels)):
                gx = 0.0
                gy = 0.0
                for dy in ti.static(range(-1, 2)):
                    for dx in ti.static(range(-1, 2)):
                        if ti.static(dx != 0 or dy != 0):  # noqa: SIM102 - compile-time if
                            if 0 <= y + dy < H and 0 <= x + dx < W:
                                v = img[c, y + dy, x + dx]
                                gx += ti.static(_SOBEL_X[dy + 1][dx + 1]) * v
                                gy += ti.static(_SOBEL_X[dx + 1][dy + 1]) * v
                acc[None][c] += (gx * gx + gy * gy) / 64.0

    return reduce


@ti.func
def gradient_magnitude_finalize(a, c: ti.template(), n_pixels):
    return a[c] / n_pixels
