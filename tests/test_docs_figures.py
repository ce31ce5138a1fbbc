"""The checker of the figures the README and the docs quote (benchmarks/docs_figures.py): its parsing and
comparison on recorded outputs (no command is run here), and the command-line reference it generates."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks import docs_figures as df

ROOT = Path(__file__).resolve().parent.parent

#: what `cmax-taichi estimate --example rotation --out out/rotation` printed (stdout), as recorded
PRINTED = [
    "first window (40614 events, 0.0001-0.0201 s): w_x 0.9971 rad/s, w_y -1.492 rad/s, w_z 3.021 rad/s"
    " (2.6 s, quick kernels)",
    "4 window(s) of example:rotation, warp rotation3, objective variance",
    "  w_x: median 0.986406 rad/s",
    "  speed: real-time factor 0.47 (seconds of data per second, without the first window: 2.58 s with"
    " compilation); median 5 evaluations per warm-started window",
    "  FWL: median 1.8938",
    "  events: 156247 of 156247 estimated",
    "  parameter          truth   estimate (median)       error",
    "  w_x [rad/s]            1              0.9864     -0.0136",
    "  collapsed windows (scale below 0.5): 0 of 4",
]


def _page(lines: list[str], excerpt: bool = False) -> str:
    kind = " (excerpt)" if excerpt else ""
    return "\n".join(["# A page", "", f"<!-- figures{kind}: cmax-taichi estimate --example rotation -->",
                      "```text", *lines, "```", "", "after"]) + "\n"


def _check(text: str) -> list[df.Drift]:
    (block,) = df.find_blocks(Path("page.md"), text)
    return df.compare_block(block, PRINTED)[0]


def test_the_quoted_output_as_printed_passes():
    assert _check(_page(PRINTED)) == []


def test_a_changed_figure_is_flagged_with_its_line():
    changed = [line.replace("156247 of", "150000 of") for line in PRINTED]
    drifts = _check(_page(changed))
    assert len(drifts) == 1
    assert drifts[0].line == 4 + 6  # the page's line of the events count
    assert "156247 -> 150000" in drifts[0].why or "150000 -> 156247" in drifts[0].why


@pytest.mark.parametrize(
    ("old", "new", "flagged"),
    [
        ("0.9864 ", "0.9664 ", False),  # 2% of an estimate: inside the 3% tolerance
        ("0.9864 ", "0.9364 ", True),  # 5%: drift
        ("1.8938", "1.9938", True),  # the FWL, 5%
        ("0 of 4", "1 of 4", True),  # small counts are exact
        ("(2.6 s,", "(9.9 s,", False),  # a timing
        ("real-time factor 0.47", "real-time factor 3.10", False),  # a speed
        ("median 5 evaluations", "median 9 evaluations", False),
        ("quick kernels", "optimized kernels", False),  # the cache's state
        ("w_x [rad/s]            1 ", "w_x [rad/s]            2 ", True),  # the truth itself
    ],
)
def test_tolerances(old, new, flagged):
    changed = [line.replace(old, new) for line in PRINTED]
    assert changed != PRINTED, old
    assert bool(_check(_page(changed))) is flagged


def test_text_changes_and_missing_lines_are_flagged():
    renamed = [line.replace("collapsed windows", "collapsed frames") for line in PRINTED]
    (drift,) = _check(_page(renamed))
    assert drift.printed is None and "reads like" in drift.why
    # a whole block must have every line
    assert any("number of lines" in d.why for d in _check(_page(PRINTED[:-1])))


def test_an_excerpt_matches_lines_in_order_and_realigned_columns():
    excerpt = ["...", "  events: 156247 of 156247 estimated", "  w_x [rad/s]   1   0.9864   -0.0136"]
    assert _check(_page(excerpt, excerpt=True)) == []
    wrong = ["  events: 156247 of 156247 estimated", "  w_x [rad/s]   1   0.8000   -0.2000"]
    assert len(_check(_page(wrong, excerpt=True))) == 1
    out_of_order = [PRINTED[-1], PRINTED[0]]
    assert len(_check(_page(out_of_order, excerpt=True))) == 1


def test_write_puts_the_printed_lines_in():
    stale = [line.replace("0.9864", "0.9876") for line in PRINTED]
    text = _page(stale)
    (block,) = df.find_blocks(Path("page.md"), text)
    drifts, matched = df.compare_block(block, PRINTED)
    assert drifts == []  # inside the tolerance, yet written as printed
    assert df.rewrite_block(text, block, PRINTED, matched) == _page(PRINTED)
    excerpt = _page(["...", "  FWL: median 1.7000"], excerpt=True)
    (block,) = df.find_blocks(Path("page.md"), excerpt)
    _, matched = df.compare_block(block, PRINTED)
    assert df.rewrite_block(excerpt, block, PRINTED, matched) == _page(["...", "  FWL: median 1.8938"], True)


def test_the_readme_quotes_its_quick_start_and_every_marker_is_well_formed():
    blocks = [b for page in df._pages() for b in df.find_blocks(page, page.read_text())]
    readme = [b for b in blocks if b.page.name == "README.md"]
    assert any(b.command.startswith("cmax-taichi estimate --example rotation") for b in readme)
    for b in blocks:
        assert b.command.startswith("cmax-taichi ") and b.lines, b
    with pytest.raises(ValueError, match="followed by a ```text block"):
        df.find_blocks(Path("bad.md"), "<!-- figures: cmax-taichi info -->\n```bash\n```\n")


def test_the_command_line_reference_is_the_parsers_help():
    assert (ROOT / "docs" / "cli.md").read_text() == df.cli_reference(), (
        "docs/cli.md is out of date: python -m benchmarks.docs_figures --write"
    )
