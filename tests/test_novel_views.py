"""Novel views for the teacher: poses sampled around the train cameras alone, rendered with
their nearest train sequence's appearance, mixed into the train batches; the stage that fits
the scene model before the teacher and tests render-and-compare with it after."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from torch import Tensor

from pae import CONFIG_DIR
from pae.config.novel_views import NOVEL_VIEW_KEYS
from pae.config.validation import validate_train_config
from pae.core.errors import ConfigError
from pae.core.geometry import orientation_error_deg
from pae.models.base import Latents
from pae.models.latents import TeacherLatentDataModule
from pae.scene_model.base import SceneModel, SceneRendering
from pae.scene_model.novel_views import (
    NovelViewBatches,
    NovelViewPool,
    NovelViewSettings,
    other_sequence_neighbours,
    partners_within,
    render_views,
    sample_novel_poses,
)
from pae.synthetic.datamodule import SyntheticDataModule
from tests.conftest import POISON_M, TINY, TINY_SCENE_MODEL, tiny_data_overrides


def _data(root: Path) -> SyntheticDataModule:
    data = SyntheticDataModule(
        root=str(root),
        **TINY,
        crop=28,
        shorter_edge=TINY["size"],
        cache_images=True,
        batch_size=8,
    )
    data.setup()
    return data


class _Flat(SceneModel):
    """A grey scene whose appearance ``a`` adds ``a / 10`` to every channel: a view's colour
    tells which appearance it was rendered with."""

    def render(
        self, poses: Tensor, scenes: Tensor, intrinsics: Tensor, width: int, height: int
    ) -> SceneRendering:
        return SceneRendering(poses.new_full((len(poses), 3, height, width), 0.2))

    def with_appearance(self, rgb: Tensor, appearance: Tensor) -> Tensor:
        return rgb + appearance[:, None].float() / 10


SETTINGS = NovelViewSettings(
    ratio=0.5, views=1.0, position_jitter_m=0.2, orientation_jitter_deg=5.0
)


def test_sampled_poses_come_from_the_train_cameras_only(
    tiny_root: Path, poisoned_root: Path
) -> None:
    """The views of data whose validation and test cameras lie POISON_M away are those of the
    clean data, every one within its sampling's reach of a train camera."""
    clean, poisoned = _data(tiny_root), _data(poisoned_root)
    assert (poisoned.datasets["val"].poses[:, :3].abs() > POISON_M / 2).any()
    cameras = NovelViewPool(poisoned, _Flat(), SETTINGS, "sequence", seed=3).cameras(0)
    same = NovelViewPool(clean, _Flat(), SETTINGS, "sequence", seed=3).cameras(0)
    torch.testing.assert_close(cameras.poses, same.poses)
    train, scenes = poisoned.train_poses()
    assert (train[:, :3].abs() < POISON_M / 2).all()
    sequences, _ = poisoned.appearance_ids("train", "sequence")
    partner = other_sequence_neighbours(train[:, :3], scenes, sequences)
    gaps = (train[:, :3] - train[partner, :3]).norm(dim=-1)
    # at most half-way from the nearer of a camera and its partner, then jittered
    reach = gaps.max() / 2 + 2 * SETTINGS.position_jitter_m
    nearest = torch.cdist(cameras.poses[:, :3], train[:, :3]).min(1).values
    assert (nearest <= reach + 1e-5).all()
    assert torch.equal(cameras.scenes, scenes[cameras.source])
    for split in ("val", "test"):
        held = poisoned.datasets[split].poses[:, :3]
        assert torch.cdist(cameras.poses[:, :3], held).min() > POISON_M / 2


