"""Render-and-compare over query sequences: neighbours along a sequence, the propagation of
refined poses from frame to frame, the median filter and the scene vote."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch

from pae.core.errors import ConfigError
from pae.core.geometry import pose_errors
from pae.core.pose_sampling import perturb
from pae.render_compare import Queries, refine
from pae.render_compare.refiner import RenderCompareRefiner
from pae.render_compare.sequences import (
    SequenceOptions,
    Sequences,
    hampel_filter,
    median_filter,
    neighbour_rows,
    propagate,
    vote_scenes,
)
from pae.scene_model.oracle import OracleSceneModel
from pae.synthetic import (
    Appearance,
    PinholeCamera,
    SyntheticSettings,
    make_scene,
    make_sequences,
    render_batch,
)
from tests.test_render_compare import _oracle_queries

SMALL_SEARCH = {"rounds": 2, "candidates": 6, "resolution": 24, "reference_size": 16}


def _walk(n: int) -> torch.Tensor:
    """Poses [n, 7] 0.1 m apart along x, all facing the same way."""
    poses = torch.zeros(n, 7)
    poses[:, 0] = 0.1 * torch.arange(n)
    poses[:, 3] = 1.0
    return poses


def test_neighbours_follow_each_sequence_in_row_order_and_stay_in_its_scene() -> None:
    sequences = torch.tensor([5, 5, 7, 5, 7])
    scenes = torch.zeros(5, dtype=torch.long)
    assert neighbour_rows(sequences, scenes, 1).tolist() == [1, 3, 4, -1, -1]
    assert neighbour_rows(sequences, scenes, -1).tolist() == [-1, 0, -1, 1, 2]
    assert neighbour_rows(sequences, scenes, 2).tolist() == [3, -1, -1, -1, -1]
    moved = torch.tensor([0, 1, 0, 0, 0])  # row 1 refined in another scene: nobody's neighbour
    assert neighbour_rows(sequences, moved, 1).tolist() == [-1, -1, 4, -1, -1]


def test_the_scene_vote_gives_each_sequence_its_most_common_scene() -> None:
    scenes = torch.tensor([0, 0, 1, 1, 1, 0, 2])
    sequences = torch.tensor([3, 3, 3, 8, 8, 8, 9])
    assert vote_scenes(scenes, sequences).tolist() == [0, 0, 0, 1, 1, 1, 2]


def test_the_median_filter_puts_a_lone_outlier_back_on_the_walk() -> None:
    walk = _walk(9)
    poses = walk.clone()
    poses[4, :3] += torch.tensor([1.5, -2.0, 0.7])
    poses[4, 3:] = torch.tensor([0.8, 0.6, 0.0, 0.0])  # 74 degrees off
    sequences = torch.zeros(9, dtype=torch.long)
    scenes = torch.zeros(9, dtype=torch.long)
    filtered = median_filter(poses, sequences, scenes, 5)
    position, orientation = pose_errors(filtered, walk)
    assert float(position[4]) < 0.11 and float(orientation[4]) < 1e-3
    torch.testing.assert_close(filtered[[0, 1, 7, 8]], walk[[0, 1, 7, 8]])
    stacked = median_filter(torch.stack([poses, walk]), sequences, scenes, 5)
    torch.testing.assert_close(stacked[0], filtered)  # leading dimensions filter alike
    assert median_filter(poses, sequences, scenes, 1) is poses


def test_the_hampel_filter_moves_only_the_frame_off_its_window() -> None:
    """A hand-held walk: the camera pans back and forth (2 degrees, not monotone), which the
    median filter flattens; the Hampel filter keeps every sharp frame and puts the lone
    outlier where the median puts it."""
    walk = _walk(11)
    angle = torch.deg2rad(2.0 * torch.tensor([0.0, 1, -1, 1, -1, 1, -1, 1, -1, 1, 0]))
    walk[:, 3], walk[:, 6] = torch.cos(angle / 2), torch.sin(angle / 2)
    poses = walk.clone()
    poses[5, :3] += torch.tensor([1.5, -2.0, 0.7])
    sequences = torch.zeros(11, dtype=torch.long)
    scenes = torch.zeros(11, dtype=torch.long)
    kept = hampel_filter(poses, sequences, scenes, 5)
    median = median_filter(poses, sequences, scenes, 5)
    others = torch.arange(11) != 5
    torch.testing.assert_close(kept[others], walk[others])
    assert float(pose_errors(median[others], walk[others])[1].max()) > 1.9  # pans flattened
    torch.testing.assert_close(kept[5], median[5])
    assert float(pose_errors(kept[5:6], walk[5:6])[0][0]) < 0.11
    turned = poses.clone()
    turned[5, 3:] = torch.tensor([0.8, 0.6, 0.0, 0.0])  # 74 degrees off, in place
    turned[5, :3] = walk[5, :3]
    torch.testing.assert_close(
        hampel_filter(turned, sequences, scenes, 5)[5],
        median_filter(turned, sequences, scenes, 5)[5],
    )
    apart = hampel_filter(poses, torch.arange(11), scenes, 5)
    torch.testing.assert_close(apart, poses)  # no neighbours: nothing moves
    stacked = hampel_filter(torch.stack([poses, walk]), sequences, scenes, 5)
    torch.testing.assert_close(stacked[0], kept)  # leading dimensions filter alike
    assert hampel_filter(poses, sequences, scenes, 1) is poses


def _consecutive_frames(n: int) -> tuple[OracleSceneModel, torch.Tensor, ...]:
    """n consecutive frames of benchmark scene 0's last walk (48 px, about 0.09 m and 5.5
    degrees apart), their intrinsics and true poses."""
    scene, camera = make_scene(0), PinholeCamera(48)
    walks = make_sequences(0, scene, SyntheticSettings(train_frames=6, test_frames=120))
    poses = walks[-1].poses[:n]
    images = render_batch(scene, poses, camera, Appearance(), supersample=1)
    f, c = camera.focal_px, camera.principal_point
    return (
        OracleSceneModel([scene]),
        torch.from_numpy(images).float().div(255).permute(0, 3, 1, 2),
        torch.tensor([f, f, c, c]).expand(n, 4),
        torch.from_numpy(poses).float(),
    )


def test_propagation_finds_a_frame_from_its_neighbours_that_its_own_start_missed() -> None:
    """One frame's start is 0.9 m and about 17 degrees off, beyond a small search's reach;
    its neighbours start near the truth, and the passes refine it from their refined poses."""
    model, images, intrinsics, truth = _consecutive_frames(6)
    starts = perturb(truth, torch.tensor([0.02, 0.0, 0.0, 0.0, 0.01, 0.0]).expand(6, 6))
    starts[3] = perturb(truth[3:4], torch.tensor([[0.6, -0.6, 0.3, 0.2, 0.2, 0.1]]))[0]
    scenes = torch.zeros(6, dtype=torch.long)
    sequences = torch.zeros(6, dtype=torch.long)
    refiner = RenderCompareRefiner.configured(model, **SMALL_SEARCH)
    alone = refiner(images, intrinsics, starts, scenes)
    assert float(pose_errors(alone.poses, truth)[0][3]) > 0.5
    found = propagate(refiner, images, intrinsics, scenes, alone, sequences, passes=2)
    position, _ = pose_errors(found.poses, truth)
    assert float(position[3]) < 0.15
    assert bool((found.score >= alone.score).all())  # a pose is only ever replaced by a better
    torch.testing.assert_close(found.initial_score, alone.initial_score)
    apart = propagate(refiner, images, intrinsics, scenes, alone, torch.arange(6), passes=2)
    torch.testing.assert_close(apart.poses, alone.poses)  # no neighbours: nothing moves


def test_refine_uses_the_sequences_only_when_asked() -> None:
    model, images, intrinsics, _, start = _oracle_queries(4)
    scenes = torch.zeros(4, dtype=torch.long)
    sequences = torch.zeros(4, dtype=torch.long)
    queries = Queries(images, intrinsics, scenes)
    plain = refine(model, queries, start, settings=SMALL_SEARCH)
    same = refine(model, queries, start, None, Sequences(sequences), SMALL_SEARCH)
    torch.testing.assert_close(same.poses, plain.poses)
    windowed = Sequences(sequences, SequenceOptions(window=3))
    filtered = refine(model, queries, start, None, windowed, SMALL_SEARCH)
    expected = median_filter(plain.poses, sequences, scenes, 3)
    torch.testing.assert_close(filtered.poses, expected)
    hampel = Sequences(sequences, SequenceOptions(window=3, fit="hampel"))
    kept = refine(model, queries, start, None, hampel, SMALL_SEARCH)
    torch.testing.assert_close(kept.poses, hampel_filter(plain.poses, sequences, scenes, 3))
    with pytest.raises(ValueError, match=r"sequences\.ids must be \[4\], got \[3\]"):
        refine(model, queries, start, sequences=Sequences(sequences[:3]))


def test_sequence_options_name_a_bad_value() -> None:
    with pytest.raises(ValueError, match="sequence_window must be 0 or odd, not 4"):
        SequenceOptions(window=4)
    with pytest.raises(ValueError, match="sequence_passes must be >= 0, not -1"):
        SequenceOptions(passes=-1)
    with pytest.raises(ValueError, match="sequence_fit must be one of median, hampel, not 'mean'"):
        SequenceOptions(window=3, fit="mean")
    assert not SequenceOptions(window=1).active and SequenceOptions(vote_scene=True).active


def test_the_callback_refuses_sequences_from_data_that_has_none() -> None:
    from pae.lit.eval_outputs import query_sequences

    class Frames:
        pass

    assert query_sequences(SequenceOptions(), Frames(), "test", torch.arange(3)) is None
    with pytest.raises(ConfigError, match="data module Frames does not say which sequence"):
        query_sequences(SequenceOptions(passes=1), Frames(), "test", torch.arange(3))


def test_the_gate_objective_is_a_calibration_option() -> None:
    from pae.render_compare import CalibrationOptions

    with pytest.raises(ValueError, match="gate_objective: unknown 'median'"):
        CalibrationOptions(gate_objective="median")
    assert CalibrationOptions(gate_objective="log_ratio").gate_objective == "log_ratio"


def test_the_vote_refines_a_sequence_in_the_scene_most_of_its_starts_are_in() -> None:
    model, images, intrinsics, _, start = _oracle_queries(4)
    predicted = torch.tensor([0, 1, 0, 0])  # the oracle holds scene 0 only
    sequences = Sequences(torch.zeros(4, dtype=torch.long), SequenceOptions(vote_scene=True))
    voted = refine(
        model, Queries(images, intrinsics, predicted), start, None, sequences, SMALL_SEARCH
    )
    assert voted.scenes.tolist() == [0, 0, 0, 0]


def test_the_callback_passes_each_querys_sequence_from_the_data(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The callback calibrates on val and refines at test with each query's sequence as the
    data module gives it for that split, at the query's row (``index``), under the sequence
    options, and refines at test under the calibration chosen on val; the sequences change
    its test poses."""
    import inspect
    from types import SimpleNamespace

    from pae.callbacks import render_compare as adapter
    from pae.callbacks.render_compare import ORACLE, RenderCompareCallback
    from tests.test_render_compare import _fake_run

    model, images, intrinsics, truth = _consecutive_frames(6)
    start = perturb(truth, torch.tensor([0.1, 0.0, 0.05, 0.0, 0.03, 0.0]).expand(6, 6))
    # the split's recordings by label row; the queries are its rows 2-7
    recordings = {
        "val": torch.tensor([9, 9, 7, 7, 7, 8, 8, 8]),
        "test": torch.tensor([9, 9, 0, 0, 0, 1, 1, 1]),
    }
    rows = torch.arange(2, 8)
    calls: dict[str, dict] = {}

    def spy(name: str, call: Any) -> Any:
        def spied(*args: Any, **kwargs: Any) -> Any:
            calls[name] = inspect.signature(call).bind(*args, **kwargs).arguments
            calls[name]["returned"] = call(*args, **kwargs)
            return calls[name]["returned"]

        return spied

    monkeypatch.setattr(adapter, "calibrate", spy("calibrate", adapter.calibrate))
    monkeypatch.setattr(adapter, "refine", spy("refine", adapter.refine))
    callback = RenderCompareCallback(
        SMALL_SEARCH, oracle=False, sequence_passes=2, sequence_window=3,
        gate_objective="log_ratio",
    )  # fmt: skip
    for split in ("val", "test"):
        trainer, module = _fake_run(model, images, intrinsics, start, truth, str(tmp_path))
        module.eval_outputs[0]["index"] = rows
        trainer.datamodule = SimpleNamespace(recording_ids=recordings.__getitem__)
        callback.refine(trainer, module, split)
    options = SequenceOptions(passes=2, window=3)
    for name, ids in (("calibrate", [7, 7, 7, 8, 8, 8]), ("refine", [0, 0, 0, 1, 1, 1])):
        sequences = calls[name]["sequences"]
        assert sequences is not None, f"{name} was given no sequences"
        assert sequences.ids.tolist() == ids and sequences.options == options
    assert calls["refine"]["calibration"] is calls["calibrate"]["returned"][0]
    refined = callback.refined["test"][ORACLE]
    assert refined is calls["refine"]["returned"].poses
    queries = Queries(images, intrinsics, torch.zeros(6, dtype=torch.long))
    plain = refine(model, queries, start, callback.calibration(ORACLE), None, callback.settings)
    assert not torch.equal(plain.poses, refined)


