"""The figures the README and the docs quote, checked against what the commands print today.

``python -m benchmarks.docs_figures --check`` re-runs every command whose output a page quotes and
reports each figure that drifted beyond its tolerance; ``--write`` puts what the commands print now into
the pages instead. Both also keep the command-line reference (``docs/cli.md``) equal to the parsers' help.

A quoted output is a ```` ```text ```` block right after a marker line::

    <!-- figures: cmax-taichi estimate --example rotation --out out/rotation -->            (the whole stdout)
    <!-- figures (excerpt): cmax-taichi estimate --example collapse --out out/collapse -->  (some lines)

A whole block is the command's stdout, line for line; an excerpt's lines (``...`` lines skipped) must
each read like a line of the stdout, in order. Lines are compared with their numbers masked and their
whitespace collapsed ("reads like"), then number by number:

* timings are not compared: a number followed by ``s``, ``ms``, ``s/window``, ``evaluations`` or
  ``iterations``, or after ``real-time factor``; nor which kernels served a window (quick or optimized);
* whole numbers below 100 (counts of windows, clusters, a seed) must be equal;
* larger whole numbers (events) may differ by 1%;
* decimals may differ by 3% of the quoted value or 0.02, whichever is larger (estimates, errors, AEE).

The commands run as ``python -m cmax_taichi.cli`` of this checkout, from a temporary folder beside a
link to ``../shared/data`` (commands that read it are skipped, saying so, where it is absent), with
``CMAX_TAICHI_COMPILE=fast`` unless ``--compile`` says otherwise. The quick kernels compute the same
values to rounding, but an optimizer's path can follow those last bits: the pages quote figures that
the data determine (not, say, a velocity component of a fraction of a pixel over the window).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: the pages whose quoted outputs are checked
PAGES = ("README.md", "docs")
#: the generated command-line reference
CLI_PAGE = ROOT / "docs" / "cli.md"
#: the width the command-line reference is wrapped at
CLI_COLUMNS = 100

MARKER = re.compile(r"^<!-- figures( \(excerpt\))?: (.+?) -->\s*$")
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
#: a number in one of these contexts is a timing (or a count that follows the load), not a figure
VOLATILE_AFTER = re.compile(r"^\s*(?:s\b|ms\b|s/window|s/step|it/s|evaluations\b|iterations\b)")
VOLATILE_BEFORE = re.compile(r"real-time factor\s*$")
#: phrases that depend on the kernel cache's state, not on the result
KERNEL_STATE = re.compile(r"\b(?:quick|optimized|generic) kernels\b")
#: tolerances (see the module docstring)
SMALL_INTEGER = 100
INTEGER_REL = 0.01
DECIMAL_REL, DECIMAL_ABS = 0.03, 0.02


@dataclasses.dataclass
class Block:
    """A quoted output: the command, whether it is an excerpt, and its lines (with their line numbers)."""

    page: Path
    command: str
    excerpt: bool
    first_line: int  # 0-based index of the first content line in the page
    lines: list[str]


@dataclasses.dataclass
class Drift:
    """One figure (or line) that does not match what the command printed."""

    line: int  # 1-based line in the page
    quoted: str
    printed: str | None
    why: str


def find_blocks(page: Path, text: str) -> list[Block]:
    """Every marked ```` ```text ```` block of a page."""
    lines = text.splitlines()
    blocks = []
    for i, line in enumerate(lines):
        match = MARKER.match(line)
        if not match:
            continue
        if i + 1 >= len(lines) or lines[i + 1].strip() != "```text":
            raise ValueError(f"{page}:{i + 1}: a figures marker must be followed by a ```text block")
        end = next((j for j in range(i + 2, len(lines)) if lines[j].strip() == "```"), None)
        if end is None:
            raise ValueError(f"{page}:{i + 2}: the ```text block is not closed")
        blocks.append(Block(page, match.group(2), bool(match.group(1)), i + 2, lines[i + 2 : end]))
    return blocks


def _tokens(line: str) -> list[tuple[str, bool]]:
    """The numbers of a line, each with whether it is volatile (a timing)."""
    found = []
    for m in NUMBER.finditer(line):
        volatile = bool(VOLATILE_AFTER.match(line[m.end() :]) or VOLATILE_BEFORE.search(line[: m.start()]))
        found.append((m.group(), volatile))
    return found