def test_views_lie_between_a_camera_and_the_nearest_one_of_another_sequence() -> None:
    """Two lanes 1 m apart: without jitter each view lies on the segment from its train camera
    to the other lane's nearest camera, with their interpolated heading; without ``between``
    it is its train camera."""
    x = torch.arange(10, dtype=torch.float64)
    lane = lambda y: torch.stack([x, torch.full_like(x, y), torch.zeros_like(x)], 1)  # noqa: E731
    half = math.radians(30) / 2
    yaw = torch.tensor([math.cos(half), 0, 0, math.sin(half)], dtype=torch.float64)
    q = torch.cat([torch.tensor([[1.0, 0, 0, 0]]).double().expand(10, 4), yaw.expand(10, 4)])
    poses = torch.cat([torch.cat([lane(0.0), lane(1.0)]), q], 1).float()
    scenes, sequences = torch.zeros(20, dtype=torch.long), (torch.arange(20) >= 10).long()
    draws = torch.Generator().manual_seed(0)
    exact = NovelViewSettings(
        ratio=0.5, views=1.0, position_jitter_m=0.0, orientation_jitter_deg=0.0
    )
    cameras = sample_novel_poses(poses, scenes, sequences, 200, exact, draws)
    start = poses[cameras.source]
    torch.testing.assert_close(cameras.poses[:, 0], start[:, 0])  # the partner is abreast
    share = (cameras.poses[:, 1] - start[:, 1]).abs()
    assert ((share >= 0) & (share <= 1 + 1e-6)).all() and share.std() > 0.2
    degrees = orientation_error_deg(cameras.poses[:, 3:], poses[:1, 3:].expand(200, 4))
    offset = torch.where(start[:, 1] > 0.5, 1 - share, share)  # from the yaw-0 lane
    torch.testing.assert_close(degrees, 30 * offset, atol=0.6, rtol=0)  # nlerp, not slerp
    on_lane = torch.cdist(cameras.poses[:, :3], poses[:, :3]).argmin(1)
    assert torch.equal(cameras.nearest, on_lane)
    still = dataclasses.replace(exact, between=False)
    kept = sample_novel_poses(poses, scenes, sequences, 50, still, draws)
    torch.testing.assert_close(kept.poses, poses[kept.source])
    middle = dataclasses.replace(exact, between_share=(0.4, 0.6))
    midway = sample_novel_poses(poses, scenes, sequences, 200, middle, draws)
    share = (midway.poses[:, 1] - poses[midway.source, 1]).abs()
    assert ((share >= 0.4 - 1e-6) & (share <= 0.6 + 1e-6)).all() and share.std() > 0.04
    either = dataclasses.replace(exact, between_orientation="either")
    kept_turn = sample_novel_poses(poses, scenes, sequences, 400, either, draws)
    share = (kept_turn.poses[:, 1] - poses[kept_turn.source, 1]).abs()
    assert share.std() > 0.2, "the position still moves between the two cameras"
    degrees = orientation_error_deg(kept_turn.poses[:, 3:], poses[:1, 3:].expand(400, 4))
    assert ((degrees < 0.1) | (degrees > 29.9)).all(), "one camera's orientation, not a blend"
    assert 150 < (degrees > 15).sum() < 250, "either camera's, drawn at random"


def test_partners_within_a_radius_reach_the_far_lane_drawn_uniformly() -> None:
    """Four sequences beside the source's: one 0.1 m away, one a lane 1 m away, one 1 m away
    turned by 90 degrees, one in another scene. Within 1.2 m and 30 degrees a partner is drawn
    from the first two about equally often, never from the turned one, the source's own
    sequence or another scene; where none lies that close, it is the nearest camera of another
    sequence."""
    x = torch.arange(10, dtype=torch.float64) * 0.05
    lane = lambda y: torch.stack([x, torch.full_like(x, y), torch.zeros_like(x)], 1)  # noqa: E731
    turned = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    q = torch.tensor([1.0, 0, 0, 0]).double().repeat(50, 1)
    q[30:40] = turned
    poses = torch.cat([torch.cat([lane(0.0), lane(0.1), lane(1.0), lane(-1.0), lane(0.0)]), q], 1)
    sequences = torch.arange(5).repeat_interleave(10)
    scenes = torch.tensor([0, 0, 0, 0, 1]).repeat_interleave(10)
    rows = torch.zeros(4000, dtype=torch.long)
    draws = torch.Generator().manual_seed(0)
    partners = partners_within(rows, poses, scenes, sequences, 1.2, 30.0, draws)
    counts = torch.bincount(sequences[partners], minlength=5)
    assert counts[0] == 0 and counts[3] == 0 and counts[4] == 0
    assert abs(counts[1].item() - 2000) < 150 and abs(counts[2].item() - 2000) < 150
    anywhere = partners_within(rows, poses, scenes, sequences, 1.2, 180.0, draws)
    assert torch.bincount(sequences[anywhere], minlength=5)[3] > 1000
    near = partners_within(rows[:5], poses, scenes, sequences, 0.05, 30.0, draws)
    nearest = other_sequence_neighbours(poses[:, :3], scenes, sequences)
    assert torch.equal(near, nearest[rows[:5]]) and torch.equal(near, torch.full((5,), 10))


