"""The bookkeeping of ``python -m cmax_taichi.lab.experiments_real``: collapse outcome, lambda selection
and the tables it prints (synthetic rows; the real runs are in test_real_data.py)."""

from __future__ import annotations

import numpy as np

from cmax_taichi.lab.experiments_real import (
    COLLAPSE_SHARE,
    WHITENING_HEADER,
    collapse_line,
    collapse_outcome,
    lambda_table,
    main,
    rotation_header,
    rotation_line,
    select_lambda,
    whitening_line,
)


def _row(warp, label, lam, covered, fwl=2.0):
    return {
        "warp": warp,
        "objective": "variance",
        "label": label,
        "lambda": lam,
        "theta": np.array([0.5]),
        "params": ["h_z"],
        "J": 1.0,
        "fwl": fwl,
        "covered": covered,
        "area": 1.0,
        "duration": 0.1,
        "seconds": 1.0,
    }


def test_collapse_outcome_separates_gathered_from_spread_out():
    assert collapse_outcome(_row("zoom1", "none", 0.0, COLLAPSE_SHARE)) == "no"
    assert collapse_outcome(_row("zoom1", "none", 0.0, 0.3, fwl=5.0)) == "collapse"
    assert collapse_outcome(_row("zoom1", "none", 0.0, 0.3, fwl=0.8)) == "spread out"


def test_select_lambda_is_the_smallest_weight_without_any_collapse():
    rows = [
        _row("zoom1", "none", 0.0, 0.3),  # unregularized rows do not count
        _row("zoom1", "divergence", 1.0, 0.3),
        _row("zoom1", "deformation", 1.0, 0.9),
        _row("zoom1", "divergence", 5.0, 0.9),
        _row("zoom1", "deformation", 5.0, 0.9),
        _row("zoom1", "divergence", 10.0, 0.9),
        _row("zoom1", "deformation", 10.0, 0.3, fwl=0.5),  # spread out also disqualifies
    ]
    assert select_lambda(rows) == 5.0
    assert select_lambda([r for r in rows if r["lambda"] in (0.0, 1.0)]) is None


def test_lambda_table_has_one_line_per_configuration_and_one_column_per_weight():
    rows = [_row("zoom1", name, lam, 0.9 if lam > 1 else 0.3) for lam in (1.0, 2.0) for name in ("a", "b")]
    table = lambda_table(rows).splitlines()
    assert table[0] == "| warp | objective | regularizer | lambda = 1 | lambda = 2 |"
    assert len(table) == 4
    assert table[2] == "| zoom1 | variance | a | collapse, FWL 2.00 | no, FWL 2.00 |"
    assert "divergence, lambda = 2" in collapse_line(_row("zoom1", "divergence", 2.0, 0.9))
    assert "| none |" in collapse_line(_row("zoom1", "none", 0.0, 0.9))


def test_rotation_table_lines_match_their_header():
    r = {
        "name": "cut",
        "n_events": 100,
        "duration": 0.02,
        "w_gt": np.array([0.0, 1.0, 0.0]),
        "none": np.array([0.0, 1.1, 0.0]),
        "error_rel": 0.1,
        "error_deg_s": 5.7,
        "fwl_est": 1.2,
        "fwl_gt": 1.1,
        "lambdas": (1.0, 10.0),
        "seconds": 3.0,
    }
    for name in ("divergence", "deformation"):
        for lam in r["lambdas"]:
            r[f"change_{name}@{lam:g}"] = 0.01
            r[f"error_{name}@{lam:g}"] = 0.12
    header = rotation_header(r["lambdas"]).splitlines()[0]
    line = rotation_line(r)
    assert header.count("|") == line.count("|")
    assert "Div, lambda = 10: change / error" in header
    assert "1.00% / 12.0%" in line


def test_missing_data_folder_is_one_line_naming_the_folder_and_the_variable(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CMAX_SHARED_DATA", str(tmp_path / "absent"))
    assert main(["--only", "slider"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(tmp_path / "absent") in err and "CMAX_SHARED_DATA" in err


def test_whitening_table_lines_match_their_header():
    row = {
        "label": "0.5 x ray",
        "theta": np.array([39.0, -39.0, 65.0]),
        "angle": 2.06,
        "behind": 347,
        "spread": 1234.4,
        "top10": 0.4321,
        "J_white": 449.6511,
        "J_white_ref": 449.6511,
        "J_plain": 0.134,
    }
    header = WHITENING_HEADER.splitlines()[0]
    for r in (row, {**row, "behind": None, "spread": None, "top10": None, "J_white_ref": None}):
        assert header.count("|") == whitening_line(r).count("|")
    line = whitening_line(row)
    assert line == (
        "| 0.5 x ray | (+39.00, -39.00, +65.00) | 2.06 | 347 | 1234 | 43.2% | 449.6511 | 449.6511 | 0.1340 |"
    )
