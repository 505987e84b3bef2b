"""The validation split held out of the train labels (pae.data.holdout)."""

from __future__ import annotations

import numpy as np
import pytest

from pae.data.holdout import held_out_rows, natural_key
from pae.data.labels import LabelError, LabelTable, read_labels
from tests.conftest import REFERENCE_LABELS


def _table(rows: list[tuple[str, str]]) -> LabelTable:
    """A label table with one row per (scene, seq) and identity poses."""
    poses = np.tile([0.0, 0, 0, 1, 0, 0, 0], (len(rows), 1))
    poses[:, 0] = np.arange(len(rows))
    return LabelTable(
        scene=[r[0] for r in rows],
        split=["train"] * len(rows),
        seq=[r[1] for r in rows],
        img_path=[f"{r[0]}/{r[1]}/{i}.png" for i, r in enumerate(rows)],
        poses=poses,
        source="train.csv",
    )


def test_the_last_sequence_in_numeric_order_of_every_scene() -> None:
    table = _table([("a", "seq2"), ("a", "seq10"), ("a", "seq2"), ("b", "seq-01"), ("b", "seq-02")])
    mask, held = held_out_rows(table, 1, None)
    assert mask.tolist() == [False, True, False, False, True]
    assert held == ["a: sequence seq10, 1 of 3 rows", "b: sequence seq-02, 1 of 2 rows"]
    assert sorted(["seq10", "seq9", "seq2"], key=natural_key) == ["seq2", "seq9", "seq10"]


def test_named_sequences_in_every_scene_or_in_one() -> None:
    table = _table([("a", "s1"), ("a", "s2"), ("b", "s1"), ("b", "s2"), ("b", "s3")])
    assert held_out_rows(table, ["s1"], None)[0].tolist() == [True, False, True, False, False]
    assert held_out_rows(table, ["b/s3"], None)[0].tolist() == [False] * 4 + [True]
    with pytest.raises(LabelError, match=r"train.csv.*no train rows of sequences \['s9'\]"):
        held_out_rows(table, ["s9"], None)
    with pytest.raises(LabelError, match="every train row of a"):
        held_out_rows(table, ["a/s1", "a/s2"], None)


def test_a_scene_with_one_sequence_holds_out_its_last_rows() -> None:
    table = _table([("a", "s1")] * 10 + [("b", "")] * 5 + [("c", "s1"), ("c", "s2")])
    mask, held = held_out_rows(table, 1, 0.25)
    assert np.flatnonzero(mask).tolist() == [7, 8, 9, 13, 14, 16]  # ceil(2.5), ceil(1.25), s2
    assert held[0] == "a: its last rows (val_fraction=0.25), 3 of 10 rows"
    mask, held = held_out_rows(table, 1, None)
    assert np.flatnonzero(mask).tolist() == [16] and held[0].startswith("a: nothing held out")


@pytest.mark.reference_labels
def test_every_reference_scene_gets_a_validation_split() -> None:
    files = sorted(REFERENCE_LABELS.glob("*/*_train.csv"))
    assert len(files) == 13, "the 7 scenes of 7-Scenes and 6 of Cambridge Landmarks"
    for path in files:
        table = read_labels(path)
        mask, _ = held_out_rows(table, 1, 0.1)
        assert 0 < mask.sum() < len(table), path
        kept, held = set(np.asarray(table.seq)[~mask]), set(np.asarray(table.seq)[mask])
        assert len(kept) == 1 or not kept & held, path  # whole sequences, unless only one