def test_recordings_come_from_where_each_frame_came_from_never_a_label() -> None:
    """A recording is a frame's folder, or the sequence an ACE-layout name holds."""
    from pae.data.converted import recording_of

    assert recording_of("chess/seq-03/frame-000000.color.png") == "chess/seq-03"
    assert recording_of("KingsCollege/seq2/frame00001.png") == "KingsCollege/seq2"
    assert recording_of("test/rgb/seq-01-frame-000007.color.png") == "test/rgb/seq-01"
    assert recording_of("test/rgb/seq2_frame00001.png") == "test/rgb/seq2"
    assert recording_of("a.png") == "."


def test_the_data_module_s_recordings_ignore_the_label_columns(tiny_root: Path) -> None:
    """The test split's recording ids follow its images' folders: relabelling every test
    row's scene and sequence (the labels a user would not have) changes none of them."""
    import dataclasses

    from pae.synthetic.datamodule import SyntheticDataModule
    from tests.conftest import TINY

    data = SyntheticDataModule(root=str(tiny_root), **TINY, crop=28, shorter_edge=TINY["size"])
    data.setup()
    table = data.tables["test"]
    ids = data.recording_ids("test")
    folders = [str(Path(path).parent) for path in table.img_path]
    assert len(set(folders)) > 1 and len(ids) == len(table)
    for a in range(len(ids)):
        for b in range(len(ids)):
            assert (ids[a] == ids[b]) == (folders[a] == folders[b])
    blank = [""] * len(table)
    data.tables["test"] = dataclasses.replace(table, scene=["scene00"] * len(table), seq=blank)
    assert torch.equal(data.recording_ids("test"), ids)
