"""``python -m cmax_taichi``: the same as the ``cmax-taichi`` command."""

from cmax_taichi.cli import console_main

console_main()
