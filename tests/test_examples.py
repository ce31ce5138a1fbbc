"""The out-of-the-box examples: `cmax-taichi estimate --example NAME` and `segment --example NAME`
simulate a recording with a fixed seed and print the estimate against the exact truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cmax_taichi.cli import main
from cmax_taichi.sim.examples import EXAMPLES, SEGMENT_EXAMPLES, example_names, make_example


def test_examples_are_listed_and_deterministic():
    assert example_names() == list(EXAMPLES) and {"rotation", "translation", "collapse"} <= set(EXAMPLES)
    assert example_names("segment") == list(SEGMENT_EXAMPLES) == ["two-objects"]
    a, b = make_example("translation"), make_example("translation")
    assert len(a.events) == len(b.events) > 10_000
    np.testing.assert_array_equal(a.events.t, b.events.t)
    np.testing.assert_array_equal(a.events.x, b.events.x)
    np.testing.assert_allclose(a.truth, [300.0, -200.0])
    with pytest.raises(ValueError, match="unknown example 'nope'; valid examples: translation"):
        make_example("nope")
    with pytest.raises(ValueError, match="kind must be"):
        example_names("other")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["estimate"], "give a recording PATH, or --example NAME"),
        (["estimate", "somewhere", "--example", "rotation"], "not both"),
        (["estimate", "--example", "nope"], "unknown example 'nope'; valid: translation, rotation"),
        (["segment"], "give a recording PATH, or --example NAME"),
        (["segment", "--example", "rotation"], "unknown example 'rotation'; valid: two-objects"),
    ],
)
def test_example_arguments_errors(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def _run_estimate(tmp_path, name, *extra):
    out = tmp_path / name
    argv = ["estimate", "--example", name, "--out", str(out), "--quiet", "--figures", "0", *extra]
    assert main(argv) == 0
    return json.loads((out / "truth.json").read_text())


@pytest.mark.slow
def test_rotation_example_recovers_the_truth(tmp_path, capsys):
    report = _run_estimate(tmp_path, "rotation", "--max-windows", "2")
    printed = capsys.readouterr().out
    assert "example 'rotation'" in printed and "w_z [rad/s]" in printed
    for row in report["parameters"]:
        assert abs(row["error"]) <= 0.1 * abs(row["truth"]) + 0.05, row
    assert report["collapsed_windows"] == 0


@pytest.mark.slow
def test_collapse_example_collapses_without_regularizers_and_not_with_them(tmp_path, capsys):
    free = _run_estimate(tmp_path, "collapse", "--max-windows", "1")
    assert free["collapsed_windows"] == 1
    assert "try --reg divergence=10 --reg deformation=10" in capsys.readouterr().out
    regularized = _run_estimate(
        tmp_path, "collapse", "--max-windows", "1", "--reg", "divergence=10", "--reg", "deformation=10"
    )
    assert regularized["collapsed_windows"] == 0
    h_x = regularized["parameters"][0]
    assert h_x["parameter"] == "h_x" and abs(h_x["error"]) < 0.2 * h_x["truth"]  # 4-DOF: 166 vs 150
    assert min(regularized["area_scale_estimate"]) > 0.9


@pytest.mark.slow
def test_segment_example_finds_both_motions(tmp_path, capsys):
    out = tmp_path / "seg"
    assert main(["segment", "--example", "two-objects", "--out", str(out), "--no-figures"]) == 0
    report = json.loads((out / "truth.json").read_text())
    assert report["accuracy"] > 0.85
    background = next(layer for layer in report["layers"] if layer["layer"] == 0)
    np.testing.assert_allclose(background["estimate"], background["truth"], atol=8.0)  # 118.3, -80.1
    obj = next(layer for layer in report["layers"] if layer["layer"] == 1)
    np.testing.assert_allclose(obj["estimate"], obj["truth"], atol=25.0)  # -224.6, 136.1
    assert "events in the cluster matched to their true layer" in capsys.readouterr().out
