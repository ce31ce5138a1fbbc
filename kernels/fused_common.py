"""What the one-launch pipelines with a hand-written backward share: the fused CMax kernel
(``fused.py``) and the dense-flow kernel (``dense_flow.py``).

* :class:`ImageLayout`: the image side of a pipeline shape (sensor, IWE channels, blur footprint, thread
  slices, objective slots, Sobel images), given once to the fields and read by the kernels built on them;
* :class:`EventLayout`: the per-event vectors ``(x, y, dt[, w][, channel])`` of the kernels' ``ev``
  argument and how the event passes accumulate (atomics on a GPU, one slice per thread on the CPU):
  :meth:`EventLayout.reader`, :meth:`EventLayout.slices`, :meth:`EventLayout.vote`;
* :func:`objective_blocks`: a fused objective's ``ti.func`` blocks;
* :func:`read_gx`, :func:`read_gy`: the readers of the ``(H, W, 2 C)`` Sobel images of the backward;
* :func:`field_bytes`: what a set of fields holds.

The kernels unpack both layouts with ``dataclasses.astuple`` (their fields' order is part of the API).
"""

from dataclasses import dataclass
from typing import Any

import taichi as ti

#: the kernels' float64 arrays (parameters, results)
F64_ARRAY = ti.types.ndarray(dtype=ti.f64, ndim=1)


@dataclass(frozen=True)
class ImageLayout:
    """The image side of one pipeline shape (the kernels unpack it in this order).

    Parameters
    ----------
    real : Taichi float type
    width, height : int
        Sensor size, px.
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
        Allocate the Sobel images (objectives whose pixel terms read the Sobel responses).
    """

    real: Any
    width: int
    height: int
    n_channels: int
    radius: int
    n_slices: int
    shared_count: bool
    objective_slots: int
    sobel: bool


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

    def ndarray_type(self, real):
        """The Taichi type of ``ev``: a 1-D array of vectors ``(x, y, dt[, w][, channel])`` (px, px, s)."""
        width = 3 + int(self.weighted) + int(self.split_polarity)
        return ti.types.ndarray(dtype=ti.types.vector(width, real), ndim=1)

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

    def vote(self, acc):
        """``vote(s, iy, ix, k, v)``: ``acc[s, iy, ix, k] += v``, atomic or, where slice ``s`` belongs to one
        thread, a plain read-modify-write."""
        atomic = self.atomic

        @ti.func
        def vote(s, iy, ix, k, v):
            if ti.static(atomic):
                acc[s, iy, ix, k] += v
            else:
                acc[s, iy, ix, k] = acc[s, iy, ix, k] + v

        return vote


@ti.func
def read_gx(src: ti.template(), c, y, x):
    """Sobel x response of channel ``c`` in the ``(H, W, 2 C)`` Sobel images."""
    return src[y, x, 2 * c]


@ti.func
def read_gy(src: ti.template(), c, y, x):
    """Sobel y response of channel ``c`` in the ``(H, W, 2 C)`` Sobel images."""
    return src[y, x, 2 * c + 1]


def objective_blocks(objective, sobel: bool) -> tuple:
    """``(pixel, finalize, adjoint)`` of a fused objective (``models.objectives.FusedObjective``), checked
    against the fields' ``sobel`` (their layout allocates the Sobel images the objective reads)."""
    if bool(objective.sobel) != bool(sobel):
        raise ValueError("the objective's use of the Sobel images is not the fields' (ImageLayout.sobel)")
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
