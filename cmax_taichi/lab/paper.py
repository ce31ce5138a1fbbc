"""The paper's published numbers (Shiba, Aoki, Gallego, Sensors 2022; ``../shared/paper/SPEC.md``,
section 7), printed beside ours by :mod:`cmax_taichi.lab.experiments`.

Tables 1 and 2 are data (``paper_tables.csv`` beside this module), read once at import; an empty cell is
a value the paper does not report (NaN). The duplicated values SPEC.md marks "(?)" (4-DOF variance
3PE = AEE = 90.22 and 10PE 18.53 twice in Table 1) are kept as published.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

__all__ = [
    "OBJECTIVES",
    "FLOW_WARPS",
    "METRICS",
    "ROWS",
    "WARP_LABEL",
    "ROTATION_CUTS",
    "PAPER_TABLE1",
    "PAPER_TABLE2",
    "PAPER_TABLE3",
]

# --- the layout of the paper's tables ---------------------------------------------------------------
OBJECTIVES = ("variance", "gradient_magnitude")
FLOW_WARPS = ("zoom1", "mitrokhin4")
METRICS = ("AEE", "3PE", "10PE", "20PE", "FWL")
#: rows of the regularized experiments: (label, regularizer names, whitening)
ROWS = (
    ("No regularizer", (), False),
    ("Whitening", (), True),
    ("Divergence", ("divergence",), False),
    ("Deformation", ("deformation",), False),
    ("Div. + Def.", ("divergence", "deformation"), False),
)
WARP_LABEL = {"zoom1": "1-DOF", "mitrokhin4": "4-DOF"}
#: the ECD cuts of table 3 (the paper reports the first two)
ROTATION_CUTS = ("boxes_rotation", "dynamic_rotation", "shapes_rotation", "poster_rotation")

# --- the paper's numbers -------------------------------------------------------------------------------
#: tables 1 and 2, one line per (table, row, objective): AEE, 3PE, 10PE, 20PE, FWL; empty = not reported
PAPER_TABLES_CSV = Path(__file__).with_name("paper_tables.csv")


def _flow_tables(path: Path) -> dict[str, dict[tuple[str, str], dict[str, tuple[float, ...]]]]:
    """``table -> (warp or "GT" / "Identity", row label) -> {objective: (AEE, 3PE, 10PE, 20PE, FWL)}``."""
    tables: dict = {}
    with open(path, newline="") as fh:
        for line in csv.DictReader(fh):
            values = tuple(float(line[m]) if line[m] else math.nan for m in METRICS)
            row = tables.setdefault(line["table"], {}).setdefault((line["row"], line["label"]), {})
            row[line["objective"]] = values
    return tables


_FLOW_TABLES = _flow_tables(PAPER_TABLES_CSV)
#: Table 1 (MVSEC, likely indoor_flying1, dt = 4 frames)
PAPER_TABLE1 = _FLOW_TABLES["table1"]
#: Table 2 (MVSEC, likely outdoor_day1, dt = 4 frames)
PAPER_TABLE2 = _FLOW_TABLES["table2"]
#: Table 3 (ECD, rotation3): ``(row, sequence) -> (RMS of the angular-velocity error in deg/s, FWL)``; the
#: paper has boxes_rotation and dynamic_rotation only
PAPER_TABLE3 = {
    ("GT", "boxes_rotation"): (math.nan, 1.559),
    ("GT", "dynamic_rotation"): (math.nan, 1.414),
    ("No regularizer", "boxes_rotation"): (8.858, 1.562),
    ("No regularizer", "dynamic_rotation"): (4.823, 1.420),
    ("Divergence", "boxes_rotation"): (9.237, 1.558),
    ("Divergence", "dynamic_rotation"): (4.826, 1.420),
    ("Deformation", "boxes_rotation"): (8.664, 1.561),
    ("Deformation", "dynamic_rotation"): (4.822, 1.420),
}
