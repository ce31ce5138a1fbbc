"""Make ``cmax_taichi.kernels`` importable from a source checkout.

The kernels live in the top-level ``kernels/`` folder and are installed as ``cmax_taichi.kernels``
(``package-dir`` in pyproject.toml). An installed wheel and an editable install resolve that name by
themselves; but running from the repository root puts this folder first on ``sys.path``, where
``cmax_taichi/kernels`` does not exist. Then we load the sibling ``kernels/`` under its package name.
"""

import importlib.util
import os
import sys

_NAME = "cmax_taichi.kernels"

if _NAME not in sys.modules:
    _here = os.path.dirname(os.path.abspath(__file__))
    _inside = os.path.join(_here, "kernels", "__init__.py")
    _sibling = os.path.join(os.path.dirname(_here), "kernels", "__init__.py")
    if not os.path.isfile(_inside) and os.path.isfile(_sibling):
        _spec = importlib.util.spec_from_file_location(
            _NAME, _sibling, submodule_search_locations=[os.path.dirname(_sibling)]
        )
        _module = importlib.util.module_from_spec(_spec)
        sys.modules[_NAME] = _module
        _spec.loader.exec_module(_module)
