"""core/backend.py shortens the source positions that Taichi 1.7.4's front end formats for every AST
node (a quarter of a fused kernel's build time, every process): kernels compile and run as before, and
a compile error still names the file, the line and the offending code.

(No ``from __future__ import annotations`` here: it turns the kernel's annotations into strings.)"""

import numpy as np
import pytest
import taichi as ti

import cmax_taichi as cm
from cmax_taichi.core import backend


def test_applied_to_taichi_1_7_4():
    expected = ti.__version__ == (1, 7, 4)
    assert backend.SHORT_SOURCE_POSITIONS is expected


def test_kernels_compile_and_run(f64):
    events = cm.Events([1.0, 5.0, 9.0], [2.0, 3.0, 4.0], [0.0, 0.01, 0.02], [1, 0, 1], (16, 12))
    prob = cm.ContrastMaximization(events, warp="translation2")
    value, grad = prob.value_and_grad([10.0, -5.0])
    assert np.isfinite(value) and np.all(np.isfinite(grad))


def test_a_compile_error_keeps_its_source_excerpt(f64):
    backend.ensure_initialized()

    @ti.kernel
    def broken() -> ti.f64:
        return undefined_name_in_kernel + 1.0  # noqa: F821 - the error under test

    with pytest.raises(ti.TaichiCompilationError) as err:
        broken()
    message = str(err.value)
    assert "test_backend_frontend.py" in message and "undefined_name_in_kernel" in message
    assert "^" in message  # the caret under the node, as Taichi formats it


def test_the_quicker_front_end_keeps_taichi_s_semantics(f64):
    """The cached sources (``CACHED_FUNCTION_SOURCES``) and the class test read from ``linecache``
    (``QUICK_CLASS_TEST``): a data-oriented class's kernel and method still bind to their instance, and
    one ti.func called at several sites (its source read once) gives each call its own arguments."""
    backend.ensure_initialized()
    expected = ti.__version__ == (1, 7, 4)
    assert backend.CACHED_FUNCTION_SOURCES is expected and backend.QUICK_CLASS_TEST is expected

    @ti.func
    def scaled(v, k):
        return v * k

    @ti.data_oriented
    class Holder:
        def __init__(self):
            self.x = ti.field(ti.f64, shape=4)

        @ti.func
        def offset(self, i):
            return i * 1.0

        @ti.kernel
        def fill(self, v: ti.f64):
            for i in self.x:
                self.x[i] = scaled(v, 2.0) + scaled(self.offset(i), 10.0)

    holder = Holder()
    holder.fill(1.5)
    assert holder.x.to_numpy().tolist() == [3.0, 13.0, 23.0, 33.0]
