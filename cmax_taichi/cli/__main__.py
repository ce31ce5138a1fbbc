"""``python -m cmax_taichi.cli``: the same as the ``cmax-taichi`` command."""

import sys

from cmax_taichi.cli import main

sys.exit(main())
