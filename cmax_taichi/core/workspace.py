"""Pooled Taichi fields and arrays shared by problems of the same shapes, and compiled kernels.

The generic chains' kernels take fields as template arguments, so every new field instance means
compiling them again (about a second each on a CPU). Problems with the same static shape (event
capacity, sensor, channels, parameters, regularizers, blur footprint, ...) therefore share one
:class:`Workspace`; the events and constants of a problem are uploaded again only when another problem
used the workspace in between. A sequence of windows solved one after the other compiles once. The
fused kernels take their arrays as arguments: their workspaces hold the arrays of one sensor, and
their kernels are kept apart (:func:`compiled`), keyed by the configuration alone, so that a problem
on another sensor reuses them.
"""

from __future__ import annotations

import contextlib
import weakref
from collections.abc import Callable, Iterator

import taichi as ti

from cmax_taichi.core import backend

_POOL: dict = {}
_COMPILED: dict = {}
backend.on_reset(_POOL.clear)
backend.on_reset(_COMPILED.clear)

MIN_CAPACITY = 1024


def capacity_for(n: int) -> int:
    """Event capacity bucket for ``n`` events: the next power of two (at least MIN_CAPACITY)."""
    cap = MIN_CAPACITY
    while cap < n:
        cap *= 2
    return cap


class Workspace:
    """The fields of one problem shape. ``owner`` is a weak reference to the problem whose events and
    constants are loaded now."""

    def __init__(self, key: tuple, build: Callable[[Workspace], None]) -> None:
        self.key = key
        self._owner = None
        build(self)

    def owned_by(self, problem) -> bool:
        return self._owner is not None and self._owner() is problem

    def take(self, problem) -> None:
        self._owner = weakref.ref(problem)

    def release(self) -> None:
        """Forget the owner: the next user uploads its events and constants (a problem that took a
        new window, or changed a constant)."""
        self._owner = None


@contextlib.contextmanager
def allocating(what: str) -> Iterator[None]:
    """Declare fields (or make host arrays) inside this block; fields are allocated (materialized) at
    its end.

    A Taichi failure while declaring or allocating them (the machine's or the device's memory, the
    address space, Taichi's limit on fields per tree) would leave Taichi unable to make any new field;
    instead the backend is re-initialised with the same settings (:func:`backend.recover`: the pools
    and compiled kernels are dropped) and one MemoryError names ``what`` and Taichi's reason. A host
    array that cannot be allocated is one MemoryError naming ``what`` too (nothing to re-initialise).
    """
    try:
        yield
        ti.lang.impl.get_runtime().materialize()
    except MemoryError as exc:  # a host (NumPy) array: Taichi's state is untouched
        reason = " ".join(str(exc).split()).rstrip(".")
        raise MemoryError(
            f"could not allocate the arrays of {what}: {reason} (the process goes on as before; a smaller "
            "sensor or window needs less)"
        ) from None
    except RuntimeError as exc:  # Taichi's allocation errors, TaichiRuntimeError, failed assertions
        reason = " ".join(str(exc).split()).rstrip(".")
        backend.recover()
        raise MemoryError(
            f"Taichi could not allocate the fields of {what}: {reason}. The Taichi backend was "
            "re-initialised with the same arch and precision (the process goes on; problems built "
            "before must be built again)"
        ) from None


def compiled(key: tuple, build: Callable[[], object]):
    """The kernels of ``key`` (a configuration: model, objective, regularizers, layout; never a sensor
    size), built by ``build()`` on first use and kept for the life of the Taichi program."""
    found = _COMPILED.get(key)
    if found is None:
        found = _COMPILED[key] = build()
    return found


def acquire(key: tuple, build: Callable[[Workspace], None], what: str = "") -> Workspace:
    """The pooled workspace for ``key``, built by ``build(ws)`` on first use inside :func:`allocating`
    (``what`` names it in the error)."""
    ws = _POOL.get(key)
    if ws is None:
        with allocating(what or f"a {key[0]} workspace"):
            ws = Workspace(key, build)
        _POOL[key] = ws
    return ws


class EventBuffer:
    """A pooled ``ti.ndarray`` of per-event vectors shared by every problem with the same vector length
    and capacity bucket; ``owner`` is a weak reference to the problem whose events it holds now.

    Taichi 1.7.4 never frees a vector ndarray: one per problem leaked about 24 bytes per event for the
    life of the process (a recording of 3,000 windows of 30,000 events: 2 GB). One buffer per capacity
    bucket (a power of two) bounds that by the window sizes a process sees, whatever the window count.
    """

    def __init__(self, dtype, n_columns: int, capacity: int) -> None:
        self.array = ti.ndarray(dtype, shape=(capacity, n_columns))
        self.capacity = capacity
        self._owner = None

    def owned_by(self, problem) -> bool:
        return self._owner is not None and self._owner() is problem

    def release(self) -> None:
        """Forget the owner: the next :meth:`load` uploads (its problem took a new window)."""
        self._owner = None

    def load(self, problem, padded) -> None:
        """Upload ``padded`` (``(capacity, n_columns)`` host array) for ``problem``, unless it holds them."""
        if not self.owned_by(problem):
            self.array.from_numpy(padded)
            self._owner = weakref.ref(problem)


def event_buffer(dtype, n_columns: int, n_events: int) -> EventBuffer:
    """The pooled event buffer for ``n_events`` vectors of ``n_columns`` (capacity: :func:`capacity_for`)."""
    capacity = capacity_for(n_events)
    key = ("events", backend.info().generation, str(dtype), int(n_columns), capacity)
    buf = _POOL.get(key)
    if buf is None:
        with allocating(f"an event buffer of {capacity:,} x {n_columns} values"):
            buf = EventBuffer(dtype, n_columns, capacity)
        _POOL[key] = buf
    return buf


def dummy(dtype, shape=(1,)):
    """A placeholder field for kernel arguments that a configuration does not use."""
    return ti.field(dtype, shape=shape)
