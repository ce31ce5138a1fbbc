"""Minimal reproduction of the Taichi bug behind the wrong fused values on Vulkan (docs/GPU.md).

Taichi 1.7.4's SPIR-V backends (Vulkan, Metal) pack the fields of one field tree with no alignment padding
(``taichi/codegen/spirv/snode_struct_compiler.cpp``: children sorted by size, offsets summed), but address
an element of ``b`` bytes at byte offset ``o`` as element ``o >> log2(b)`` of the buffer seen as a ``b``-byte
array (``at_buffer`` in ``spirv_codegen.cpp``). An f64 placed after an odd number of 4-byte fields sits at
4 mod 8, so every read and write of it lands 4 bytes too low, over the last 4 bytes of its neighbour.
The f64 field itself looks right (its reads and writes agree); the neighbour is silently clobbered.
Reported upstream as taichi-dev/taichi#8803 (open). The LLVM backends (CPU, CUDA) align their structs.

    python benchmarks/taichi_f64_alignment.py --arch vulkan   # prints "c = 0.0 (clobbered)" on lavapipe
    python benchmarks/taichi_f64_alignment.py --arch cpu      # prints "c = 3.0 (intact)"

Exit status 1 when the neighbour was clobbered. cmax-taichi avoids it by giving its f64 fields a field
tree of their own (``kernels/fused.py``, ``FusedFields.gsum``).
"""

from __future__ import annotations

import argparse
import sys

import taichi as ti


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arch", default="vulkan", choices=("vulkan", "metal", "cuda", "cpu"))
    arch = parser.parse_args().arch
    ti.init(arch=getattr(ti, arch), log_level=ti.ERROR)
    # three 4-byte fields, then one f64: the gfx layout puts the f64 at byte offset 12 (4 mod 8)
    a = ti.field(ti.f32, shape=())
    b = ti.field(ti.f32, shape=())
    c = ti.field(ti.f32, shape=())
    d = ti.field(ti.f64, shape=())

    @ti.kernel
    def write_f64():
        d[None] = 0.0

    a[None], b[None], c[None] = 1.0, 2.0, 3.0
    write_f64()
    running = str(ti.lang.impl.current_cfg().arch).split(".")[-1]
    offset = d._get_field_members()[0].ptr.snode().parent.offset_bytes_in_parent_cell
    clobbered = c[None] != 3.0
    state = "clobbered" if clobbered else "intact"
    print(
        f"arch {running}: f64 field at byte offset {offset}; after writing it, "
        f"a = {a[None]}, b = {b[None]}, c = {c[None]} ({state}; expected 1, 2, 3)"
    )
    return 1 if clobbered else 0


if __name__ == "__main__":
    sys.exit(main())
