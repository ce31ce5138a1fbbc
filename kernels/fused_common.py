"""What the one-launch pipelines with a hand-written backward share: the fused CMax kernel
(``fused.py``) and the dense-flow kernel (``dense_flow.py``).

Their kernels take every array that depends on the sensor as an argument (flat Taichi ndarrays, or
NumPy arrays read in place on the CPU) together with the image's width and height, and use no Taichi
field: one compiled kernel serves every sensor size, and its offline-cache key depends on the kernel's
configuration only (a kernel that reads fields is keyed by their ids too, which depend on what the
process allocated before it: another process, or another command, would compile it again).

* :class:`ImageLayout`: the compile-time image side of a pipeline shape (IWE channels, blur footprint,
  thread slices, objective slots, Sobel images), read by the kernels;
* :class:`KernelArgs`: a kernel's array and size arguments as its ``ti.func``s read them;
* :class:`Planes`: a stack of ``H x W`` planes in one flat array (:func:`at`, :func:`load`, :func:`store`);
* :class:`EventLayout`: the per-event vectors ``(x, y, dt[, w][, channel])`` of the kernels' ``ev``
  argument and how the event passes accumulate (atomics on a GPU, one slice per thread on the CPU):
  :meth:`EventLayout.reader`, :meth:`EventLayout.slices`, :meth:`EventLayout.vote`;
* :func:`objective_blocks`: a fused objective's ``ti.func`` blocks;
* :func:`read_plane`, :func:`read_gx`, :func:`read_gy`: the readers of the image and Sobel planes;
* :func:`real_array`: the Taichi type of a flat array of the kernels' float type.

The kernels unpack :class:`ImageLayout` and :class:`EventLayout` with ``dataclasses.astuple`` (their
fields' order is part of the API).
"""

from dataclasses import dataclass
from typing import Any

import taichi as ti

#: the kernels' float64 arrays (parameters, results)
F64_ARRAY = ti.types.ndarray(dtype=ti.f64, ndim=1)
#: the kernels' flat integer arrays (masks, pixel counts)
U32_ARRAY = ti.types.ndarray(dtype=ti.u32, ndim=1)
I32_ARRAY = ti.types.ndarray(dtype=ti.i32, ndim=1)


def real_array(real, ndim: int = 1):
    """The Taichi type of an ndarray of the kernels' float type (a primitive type of its own: ``real``
    may be the default float alias, which ndarray annotations do not take)."""
    return ti.types.ndarray(dtype=ti.f64 if real == ti.f64 else ti.f32, ndim=ndim)


@dataclass(frozen=True)
class ImageLayout:
    """The compile-time image side of one pipeline shape (the kernels unpack it in this order); the
    sensor's width and height are the kernels' arguments.

    Parameters
    ----------
    real : Taichi float type
    n_channels : int
        IWE channels (per reference time, in the dense flow).
    radius : int
        Blur footprint radius (px); 0 = no blur.
    n_slices : int
        Accumulation slices of the event passes (CPU threads; 1 with atomics).
    shared_count : bool
        The count ``C`` shares IWE channel 0 (unit weights, one channel).
    objective_slots : int
        Accumulator slots per channel of the objective.
    sobel : bool
        Keep the Sobel images (objectives whose pixel terms read the Sobel responses).
    """

    real: Any
    n_channels: int
    radius: int
    n_slices: int
    shared_count: bool
    objective_slots: int
    sobel: bool


class KernelArgs:
    """A kernel's array and size arguments, as the ``ti.func``s of its factory read them.

    Taichi 1.7.4 lets a ``ti.func`` read a field through its closure, but an ndarray only as an argument
    of the kernel being built. A kernel that takes its arrays as arguments binds them here as the first
    statement of its body, ``ti.static(args.bind(images=images, width=width, ...))``: while Taichi
    builds that body, the ``ti.func``s it inlines read ``args.images``, ``args.width`` (and every
    :class:`Planes` made on ``args``) as that kernel's own arguments. Outside a build the attributes
    are stale: nothing but a kernel's body may read them.
    """

    def bind(self, **arguments) -> None:
        vars(self).update(arguments)


@dataclass(frozen=True, eq=False)
class Planes:
    """``count`` planes of ``H x W`` pixels in the flat array ``args.<array>``, from plane ``base``:
    pixel ``(y, x)`` of plane ``p`` at ``((base + p) H + y) W + x``, with ``W, H`` = ``args.width``,
    ``args.height`` (row-major: the pixels of a segment of a row are contiguous, so a segment's blur
    taps are vector loads)."""

    args: KernelArgs
    array_name: str
    base: int
    count: int

    @property
    def array(self):
        """The bound array (inside a kernel's build)."""
        return getattr(self.args, self.array_name)

    @property
    def width(self):
        return self.args.width

    @property
    def height(self):
        return self.args.height


def loops_over_local_vectors() -> bool:
    """Whether the running arch compiles a run-time loop that indexes a local vector (``tv[k + r]``):
    the LLVM backends (CPU, CUDA) do; Taichi 1.7.4's SPIR-V code generator (Vulkan, Metal, OpenGL) fails
    on it ("Value ... does not yet exist"), so there such loops are unrolled."""
    return ti.lang.impl.current_cfg().arch in (ti.x64, ti.arm64, ti.cuda, ti.amdgpu)