def test_views_keep_their_distance_from_every_train_camera() -> None:
    """Two lanes 1 m apart: with ``min_distance_m`` 0.3 every view lies at least 0.3 m from
    every train camera (between the lanes, where none was taken); asked for more than the
    draws can find (2 m), it still gives the views asked for, the farthest drawn."""
    x = torch.arange(20, dtype=torch.float64) * 0.1
    lane = lambda y: torch.stack([x, torch.full_like(x, y), torch.zeros_like(x)], 1)  # noqa: E731
    q = torch.tensor([1.0, 0, 0, 0]).double().repeat(40, 1)
    poses = torch.cat([torch.cat([lane(0.0), lane(1.0)]), q], 1).float()
    scenes, sequences = torch.zeros(40, dtype=torch.long), (torch.arange(40) >= 20).long()
    spread = NovelViewSettings(
        ratio=1.0,
        views=1.0,
        position_jitter_m=0.05,
        orientation_jitter_deg=1.0,
        between_radius_m=1.5,
        min_distance_m=0.3,
    )
    cameras = sample_novel_poses(poses, scenes, sequences, 300, spread, torch.Generator())
    clear = torch.cdist(cameras.poses[:, :3], poses[:, :3]).min(1).values
    assert len(cameras.poses) == 300 and (clear >= 0.3 - 1e-5).all()
    assert torch.equal(cameras.nearest, torch.cdist(cameras.poses[:, :3], poses[:, :3]).argmin(1))
    anywhere = dataclasses.replace(spread, min_distance_m=0.0)
    drawn = sample_novel_poses(poses, scenes, sequences, 300, anywhere, torch.Generator())
    assert (torch.cdist(drawn.poses[:, :3], poses[:, :3]).min(1).values < 0.3).float().mean() > 0.3
    too_far = dataclasses.replace(spread, min_distance_m=2.0)
    farthest = sample_novel_poses(poses, scenes, sequences, 300, too_far, torch.Generator())
    assert len(farthest.poses) == 300
    assert torch.cdist(farthest.poses[:, :3], poses[:, :3]).min(1).values.min() > 0.3


def test_each_view_has_its_sources_intrinsics_and_its_nearest_cameras_appearance(
    tiny_root: Path,
) -> None:
    data = _data(tiny_root)
    pool = NovelViewPool(data, _Flat(), SETTINGS, "sequence", seed=0)
    cameras = pool.cameras(0)
    images = render_views(_Flat(), cameras, pool.intrinsics, pool.appearance, (32, 32), size=16)
    assert images.shape == (len(cameras.poses), 3, 32, 32) and images.dtype == torch.uint8
    expected = (0.2 + pool.appearance[cameras.nearest].float() / 10).clamp(0, 1) * 255
    torch.testing.assert_close(images[:, 0, 5, 7].float(), expected.round(), atol=1, rtol=0)
    assert len(set(pool.appearance[cameras.nearest].tolist())) > 1


