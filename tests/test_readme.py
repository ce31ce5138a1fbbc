"""The README's example runs as written and does what the README says; the docs home page carries the
same example, and the README's quick start is the one CI runs."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


@pytest.mark.parametrize("page", [README, ROOT / "docs" / "index.md"], ids=["README", "docs-index"])
def test_readme_example_runs_and_recovers_the_flow(page):
    blocks = re.findall(r"```python\n(.*?)```", page.read_text(), re.S)
    assert blocks, f"{page.name} has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], str(page), "exec"), namespace)  # noqa: S102 - our own docs
    theta = namespace["theta"]
    assert abs(theta[0] - 120.0) < 6.0 and abs(theta[1]) < 6.0
    assert namespace["image"].shape == (180, 240)
    assert np.isfinite(namespace["maps"]["R_divergence"])


def test_readme_states_install_and_test_commands():
    text = README.read_text()
    assert 'python -m pip install -e ".[test]"' in text
    assert "python -m pytest -q" in text
    ci = (README.parent / ".ci" / "run").read_text()
    assert 'python -m pip install --quiet -e ".[test]"' in ci
    assert "python -m pytest -q" in ci
    assert 'mkdocs build --strict --site-dir "$(mktemp -d)"' in ci


def test_readme_quick_start_is_the_out_of_the_box_set_up():
    """The README stays a front page, and its quick start is exactly the commands a fresh clone runs."""
    text = README.read_text()
    assert len(text.splitlines()) <= 250
    quick = text.split("## Quick start", 1)[1]
    block = re.search(r"```bash\n(.*?)```", quick, re.S).group(1)
    assert block.splitlines() == [
        'python -m pip install -e ".[test]"',
        "cmax-taichi estimate --example rotation --out out/rotation",
        "cmax-taichi estimate --example collapse --out out/collapse",
        "cmax-taichi estimate --example collapse --reg divergence=10 --reg deformation=10"
        " --out out/collapse-reg",
        "cmax-taichi flow --example planes --out out/planes",
        "cmax-taichi segment --example two-objects --out out/segment",
        "python -m pytest -q",
    ]