def skeleton(line: str) -> str:
    """The line with its numbers masked, the kernel state neutral and whitespace collapsed."""
    return " ".join(NUMBER.sub("#", KERNEL_STATE.sub("kernels", line)).split())


def tolerance(quoted: str) -> float:
    """The largest difference allowed from the quoted number."""
    value = float(quoted)
    if re.fullmatch(r"[-+]?\d+", quoted):
        return 0.0 if abs(value) < SMALL_INTEGER else INTEGER_REL * abs(value)
    return max(DECIMAL_ABS, DECIMAL_REL * abs(value))


def compare_line(quoted: str, printed: str) -> str | None:
    """Why two lines that read alike differ beyond the tolerances, or None."""
    problems = []
    for (a, volatile), (b, _) in zip(_tokens(quoted), _tokens(printed), strict=True):
        if volatile:
            continue
        tol = tolerance(a)
        if abs(float(a) - float(b)) > tol:
            problems.append(f"{a} -> {b} (tolerance {tol:g})")
    return "; ".join(problems) or None


def compare_block(block: Block, output: list[str]) -> tuple[list[Drift], list[str | None]]:
    """The drifts of a quoted block against the command's stdout, and for each quoted line the printed
    line it was matched with (None for ``...`` lines and lines no printed line reads like)."""
    drifts: list[Drift] = []
    matched: list[str | None] = []
    if not block.excerpt and len(block.lines) != len(output):
        drifts.append(Drift(block.first_line + 1, f"{len(block.lines)} lines", f"{len(output)} lines",
                            "the command printed another number of lines"))
    cursor = 0
    for k, line in enumerate(block.lines):
        if line.strip() in ("", "..."):
            matched.append(None)
            continue
        shape = skeleton(line)
        hit = next((j for j in range(cursor, len(output)) if skeleton(output[j]) == shape), None)
        if hit is None:
            matched.append(None)
            drifts.append(Drift(block.first_line + k + 1, line, None, "no printed line reads like it"))
            continue
        cursor = hit + 1
        matched.append(output[hit])
        why = compare_line(line, output[hit])
        if why:
            drifts.append(Drift(block.first_line + k + 1, line, output[hit], why))
    return drifts, matched


def rewrite_block(text: str, block: Block, output: list[str], matched: list[str | None]) -> str:
    """The page with the block replaced by what the command printed (an excerpt: line by line)."""
    lines = text.splitlines(keepends=True)
    if block.excerpt:
        pairs = zip(block.lines, matched, strict=True)
        new = [printed if printed is not None else old for old, printed in pairs]
    else:
        new = output
    start, end = block.first_line, block.first_line + len(block.lines)
    lines[start:end] = [line + "\n" for line in new]
    return "".join(lines)


def _pages() -> list[Path]:
    pages = []
    for name in PAGES:
        path = ROOT / name
        pages += sorted(path.glob("*.md")) if path.is_dir() else [path]
    return pages


def run_command(command: str, workdir: Path, env: dict[str, str], timeout: float) -> list[str]:
    """The stdout lines of a quoted ``cmax-taichi ...`` command (``python -m cmax_taichi.cli``, the same
    entry point), run in ``workdir``."""
    argv = shlex.split(command)
    if argv[0] != "cmax-taichi":
        raise ValueError(f"only cmax-taichi commands are checked, not {command!r}")
    proc = subprocess.run([sys.executable, "-m", "cmax_taichi.cli", *argv[1:]], cwd=workdir, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-1:] or ["(no stderr)"]
        raise RuntimeError(f"{command!r} exited with {proc.returncode}: {tail[0]}")
    return proc.stdout.rstrip("\n").splitlines()


