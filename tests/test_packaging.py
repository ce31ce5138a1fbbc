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
