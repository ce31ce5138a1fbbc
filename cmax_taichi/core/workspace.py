"""Pooled Taichi fields shared by problems of the same shapes.

Kernels take fields as template arguments, so every new field instance means compiling the kernels
again (about a second each on a CPU). Problems with the same static shape (event capacity, sensor,
channels, parameters, regularizers, blur footprint, ...) therefore share one :class:`Workspace`; the
events and constants of a problem are uploaded again only when another problem used the workspace in
between. A sequence of windows solved one after the other compiles once.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable

import taichi as ti

from cmax_taichi.core import backend

_POOL: dict = {}
backend.on_reset(_POOL.clear)

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


def acquire(key: tuple, build: Callable[[Workspace], None]) -> Workspace:
    """The pooled workspace for ``key``, built by ``build(ws)`` on first use."""
    ws = _POOL.get(key)
    if ws is None:
        ws = _POOL[key] = Workspace(key, build)
    return ws


def dummy(dtype, shape=(1,)):
    """A placeholder field for kernel arguments that a configuration does not use."""
    return ti.field(dtype, shape=shape)
