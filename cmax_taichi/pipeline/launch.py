"""The arrays a hand-written-gradient kernel takes as arguments, and its launch from Python.

The fused kernels (``kernels/fused.py``, ``kernels/dense_flow.py``) read no Taichi field: every array
they use is an argument. On the CPU those are NumPy arrays that Taichi reads in place
(:class:`HostArray`: no copy per launch); on a GPU, Taichi ndarrays in device memory
(:func:`kernel_arrays`). :class:`DirectLaunch` launches a compiled kernel through its C++ launch
context, without Taichi's per-call Python work.
"""

from __future__ import annotations

import numpy as np
import taichi as ti
from taichi.lang import impl as ti_impl

from cmax_taichi.core import backend

__all__ = ["DirectLaunch", "HostArray", "array_bytes", "kernel_arrays", "plain"]


class DirectLaunch:
    """One compiled Taichi kernel launched through its C++ launch context.

    ``Kernel.__call__`` of Taichi 1.7.4 spends ~60-80 us of Python per launch of the fused kernel
    (12 arguments: template mapping, type checks and conversion of each, the compiled-kernel lookup);
    the kernel itself runs in tens of us for a small window. After one ordinary call has compiled it,
    this holds the compiled kernel and one launch context: a call sets the arguments that changed and
    launches (a few us). Taichi internals (the version is pinned in pyproject.toml): where they differ,
    :meth:`make` returns None and the ordinary call serves. Valid while Taichi runs the program it was
    made in (:meth:`valid`: a reset or re-initialisation makes a new one).
    """

    def __init__(self, kernel, args: tuple) -> None:
        primal = kernel._primal
        key = primal.ensure_compiled(*args)
        self._t_kernel = primal.compiled_kernels[key]
        prog = self._prog = ti_impl.get_runtime().prog
        self._data = prog.compile_kernel(prog.config(), prog.get_device_caps(), self._t_kernel)
        self.ctx = self._t_kernel.make_launch_context()
        self.set_for = None  # (the caller's record of what its arrays were last set for)

    @classmethod
    def make(cls, kernel, args: tuple) -> DirectLaunch | None:
        try:
            return cls(kernel, args)
        except (AttributeError, KeyError, TypeError, RuntimeError):
            return None

    def valid(self) -> bool:
        return ti_impl.get_runtime().prog is self._prog

    def set_array(self, index: int, array) -> None:
        """Array argument ``index``: a Taichi ndarray, or a :class:`HostArray`. Before every launch: a
        launch replaces the arrays in the context with device pointers."""
        if isinstance(array, HostArray):
            self.ctx.set_arg_external_array_with_shape((index,), array.address, array.nbytes, array.shape, 0)
        else:
            self.ctx.set_arg_ndarray((index,), array.arr)

    def launch(self) -> None:
        self._prog.launch_kernel(self._data, self.ctx)


class HostArray:
    """A C-contiguous NumPy array of scalars passed to a kernel as an external array (on the CPU, Taichi
    reads it in place: no copy), with what the launch context needs (its address, size and shape)."""

    def __init__(self, array: np.ndarray) -> None:
        if not array.flags.c_contiguous:
            raise ValueError("a kernel's host array must be C-contiguous")
        self.array = array
        self.address = int(array.ctypes.data)
        self.nbytes = array.nbytes
        self.shape = array.shape


def array_bytes(arrays: dict) -> int:
    """Bytes held by the arrays of :func:`kernel_arrays`."""
    total = 0
    for a in arrays.values():
        if isinstance(a, HostArray):
            total += a.nbytes
        else:
            total += int(np.prod(a.shape)) * np.dtype(ti_to_numpy(a.dtype)).itemsize
    return total


def ti_to_numpy(dtype):
    """The NumPy type of a Taichi primitive type."""
    return {ti.f32: np.float32, ti.f64: np.float64, ti.u32: np.uint32, ti.i32: np.int32}[dtype]


def plain(array):
    """What an ordinary kernel call takes for an array argument (the NumPy array of a host array)."""
    return array.array if isinstance(array, HostArray) else array


def kernel_arrays(sizes: dict, on_device: bool) -> dict:
    """The arrays of ``sizes`` (``{name: (kind, length)}``, ``FusedShape.array_sizes``), zeroed: host
    arrays that the CPU reads in place, or Taichi ndarrays on a GPU. In the kernels' argument order."""
    dtypes = {"real": backend.numpy_real(), "f64": np.float64, "u32": np.uint32, "i32": np.int32}
    arrays = {}
    for name, (kind, length) in sizes.items():
        if on_device:
            taichi_type = {"real": backend.real(), "f64": ti.f64, "u32": ti.u32, "i32": ti.i32}[kind]
            arrays[name] = ti.ndarray(taichi_type, shape=max(int(length), 1))
            arrays[name].fill(0)
        else:
            arrays[name] = HostArray(np.zeros(max(int(length), 1), dtype=dtypes[kind]))
    return arrays
