"""``cmax-taichi reproduce``: the paper's numbers as transcribed, the table writers, one quick run, and
the command's errors."""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import pytest

from cmax_taichi.cli import main
from cmax_taichi.lab import experiment_reports as reports
from cmax_taichi.lab import experiments as ex

SPEC = Path(__file__).resolve().parents[2] / "shared" / "paper" / "SPEC.md"


def _spec_rows(title: str) -> dict[str, list[list[float]]]:
    """Rows of a results table of SPEC.md section 7: label -> [[5 numbers var.], [5 numbers GM]]."""
    if not SPEC.exists():
        pytest.skip(f"{SPEC} is absent (it sits beside the checkout)")
    text = SPEC.read_text()
    block = text[text.index(title) :]
    block = block[: block.index("\n\n", block.index("|---"))]
    rows = {}
    for line in block.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 3 or not re.match(r"^(1DOF|4DOF|Identity)", cells[0]):
            continue

        def nums(cell: str) -> list[float] | None:
            if cell == "same":
                return None
            return [float(v) for v in re.findall(r"\d+\.\d+", cell)]

        var, gm = nums(cells[1]), nums(cells[2])
        rows[cells[0]] = [var, gm if gm is not None else var]
    return rows


@pytest.mark.parametrize(
    "title, table", [("Table 1 (MVSEC", ex.PAPER_TABLE1), ("Table 2 (MVSEC", ex.PAPER_TABLE2)]
)
def test_paper_numbers_are_the_ones_of_the_spec(title, table):
    rows = _spec_rows(title)
    names = {"none": "No regularizer", "Whitening": "Whitening", "Div": "Divergence", "Def": "Deformation"}
    names["Div+Def"] = "Div. + Def."
    checked = 0
    for label, (var, gm) in rows.items():
        if label == "Identity":
            key = ("Identity", "")
        else:
            dof, row = label.split(" ", 1)
            key = ({"1DOF": "zoom1", "4DOF": "mitrokhin4"}[dof], names[row])
        assert list(table[key]["variance"]) == var, label
        assert list(table[key]["gradient_magnitude"]) == gm, label
        checked += 1
    assert checked == 11


def _fake_flow_result(value: float) -> dict:
    row = {o: (value, 50.0, 10.0, 1.0, 1.1) for o in ex.OBJECTIVES}
    result = {key: row for key, _ in reports.row_keys()}
    result[("GT", "")] = {o: (math.nan,) * 4 + (1.2,) for o in ex.OBJECTIVES}
    return result


def test_flow_table_writers_put_ours_beside_the_paper(tmp_path):
    result = _fake_flow_result(3.25)
    md = ex.flow_table_markdown(result, ex.PAPER_TABLE1, "Table 1")
    assert "| 1-DOF Divergence | 3.25 (4.00) | 50.00 (46.02) |" in md
    assert "| GT flow | – | – | – | – | 1.20 (1.05) |" in md
    assert len([line for line in md.splitlines() if line.startswith("| ")]) == 1 + 12
    path = tmp_path / "t.csv"
    ex.flow_table_csv(result, ex.PAPER_TABLE1, path, "table1")
    rows = list(csv.DictReader(path.read_text().splitlines()))
    assert len(rows) == 12 * 2 * 5
    hit = [r for r in rows if r["row"] == "4-DOF Div. + Def." and r["objective"] == "variance"]
    assert [float(r["paper"]) for r in hit] == [5.14, 65.61, 10.75, 0.38, 1.16]


def test_search_check_tells_a_missed_maximum_from_a_preferred_collapse():
    meta = [
        {
            "gt_fwl": 1.2,
            "fwl": {"variance/zoom1/Divergence": 5.0, "variance/mitrokhin4/Deformation": 1.2},
            "J_estimate_truth": {
                "variance/zoom1/Divergence": [2.0, 1.1],
                "variance/mitrokhin4/Deformation": [1.1, 1.2],
            },
        }
    ]
    lines = "\n".join(reports.search_check(meta))
    assert "prefers the collapse to the truth (1): variance/zoom1/Divergence (interval 1)" in lines
    assert "missed it (1): variance/mitrokhin4/Deformation (interval 1): J 1.1000 < 1.2000" in lines


