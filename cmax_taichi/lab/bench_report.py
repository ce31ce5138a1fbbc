"""The benchmark's report: machine and versions, the Markdown tables (also the table of
docs/BENCHMARK.md), ``results.csv`` and ``results.png``."""

from __future__ import annotations

import csv
import datetime as _dt
import math
import os
import platform
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cmax_taichi.core import backend

if TYPE_CHECKING:
    from cmax_taichi.lab.bench import Plan, Row

__all__ = ["machine_info", "segmentation_markdown", "markdown_report", "write_csv", "write_plot"]


def machine_info() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    versions = {"python": platform.python_version(), "numpy": np.__version__}
    try:
        import taichi as ti

        versions["taichi"] = ".".join(str(v) for v in ti.__version__)
    except Exception:  # pragma: no cover - taichi is a dependency
        versions["taichi"] = "?"
    try:
        import torch

        versions["torch"] = torch.__version__
        torch_threads = torch.get_num_threads()
    except ImportError:
        versions["torch"] = "not installed"
        torch_threads = 0
    try:
        load = os.getloadavg()
    except OSError:
        load = (float("nan"),) * 3
    from cmax_taichi import __version__

    versions["cmax-taichi"] = __version__
    info = backend.info()
    return {
        "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "load_average_1min": round(load[0], 2),
        "arch": info.arch,
        "precision": info.precision,
        "torch_threads": torch_threads,
        "versions": versions,
    }


def _fmt(v, digits=3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}g}" if abs(v) < 1000 else f"{v:.0f}"
    return str(v)


def segmentation_markdown(seg: list[dict]) -> list[str]:
    """The segmentation timing table (``segment_eval.timing`` rows) with its caption."""
    from cmax_taichi.lab.segment_eval import timing_table

    return [
        "",
        "Motion segmentation (`cmax_taichi.segment`, mitrokhin4 with both regularizers, lambda = 1, "
        "simulated 3-object windows; medians of 5 complete segmentations after one that compiles; CPU = "
        "process time of all threads; value_and_grad of all clusters: median of 20):",
        "",
        *timing_table(seg),
    ]


def markdown_report(
    rows: list[Row],
    machine: dict,
    plan: Plan,
    solve: dict | None,
    wall_s: float,
    seg: list[dict] | None = None,
) -> str:
    """The Markdown report (also the table of docs/BENCHMARK.md)."""
    v = machine["versions"]
    lines = [
        f"Benchmark `{plan.label}` run on {machine['date']}: {machine['cpu']}, {machine['cores']} cores "
        f"(load average {machine['load_average_1min']} at the start), Taichi {v['taichi']} "
        f"({machine['arch']}, {machine['precision']}), PyTorch {v['torch']} "
        f"({machine['torch_threads']} threads), NumPy {v['numpy']}, Python {v['python']}, "
        f"cmax-taichi {v['cmax-taichi']}; {wall_s / 60:.1f} min in all.",
        "",
        "Times are medians over interleaved rounds after a warm-up, of one `value_and_grad` (NumPy: one "
        "value); a call shorter than 100 ms is timed in bursts of 2-8 consecutive calls per round (about "
        "10 ms of them), the "
        "median over every call of a burst but the first (the call after a call of the same implementation, "
        "as an optimizer's evaluations follow each other); `after others ms` is the median of each burst's "
        "first call, made right after the other implementations' calls, in the caches they left (the same "
        "calls as the median for a call of 100 ms or more); Mev/s = million events per second; "
        "`x torch` = PyTorch's median / this median. "
        "Every implementation was first checked against the others on the same inputs "
        "(value to 1e-9 relative in f64, gradient to 1e-6 against PyTorch and to 1e-4 against central "
        "differences of the reference up to 1e4 events); a `DISAGREES` row has no time.",
        "",
        "| N | sensor | window | warp | regularizers | impl | measured | median ms | after others ms | Mev/s "
        "| x torch | first call s | peak RSS MB | fields MB |",
        "|---:|---|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        head = f"| {r.n} | {r.sensor} | {r.window} | {r.warp} | {r.regs} | {r.impl} |"
        if r.status != "ok":
            lines.append(f"{head} {r.status} | | | | | | | |")
            continue
        lines.append(
            f"{head} {r.measured} | {_fmt(r.median_ms)} | {_fmt(r.first_of_burst_ms)} | "
            f"{_fmt(r.events_per_s / 1e6)} | {_fmt(r.vs_torch)} | {_fmt(r.first_call_s)} | "
            f"{_fmt(r.peak_rss_mb)} | {_fmt(r.field_mb)} |"
        )
    if solve:
        lines += [
            "",
            f"Window solve ({solve['events']} events, {solve['sensor']}, {solve['warp']}, "
            f"{solve['regularizers']}): "
            f"`{solve['call']}` takes **{solve['median_ms']:.1f} ms** (median of {solve['repeats']}, min "
            f"{solve['min_ms']:.1f} ms): {solve['n_evaluations']} evaluations, the winning run "
            f"{solve['n_iterations_winning_run']} Adam iterations.",
        ]
    if seg:
        lines += segmentation_markdown(seg)
    if plan.notes:
        lines += [""] + [f"* {n}" for n in plan.notes]
    return "\n".join(lines) + "\n"


def write_csv(rows: list[Row], path: Path) -> None:
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(asdict(rows[0]).keys()))
        writer.writeheader()
        for r in rows:
            writer.writerow(asdict(r))


def write_plot(rows: list[Row], path: Path) -> bool:
    """Time per evaluation and speed-up over PyTorch against N (sensor 346x260); False without rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r.status == "ok"]
    if not ok:
        return False
    sensor = "346x260" if any(r.sensor == "346x260" for r in ok) else ok[0].sensor
    kinds = {r.window for r in ok if r.sensor == sensor}
    kind = next(k for k in ("textured", "edges", "uniform") if k in kinds) if kinds <= {
        "textured", "edges", "uniform"} else sorted(kinds)[0]  # fmt: skip
    sel = [r for r in ok if r.sensor == sensor and r.window == kind]
    combos = sorted({(r.warp, r.regs) for r in sel})
    fig, axes = plt.subplots(2, len(combos), figsize=(3.2 * len(combos), 6.0), squeeze=False)
    colors = {"taichi": "C0", "taichi-chain": "C2", "torch": "C1", "numpy": "C3"}
    for j, (warp, regs) in enumerate(combos):
        ax, ax2 = axes[0, j], axes[1, j]
        for impl in colors:
            pts = sorted(
                (r.n, r.median_ms, r.vs_torch)
                for r in sel
                if r.impl == impl and (r.warp, r.regs) == (warp, regs)
            )
            if not pts:
                continue
            ns, ms, sp = zip(*pts, strict=True)
            ax.loglog(ns, ms, "o-", color=colors[impl], label=impl, ms=3)
            if impl != "torch":
                ax2.semilogx(ns, sp, "o-", color=colors[impl], label=impl, ms=3)
        ax.set_title(f"{warp}, {regs}", fontsize=9)
        ax.set_xlabel("events N")
        ax2.set_xlabel("events N")
        ax2.axhline(1.0, color="k", lw=0.5)
        if j == 0:
            ax.set_ylabel(f"ms per evaluation ({sensor}, {kind})")
            ax2.set_ylabel("speed-up over PyTorch")
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True
