"""The formulas of the pipeline, each written once as a ``@ti.func`` (or a factory closed over static
sizes and an image layout), for the generic kernel chain (``iwe.py``, ``objectives.py``, ``maps.py``,
``loss.py``; differentiated by Taichi's reverse mode), the fused kernel (``fused.py``, hand-written
backward) and the multi-cluster kernels (``clusters.py``).

Blocks:

* bilinear voting: :func:`in_window`, :func:`bilinear_footprint`, :func:`corner_in_image`,
  :func:`corner_weights`, the whole footprint, :func:`make_footprint`, and its uses,
  :func:`make_bilinear` (the autodiff chains' atomic vote and the bilinear lookup);
* Gaussian blur along one axis: :func:`make_tap_sum` (footprint unrolled with ``ti.static``);
* support weight of the regularizer maps: :func:`support_weight`, :func:`support_weight_grad`;
* objectives: per-pixel terms, finalize and adjoint of ``variance``, ``mean_square`` and
  ``gradient_magnitude`` (one Sobel table, :data:`SOBEL_X`; :func:`make_sobel`,
  :func:`make_sobel_transpose`);
* the augmented objective: :func:`support_ratio`, :func:`scaled_penalty`, :func:`make_augmented`.

Literals such as ``0.0`` take Taichi's default float, which ``core/backend.py`` sets to the
working precision. Images are read through small ``read(src, c, y, x)`` functions of the caller, so
one block serves the channel-first images of the chain, ``(C, H, W)``, and the channel-last ones of
the fused kernel, ``(H, W, C)``. Blocks only read and return values: writes (atomic adds in
differentiated kernels, plain stores in the fused kernel) stay with the caller, except the atomic
vote of :func:`make_bilinear` that the autodiff chains share. Formulas: docs/FORMULAS.md.
"""

from typing import NamedTuple

import taichi as ti

SUPPORT_KAPPA = 0.05  # soft "pixel received events" weight m = C / (C + kappa)


class Size(NamedTuple):
    """An image's size as the factories below read it (``size.width``, ``size.height``, px): compiled
    in here; a kernel that takes its size as arguments binds them to an object with the same two
    attributes (``fused_common.KernelArgs``)."""

    width: int
    height: int


#: Sobel x kernel as a correlation, ``[row dy][column dx]``; the y kernel is its transpose
SOBEL_X = ((-1.0, 0.0, 1.0), (-2.0, 0.0, 2.0), (-1.0, 0.0, 1.0))
SOBEL_NORM = 64.0  # (Sobel / 8)^2 = Sobel^2 / 64


# --- bilinear voting ---------------------------------------------------------------------------------
@ti.func
def in_window(q, width: ti.template(), height: ti.template()):
    """A warped position ``q`` (px) whose bilinear footprint touches the image: inside
    ``(-1, W) x (-1, H)`` (False for NaN). Bitwise, not ``and``: a short-circuit is a branch, and a
    load that LLVM sinks under it keeps a loop that only gathers from being vectorized (the fused
    kernel's ``grad_at``)."""
    return (q[0] > -1.0) & (q[0] < width) & (q[1] > -1.0) & (q[1] < height)


@ti.func
def bilinear_footprint(q):
    """Integer top-left corner and fractional offsets ``(ix, iy, ax, ay)`` of a position ``q`` (px)."""
    x0 = ti.floor(q[0])
    y0 = ti.floor(q[1])
    return ti.cast(x0, ti.i32), ti.cast(y0, ti.i32), q[0] - x0, q[1] - y0


@ti.func
def corner_in_image(
    ix, iy, dx: ti.template(), dy: ti.template(), width: ti.template(), height: ti.template()
):
    """Corner ``(ix + dx, iy + dy)`` of a footprint is a pixel of the image (bitwise, as
    :func:`in_window`)."""
    return (ix + dx >= 0) & (ix + dx < width) & (iy + dy >= 0) & (iy + dy < height)


@ti.func
def corner_weights(ax, ay, dx: ti.template(), dy: ti.template()):
    """Bilinear weights ``(wx, wy)`` of corner ``(dx, dy)`` (0 or 1 each); the vote weight is
    ``wx * wy``, and ``d(wx)/d(ax) = +-1`` (+ for ``dx = 1``), likewise ``wy``."""
    wx = ax if ti.static(dx == 1) else 1.0 - ax
    wy = ay if ti.static(dy == 1) else 1.0 - ay
    return wx, wy