def test_sensitivity_and_complexity_writers(tmp_path):
    rows = []
    for warp in ex.FLOW_WARPS:
        rows.append(dict(warp=warp, regularizer="none", AEE=90.0, FWL=5.0, identity_AEE=4.0, gt_FWL=1.2))
        rows[-1]["lambda"] = 0.0
        for label, _, _ in ex.ROWS[2:]:
            for lam in (0.1, 1.0):
                row = dict(warp=warp, regularizer=label, AEE=3.0 if lam == 1.0 else 90.0, FWL=1.1)
                rows.append({**row, "lambda": lam, "identity_AEE": 4.0, "gt_FWL": 1.2})
    md, png = ex.sensitivity_outputs(rows, tmp_path)
    assert png.exists() and png.stat().st_size > 10_000
    assert "| 4-DOF | Div. + Def. | 90.00 / 5.00 | 90.00 / 1.10 | 3.00 / 1.10 |" in md
    timing = [
        dict(n_events=n, config=c, seconds=s * n * 1e-7, arch="cpu", precision="f64")
        for n in (1000, 4000)
        for (c, _), s in zip(ex.COMPLEXITY_CONFIGS, (1.0, 1.5, 1.6, 2.0), strict=True)
    ]
    md, png = ex.complexity_outputs(timing, tmp_path)
    assert png.exists() and "| 4000 | 0.40 | 0.60 (1.50x) | 0.64 (1.60x) | 0.80 (2.00x) |" in md


#: ``../shared/data`` beside the checkout (this file is ``<checkout>/tests/test_experiments.py``)
BESIDE_CHECKOUT = Path(__file__).resolve().parents[2] / "shared" / "data"


def _default_paths_of_this_checkout(monkeypatch) -> None:
    """Unset ``CMAX_SHARED_DATA``; skip unless ``cmax_taichi`` is imported from this checkout (the
    default data path is relative to the package's files)."""
    monkeypatch.delenv("CMAX_SHARED_DATA", raising=False)
    if Path(ex.__file__).resolve().parents[2] != Path(__file__).resolve().parents[1]:
        pytest.skip(f"cmax_taichi is imported from {ex.__file__}, not from this checkout")


def test_default_data_path_is_shared_data_beside_the_checkout(monkeypatch, tmp_path):
    from cmax_taichi.lab import experiments_real

    _default_paths_of_this_checkout(monkeypatch)
    assert ex.shared_data_root() == BESIDE_CHECKOUT
    assert ex.default_data_dir() == BESIDE_CHECKOUT / "ecd_rotation"
    assert experiments_real.default_data_dir() == BESIDE_CHECKOUT
    monkeypatch.setenv("CMAX_SHARED_DATA", str(tmp_path))
    assert ex.default_data_dir() == tmp_path / "ecd_rotation"
    assert experiments_real.default_data_dir() == tmp_path


@pytest.mark.slow
def test_reproduce_table3_quick_on_the_default_data_path(tmp_path, monkeypatch, capsys):
    """``reproduce table3`` without ``--data`` reads ``../shared/data/ecd_rotation`` beside the checkout
    (it once looked one folder too deep and skipped on every machine)."""
    _default_paths_of_this_checkout(monkeypatch)
    data = BESIDE_CHECKOUT / "ecd_rotation"
    if not data.is_dir():
        pytest.skip(f"real-data folder {data} is absent (it sits beside the checkout, not in it)")
    code = main(["reproduce", "table3", "--quick", "--out", str(tmp_path), "--no-progress"])
    assert code == 0
    md = (tmp_path / "table3.md").read_text()
    assert "| GT pose |" in md and "boxes_rotation" in md and "(8.858 / 1.562)" in md
    rows = list(csv.DictReader((tmp_path / "table3.csv").read_text().splitlines()))
    assert {r["row"] for r in rows} == {"GT", "No regularizer", "Divergence", "Deformation"}
    for r in rows:
        fwl = float(r["fwl"])
        assert 1.0 < fwl < 3.0  # every estimate (and the gyro) sharpens the IWE
        if r["row"] != "GT":
            assert float(r["rms_deg_s"]) < 40.0  # within a fraction of |w| (about 70-100 deg/s)
    assert "table3" in capsys.readouterr().out


def test_reproduce_errors_are_one_line(tmp_path, capsys):
    code = main(["reproduce", "table3", "--quick", "--out", str(tmp_path), "--data", str(tmp_path / "none")])
    assert code == 2
    err = capsys.readouterr().err
    assert "no ECD rotation cut" in err and "Traceback" not in err
    with pytest.raises(SystemExit):
        main(["reproduce", "table9", "--out", str(tmp_path)])
    assert main(["reproduce", "table1", "--quick", "--windows", "0", "--out", str(tmp_path)]) == 2
    capsys.readouterr()
    # 1e12 intervals simulated for minutes before anything said the run could never end: refused at once
    assert main(["reproduce", "table1", "--quick", "--windows", "1000000000000", "--out", str(tmp_path)]) == 2
    assert "windows must be a whole number from 1 to 1,000" in capsys.readouterr().err
    with pytest.raises(ValueError, match="unknown experiment"):
        ex.reproduce("table7", tmp_path)
