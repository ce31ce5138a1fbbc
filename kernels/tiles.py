"""Where a window's image work happens: segment masks of the pixels its warped events touch, dilated
by the footprint of each image pass.

Every image pass of the pipelines (slice sums, blurs, objective and map reductions, Sobel, adjoints,
clears) runs over the pixels the events can reach rather than over all ``W x H``: a 5,000-event window
touches a few ten thousand pixels of a 1280x720 sensor. The image is cut into **segments** of
:data:`SEG` = 4 pixels of one row; a *mask* holds one bit per segment, 32 segments to a ``u32`` word
(``words`` per row). Bit ``b`` of word ``j`` of row ``y`` is the segment of pixels
``x0 = SEG (32 j + b) .. x0 + 3`` of row ``y``.

* The splat calls :func:`TileOps.mark` for every footprint it votes: the segments of its top-left row
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
  marks cleared for the next call). The fused kernel then loops over rows and iterates the set bits of
  a row's words (:func:`first_pixel`, :func:`drop_lowest`); the autodiff chains need flat loops and
  read the regions as **lists** of segments in row-major order (:meth:`TileOps.prefix`,
  :meth:`TileOps.fill`, :func:`make_entry`), and clear what the last evaluation wrote over the last
  lists before the next (:func:`make_clear_kernel`).

Everything here is integer work on ``u32`` / ``i32`` fields, never differentiated; the lists and
masks are a function of the set of touched pixels only, so the order of every pass and reduction that
follows them is fixed (the same input gives the same sums to the last bit). ``clz`` is avoided (its
SPIR-V lowering fails in Taichi 1.7.4 on Vulkan): the lowest set bit comes from ``popcnt``.
"""

import taichi as ti

SEG = 4  # pixels per segment (of one row)
WORD = 32  # segments per mask word


