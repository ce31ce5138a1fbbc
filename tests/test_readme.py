"""The README's example runs as written and does what the README says."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_example_runs_and_recovers_the_flow():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks, "README has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], str(README), "exec"), namespace)  # noqa: S102 - our own README
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