@ti.func
def at(view: ti.template(), p, y, x):
    """Index of pixel ``(y, x)`` of plane ``p`` of ``view`` (a :class:`Planes`) in its array. Written as
    the plane's offset plus the pixel's, so that the accesses of one pixel to several planes share the
    pixel's part (LLVM eliminates common subexpressions, not reassociated ones)."""
    return ((view.base + p) * view.args.height + y) * view.args.width + x


@ti.func
def plane_size(view: ti.template()):
    """Pixels per plane, ``H W``."""
    return view.args.height * view.args.width


@ti.func
def load(view: ti.template(), p, y, x):
    """Pixel ``(y, x)`` of plane ``p`` of ``view``."""
    return view.array[at(view, p, y, x)]


@ti.func
def store(view: ti.template(), p, y, x, v):
    """Pixel ``(y, x)`` of plane ``p`` of ``view`` set to ``v``."""
    view.array[at(view, p, y, x)] = v


@ti.func
def read_plane(src: ti.template(), c, y, x):
    """Pixel ``(y, x)`` of plane ``c`` of ``src`` (the ``read`` of ``blocks.make_sobel``)."""
    return load(src, c, y, x)


@ti.func
def read_gx(src: ti.template(), c, y, x):
    """Sobel x response of channel ``c`` in Sobel planes ``(gx_0, gy_0, gx_1, ...)``."""
    return load(src, 2 * c, y, x)


@ti.func
def read_gy(src: ti.template(), c, y, x):
    """Sobel y response of channel ``c`` in Sobel planes ``(gx_0, gy_0, gx_1, ...)``."""
    return load(src, 2 * c + 1, y, x)


@dataclass(frozen=True)
class EventLayout:
    """The event vectors of a kernel's ``ev`` argument and the accumulation of its event passes.

    Parameters
    ----------
    weighted : bool
        Each event carries its vote weight ``w`` (else 1).
    split_polarity : bool
        Each event carries its IWE channel (else channel 0).
    atomic : bool
        The event passes add atomically into slice 0 (GPU); else each CPU thread owns a slice.
    """

    weighted: bool
    split_polarity: bool
    atomic: bool

    @property
    def width(self) -> int:
        """Values per event: ``(x, y, dt[, w][, channel])``."""
        return 3 + int(self.weighted) + int(self.split_polarity)

    def ndarray_type(self, real):
        """The Taichi type of ``ev``: an ``(n, width)`` array, a row ``(x, y, dt[, w][, channel])`` (px, px,
        s) per event. Scalar, not an array of vectors: Taichi 1.7.4 keys a kernel's compiled instance by
        its arguments' element types, and gives an external array of vectors a new type object at every
        call, so that each new problem built the kernel again (about a second of front end). Two
        dimensions, not one flat array with a compile-time stride: LLVM vectorizes the gather loops over
        the former and not the latter (tests/test_fused_vectorized.py)."""
        return real_array(real, ndim=2)

    def row(self):
        """``row(ev, i)``: event ``i`` of ``ev`` as a vector (what :meth:`reader` reads)."""
        width = self.width

        @ti.func
        def row(ev: ti.template(), i):
            return ti.Vector([ev[i, k] for k in ti.static(range(width))])

        return row

    def reader(self):
        """``event(e) -> (p, dt, b, ch)``: position (px), time offset (s), vote weight and IWE channel of
        one event vector."""
        weighted, split = self.weighted, self.split_polarity
        i_w, i_ch = 3, (4 if weighted else 3)

        @ti.func
        def event(e):
            b = 1.0
            if ti.static(weighted):
                b = e[i_w]
            ch = 0
            if ti.static(split):
                ch = ti.cast(e[i_ch], ti.i32)
            return ti.Vector([e[0], e[1]]), e[2], b, ch

        return event

    @staticmethod
    def slices(n_slices: int):
        """``slice_events(s, n) -> (lo, hi)``: the events ``[lo, hi)`` of thread slice ``s`` of
        ``n_slices`` (the last takes the remainder)."""
        S = int(n_slices)

        @ti.func
        def slice_events(s, n):
            chunk = n // S
            lo = s * chunk
            hi = lo + chunk
            if s == S - 1:
                hi = n
            return lo, hi

        return slice_events

    def vote(self, acc: Planes):
        """``vote(i, v)``: element ``i`` of the votes ``acc`` ``+= v`` (the caller's index: :func:`at` of a
        footprint's corner, channel planes apart): atomic or, where the slice belongs to one thread, a
        plain read-modify-write."""
        atomic = self.atomic

        @ti.func
        def vote(i, v):
            if ti.static(atomic):
                acc.array[i] += v
            else:
                acc.array[i] = acc.array[i] + v

        return vote


def objective_blocks(objective, sobel: bool) -> tuple:
    """``(pixel, finalize, adjoint)`` of a fused objective (``models.objectives.FusedObjective``), checked
    against the layout's ``sobel`` (it keeps the Sobel images the objective reads)."""
    if bool(objective.sobel) != bool(sobel):
        raise ValueError("the objective's use of the Sobel images is not the layout's (ImageLayout.sobel)")
    return objective.pixel, objective.finalize, objective.adjoint


def field_bytes(fields) -> int:
    """Bytes held by Taichi scalar fields (f32: 4 bytes an element, else 8)."""
    total = 0
    for f in fields:
        size = 1
        for s in f.shape:
            size *= s
        total += size * (4 if f.dtype == ti.f32 else 8)
    return total