def test_batches_mix_every_train_image_with_views_drawn_by_seed_and_epoch(
    tiny_root: Path,
) -> None:
    data = _data(tiny_root)

    def epoch_of(settings: NovelViewSettings, epoch: int, seed: int = 0) -> list[dict]:
        pool = NovelViewPool(data, _Flat(), settings, "sequence", seed)
        batches = NovelViewBatches(data, pool, settings.ratio, seed, lambda: epoch)
        return [batches[i] for i in range(len(batches))]

    batches = epoch_of(SETTINGS, 0)
    n = len(data.datasets["train"])
    assert len(batches) == n // 8
    for batch in batches:
        assert len(batch["image"]) == len(batch["pose"]) == 8 + 4
        assert (batch["index"][:8] >= 0).all() and (batch["index"][8:] == -1).all()
        assert batch["image"].dtype == torch.uint8
    again = epoch_of(SETTINGS, 0)
    assert all(torch.equal(a["pose"], b["pose"]) for a, b in zip(batches, again, strict=True))
    later = epoch_of(SETTINGS, 1)
    assert not torch.equal(batches[0]["pose"], later[0]["pose"])
    pool = NovelViewPool(data, _Flat(), SETTINGS, "sequence", 0)
    torch.testing.assert_close(pool.cameras(0).poses, pool.cameras(5).poses)  # cached
    fresh = NovelViewPool(data, _Flat(), dataclasses.replace(SETTINGS, cache=False), "sequence", 0)
    assert not torch.equal(fresh.cameras(0).poses, fresh.cameras(1).poses)
    assert pool.count == n


class _MeanColour(torch.nn.Module):
    """A teacher whose latents are an image's mean colour: a rendered view's latents tell
    that the teacher saw that view."""

    def forward(self, images: Tensor, scene: Tensor) -> tuple[Tensor, Latents]:
        colour = images.mean(dim=(2, 3))
        pose = torch.cat([colour, torch.ones(len(images), 1), colour.new_zeros(len(images), 3)], 1)
        return pose, Latents(colour, -colour)


def test_student_data_adds_the_views_latents_and_their_poses_to_the_store(
    tiny_root: Path,
) -> None:
    data = _data(tiny_root)
    pool = NovelViewPool(data, _Flat(), SETTINGS, "sequence", seed=0)
    train, scenes = data.train_poses()

    def module(train_on_views: bool, store_views: bool) -> TeacherLatentDataModule:
        latents = TeacherLatentDataModule(
            data,
            _MeanColour(),
            views=lambda: pool.views(0),
            train_on_views=train_on_views,
            store_views=store_views,
        )
        latents.setup("fit")
        return latents

    both = module(True, True)
    views = pool.views(0)
    n, m = len(train), len(views["pose"])
    assert len(both.latents) == n + m and both.view_rows == m
    torch.testing.assert_close(both.latents.tensors["pose"][n:], views["pose"])
    rendered = data.preprocess(views["image"], train=False).mean(dim=(2, 3))
    torch.testing.assert_close(both.latents.tensors["z_x"][n:], rendered)
    store, store_scenes = both.store_poses()
    torch.testing.assert_close(store, torch.cat([train, views["pose"]]))
    assert torch.equal(store_scenes, torch.cat([scenes, views["scene"]]))
    train_only = module(True, False)
    assert len(train_only.latents) == n + m
    torch.testing.assert_close(train_only.store_poses()[0], train)
    store_only = module(False, True)
    assert len(store_only.latents) == n and len(store_only.store_poses()[0]) == n + m
    poses_only = TeacherLatentDataModule(  # the store needs no rendered image
        data,
        _MeanColour(),
        views=lambda: {"pose": views["pose"], "scene": views["scene"]},
        store_views=True,
    )
    poses_only.setup("fit")
    torch.testing.assert_close(poses_only.store_poses()[0], store)


