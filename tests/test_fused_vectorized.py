"""The fused kernel's gather loops are vectorized by LLVM (``kernels/fused.py``'s ``grad_at`` has no
branch for that): a branch added there keeps them scalar, a fifth of the CPU time of a call with both
regularizers at 1M events (benchmarks/NOTES.md, 2026-12-05). Checked in the optimized LLVM IR that
Taichi writes out, in a child process (its own Taichi program, no offline cache, so the kernel is
compiled here rather than loaded)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

CHILD = textwrap.dedent(
    """
    import taichi as ti
    _init = ti.init

    def init(*args, **kwargs):
        kwargs.update(offline_cache=False, print_kernel_llvm_ir_optimized=True)
        return _init(*args, **kwargs)

    ti.init = init
    import numpy as np
    import cmax_taichi as cm
    from cmax_taichi.core import backend
    from cmax_taichi.pipeline.fused import FusedPipeline

    backend.init(precision="f64")
    FusedPipeline.loops = "{loops}"
    rng = np.random.default_rng(0)
    n = 3000
    events = cm.Events(
        rng.uniform(0, 63, n), rng.uniform(0, 47, n), np.sort(rng.uniform(0, 0.02, n)),
        rng.integers(0, 2, n), (64, 48),
    )
    prob = cm.ContrastMaximization(events, warp="translation2", regularizers={{"divergence": 1.0}})
    value, grad = prob.value_and_grad(np.array([30.0, -20.0]))
    assert np.isfinite(value) and np.all(np.isfinite(grad))
    """
)


@pytest.mark.parametrize("loops", ["serial", "parallel"])
def test_the_gather_loops_are_vectorized(tmp_path, loops):
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run(
        [sys.executable, "-c", CHILD.format(loops=loops)],
        cwd=tmp_path,  # Taichi writes the IR files into the working directory
        env={**os.environ, "PYTHONPATH": str(root)},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    ir = "".join(
        path.read_text() for path in sorted(tmp_path.glob("taichi_kernel_cpu_llvm_ir_optimized_*.ll"))
    )
    assert "define" in ir, "no optimized IR was written"
    assert "vector.body:" in ir, "no vectorized loop in the fused kernel's optimized IR"