def reach(px: int) -> int:
    """Segments of x dilation that cover ``px`` pixels on each side: ``ceil(px / SEG)``."""
    return -(-int(px) // SEG)


class TileFields:
    """The mask fields of one ``width x height`` image and its regions.

    Parameters
    ----------
    width, height : int
        Image size, px.
    regions : sequence of (int, int)
        ``(kx, ry)`` of each region (segments along x, rows along y); the first must be ``(0, 0)``
        (``F0``).
    history : sequence of int
        Regions whose previous masks are kept (``old``), so that a pass can clear what the previous
        call left outside the new region (:meth:`TileOps.stale`).
    lists : bool
        Also keep each region as a list of segments (the autodiff chains' flat loops).
    """

    def __init__(self, width: int, height: int, regions, *, history=(), lists: bool = False) -> None:
        regions = tuple((int(kx), int(ry)) for kx, ry in regions)
        if not regions or regions[0] != (0, 0):
            raise ValueError("region 0 must be (0, 0): the touched segments")
        if any(kx < 0 or ry < 0 or kx >= WORD for kx, ry in regions):
            raise ValueError(f"region dilations must be 0 <= kx < {WORD} and ry >= 0, got {regions}")
        W, H = int(width), int(height)
        self.width, self.height = W, H
        self.regions = regions
        self.history = tuple(int(h) for h in history)
        self.n_segments = -(-W // SEG)
        self.n_words = -(-self.n_segments // WORD)
        self.kxs = tuple(sorted({kx for kx, _ in regions}))  # distinct x dilations (build_x)
        R, NW = len(regions), self.n_words
        self.marks = ti.field(ti.u32, shape=(H + 1, NW))  # row iy + 1: set by the splat; cleared by build_y
        self.xmask = ti.field(ti.u32, shape=(len(self.kxs), H, NW))  # F0 dilated along x
        self.masks = ti.field(ti.u32, shape=(R, H, NW))  # the regions of the last build
        self.old = ti.field(ti.u32, shape=(max(len(self.history), 1), H, NW))  # regions of the call before
        self.rowpx = ti.field(ti.i32, shape=(R, H))  # in-image pixels of each region's row
        self.pixels = ti.field(ti.i32, shape=R)  # in-image pixels of each region
        self.lists = None
        if lists:
            self.rows = ti.field(ti.i32, shape=(R, H + 1))  # list offset of each row
            self.lists = ti.field(ti.i32, shape=(R, H * self.n_segments))  # y * n_segments + segment
            self.count = ti.field(ti.i32, shape=R)  # segments per list

    def nbytes(self) -> int:
        """Bytes held by the mask and list fields."""
        R, H, NW = len(self.regions), self.height, self.n_words
        total = 4 * NW + 4 * H * NW * (1 + len(self.kxs) + R + max(len(self.history), 1)) + 4 * R * (H + 1)
        if self.lists is not None:
            total += 4 * R * (H + 1 + H * self.n_segments + 1)
        return total


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


def make_in_image(width: int):
    """``in_image(x)``: column ``x`` of a segment lies in the image of ``width`` px (only the last segment
    of a row can stick out; always true when the width is a multiple of :data:`SEG`)."""
    W = int(width)
    partial = SEG * (-(-W // SEG)) - W  # columns of a row's last segment beyond the image

    @ti.func
    def in_image(x):
        inside = True
        if ti.static(partial > 0):
            inside = x < W
        return inside

    return in_image


def make_mark(width: int, height: int):
    """``mark(tf, ix, iy)``: mark the footprint with top-left corner ``(ix, iy)`` (px; ``-1 .. W - 1``,
    ``-1 .. H - 1``) in ``tf.marks``: the segments of mark row ``iy + 1`` holding columns ``ix`` and
    ``ix + 1`` clipped into the image (the footprint's second row comes with ``F0``). Atomic, after
    a load that skips bits already set."""
    W, H = int(width), int(height)

    @ti.func
    def set_bits(tf: ti.template(), y, j, bits):
        if (tf.marks[y, j] & bits) != bits:
            ti.atomic_or(tf.marks[y, j], bits)

    @ti.func
    def mark(tf: ti.template(), ix, iy):
        y = ti.min(ti.max(iy, -1), H - 1) + 1
        s0 = ti.max(ix, 0) // SEG
        s1 = ti.min(ix + 1, W - 1) // SEG
        j0 = s0 // WORD
        b0 = ti.u32(1) << ti.cast(s0 % WORD, ti.u32)
        b1 = ti.u32(1) << ti.cast(s1 % WORD, ti.u32)
        if s1 // WORD == j0:
            set_bits(tf, y, j0, b0 | b1)
        else:
            set_bits(tf, y, j0, b0)
            set_bits(tf, y, j0 + 1, b1)

    return mark


def make_mark_position(width: int, height: int):
    """``mark_position(tf, q)``: :func:`make_mark`'s mark of the footprint of a warped position ``q``
    (px) whose footprint touches the image (nothing otherwise, NaN included)."""
    W, H = int(width), int(height)
    mark = make_mark(W, H)

    @ti.func
    def mark_position(tf: ti.template(), q):
        if q[0] > -1.0 and q[0] < W and q[1] > -1.0 and q[1] < H:
            mark(tf, ti.cast(ti.floor(q[0]), ti.i32), ti.cast(ti.floor(q[1]), ti.i32))

    return mark_position


def make_entry(width: int):
    """``entry(tf, ri, k) -> (y, x0)``: row and first pixel column of entry ``k`` of list ``ri``."""
    NS = -(-int(width) // SEG)

    @ti.func
    def entry(tf: ti.template(), ri: ti.template(), k):
        e = tf.lists[ri, k]
        return e // NS, (e % NS) * SEG

    return entry


class TileOps:
    """The Taichi functions over the fields of a :class:`TileFields` of one geometry (sizes, regions and
    history compiled in). Each takes the fields as its first (template) argument, so kernels built
    from one ``TileOps`` serve every ``TileFields`` of that geometry."""

    def __init__(self, tf: TileFields) -> None:
        self.geometry = (tf.width, tf.height, tf.regions, tf.history, tf.lists is not None)
        W, H = tf.width, tf.height
        NS, NW, R = tf.n_segments, tf.n_words, len(tf.regions)
        regions, kxs, history = tf.regions, tf.kxs, tf.history
        kx_slot = tuple(kxs.index(kx) for kx, _ in regions)
        tail = NS - WORD * (NW - 1)  # segments in the last word of a row
        last_mask = (1 << tail) - 1 if tail < WORD else 0xFFFFFFFF
        partial = SEG * NS - W  # columns of the last segment beyond the image
        self.partial = partial

        mark = make_mark(W, H)

        @ti.func
        def touched(tf: ti.template(), y, j):
            """Word ``j`` of ``F0`` in row ``y``: the footprints whose top row is ``y`` (mark row
            ``y + 1``) or ``y - 1`` (mark row ``y``)."""
            w = ti.u32(0)
            if 0 <= j < NW:
                w = tf.marks[y + 1, j] | tf.marks[y, j]
            return w

        @ti.func
        def row_pixels(w, j):
            """In-image pixels of the segments of word ``j``'s value ``w``."""
            px = ti.cast(ti.math.popcnt(w), ti.i32) * SEG
            if ti.static(partial > 0):  # noqa: SIM102 - compile-time if
                if j == NW - 1 and (w >> ti.u32(tail - 1)) & ti.u32(1) != ti.u32(0):
                    px -= partial
            return px

        @ti.func
        def build_x(tf: ti.template(), y):
            """Row ``y`` of ``F0`` (region 0), of its x-dilations and of the regions without y-dilation,
            with their in-image pixel counts (a row pass; reads the marks of rows ``y`` and ``y - 1``)."""
            px = ti.Vector([0 for _ in ti.static(range(R))])
            for j in range(NW):
                w = touched(tf, y, j)
                left = touched(tf, y, j - 1)
                right = touched(tf, y, j + 1)
                tf.masks[0, y, j] = w
                px[0] += row_pixels(w, j)
                for s in ti.static(range(len(kxs))):
                    d = w
                    for k in ti.static(range(1, kxs[s] + 1)):
                        d |= (w << ti.u32(k)) | (w >> ti.u32(k))
                        d |= (left >> ti.u32(WORD - k)) | (right << ti.u32(WORD - k))
                    if j == NW - 1:
                        d &= ti.u32(last_mask)
                    tf.xmask[s, y, j] = d
                    for ri in ti.static(range(1, R)):
                        if ti.static(regions[ri][1] == 0 and kx_slot[ri] == s):
                            tf.masks[ri, y, j] = d
                            px[ri] += row_pixels(d, j)
            for ri in ti.static(range(R)):
                if ti.static(regions[ri][1] == 0):
                    tf.rowpx[ri, y] = px[ri]

        @ti.func
        def build_y(tf: ti.template(), y):
            """Row ``y`` of the regions with y-dilation (from :meth:`build_x`'s rows ``y - ry .. y + ry``:
            a later row pass), their in-image pixel counts, and the marks of row ``y`` cleared."""
            for ri in ti.static(range(1, R)):
                ry = ti.static(regions[ri][1])
                if ti.static(ry > 0):
                    px = 0
                    for j in range(NW):
                        w = ti.u32(0)
                        for dy in ti.static(range(-ry, ry + 1)):
                            if 0 <= y + dy < H:
                                w |= tf.xmask[kx_slot[ri], y + dy, j]
                        tf.masks[ri, y, j] = w
                        px += row_pixels(w, j)
                    tf.rowpx[ri, y] = px
            for j in range(NW):
                tf.marks[y + 1, j] = ti.u32(0)
                if y == 0:
                    tf.marks[0, j] = ti.u32(0)

        @ti.func
        def stale(tf: ti.template(), h: ti.template(), y, j):
            """Segments of history slot ``h`` (region ``history[h]``) in the previous call's region but
            not in the new one (row ``y``, word ``j``); the new region becomes the old one."""
            new = tf.masks[history[h], y, j]
            w = tf.old[h, y, j] & ~new
            tf.old[h, y, j] = new
            return w

        in_image = make_in_image(W)

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
            for j in range(NW):
                segments_of_word(j, tf.masks[ri, y, j], y, body, state)

        @ti.func
        def pixels_of_segment(y, x0, body_state: ti.template()):
            for p in ti.static(range(SEG)):
                if in_image(x0 + p):
                    body_state[0](y, x0 + p, body_state[1])

        @ti.func
        def each_pixel(tf: ti.template(), ri: ti.template(), y, body: ti.template(), state: ti.template()):
            """``body(y, x, state)`` at every in-image pixel of region ``ri`` in row ``y``, left to right
            (``state`` as in :meth:`each_segment`)."""
            each_segment(tf, ri, y, pixels_of_segment, (body, state))

        @ti.func
        def each_stale_segment(
            tf: ti.template(), h: ti.template(), y, body: ti.template(), state: ti.template()
        ):
            """``body(y, x0, state)`` for every segment of row ``y`` that :meth:`stale` returns for history
            slot ``h`` (the previous call's region less the new one; the new one becomes the old)."""
            for j in range(NW):
                segments_of_word(j, stale(tf, h, y, j), y, body, state)

        self.mark, self.build_x, self.build_y, self.stale, self.in_image = (
            mark,
            build_x,
            build_y,
            stale,
            in_image,
        )
        self.each_segment, self.each_pixel, self.each_stale_segment = (
            each_segment,
            each_pixel,
            each_stale_segment,
        )

        if tf.lists is not None:

            @ti.func
            def prefix(tf: ti.template()):
                """List offsets of every row, list lengths, pixel counts (at the top level of a kernel,
                after :meth:`build_y`: serial loops)."""
                for ri in ti.static(range(R)):
                    tf.rows[ri, 0] = 0
                    tf.count[ri] = 0
                    tf.pixels[ri] = 0
                ti.loop_config(serialize=True)
                for y in range(H):
                    for ri in ti.static(range(R)):
                        n = 0
                        for j in range(NW):
                            n += ti.cast(ti.math.popcnt(tf.masks[ri, y, j]), ti.i32)
                        tf.count[ri] += n
                        tf.rows[ri, y + 1] = tf.count[ri]
                        tf.pixels[ri] += tf.rowpx[ri, y]

            @ti.func
            def fill(tf: ti.template(), y):
                """Row ``y``'s segments into every list (a row pass after :meth:`prefix`)."""
                for ri in ti.static(range(R)):
                    pos = tf.rows[ri, y]
                    for j in range(NW):
                        w = tf.masks[ri, y, j]
                        while w != ti.u32(0):
                            tf.lists[ri, pos] = y * NS + j * WORD + lowest_bit(w)
                            pos += 1
                            w = drop_lowest(w)

            @ti.kernel
            def compact(tf: ti.template()):
                """Regions and lists of the marks the splats left (and the marks cleared)."""
                for y in range(H):
                    build_x(tf, y)
                for y in range(H):
                    build_y(tf, y)
                prefix(tf)
                for y in range(H):
                    fill(tf, y)

            self.prefix, self.fill, self.compact = prefix, fill, compact


_OPS: dict = {}


def ops_for(tf: TileFields) -> TileOps:
    """The (cached) :class:`TileOps` of ``tf``'s geometry."""
    key = (tf.width, tf.height, tf.regions, tf.history, tf.lists is not None)
    ops = _OPS.get(key)
    if ops is None:
        ops = _OPS[key] = TileOps(tf)
    return ops


def make_clear_kernel(tf: TileFields, region: int, images=(), rows=(), scalars=()):
    """A kernel ``clear()`` that zeroes what one evaluation of an autodiff chain wrote, before the next:
    ``images`` (``(C, H, W)`` or ``(H, W)`` fields; pass ``f.grad`` to clear a gradient) over the
    segments of list ``region`` of ``tf`` (the last compaction's: the region everything was written
    in), ``rows`` (pairs ``(field, list)``: per-entry ``(n, k)`` partial sums, the first
    ``count[list]`` rows) and ``scalars`` (0-D fields). Built per set of fields (they are closed
    over)."""
    entry = make_entry(tf.width)
    in_image = make_in_image(tf.width)

    @ti.kernel
    def clear():
        for k in range(tf.count[region]):
            y, x0 = entry(tf, region, k)
            for p in ti.static(range(SEG)):
                x = x0 + p
                if in_image(x):
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


class SegmentPasses:
    """The per-segment image operations of the fused kernel's row passes over ``(H, W, C)`` plane fields
    (``fused._planes``): the separable blur's two 1-D passes, the blur along y applied twice (the
    backward's ``B_y^T B_y``), stores and clears, at the :data:`SEG` pixels ``x0 .. x0 + SEG - 1`` of
    row ``y``, with zero padding at the image's borders. Away from the borders the taps read whole
    segments without bounds checks (vector loads).

    Parameters
    ----------
    width, height : int
        Image size, px.
    radius : int
        Blur footprint radius, px (0: no blur, one tap of 1).
    """

    def __init__(self, width: int, height: int, radius: int) -> None:
        W, H, r_ = int(width), int(height), int(radius)
        partial = SEG * (-(-W // SEG)) - W  # columns of a row's last segment beyond the image
        in_image = make_in_image(W)

        @ti.func
        def whole(x0):
            """All pixels of the segment at ``x0`` are in the image (always, when the width is a multiple
            of the segment)."""
            inside = True
            if ti.static(partial > 0):
                inside = x0 + SEG <= W
            return inside

        @ti.func
        def load_taps(taps: ti.template()):
            """The blur taps as a local vector (a field is loaded again after every store: LLVM cannot
            tell the fields apart)."""
            tv = ti.Vector([1.0 for _ in ti.static(range(2 * r_ + 1))])
            if ti.static(r_ > 0):
                for k in ti.static(range(2 * r_ + 1)):
                    tv[k] = taps[k]
            return tv

        @ti.func
        def pixel_of(src: ti.template(), votes: ti.template(), c: ti.template(), y, x):
            v = 0.0
            if ti.static(votes):  # slice 0 of the vote field
                v = src[0, y, x, c]
            else:
                v = src[y, x, c]
            return v

        @ti.func
        def blur_x(src: ti.template(), votes: ti.template(), c: ti.template(), y, x0, tv):
            """``sum_k taps_k src[y, x + k, c]`` at the segment's pixels (``votes``: ``src`` is the
            vote field, read in its slice 0)."""
            v = ti.Vector([0.0 for _ in ti.static(range(SEG))])
            if whole(x0) and x0 >= r_ and x0 + SEG - 1 + r_ < W:
                for k in ti.static(range(-r_, r_ + 1)):
                    for p in ti.static(range(SEG)):
                        v[p] += tv[k + r_] * pixel_of(src, votes, c, y, x0 + p + k)
            else:
                for k in ti.static(range(-r_, r_ + 1)):
                    for p in ti.static(range(SEG)):
                        if 0 <= x0 + p + k < W and in_image(x0 + p):
                            v[p] += tv[k + r_] * pixel_of(src, votes, c, y, x0 + p + k)
            return v

        @ti.func
        def blur_y(src: ti.template(), c: ti.template(), y, x0, tv):
            """``sum_k taps_k src[y + k, x, c]`` at the segment's pixels."""
            v = ti.Vector([0.0 for _ in ti.static(range(SEG))])
            if whole(x0) and y >= r_ and y < H - r_:
                for k in ti.static(range(-r_, r_ + 1)):
                    for p in ti.static(range(SEG)):
                        v[p] += tv[k + r_] * src[y + k, x0 + p, c]
            else:
                for k in ti.static(range(-r_, r_ + 1)):
                    if 0 <= y + k < H:
                        for p in ti.static(range(SEG)):
                            if in_image(x0 + p):
                                v[p] += tv[k + r_] * src[y + k, x0 + p, c]
            return v

        @ti.func
        def store(dst: ti.template(), c: ti.template(), y, x0, v):
            if whole(x0):
                for p in ti.static(range(SEG)):
                    dst[y, x0 + p, c] = v[p]
            else:
                for p in ti.static(range(SEG)):
                    if in_image(x0 + p):
                        dst[y, x0 + p, c] = v[p]

        @ti.func
        def twice_taps(y, tv):
            """The taps of ``B_y^T B_y`` at row ``y`` (offsets ``-2 r .. 2 r``): the Gaussian convolved
            with itself, less the products of the first blur's taps that fall outside the image."""
            wide = ti.Vector([0.0 for _ in ti.static(range(4 * r_ + 1))])
            if ti.static(r_ > 0):
                for k1 in ti.static(range(-r_, r_ + 1)):
                    if 0 <= y + k1 < H:
                        for k2 in ti.static(range(-r_, r_ + 1)):
                            wide[k1 + k2 + 2 * r_] += tv[k1 + r_] * tv[k2 + r_]
            else:
                wide[0] = 1.0
            return wide

        @ti.func
        def twice_blur_y(src: ti.template(), wide, c: ti.template(), y, x0):
            """``(B_y^T B_y src)[y, x, c]`` at the segment's pixels, with the taps of :func:`twice_taps`."""
            v = ti.Vector([0.0 for _ in ti.static(range(SEG))])
            if whole(x0) and y >= 2 * r_ and y < H - 2 * r_:
                for k in ti.static(range(-2 * r_, 2 * r_ + 1)):
                    for p in ti.static(range(SEG)):
                        v[p] += wide[k + 2 * r_] * src[y + k, x0 + p, c]
            else:
                for k in ti.static(range(-2 * r_, 2 * r_ + 1)):
                    if 0 <= y + k < H:
                        for p in ti.static(range(SEG)):
                            if in_image(x0 + p):
                                v[p] += wide[k + 2 * r_] * src[y + k, x0 + p, c]
            return v

        @ti.func
        def clear(y, x0, dst: ti.template()):
            """``dst`` zeroed at the segment (the argument order of a :meth:`TileOps.each_segment` body)."""
            for p in ti.static(range(SEG)):
                if in_image(x0 + p):
                    for c in ti.static(range(dst.shape[2])):
                        dst[y, x0 + p, c] = 0.0

        self.load_taps, self.blur_x, self.blur_y, self.store = load_taps, blur_x, blur_y, store
        self.twice_taps, self.twice_blur_y, self.clear = twice_taps, twice_blur_y, clear
