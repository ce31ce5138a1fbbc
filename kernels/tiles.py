"""Where a window's image work happens: segment masks of the pixels its warped events touch, dilated
by the footprint of each image pass.

Every image pass of the pipelines (slice sums, blurs, objective and map reductions, Sobel, adjoints,
clears) runs over the pixels the events can reach rather than over all ``W x H``: a 5,000-event window
touches a few ten thousand pixels of a 1280x720 sensor. The image is cut into **segments** of
:data:`SEG` = 4 pixels of one row; a *mask* holds one bit per segment, 32 segments to a ``u32`` word
(``words`` per row). Bit ``b`` of word ``j`` of row ``y`` is the segment of pixels
``x0 = SEG (32 j + b) .. x0 + 3`` of row ``y``.

* The splat calls :meth:`TileOps.mark` for every footprint it votes: the segments of its top-left row
  ``iy`` (``-1 .. H - 1``, kept in mark row ``iy + 1``) holding its columns ``ix, ix + 1`` (clipped into
  the image; a check before the ``atomic_or``, so an already set bit costs one load). The footprint's
  second row is added when ``F0`` is built.
* ``F0``, the touched segments: row ``y`` holds the footprints whose top row is ``y`` or ``y - 1`` (mark
  rows ``y + 1`` and ``y``).
* A **region** ``(kx, ry)`` is ``F0`` dilated by ``kx`` segments along x and ``ry`` rows along y: the
  pixels within ``SEG kx`` columns and ``ry`` rows of a touched one. A pass reaching ``r`` pixels along
  x needs ``kx = ceil(r / SEG)`` (:func:`reach`); along y the dilation is exact. Region 0 is always
  ``F0`` itself.
* Two row passes compute them (:meth:`TileOps.build_x`: ``F0`` and its x-dilations per row;
  :meth:`TileOps.build_y`: the y-dilations, the in-image pixel count of each region's row, and the
  marks cleared for the next call). The fused kernels then loop over rows and iterate the set bits of
  a row's words (:func:`first_pixel`, :func:`drop_lowest`); the autodiff chains need flat loops and
  read the regions as **lists** of segments in row-major order (:meth:`TileOps.prefix`,
  :meth:`TileOps.fill`, :func:`make_entry`), and clear what the last evaluation wrote over the last
  lists before the next (:func:`make_clear_kernel`).

**Storage.** A :class:`TileLayout` (regions, history, lists: compile-time) says what is kept; the masks
live in one flat ``u32`` array ``words`` (marks, x-dilations, regions, previous regions, in that order:
:meth:`TileLayout.word_offsets`) and the rows' pixel counts in one flat ``i32`` array ``rowpx``. The
functions of :class:`TileOps` take the storage ``tf`` as a template argument and read its ``width`` and
``height`` from it: Python ints for :class:`TileFields` (the chains' fields, compiled for one sensor), or
a kernel's size arguments (the fused kernels: one compiled kernel for every sensor, their arrays bound
by ``fused_common.KernelArgs``). Every size below (segments, words, the last word's bits) is derived
from the width where it is used, so that both compile from one source.

Everything here is integer work on ``u32`` / ``i32`` arrays, never differentiated; the lists and
masks are a function of the set of touched pixels only, so the order of every pass and reduction that
follows them is fixed (the same input gives the same sums to the last bit). ``clz`` is avoided (its
SPIR-V lowering fails in Taichi 1.7.4 on Vulkan): the lowest set bit comes from ``popcnt``.
"""

from dataclasses import dataclass

import taichi as ti

SEG = 4  # pixels per segment (of one row)
WORD = 32  # segments per mask word


