"""Entry point: ``python -m benchmarks.run [--quick] [--out DIR] [--precision f64|f32]``.

The same as ``cmax-taichi bench``; the harness is :mod:`cmax_taichi.lab.bench`.
"""

import sys

from cmax_taichi.lab.bench import main

if __name__ == "__main__":
    sys.exit(main())
