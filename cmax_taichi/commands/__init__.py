"""Sub-commands of the ``cmax-taichi`` command line (see ``cmax_taichi/cli.py``)."""
