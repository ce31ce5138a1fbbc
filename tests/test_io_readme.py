"""The "Reading recordings" example of docs/formats.md runs as written on the shared slider_depth cut."""

from __future__ import annotations

import re
from pathlib import Path

from conftest import shared_data_dir

PAGE = Path(__file__).resolve().parents[1] / "docs" / "formats.md"


def test_docs_reading_example(monkeypatch, tmp_path):
    monkeypatch.setenv("CMAX_TAICHI_CACHE", str(tmp_path))
    folder = shared_data_dir("ecd_slider_depth")
    section = PAGE.read_text().split("# Reading recordings", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert '"path/to/slider_depth"' in code
    namespace: dict = {}
    exec(compile(code.replace('"path/to/slider_depth"', repr(str(folder))), str(PAGE), "exec"), namespace)  # noqa: S102
    assert len(namespace["first"]) == 30000 and namespace["poses"].shape == (339, 8)
    assert namespace["early"].t[-1] < namespace["rec"].t_start + 0.01
    assert len(namespace["events"]) == 20000 and namespace["prob"] is not None