@ti.func
def _vote_corner(img: ti.template(), _unused: ti.template(), c, y, x, wx, wy, b, _vals):
    img[c, y, x] += b * wx * wy
    return 0.0


@ti.func
def _numer_corner(_count: ti.template(), numer: ti.template(), base, y, x, wx, wy, ab, vals):
    w = ab * wx * wy
    for r in ti.static(range(vals.n)):
        numer[base + r, y, x] += w * vals[r]
    return 0.0


@ti.func
def _count_numer_corner(count: ti.template(), numer: ti.template(), base, y, x, wx, wy, ab, vals):
    count[y, x] += ab * wx * wy
    return _numer_corner(count, numer, base, y, x, wx, wy, ab, vals)


@ti.func
def _sample_corner(img: ti.template(), _unused: ti.template(), c, y, x, wx, wy, _b, _vals):
    return wx * wy * img[c, y, x]


def make_bilinear(size):
    """``(vote, vote_maps, sample)`` over the in-image corners of the footprint of a warped position
    ``q`` (px); nothing happens for ``q`` outside ``(-1, W) x (-1, H)`` (or not finite).

    * ``vote(img, c, q, b)``: ``img[c, y, x] += b wx wy`` (atomic adds: reverse-mode safe);
    * ``vote_maps(count, numer, base, q, ab, vals, with_count)``: per corner ``w = ab wx wy``,
      ``count[y, x] += w`` (``with_count``, static) and ``numer[base + r, y, x] += w vals[r]``: a
      numerator's votes are the count's times the quantity, so a quantity of exactly 1 gives a map of
      exactly 1 (the penalties' kinks sit there);
    * ``sample(img, c, q)``: the bilinear interpolation of ``img[c]`` (0 outside the image).

    All three walk one footprint, :func:`make_footprint`, with their own corner function; ``size`` has
    the image's ``width`` and ``height`` (as :func:`make_sobel`).
    """
    votes = make_footprint(_vote_corner, size)
    count_numer_votes = make_footprint(_count_numer_corner, size)
    numer_votes = make_footprint(_numer_corner, size)
    samples = make_footprint(_sample_corner, size)

    @ti.func
    def vote(img: ti.template(), c, q, b):
        votes(img, img, c, q, b, 0.0)

    @ti.func
    def vote_maps(count: ti.template(), numer: ti.template(), base, q, ab, vals, with_count: ti.template()):
        if ti.static(with_count):
            count_numer_votes(count, numer, base, q, ab, vals)
        else:
            numer_votes(count, numer, base, q, ab, vals)

    @ti.func
    def sample(img: ti.template(), c, q):
        return samples(img, img, c, q, 0.0, 0.0)

    return vote, vote_maps, sample


def make_footprint(corner, size):
    """``over(dst, aux, c, q, b, vals)``: the sum of ``corner(dst, aux, c, y, x, wx, wy, b, vals)`` over
    the in-image corners ``(y, x)`` of the bilinear footprint of ``q`` (px), ``(wx, wy)`` their weights
    (:func:`corner_weights`); 0 for ``q`` outside ``(-1, W) x (-1, H)`` (or not finite). ``corner`` is a
    ``ti.func``: a vote writes (atomic adds) and returns 0, a lookup returns its term. The corners are
    unrolled with ``ti.static``; ``size`` has the image's ``width`` and ``height``."""

    @ti.func
    def over(dst: ti.template(), aux: ti.template(), c, q, b, vals):
        W, H = size.width, size.height
        total = 0.0
        if in_window(q, W, H):
            ix, iy, ax, ay = bilinear_footprint(q)
            for dy in ti.static(range(2)):
                for dx in ti.static(range(2)):
                    if corner_in_image(ix, iy, dx, dy, W, H):
                        wx, wy = corner_weights(ax, ay, dx, dy)
                        total += corner(dst, aux, c, iy + dy, ix + dx, wx, wy, b, vals)
        return total

    return over


