"""cmax_taichi.segment on labelled synthetic two-object scenes, the evaluation metrics, bad input, and
the ``cmax-taichi segment`` command."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from conftest import shared_data_dir

import cmax_taichi as cm
from cmax_taichi.cli import main as cli_main
from cmax_taichi.lab import segment_eval as se

pytestmark = pytest.mark.usefixtures("f64")

SENSOR = (120, 90)
REGS = {"divergence": 1.0, "deformation": 1.0}


def _scene(seed: int = 0, n: int = 8000) -> se.SyntheticScene:
    return se.synthetic_scene(2, n, sensor_size=SENSOR, duration=0.04, speed=(150.0, 300.0), seed=seed)


def test_two_objects_with_regularizers():
    scene = _scene()
    res = cm.segment(scene.events, 2, warp="mitrokhin4", regularizers=REGS)
    n = len(scene.events)
    assert res.labels.shape == (n,) and res.labels.dtype.kind == "i"
    assert res.probabilities.shape == (n, 2)
    np.testing.assert_allclose(res.probabilities.sum(axis=1), 1.0, atol=1e-9)
    assert res.thetas.shape == (2, 4)
    assert res.iwes.shape == (2, SENSOR[1], SENSOR[0])
    assert res.warps == ("mitrokhin4", "mitrokhin4")
    assert len(res.history) >= 1 and res.seconds > 0
    assert not res.empty.any()
    assert se.label_accuracy(res.labels, scene.labels, 2) > 0.9
    errors = se.motion_errors(res, scene)
    assert max(errors) < 1.5, errors  # px at the reference time
    assert min(se.spread_ratios(res, scene)) > 0.9  # no cluster shrinks its object

    # the same window with hard assignments, and sharper soft memberships
    hard = cm.segment(scene.events, 2, warp="mitrokhin4", regularizers=REGS, hard=True, max_iterations=4)
    assert set(np.unique(hard.probabilities)) <= {0.0, 1.0}
    assert se.label_accuracy(hard.labels, scene.labels, 2) > 0.9
    sharp = cm.segment(
        scene.events, 2, warp="mitrokhin4", regularizers=REGS, temperature=0.5, max_iterations=4
    )
    assert se.label_accuracy(sharp.labels, scene.labels, 2) > 0.9


def test_more_clusters_than_motions_and_mixed_warps():
    """K = 3 on two objects: every object stays in one cluster; the surplus one is small or empty.
    One warp per cluster: thetas come back as a list."""
    scene = _scene(seed=1)
    res = cm.segment(scene.events, 3, warp="mitrokhin4", regularizers=REGS)
    mapping = se.match_clusters(res.labels, scene.labels, 3)
    surplus = ({0, 1, 2} - set(mapping.values())).pop()
    assert res.empty[surplus] or res.sizes[surplus] < 0.1 * len(scene.events)
    assert se.label_accuracy(res.labels, scene.labels, 3) > 0.85

    mixed = cm.segment(scene.events, 2, warp=["translation2", "mitrokhin4"], regularizers=REGS)
    assert isinstance(mixed.thetas, list) and [t.size for t in mixed.thetas] == [2, 4]
    assert se.label_accuracy(mixed.labels, scene.labels, 2) > 0.9


def test_distorted_camera_keeps_input_indexing():
    """Events that undistortion pushes off the sensor get label -1 and zero probabilities."""
    scene = _scene(seed=2, n=6000)
    camera = cm.Camera(fx=100.0, fy=100.0, cx=59.5, cy=44.5, dist=(-0.3, 0.1, 0.0, 0.0, 0.0))
    res = cm.segment(scene.events, 2, warp="mitrokhin4", regularizers=REGS, camera=camera, max_iterations=3)
    assert res.labels.shape == (len(scene.events),)
    dropped = ~res.kept
    assert dropped.any() and np.all(res.labels[dropped] == -1)
    assert np.all(res.probabilities[dropped] == 0.0)
    assert len(res.events) == int(res.kept.sum())


def test_bad_input():
    scene = _scene(n=2000)
    ev = scene.events
    empty = cm.Events(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), SENSOR)
    with pytest.raises(ValueError, match="empty"):
        cm.segment(empty, 2)
    with pytest.raises(ValueError, match="at least 1"):
        cm.segment(ev, 0)
    with pytest.raises(ValueError, match="more than the 3 events"):
        cm.segment(ev[:3], 4)
    with pytest.raises(TypeError, match="integer"):
        cm.segment(ev, 2.0)
    with pytest.raises(ValueError, match="temperature"):
        cm.segment(ev, 2, temperature=0)
    with pytest.raises(ValueError, match="seed must be at least 0, got -1"):  # not numpy's words
        cm.segment(ev, 2, seed=-1)
    with pytest.raises(ValueError, match="one warp or one per cluster"):
        cm.segment(ev, 2, warp=["translation2"] * 3)
    with pytest.raises(ValueError, match="unknown warp|not registered|valid"):
        cm.segment(ev, 2, warp="nope")
    with pytest.raises(TypeError, match="Events"):
        cm.segment(np.zeros((10, 4)), 2)


def test_metrics():
    truth = np.array([0, 0, 0, 1, 1, 1, 2, 2, -1])
    labels = np.array([2, 2, 2, 0, 0, 1, 1, 1, 0])  # object 0 -> cluster 2, 1 -> 0, 2 -> 1, one error
    assert se.match_clusters(labels, truth, 3) == {0: 2, 1: 0, 2: 1}
    assert se.label_accuracy(labels, truth, 3) == pytest.approx(7 / 8)
    # the brute-force fallback agrees with the Hungarian algorithm
    rng = np.random.default_rng(0)
    for _ in range(5):
        truth = rng.integers(-1, 4, 200)
        labels = rng.integers(0, 4, 200)
        conf = np.array([[np.sum((truth == o) & (labels == c)) for c in range(4)] for o in range(4)])
        best = max(sum(conf[o, c] for o, c in enumerate(p)) for p in itertools.permutations(range(4)))
        assert se.label_accuracy(labels, truth, 4) == pytest.approx(best / np.sum(truth >= 0))


def test_motion_error_of_the_truth_is_small():
    """A translating scene segmented by its true labels and velocities: endpoint error ~ the jitter."""
    scene = _scene(seed=3, n=3000)
    v = np.stack([m["velocity"] for m in scene.motions])
    res = cm.SegmentationResult(
        labels=np.where(scene.labels < 0, 0, scene.labels),
        probabilities=np.zeros((len(scene.events), 2)),
        thetas=v,
        warps=("translation2", "translation2"),
        iwes=np.zeros((2, SENSOR[1], SENSOR[0])),
        empty=np.zeros(2, dtype=bool),
    )
    assert max(se.motion_errors(res, scene)) < 0.6  # jitter is 0.3 px per axis


def test_cli_segment(tmp_path):
    scene = _scene(seed=4, n=6000)
    ev = scene.events
    txt = tmp_path / "events.txt"
    np.savetxt(
        txt, np.column_stack([ev.t, ev.x, ev.y, (ev.p > 0).astype(int)]), fmt=["%.9f", "%.4f", "%.4f", "%d"]
    )
    out = tmp_path / "out"
    code = cli_main(
        [
            "segment",
            str(txt),
            "-k",
            "2",
            "--warp",
            "mitrokhin4",
            "--reg",
            "divergence=1",
            "--reg",
            "deformation=1",
            "--sensor-size",
            str(SENSOR[0]),
            str(SENSOR[1]),
            "--out",
            str(out),
        ]
    )
    assert code == 0
    labels = np.load(out / "labels.npy")
    assert labels.shape == (len(ev),)
    csv = np.loadtxt(out / "labels.csv", delimiter=",", skiprows=1)
    assert csv.shape == (len(ev), 7)
    summary = json.loads((out / "segmentation.json").read_text())
    assert summary["settings"]["clusters"] == 2 and len(summary["clusters"]) == 2
    assert set(summary["clusters"][0]["units"].values()) == {"px/s", "1/s", "rad/s"}
    for name in ("events_by_cluster.png", "cluster_iwes.png"):
        assert (out / "figures" / name).stat().st_size > 10_000
    # labels follow the file's event order
    assert se.label_accuracy(labels, scene.labels, 2) > 0.9


def test_cli_bad_input(tmp_path, capsys):
    assert cli_main(["segment", str(tmp_path / "missing"), "-k", "2"]) == 2
    assert "no such file" in capsys.readouterr().err
    txt = tmp_path / "events.txt"
    np.savetxt(txt, [[0.0, 1, 1, 1], [0.01, 2, 2, 0]], fmt="%g")
    assert cli_main(["segment", str(txt), "-k", "0"]) == 2
    assert "at least 1" in capsys.readouterr().err
    assert cli_main(["segment", str(txt), "-k", "3"]) == 2
    assert "fewer than the 3 clusters" in capsys.readouterr().err
    assert cli_main(["segment", str(txt), "-k", "2", "--warp", "translation2,se2,sim2"]) == 2
    assert "one model or 2" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_on_ecd_dynamic_rotation(tmp_path, capsys):
    """The real recording (a person in front of a rotating camera, raw distorted events.txt with
    calib.txt): the reader's camera undistorts, labels keep the file's indexing, figures are written,
    and the command prints what it really segmented (the events dropped by undistortion said apart).
    (translation2 and a 10,000-event window keep the test short; docs/SEGMENTATION.md shows rotation3.)"""
    path = shared_data_dir("ecd_rotation", "dynamic_rotation")
    out = tmp_path / "dyn"
    args = ["segment", str(path), "-k", "2", "--warp", "translation2", "--events", "10000"]
    assert cli_main(args + ["--max-iterations", "3", "--out", str(out)]) == 0
    labels = np.load(out / "labels.npy")
    assert labels.shape == (10000,)
    dropped = int((labels < 0).sum())
    assert 0 < dropped < 3000  # undistortion drops the events it pushes off the sensor
    text = capsys.readouterr().out
    assert (
        f"segmented {10000 - dropped} of 10000 events" in text
        and f"({dropped} dropped by undistortion)" in text
    )
    sizes = [
        int(line.split("]: ")[1].split(" events")[0]) for line in text.splitlines() if "  cluster " in line
    ]
    assert sum(sizes) == 10000 - dropped
    assert set(np.unique(labels[labels >= 0])) <= {0, 1}
    assert (out / "figures" / "cluster_iwes.png").exists()


def test_docs_example():
    """The motion segmentation example of docs/SEGMENTATION.md runs as written and separates the two
    objects."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "SEGMENTATION.md").read_text()
    section = text.split("# Motion segmentation", 1)[1]
    block = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    namespace: dict = {}
    exec(compile(block, "docs/SEGMENTATION.md", "exec"), namespace)  # noqa: S102 - our own docs
    assert namespace["accuracy"] > 0.95
    assert namespace["seg"].thetas.shape == (2, 4)
