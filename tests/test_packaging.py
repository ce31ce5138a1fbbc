"""The kernels ship inside the package: a non-editable install imports cmax_taichi.kernels."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_non_editable_install_ships_kernels(tmp_path):
    target = tmp_path / "site"
    build = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(target),
            str(ROOT),
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    if build.returncode != 0 and "setuptools" in build.stderr.lower() and "no module" in build.stderr.lower():
        pytest.skip("setuptools is not installed in this environment")
    if build.returncode != 0 and "project.license" in build.stderr:
        pytest.skip("this environment's setuptools predates the test extra's setuptools>=77 (PEP 639)")
    assert build.returncode == 0, build.stderr
    assert (target / "cmax_taichi" / "kernels" / "warps" / "zoom1.py").is_file()
    assert (target / "cmax_taichi" / "kernels" / "warps" / "common.py").is_file()
    # every sub-package of the source tree is shipped
    for init in (ROOT / "cmax_taichi").rglob("__init__.py"):
        rel = init.relative_to(ROOT)
        assert (target / rel).is_file(), f"{rel.parent} is not in the wheel (pyproject packages)"
    env = dict(os.environ, PYTHONPATH=str(target))
    code = (
        "import cmax_taichi, cmax_taichi.kernels.iwe as k, cmax_taichi.io, cmax_taichi.cli; "
        "assert 'site' in cmax_taichi.__file__ and 'site' in k.__file__, (cmax_taichi.__file__, k.__file__); "
        "print(cmax_taichi.warp_names())"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert "mitrokhin4" in run.stdout


def test_editable_or_source_import_resolves_kernels():
    import cmax_taichi.kernels.iwe as kiwe
    import cmax_taichi.kernels.warps.zoom1 as kzoom

    import cmax_taichi

    assert Path(kiwe.__file__).resolve().parent == ROOT / "kernels"
    assert Path(kzoom.__file__).resolve().parent == ROOT / "kernels" / "warps"
    assert Path(cmax_taichi.__file__).resolve().parent == ROOT / "cmax_taichi"


#: the third-party modules the package may import without their being dependencies: each is optional,
#: imported where a feature needs it, and that code says which extra (or package) to install
OPTIONAL_IMPORTS = {
    "aedat": "aedat",  # the AEDAT4 reader
    "faery": "formats",  # Prophesee RAW / DAT, Event Stream
    "ray": "ray",  # estimate --engine ray
    "optuna": "tpe",  # maximize(init="tpe")
    "torch": "bench",  # the benchmark's PyTorch twin
    "rosbags": "rosbag",  # ROS1 / ROS2 bags
    "dv_processing": "live",  # estimate --live (dv-processing TCP streams)
    "hdf5plugin": None,  # a compressed HDF5 dataset (DSEC): its message says pip install hdf5plugin
    "PIL": None,  # Pillow, which matplotlib depends on
}
#: import name -> distribution name, where they differ
DISTRIBUTIONS = {"PIL": "pillow"}


def _third_party_imports() -> dict[str, set[str]]:
    import ast

    found: dict[str, set[str]] = {}
    for root in ("cmax_taichi", "kernels"):
        for path in (ROOT / root).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    modules = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    modules = [node.module]
                else:
                    continue
                for module in modules:
                    top = module.split(".")[0]
                    if top not in sys.stdlib_module_names and top not in (
                        "cmax_taichi",
                        "kernels",
                        "__future__",
                    ):
                        found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def test_every_import_is_a_dependency_or_a_declared_extra():
    """A plain ``pip install -e .`` runs every README command: each third-party module the package
    imports (at the top of a module or inside a function: the dense flow's SciPy was a function-level
    import, and 'cmax-taichi flow' crashed after the README's install) is in ``dependencies``, or is
    one of the optional modules above, whose extras pyproject declares."""
    import re

    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]

    def names(requirements) -> set[str]:
        return {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].strip().lower() for r in requirements}

    required = names(project["dependencies"])
    extras = project["optional-dependencies"]
    for module, files in _third_party_imports().items():
        if module in OPTIONAL_IMPORTS:
            extra = OPTIONAL_IMPORTS[module]
            assert extra is None or extra in extras, f"{module}: extra {extra!r} is not declared"
            continue
        distribution = DISTRIBUTIONS.get(module, module).lower()
        assert distribution in required, f"{module} (imported by {sorted(files)}) is not a dependency"
    for module in ("scipy", "numpy", "taichi", "h5py", "matplotlib", "tqdm"):
        assert module in required