# --- Gaussian blur ----------------------------------------------------------------------------------
def make_tap_sum(read, radius: int, axis: int, size):
    """``tap_sum(src, taps, c, y, x, checked) = sum_k taps[k + radius] * read(src, c, ...)`` at the
    ``2 radius + 1`` neighbours of ``(y, x)`` along ``axis`` (1 = x, 0 = y), zero padding.

    ``read(src, c, y, x)`` is the caller's ``ti.func`` reading one pixel of its layout. ``checked``
    (static) bounds-checks every tap; pass False where the whole footprint lies inside the image. The
    Gaussian taps are symmetric, so the same sum is the transposed blur of the backward pass. ``size``
    has the image's ``width`` and ``height`` (as :func:`make_sobel`).
    """

    @ti.func
    def tap_sum(src: ti.template(), taps: ti.template(), c, y, x, checked: ti.template()):
        extent = size.width if ti.static(axis == 1) else size.height
        acc = 0.0
        for k in ti.static(range(-radius, radius + 1)):
            yy = y + (k if ti.static(axis == 0) else 0)
            xx = x + (k if ti.static(axis == 1) else 0)
            if ti.static(checked):
                pos = xx if ti.static(axis == 1) else yy
                if 0 <= pos < extent:
                    acc += taps[k + radius] * read(src, c, yy, xx)
            else:
                acc += taps[k + radius] * read(src, c, yy, xx)
        return acc

    return tap_sum


@ti.func
def read_chw(src: ti.template(), c, y, x):
    """Pixel of a channel-first ``(C, H, W)`` image."""
    return src[c, y, x]


@ti.func
def read_hwc(src: ti.template(), c, y, x):
    """Pixel of a channel-last ``(H, W, C)`` image."""
    return src[y, x, c]


# --- regularizer maps ----------------------------------------------------------------------------------
@ti.func
def support_weight(cnt):
    """``m = C / (C + kappa)`` of a pixel's vote count ``C > 0``."""
    return cnt / (cnt + SUPPORT_KAPPA)


@ti.func
def support_weight_grad(cnt):
    """``dm/dC = kappa / (C + kappa)^2``."""
    return SUPPORT_KAPPA / ((cnt + SUPPORT_KAPPA) * (cnt + SUPPORT_KAPPA))


# --- objectives ---------------------------------------------------------------------------------------
# Each objective is the sum over pixels of per-pixel terms (a vector of its accumulator slots), read
# at the end by ``finalize(a, c, n_pixels)`` from channel c's slots ``a[slots * c : slots * (c + 1)]``.
# ``pixel(v, gx, gy)`` sees the blurred IWE value v and its Sobel responses gx, gy (unnormalised; 0
# unless the objective declares that it needs them). ``adjoint(a, c, n_pixels) -> (scale, offset)``
# gives the pixel adjoint of G_c as ``dG_c/dI = scale * L(I) + offset``, with ``L`` the identity or,
# for a Sobel objective, ``Sobel_x^T Sobel_x + Sobel_y^T Sobel_y``.
VARIANCE_SLOTS = 2  # sum I, sum I^2
MEAN_SQUARE_SLOTS = 1  # sum I^2
GRADIENT_MAGNITUDE_SLOTS = 1  # sum |Sobel I / 8|^2


@ti.func
def variance_pixel(v, gx, gy):
    return ti.Vector([v, v * v])


@ti.func
def variance_finalize(a, c: ti.template(), n_pixels):
    mean = a[2 * c] / n_pixels
    return a[2 * c + 1] / n_pixels - mean * mean


@ti.func
def variance_adjoint(a, c: ti.template(), n_pixels):
    """``dG/dI = 2 (I - mean) / N``."""
    scale = 2.0 / n_pixels
    return scale, -scale * a[2 * c] / n_pixels


@ti.func
def mean_square_pixel(v, gx, gy):
    return ti.Vector([v * v])


@ti.func
def mean_square_finalize(a, c: ti.template(), n_pixels):
    return a[c] / n_pixels


@ti.func
def mean_square_adjoint(a, c: ti.template(), n_pixels):
    """``dG/dI = 2 I / N``."""
    return 2.0 / n_pixels, 0.0


@ti.func
def gradient_magnitude_pixel(v, gx, gy):
    return ti.Vector([(gx * gx + gy * gy) / SOBEL_NORM])


@ti.func
def gradient_magnitude_finalize(a, c: ti.template(), n_pixels):
    return a[c] / n_pixels


@ti.func
def gradient_magnitude_adjoint(a, c: ti.template(), n_pixels):
    """``dG/dI = 2 (Sobel_x^T Sobel_x I + Sobel_y^T Sobel_y I) / (64 N)``."""
    return 2.0 / (SOBEL_NORM * n_pixels), 0.0


