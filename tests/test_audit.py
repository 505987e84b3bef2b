"""The pose-only random-guess audit: the test store finds the query's own pose, the train
store cannot, and the command prints the table from label files alone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pae.data.labels import LabelTable, read_labels, write_labels
from pae.data_cli import main
from pae.refine.audit import guess_audit
from tests.conftest import REFERENCE_LABELS


def _table(scene: str, split: str, positions: np.ndarray) -> LabelTable:
    poses = np.concatenate([positions, np.tile([1.0, 0, 0, 0], (len(positions), 1))], axis=1)
    return LabelTable(
        scene=[scene] * len(poses),
        split=[split] * len(poses),
        seq=["seq-01"] * len(poses),
        img_path=[f"{scene}/{i}.png" for i in range(len(poses))],
        poses=poses,
    )


def _walks() -> tuple[LabelTable, LabelTable]:
    """Test cameras every 0.5 m along a line; train cameras 2 m beside them."""
    along = np.stack([np.arange(60) * 0.5, np.zeros(60), np.zeros(60)], axis=1)
    test = LabelTable.concat([_table("a", "test", along), _table("b", "test", along + 100)])
    train = LabelTable.concat(
        [
            _table("a", "train", along + np.array([0, 2, 0])),
            _table("b", "train", along + np.array([100, 102, 100])),
        ]
    )
    return test, train


def test_test_store_finds_the_own_pose_and_the_train_store_cannot() -> None:
    test, train = _walks()
    rows = guess_audit(test, train, sigma_m=0.1, k=1, seed=0)
    assert [r.scene for r in rows] == ["a", "b"]
    for row in rows:
        assert (row.test_rows, row.train_rows) == (60, 60)
        assert row.test_to_train_m == pytest.approx(2.0)
        assert row.knn_mean_test_store_m == 0.0
        assert row.knn_mean_m == pytest.approx(2.0, abs=0.3)
        assert 0.05 < row.guess_m < 0.3


def test_audit_guess_command_prints_the_table(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    test, train = _walks()
    write_labels(tmp_path / "test.csv", test)
    write_labels(tmp_path / "train.csv", train)
    args = ["audit-guess", "--test", str(tmp_path / "test.csv"), "--train"]
    assert main([*args, str(tmp_path / "train.csv"), "--k", "1", "--sigma", "0.1"]) == 0
    out = capsys.readouterr().out
    assert "| a | 60 | 2.00 |" in out and "| average |" in out and "test store *" in out
    only_a = tmp_path / "train_a.csv"
    write_labels(only_a, train.select(np.asarray(train.scene) == "a"))
    assert main([*args, str(only_a)]) == 1
    assert "no train rows for the test scenes ['b']" in capsys.readouterr().err


@pytest.mark.reference_labels
def test_on_real_cambridge_labels_the_test_store_beats_the_train_store() -> None:
    folder = REFERENCE_LABELS / "CambridgeLandmarks"
    test = read_labels(folder / "ShopFacade_test.csv")
    train = read_labels(folder / "ShopFacade_train.csv")
    (row,) = guess_audit(test, train, sigma_m=1.0, k=3, seed=0)
    assert row.knn_mean_test_store_m < 0.5 * row.guess_m
    assert row.knn_mean_test_store_m < row.knn_mean_m
