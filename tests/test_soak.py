"""A small version of the soak benchmark: windows through ``sequence.process`` in a fresh
process, with equal and with varying window sizes; the resident memory does not grow after the first
windows (the full check, ``python -m benchmarks.soak --windows 2000``, is in benchmarks/NOTES.md).

Before the event buffers were pooled and a problem took each next window in place, every window kept
about 24 bytes per event for the life of the process: 3,000-event windows grew the RSS by about 0.07 MB
per window, 10 MB over these 150 windows."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("varying", [False, True], ids=["equal", "varying"])
def test_memory_stays_flat_over_windows(tmp_path, varying):
    args = [sys.executable, "-m", "benchmarks.soak", "--windows", "250", "--events", "3000"]
    args += ["--out", str(tmp_path)] + (["--varying"] if varying else [])
    proc = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = dict(line.split(": ", 1) for line in proc.stdout.splitlines() if ": " in line)
    assert int(summary["windows"]) == 250 and int(summary["ref_window"]) == 100
    growth = float(summary["growth_mb"])
    assert growth <= 2.0, f"RSS grew by {growth} MB between window 100 and 250"
    assert (tmp_path / "soak.csv").exists() and (tmp_path / "soak.png").exists()