def make_sobel(read, size):
    """``sobel(src, c, y, x) -> (gx, gy)``: the Sobel responses (unnormalised) of channel ``c`` at
    ``(y, x)`` with zero padding; ``read(src, c, y, x)`` reads one pixel of the caller's layout, ``size``
    has the image's ``width`` and ``height`` (:class:`Size`, or a kernel's bound size arguments)."""

    @ti.func
    def sobel(src: ti.template(), c, y, x):
        W, H = size.width, size.height
        gx = 0.0
        gy = 0.0
        for dy in ti.static(range(-1, 2)):
            for dx in ti.static(range(-1, 2)):
                if ti.static(dx != 0 or dy != 0):  # noqa: SIM102 - compile-time if
                    if 0 <= y + dy < H and 0 <= x + dx < W:
                        v = read(src, c, y + dy, x + dx)
                        gx += ti.static(SOBEL_X[dy + 1][dx + 1]) * v
                        gy += ti.static(SOBEL_X[dx + 1][dy + 1]) * v
        return gx, gy

    return sobel


def make_sobel_transpose(read_x, read_y, size):
    """``sobel_t(src, c, y, x) = (Sobel_x^T gx + Sobel_y^T gy)(y, x)``: the transposed Sobel of the
    response images ``gx = read_x(src, c, ., .)``, ``gy = read_y(src, c, ., .)`` (zero padding) of an
    image of ``size`` (as :func:`make_sobel`)."""

    @ti.func
    def sobel_t(src: ti.template(), c, y, x):
        W, H = size.width, size.height
        a = 0.0
        for dy in ti.static(range(-1, 2)):
            for dx in ti.static(range(-1, 2)):
                if ti.static(dx != 0 or dy != 0):  # noqa: SIM102 - compile-time if
                    if 0 <= y - dy < H and 0 <= x - dx < W:
                        a += ti.static(SOBEL_X[dy + 1][dx + 1]) * read_x(src, c, y - dy, x - dx)
                        a += ti.static(SOBEL_X[dx + 1][dy + 1]) * read_y(src, c, y - dy, x - dx)
        return a

    return sobel_t


# --- the augmented objective J = G / G0 - sum_r lambda_r R_r --------------------------------------------
@ti.func
def support_ratio(weighted_sum, support_sum):
    """``sum m P / sum m``, 0 where no pixel has support."""
    ratio = 0.0
    if support_sum > 0.0:
        ratio = weighted_sum / support_sum
    return ratio


@ti.func
def scaled_penalty(ratio, scale, one_sided: ti.template()):
    """``R = s ratio``, hinged to ``max(0, R)`` when ``one_sided``."""
    rr = scale * ratio
    if ti.static(one_sided):
        rr = ti.max(rr, 0.0)
    return rr


@ti.func
def scaled_penalty_slope(ratio, scale, one_sided: ti.template()):
    """``dR/d ratio`` of :func:`scaled_penalty` for hand-written backwards (autodiff differentiates
    :func:`scaled_penalty` itself): at the kink of the hinge no gradient passes, as Taichi's autodiff
    of ``ti.max`` does."""
    slope = scale
    if ti.static(one_sided):  # noqa: SIM102 - compile-time if
        if scale * ratio <= 0.0:
            slope = 0.0
    return slope


def make_augmented(one_sided: tuple):
    """``augmented(g, g0, sums, base, lam) -> (J, R)``: ``J = g / g0 - sum_r lambda_r R_r`` with
    ``R_r = s_r sums[base + 1 + r] / sums[base]`` (support-weighted mean penalty, :func:`scaled_penalty`)
    and ``lam = (lambda_0, ..., s_0, ...)``; ``R`` is the vector of the ``R_r`` (length >= 1)."""
    n_regs = len(one_sided)

    @ti.func
    def augmented(g, g0, sums, base: ti.template(), lam):
        j = g / g0
        rvals = ti.Vector([0.0 for _ in ti.static(range(max(n_regs, 1)))])
        for r in ti.static(range(n_regs)):
            ratio = support_ratio(sums[base + 1 + r], sums[base])
            rr = scaled_penalty(ratio, lam[n_regs + r], ti.static(one_sided[r]))
            j -= lam[r] * rr
            rvals[r] = rr
        return j, rvals

    return augmented