def reach(px: int) -> int:
    """Segments of x dilation that cover ``px`` pixels on each side: ``ceil(px / SEG)``."""
    return -(-int(px) // SEG)


def segments_of(width: int) -> int:
    """Segments per row of an image ``width`` px wide (host side; :func:`n_segments` in a kernel)."""
    return -(-int(width) // SEG)


def words_of(width: int) -> int:
    """Mask words per row of an image ``width`` px wide (host side; :func:`n_words` in a kernel)."""
    return -(-int(width) // (SEG * WORD))


@ti.func
def n_segments(width):
    """Segments per row (``width`` a Python int or a kernel's size argument)."""
    return (width + SEG - 1) // SEG


@ti.func
def n_words(width):
    """Mask words per row: ``ceil(n_segments / WORD)``."""
    return (width + SEG * WORD - 1) // (SEG * WORD)


@ti.func
def in_image(x, width):
    """Column ``x`` of a segment lies in the image (only a row's last segment can stick out)."""
    return x < width


@dataclass(frozen=True)
class TileLayout:
    """What a set of masks keeps (compile-time; the sizes follow the image's width and height).

    Parameters
    ----------
    regions : tuple of (int, int)
        ``(kx, ry)`` of each region (segments along x, rows along y); the first must be ``(0, 0)``
        (``F0``).
    history : tuple of int
        Regions whose previous masks are kept (``old``), so that a pass can clear what the previous
        call left outside the new region (:meth:`TileOps.stale`).
    lists : bool
        Also keep each region as a list of segments (the autodiff chains' flat loops).
    """

    regions: tuple
    history: tuple = ()
    lists: bool = False

    def __post_init__(self) -> None:
        regions = tuple((int(kx), int(ry)) for kx, ry in self.regions)
        if not regions or regions[0] != (0, 0):
            raise ValueError("region 0 must be (0, 0): the touched segments")
        if any(kx < 0 or ry < 0 or kx >= WORD for kx, ry in regions):
            raise ValueError(f"region dilations must be 0 <= kx < {WORD} and ry >= 0, got {regions}")
        object.__setattr__(self, "regions", regions)
        object.__setattr__(self, "history", tuple(int(h) for h in self.history))

    @property
    def kxs(self) -> tuple:
        """The distinct x dilations (one x-dilated mask each, :meth:`TileOps.build_x`)."""
        return tuple(sorted({kx for kx, _ in self.regions}))

    def word_planes(self) -> tuple[int, int, int]:
        """``(x-dilated masks, regions, previous regions)``: the ``H x words`` planes after the marks."""
        return len(self.kxs), len(self.regions), max(len(self.history), 1)

    def n_words_total(self, width: int, height: int) -> int:
        """Length of the ``words`` array of a ``width x height`` image: the marks (``H + 1`` rows) and
        the planes of :meth:`word_planes`."""
        return words_of(width) * ((height + 1) + height * sum(self.word_planes()))

    def n_rowpx(self, height: int) -> int:
        """Length of the ``rowpx`` array: one in-image pixel count per region and row."""
        return len(self.regions) * height


class TileFields:
    """The masks of one ``width x height`` image as Taichi fields (the autodiff chains: compiled for
    this sensor), and, with ``lists``, each region as a list of segments.

    Parameters
    ----------
    width, height : int
        Image size, px.
    regions, history, lists
        As :class:`TileLayout`.
    """

    def __init__(self, width: int, height: int, regions, *, history=(), lists: bool = False) -> None:
        self.layout = TileLayout(tuple(regions), tuple(history), bool(lists))
        W, H = int(width), int(height)
        self.width, self.height = W, H
        self.regions, self.history = self.layout.regions, self.layout.history
        self.n_segments = segments_of(W)
        self.n_words = words_of(W)
        R = len(self.regions)
        self.words = ti.field(ti.u32, shape=self.layout.n_words_total(W, H))
        self.rowpx = ti.field(ti.i32, shape=self.layout.n_rowpx(H))
        self.lists = None
        if lists:
            self.pixels = ti.field(ti.i32, shape=R)  # in-image pixels of each region
            self.rows = ti.field(ti.i32, shape=(R, H + 1))  # list offset of each row
            self.lists = ti.field(ti.i32, shape=(R, H * self.n_segments))  # y * n_segments + segment
            self.count = ti.field(ti.i32, shape=R)  # segments per list

    def masks(self):
        """The regions of the last build, ``(R, H, words)`` NumPy ``uint32`` (tests)."""
        return region_masks(self.layout, self.words.to_numpy(), self.width, self.height)

    def nbytes(self) -> int:
        """Bytes held by the mask and list fields."""
        R, H = len(self.regions), self.height
        total = 4 * (self.layout.n_words_total(self.width, H) + self.layout.n_rowpx(H))
        if self.lists is not None:
            total += 4 * R * (H + 1 + H * self.n_segments + 2)
        return total


def region_masks(layout: TileLayout, words, width: int, height: int):
    """The regions' masks ``(R, H, words)`` out of a ``words`` array (host side: tests, checks)."""
    NW, H = words_of(width), int(height)
    n_kx, R, _ = layout.word_planes()
    start = NW * (H + 1) + n_kx * H * NW
    return words[start : start + R * H * NW].reshape(R, H, NW)


@ti.func
def lowest_bit(w):
    """Index of the lowest set bit of a non-zero ``u32``."""
    return ti.cast(ti.math.popcnt((w & (ti.u32(0) - w)) - ti.u32(1)), ti.i32)


@ti.func
def drop_lowest(w):
    """``w`` without its lowest set bit."""
    return w & (w - ti.u32(1))


@ti.func
def first_pixel(j, w):
    """First pixel column of the segment of the lowest set bit of word ``j``'s value ``w``."""
    return (j * WORD + lowest_bit(w)) * SEG


@ti.func
def _mark_word(tf: ti.template(), y, j):
    """Index in ``tf.words`` of word ``j`` of mark row ``y`` (``0 .. H``)."""
    return y * n_words(tf.width) + j


@ti.func
def _set_bits(tf: ti.template(), y, j, bits):
    i = _mark_word(tf, y, j)
    if (tf.words[i] & bits) != bits:
        ti.atomic_or(tf.words[i], bits)


@ti.func
def mark(tf: ti.template(), ix, iy):
    """Mark the footprint with top-left corner ``(ix, iy)`` (px; ``-1 .. W - 1``, ``-1 .. H - 1``) in
    ``tf``'s marks: the segments of mark row ``iy + 1`` holding columns ``ix`` and ``ix + 1`` clipped
    into the image (the footprint's second row comes with ``F0``). Atomic, after a load that skips bits
    already set."""
    W, H = tf.width, tf.height
    y = ti.min(ti.max(iy, -1), H - 1) + 1
    s0 = ti.max(ix, 0) // SEG
    s1 = ti.min(ix + 1, W - 1) // SEG
    j0 = s0 // WORD
    b0 = ti.u32(1) << ti.cast(s0 % WORD, ti.u32)
    b1 = ti.u32(1) << ti.cast(s1 % WORD, ti.u32)
    if s1 // WORD == j0:
        _set_bits(tf, y, j0, b0 | b1)
    else:
        _set_bits(tf, y, j0, b0)
        _set_bits(tf, y, j0 + 1, b1)


@ti.func
def mark_position(tf: ti.template(), q):
    """:func:`mark` of the footprint of a warped position ``q`` (px) whose footprint touches the image
    (nothing otherwise, NaN included)."""
    if q[0] > -1.0 and q[0] < tf.width and q[1] > -1.0 and q[1] < tf.height:
        mark(tf, ti.cast(ti.floor(q[0]), ti.i32), ti.cast(ti.floor(q[1]), ti.i32))


@ti.func
def entry(tf: ti.template(), ri: ti.template(), k):
    """``(y, x0)``: row and first pixel column of entry ``k`` of list ``ri`` (a :class:`TileFields`
    with lists)."""
    NS = n_segments(tf.width)
    e = tf.lists[ri, k]
    return e // NS, (e % NS) * SEG


class TileOps:
    """The Taichi functions over the masks of one :class:`TileLayout` (regions and history compiled in,
    the image size read from the storage ``tf`` each takes as its first, template, argument)."""

    def __init__(self, layout: TileLayout) -> None:
        self.layout = layout
        regions, history = layout.regions, layout.history
        kxs = layout.kxs
        n_kx, R, n_old = layout.word_planes()
        kx_slot = tuple(kxs.index(kx) for kx, _ in regions)

        @ti.func
        def plane_word(tf: ti.template(), plane: ti.template(), y, j):
            """Index in ``tf.words`` of word ``j`` of row ``y`` of plane ``plane`` (after the marks:
            x-dilations ``0 .. n_kx - 1``, regions, previous regions)."""
            NW = n_words(tf.width)
            return NW * (tf.height + 1 + plane * tf.height + y) + j

        @ti.func
        def region_word(tf: ti.template(), ri: ti.template(), y, j):
            return plane_word(tf, n_kx + ri, y, j)

        @ti.func
        def old_word(tf: ti.template(), h: ti.template(), y, j):
            return plane_word(tf, n_kx + R + h, y, j)

        @ti.func
        def touched(tf: ti.template(), y, j):
            """Word ``j`` of ``F0`` in row ``y``: the footprints whose top row is ``y`` (mark row
            ``y + 1``) or ``y - 1`` (mark row ``y``)."""
            w = ti.u32(0)
            if 0 <= j < n_words(tf.width):
                w = tf.words[_mark_word(tf, y + 1, j)] | tf.words[_mark_word(tf, y, j)]
            return w

        @ti.func
        def row_pixels(tf: ti.template(), w, j):
            """In-image pixels of the segments of word ``j``'s value ``w``: 4 per segment, less the
            columns of a row's last segment beyond the image where its bit is set."""
            W = tf.width
            NS = n_segments(W)
            NW = n_words(W)
            px = ti.cast(ti.math.popcnt(w), ti.i32) * SEG
            partial = SEG * NS - W  # columns of the last segment beyond the image
            tail = NS - WORD * (NW - 1)  # segments in the last word
            if partial > 0 and j == NW - 1:  # noqa: SIM102
                if (w >> ti.cast(tail - 1, ti.u32)) & ti.u32(1) != ti.u32(0):
                    px -= partial
            return px

        @ti.func
        def last_word_mask(tf: ti.template()):
            """The bits of the segments in the last word of a row."""
            NW = n_words(tf.width)
            tail = n_segments(tf.width) - WORD * (NW - 1)
            mask = ti.u32(0xFFFFFFFF)
            if tail < WORD:
                mask = (ti.u32(1) << ti.cast(tail, ti.u32)) - ti.u32(1)
            return mask

        @ti.func
        def build_x(tf: ti.template(), y):
            """Row ``y`` of ``F0`` (region 0), of its x-dilations and of the regions without y-dilation,
            with their in-image pixel counts (a row pass; reads the marks of rows ``y`` and ``y - 1``)."""
            NW = n_words(tf.width)
            last = last_word_mask(tf)
            px = ti.Vector([0 for _ in ti.static(range(R))])
            for j in range(NW):
                w = touched(tf, y, j)
                left = touched(tf, y, j - 1)
                right = touched(tf, y, j + 1)
                tf.words[region_word(tf, 0, y, j)] = w
                px[0] += row_pixels(tf, w, j)
                for s in ti.static(range(n_kx)):
                    d = w
                    for k in ti.static(range(1, kxs[s] + 1)):
                        d |= (w << ti.u32(k)) | (w >> ti.u32(k))
                        d |= (left >> ti.u32(WORD - k)) | (right << ti.u32(WORD - k))
                    if j == NW - 1:
                        d &= last
                    tf.words[plane_word(tf, s, y, j)] = d
                    for ri in ti.static(range(1, R)):
                        if ti.static(regions[ri][1] == 0 and kx_slot[ri] == s):
                            tf.words[region_word(tf, ri, y, j)] = d
                            px[ri] += row_pixels(tf, d, j)
            for ri in ti.static(range(R)):
                if ti.static(regions[ri][1] == 0):
                    tf.rowpx[ri * tf.height + y] = px[ri]

        @ti.func
        def build_y(tf: ti.template(), y):
            """Row ``y`` of the regions with y-dilation (from :meth:`build_x`'s rows ``y - ry .. y + ry``:
            a later row pass), their in-image pixel counts, and the marks of row ``y`` cleared."""
            H = tf.height
            NW = n_words(tf.width)
            for ri in ti.static(range(1, R)):
                ry = ti.static(regions[ri][1])
                if ti.static(ry > 0):
                    px = 0
                    for j in range(NW):
                        w = ti.u32(0)
                        for dy in ti.static(range(-ry, ry + 1)):
                            if 0 <= y + dy < H:
                                w |= tf.words[plane_word(tf, kx_slot[ri], y + dy, j)]
                        tf.words[region_word(tf, ri, y, j)] = w
                        px += row_pixels(tf, w, j)
                    tf.rowpx[ri * H + y] = px
            for j in range(NW):
                tf.words[_mark_word(tf, y + 1, j)] = ti.u32(0)
                if y == 0:
                    tf.words[_mark_word(tf, 0, j)] = ti.u32(0)

        @ti.func
        def stale(tf: ti.template(), h: ti.template(), y, j):
            """Segments of history slot ``h`` (region ``history[h]``) in the previous call's region but
            not in the new one (row ``y``, word ``j``); the new region becomes the old one."""
            new = tf.words[region_word(tf, history[h], y, j)]
            i = old_word(tf, h, y, j)
            w = tf.words[i] & ~new
            tf.words[i] = new
            return w

        @ti.func
        def segments_of_word(j, w, y, body: ti.template(), state: ti.template()):
            """``body(y, x0, state)`` for the segment of every set bit of word ``j``'s value ``w``."""
            while w != ti.u32(0):
                x0 = first_pixel(j, w)
                w = drop_lowest(w)
                body(y, x0, state)

        @ti.func
        def each_segment(tf: ti.template(), ri: ti.template(), y, body: ti.template(), state: ti.template()):
            """``body(y, x0, state)`` for every segment of region ``ri`` in row ``y``, left to right (``x0``:
            its first column). ``state`` reaches ``body`` by reference (a template): a local vector, a
            field, or a tuple of them, indexed in ``body`` (unpacking a tuple copies its elements)."""
            for j in range(n_words(tf.width)):
                segments_of_word(j, tf.words[region_word(tf, ri, y, j)], y, body, state)

        @ti.func
        def pixels_of_segment(y, x0, body_state: ti.template()):
            for p in ti.static(range(SEG)):
                if in_image(x0 + p, body_state[2]):
                    body_state[0](y, x0 + p, body_state[1])

        @ti.func
        def each_pixel(tf: ti.template(), ri: ti.template(), y, body: ti.template(), state: ti.template()):
            """``body(y, x, state)`` at every in-image pixel of region ``ri`` in row ``y``, left to right
            (``state`` as in :meth:`each_segment`)."""
            each_segment(tf, ri, y, pixels_of_segment, (body, state, tf.width))

        @ti.func
        def each_stale_segment(
            tf: ti.template(), h: ti.template(), y, body: ti.template(), state: ti.template()
        ):
            """``body(y, x0, state)`` for every segment of row ``y`` that :meth:`stale` returns for history
            slot ``h`` (the previous call's region less the new one; the new one becomes the old)."""
            for j in range(n_words(tf.width)):
                segments_of_word(j, stale(tf, h, y, j), y, body, state)

        @ti.func
        def row_pixel_count(tf: ti.template(), ri: ti.template(), y):
            """In-image pixels of region ``ri`` in row ``y`` (of the last build)."""
            return tf.rowpx[ri * tf.height + y]

        self.build_x, self.build_y, self.stale = build_x, build_y, stale
        self.each_segment, self.each_pixel, self.each_stale_segment = (
            each_segment,
            each_pixel,
            each_stale_segment,
        )
        self.row_pixel_count = row_pixel_count

        if layout.lists:

            @ti.func
            def prefix(tf: ti.template()):
                """List offsets of every row, list lengths, pixel counts (at the top level of a kernel,
                after :meth:`build_y`: serial loops)."""
                for ri in ti.static(range(R)):
                    tf.rows[ri, 0] = 0
                    tf.count[ri] = 0
                    tf.pixels[ri] = 0
                ti.loop_config(serialize=True)
                for y in range(tf.height):
                    for ri in ti.static(range(R)):
                        n = 0
                        for j in range(n_words(tf.width)):
                            n += ti.cast(ti.math.popcnt(tf.words[region_word(tf, ri, y, j)]), ti.i32)
                        tf.count[ri] += n
                        tf.rows[ri, y + 1] = tf.count[ri]
                        tf.pixels[ri] += row_pixel_count(tf, ri, y)

            @ti.func
            def fill(tf: ti.template(), y):
                """Row ``y``'s segments into every list (a row pass after :meth:`prefix`)."""
                NS = n_segments(tf.width)
                for ri in ti.static(range(R)):
                    pos = tf.rows[ri, y]
                    for j in range(n_words(tf.width)):
                        w = tf.words[region_word(tf, ri, y, j)]
                        while w != ti.u32(0):
                            tf.lists[ri, pos] = y * NS + j * WORD + lowest_bit(w)
                            pos += 1
                            w = drop_lowest(w)

            @ti.kernel
            def compact(tf: ti.template()):
                """Regions and lists of the marks the splats left (and the marks cleared)."""
                for y in range(tf.height):
                    build_x(tf, y)
                for y in range(tf.height):
                    build_y(tf, y)
                prefix(tf)
                for y in range(tf.height):
                    fill(tf, y)

            self.prefix, self.fill, self.compact = prefix, fill, compact


_OPS: dict = {}


def ops_for(layout: TileLayout) -> TileOps:
    """The (cached) :class:`TileOps` of ``layout`` (a :class:`TileLayout`, or a :class:`TileFields`:
    its layout)."""
    layout = getattr(layout, "layout", layout)
    ops = _OPS.get(layout)
    if ops is None:
        ops = _OPS[layout] = TileOps(layout)
    return ops


def make_clear_kernel(tf: TileFields, region: int, images=(), rows=(), scalars=()):
    """A kernel ``clear()`` that zeroes what one evaluation of an autodiff chain wrote, before the next:
    ``images`` (``(C, H, W)`` or ``(H, W)`` fields; pass ``f.grad`` to clear a gradient) over the
    segments of list ``region`` of ``tf`` (the last compaction's: the region everything was written
    in), ``rows`` (pairs ``(field, list)``: per-entry ``(n, k)`` partial sums, the first
    ``count[list]`` rows) and ``scalars`` (0-D fields). Built per set of fields (they are closed
    over)."""

    @ti.kernel
    def clear():
        for k in range(tf.count[region]):
            y, x0 = entry(tf, region, k)
            for p in ti.static(range(SEG)):
                x = x0 + p
                if in_image(x, tf.width):
                    for img in ti.static(images):
                        if ti.static(len(img.shape) == 2):
                            img[y, x] = 0.0
                        else:
                            for c in ti.static(range(img.shape[0])):
                                img[c, y, x] = 0.0
        for field, lst in ti.static(rows):
            for k in range(tf.count[lst]):
                for j in ti.static(range(field.shape[1])):
                    field[k, j] = 0.0
        for f in ti.static(scalars):
            if ti.static(isinstance(f, ti.MatrixField)):
                for j in ti.static(range(f.n)):
                    f[None][j] = 0.0
            else:
                f[None] = 0.0

    return clear