def cli_reference() -> str:
    """docs/cli.md: every command's ``--help``, as the parsers print it."""
    from cmax_taichi.cli import build_parser

    parser = build_parser()
    columns = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(CLI_COLUMNS)  # argparse wraps at the terminal's width
    try:
        texts = [parser.format_help()]
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        texts += [command.format_help() for command in sub.choices.values()]
    finally:
        if columns is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = columns
    parts = ["# Command-line reference", "",
             "Every command's `--help`, generated from the parsers by `python -m benchmarks.docs_figures "
             "--write`", "(`--check` tells when it is out of date). Bad input on any command is one line on "
             "stderr and exit code 2.", "", "```text", texts[0].rstrip(), "```"]
    for name, text in zip(sub.choices, texts[1:], strict=True):
        parts += ["", f"## {name}", "", "```text", text.rstrip(), "```"]
    return "\n".join(parts) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--check", action="store_true", help="report drift beyond the tolerances (exit 1)")
    mode.add_argument("--write", action="store_true", help="put what the commands print now into the pages")
    mode.add_argument("--list", action="store_true", help="list the quoted blocks and their commands")
    ap.add_argument("--compile", default="fast", choices=["auto", "full", "fast"],
                    help="CMAX_TAICHI_COMPILE of the runs (default fast: same values, quick compiles)")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per command (default 300)")
    args = ap.parse_args(argv)

    blocks = [b for page in _pages() for b in find_blocks(page, page.read_text())]
    if args.list:
        for b in blocks:
            kind = "excerpt" if b.excerpt else "whole"
            print(f"{b.page.relative_to(ROOT)}:{b.first_line}  ({kind}, {len(b.lines)} lines)  {b.command}")
        return 0
    print(f"tolerances: whole numbers below {SMALL_INTEGER} equal, larger ones {INTEGER_REL:.0%}; decimals "
          f"{DECIMAL_REL:.0%} or {DECIMAL_ABS}, the larger; timings not compared")

    failures = 0
    shared = ROOT.parent / "shared" / "data"
    # this checkout's package, whatever is installed: the pages describe this code
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    env = dict(os.environ, CMAX_TAICHI_COMPILE=args.compile, PYTHONUNBUFFERED="1", PYTHONPATH=path)
    outputs: dict[str, list[str] | str] = {}
    with tempfile.TemporaryDirectory(prefix="docs-figures-") as tmp:
        workdir = Path(tmp) / "run"
        workdir.mkdir()
        if shared.is_dir():
            (Path(tmp) / "shared").mkdir()
            (Path(tmp) / "shared" / "data").symlink_to(shared)
        for b in blocks:
            if b.command in outputs:
                continue
            if "../shared/data" in b.command and not shared.is_dir():
                outputs[b.command] = f"skipped: {shared} is absent"
                continue
            try:
                outputs[b.command] = run_command(b.command, workdir, env, args.timeout)
            except (RuntimeError, ValueError, subprocess.TimeoutExpired) as exc:
                outputs[b.command] = f"failed: {exc}"
                failures += 1
            finally:
                shutil.rmtree(workdir / "out", ignore_errors=True)

    for page in _pages():
        text = page.read_text()
        report: list[str] = []
        # from the last block up, so that a rewrite does not move the blocks still to do
        for b in reversed(find_blocks(page, text)):
            where = f"{page.relative_to(ROOT)}:{b.first_line + 1}"
            output = outputs[b.command]
            if isinstance(output, str):
                report.insert(0, f"{where}  {b.command}: {output}")
                continue
            drifts, matched = compare_block(b, output)
            if args.write:
                text = rewrite_block(text, b, output, matched)
                report.insert(0, f"{where}  {b.command}: written ({len(drifts)} line(s) had drifted)")
                continue
            checked = sum(1 for line in b.lines for _, v in _tokens(line) if not v)
            verdict = "OK" if not drifts else f"{len(drifts)} DRIFT"
            lines = [f"{where}  {b.command}: {checked} figures, {verdict}"]
            for d in drifts:
                lines.append(f"  line {d.line}: {d.why}\n    quoted:  {d.quoted.strip()}\n    printed: "
                             f"{'(none)' if d.printed is None else d.printed.strip()}")
            report[:0] = lines
            failures += bool(drifts)
        if report:
            print("\n".join(report))
        if args.write:
            page.write_text(text)

    reference = cli_reference()
    if args.write:
        CLI_PAGE.write_text(reference)
        print(f"{CLI_PAGE.relative_to(ROOT)}: written")
    elif not CLI_PAGE.exists() or CLI_PAGE.read_text() != reference:
        print(f"{CLI_PAGE.relative_to(ROOT)}: out of date with the parsers (run --write)")
        failures += 1
    else:
        print(f"{CLI_PAGE.relative_to(ROOT)}: OK")
    print("docs figures: " + ("OK" if not failures else f"{failures} problem(s)"))
    return 1 if failures and not args.write else 0


if __name__ == "__main__":
    sys.exit(main())
