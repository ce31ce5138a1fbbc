"""What :mod:`cmax_taichi.lab.experiments` writes: Markdown tables with the paper's numbers beside ours,
CSV files and the plots of the sensitivity and complexity studies."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from cmax_taichi.lab.paper import (
    FLOW_WARPS,
    METRICS,
    OBJECTIVES,
    PAPER_TABLE3,
    ROTATION_CUTS,
    ROWS,
    WARP_LABEL,
)

__all__ = [
    "COMPLEXITY_CONFIGS",
    "row_keys",
    "search_check",
    "flow_table_markdown",
    "flow_table_csv",
    "rotation_table_markdown",
    "rotation_table_csv",
    "sensitivity_outputs",
    "complexity_outputs",
    "write_rows_csv",
]

#: regularizers of the complexity study: (label, regularizer names)
COMPLEXITY_CONFIGS = (
    ("none", ()),
    ("divergence", ("divergence",)),
    ("deformation", ("deformation",)),
    ("both", ("divergence", "deformation")),
)


def _fmt(v: float, digits: int = 2) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


# --- tables 1 and 2 ----------------------------------------------------------------------------------
def search_check(meta: list[dict]) -> list[str]:
    """Markdown lines on the global search, per (row, interval): where J at the truth beats J at the
    estimate (the search missed a better point), and where the estimate collapsed (FWL above 1.5 times
    the ground truth's) with J at least that of the truth (the objective itself prefers the collapse)."""
    missed, preferred, n = [], [], 0
    for w, m in enumerate(meta):
        for key, (j_est, j_true) in m.get("J_estimate_truth", {}).items():
            n += 1
            name = f"{key.replace('gradient_magnitude', 'GM')} (interval {w + 1})"
            if j_true > j_est + 1e-9 * max(1.0, abs(j_est)):
                missed.append(f"{name}: J {j_est:.4f} < {j_true:.4f}")
            elif m["fwl"][key] > 1.5 * m["gt_fwl"]:
                preferred.append(f"{name}: J {j_est:.4f} >= {j_true:.4f}")
    lines = [f"Search check over {n} estimates (J at the estimate vs J at the true parameters):", ""]
    lines.append(
        f"* collapsed, and J prefers the collapse to the truth ({len(preferred)}): "
        + ("; ".join(preferred) if preferred else "none")
    )
    lines.append(
        f"* the truth has a higher J than the estimate, so the search missed it ({len(missed)}): "
        + ("; ".join(missed) if missed else "none")
    )
    return lines


def row_keys():
    """``(result key, row name)`` of tables 1 and 2, in the paper's order."""
    yield ("GT", ""), "GT flow"
    yield ("Identity", ""), "Identity warp"
    for warp in FLOW_WARPS:
        for label, _, _ in ROWS:
            yield (warp, label), f"{WARP_LABEL[warp]} {label}"


def flow_table_markdown(result: dict, paper: dict, title: str) -> str:
    """Markdown: one line per row, each cell ``ours (paper)``."""
    head = (
        "| row | "
        + " | ".join(f"{m} var." for m in METRICS)
        + " | "
        + " | ".join(f"{m} GM" for m in METRICS)
        + " |"
    )
    lines = [f"### {title}", "", "Each cell: ours (paper). Var. = variance, GM = gradient magnitude.", ""]
    lines += [head, "|" + "---|" * (1 + 2 * len(METRICS))]
    for key, name in row_keys():
        cells = []
        for objective in OBJECTIVES:
            ours = result[key][objective]
            theirs = paper[key][objective]
            for i in range(len(METRICS)):
                if not math.isfinite(ours[i]) and not math.isfinite(theirs[i]):
                    cells.append("–")
                else:
                    cells.append(f"{_fmt(ours[i])} ({_fmt(theirs[i])})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if ("_meta", "") in result:
        lines += [""] + search_check(result[("_meta", "")])
    return "\n".join(lines) + "\n"


def flow_table_csv(result: dict, paper: dict, path: Path, table: str) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["table", "row", "objective", "metric", "ours", "paper"])
        for key, name in row_keys():
            for objective in OBJECTIVES:
                for i, m in enumerate(METRICS):
                    w.writerow(
                        [table, name, objective, m, result[key][objective][i], paper[key][objective][i]]
                    )


# --- table 3 -----------------------------------------------------------------------------------------
def rotation_table_markdown(result: dict) -> str:
    cuts = [c for c in ROTATION_CUTS if ("GT", c) in result]
    lines = [
        "### Table 3: ECD rotation cuts, rotation3 (RMS deg/s / FWL)",
        "",
        "Each cell: ours (paper); the paper reports boxes_rotation and dynamic_rotation only.",
        "",
        "| row | " + " | ".join(cuts) + " |",
        "|---|" + "---|" * len(cuts),
    ]
    for row in ("GT", "No regularizer", "Divergence", "Deformation"):
        cells = []
        for cut in cuts:
            rms, fw = result[(row, cut)]
            prms, pfw = PAPER_TABLE3.get((row, cut), (math.nan, math.nan))
            ours = f"{_fmt(rms, 3)} / {_fmt(fw, 3)}"
            theirs = f" ({_fmt(prms, 3)} / {_fmt(pfw, 3)})" if (row, cut) in PAPER_TABLE3 else ""
            cells.append(ours + theirs)
        lines.append(f"| {'GT pose' if row == 'GT' else row} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def rotation_table_csv(result: dict, path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["row", "sequence", "rms_deg_s", "fwl", "paper_rms_deg_s", "paper_fwl"])
        for (row, cut), value in sorted(result.items()):
            if row == "_meta":
                continue
            paper = PAPER_TABLE3.get((row, cut), (math.nan, math.nan))
            w.writerow([row, cut, value[0], value[1], paper[0], paper[1]])


# --- sensitivity and complexity --------------------------------------------------------------------------
def _pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (the plots go to files)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save_plot(fig, path: Path) -> Path:
    """Lay out, write (110 dpi) and close ``fig``; returns ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    _pyplot().close(fig)
    return path


def sensitivity_outputs(rows: list[dict], out: Path) -> tuple[str, Path]:
    plt = _pyplot()
    regs = [label for label, _, _ in ROWS[2:]]
    lambdas = sorted({r["lambda"] for r in rows if r["lambda"] > 0})
    fig, axes = plt.subplots(2, len(FLOW_WARPS), figsize=(5.2 * len(FLOW_WARPS), 7), squeeze=False)
    for j, warp in enumerate(FLOW_WARPS):
        none = next(r for r in rows if r["warp"] == warp and r["regularizer"] == "none")
        for i, metric in enumerate(("AEE", "FWL")):
            ax = axes[i, j]
            for label in regs:
                pts = sorted(
                    (r["lambda"], r[metric]) for r in rows if r["warp"] == warp and r["regularizer"] == label
                )
                ax.plot([a for a, _ in pts], [b for _, b in pts], "o-", label=label)
            ax.axhline(none[metric], color="k", ls=":", label="no regularizer")
            ref = none["identity_AEE"] if metric == "AEE" else none["gt_FWL"]
            ax.axhline(
                ref, color="gray", ls="--", label="identity warp" if metric == "AEE" else "ground truth"
            )
            ax.set_xscale("log")
            if metric == "AEE":
                ax.set_yscale("log")
            ax.set_xlabel("lambda")
            ax.set_ylabel(f"{metric}" + (" (px)" if metric == "AEE" else ""))
            ax.set_title(f"{WARP_LABEL[warp]} ({warp}), variance, indoor_flying")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
    png = _save_plot(fig, out / "sensitivity.png")
    lines = [
        "### Sensitivity: AEE (px) / FWL against lambda (indoor_flying, variance)",
        "",
        f"Identity warp AEE {rows[0]['identity_AEE']:.2f} px; ground-truth FWL {rows[0]['gt_FWL']:.2f}. "
        "lambda = 0 is the unregularized estimate.",
        "",
        "| warp | regularizer | 0 | " + " | ".join(f"{lam:g}" for lam in lambdas) + " |",
        "|---|---|---|" + "---|" * len(lambdas),
    ]
    for warp in FLOW_WARPS:
        none = next(r for r in rows if r["warp"] == warp and r["regularizer"] == "none")
        for label in regs:
            cells = [f"{none['AEE']:.2f} / {none['FWL']:.2f}"]
            for lam in lambdas:
                r = next(
                    r for r in rows if r["warp"] == warp and r["regularizer"] == label and r["lambda"] == lam
                )
                cells.append(f"{r['AEE']:.2f} / {r['FWL']:.2f}")
            lines.append(f"| {WARP_LABEL[warp]} | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n", png


def complexity_outputs(rows: list[dict], out: Path) -> tuple[str, Path]:
    plt = _pyplot()
    sizes = sorted({r["n_events"] for r in rows})
    fig, ax = plt.subplots(figsize=(6, 4.2))
    for label, _ in COMPLEXITY_CONFIGS:
        pts = sorted((r["n_events"], r["seconds"]) for r in rows if r["config"] == label)
        ax.plot([a for a, _ in pts], [1e3 * b for _, b in pts], "o-", label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("events per window")
    ax.set_ylabel("ms per value_and_grad")
    ax.set_title(f"mitrokhin4, variance, 346x260 ({rows[0]['arch']}, {rows[0]['precision']})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    png = _save_plot(fig, out / "complexity.png")
    lines = [
        "### Complexity: ms per objective-and-gradient evaluation (mitrokhin4, variance, 346x260)",
        "",
        f"Backend: {rows[0]['arch']}, {rows[0]['precision']}; median of repeated runs. "
        "In brackets: the ratio to no regularizer.",
        "",
        "| events | " + " | ".join(label for label, _ in COMPLEXITY_CONFIGS) + " |",
        "|---|" + "---|" * len(COMPLEXITY_CONFIGS),
    ]
    for n in sizes:
        base = next(r["seconds"] for r in rows if r["n_events"] == n and r["config"] == "none")
        cells = []
        for label, _ in COMPLEXITY_CONFIGS:
            s = next(r["seconds"] for r in rows if r["n_events"] == n and r["config"] == label)
            cells.append(f"{1e3 * s:.2f}" + ("" if label == "none" else f" ({s / base:.2f}x)"))
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n", png


def write_rows_csv(rows: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