def test_novel_view_settings_are_checked_before_any_work(compose_train, tmp_path: Path) -> None:
    assert set(NOVEL_VIEW_KEYS) == {"enabled"} | {
        f.name for f in dataclasses.fields(NovelViewSettings)
    }
    typo = compose_train("+teacher.novel_views.typo=1")
    for overrides in (["+teacher.novel_views.typo=1"], []):  # the command line, or a file
        with pytest.raises(ConfigError, match=r"teacher\.novel_views\.typo: not a setting"):
            validate_train_config(typo, overrides)
    for override, message in (
        ("teacher.novel_views.ratio=0", r"teacher\.novel_views\.ratio must be a number > 0"),
        ("teacher.novel_views.size=2", r"teacher\.novel_views\.size must be an integer >= 4"),
        ("teacher.novel_views.between_radius_m=0", r"between_radius_m must be a number > 0"),
        ("teacher.novel_views.between_max_turn_deg=-1", r"between_max_turn_deg must be a"),
        ("teacher.novel_views.min_distance_m=-1", r"min_distance_m must be a number >= 0"),
        ("teacher.novel_views.between_share=[0.6,0.4]", r"between_share must be \[lo, hi\]"),
        ("teacher.novel_views.between_share=0.5", r"between_share must be \[lo, hi\] with"),
        ("teacher.novel_views.between_orientation=slerp", r"between_orientation must be one of"),
        ("teacher.novel_views.enabled=true", r"stage=teacher needs scene_model_ckpt=PATH"),
        ("student.store_novel_views=1", r"student\.store_novel_views must be true or false"),
    ):
        with pytest.raises(ConfigError, match=message):
            validate_train_config(compose_train(override))
    for overrides, message in (
        (["student.novel_views=true"], r"stage=pipeline needs scene_model_ckpt=PATH"),
        (
            ["student.store_novel_views=true", "student.cache_latents=false"],
            r"student\.novel_views and student\.store_novel_views need student\.cache_latents",
        ),
    ):
        with pytest.raises(ConfigError, match=message):
            validate_train_config(compose_train("stage=pipeline", *overrides))
    with pytest.raises(ConfigCompositionException, match=r"teacher\.novel_views\.cache"):
        compose_train("teacher.novel_views.cache=maybe")  # the schema types it
    on = compose_train(
        "stage=novel_views", "teacher.novel_views.enabled=true", "student.novel_views=true"
    )
    validate_train_config(on)  # the scene_fit step makes the checkpoint the teacher reads
    with pytest.raises(ConfigError, match=r"scene_fit: scene_model.model._target_=\S+ does not"):
        validate_train_config(compose_train("stage=novel_views", "scene_model=oracle"))


def test_the_novel_views_stage_fits_the_scene_model_once(tiny_root: Path, tmp_path: Path) -> None:
    """stage=novel_views on the tiny benchmark: the scene model fitted without a teacher, the
    teacher trained on the train images and its views, render-and-compare from that teacher
    against the same scene model, which the scene_model step does not fit again."""
    from pae.train import run

    overrides = [
        *tiny_data_overrides(tiny_root),
        "data.batch_size=8",
        "callbacks=minimal",
        "+trainer.enable_progress_bar=false",
        "stage=novel_views",
        "teacher.max_epochs=1",
        "teacher.novel_views.enabled=true",
        "teacher.novel_views.size=16",
        "student.max_epochs=1",
        "student.novel_views=true",
        "student.store_novel_views=true",
        *TINY_SCENE_MODEL,
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    metrics = run(cfg, tmp_path)
    fitted = tmp_path / "scene_fit" / "checkpoints" / "last.ckpt"
    assert fitted.is_file()
    assert not (tmp_path / "scene_model" / "checkpoints").exists()
    assert metrics["bench/teacher/novel_views_render_s"] > 0
    train_rows = len(_data(tiny_root).datasets["train"])  # views: 1.0, one per train image
    assert metrics["bench/student/novel_view_rows"] == train_rows
    assert "test/scene_model/psnr_db" in metrics and "bench/scene_fit/fit_s" in metrics
    for method in ("teacher", "student", "render_compare"):
        assert metrics[f"test/{method}/pos_median_m"] >= 0, method
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["test/render_compare/pos_median_m"] == metrics["test/render_compare/pos_median_m"]
