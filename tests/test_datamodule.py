from pathlib import Path

import numpy as np
import pytest
import torch

from pae.data.datamodule import PoseDataModule
from pae.data.labels import LabelError, read_labels, write_labels
from pae.models.backbones import Backbone
from pae.models.latents import TeacherLatentDataModule
from pae.models.posenet import PoseNet


def _data(root: Path, **kwargs) -> PoseDataModule:
    data = PoseDataModule(
        root=str(root),
        train_labels=str(root / "labels" / "all_train.csv"),
        test_labels=str(root / "labels" / "all_test.csv"),
        shorter_edge=32,
        crop=28,
        batch_size=8,
        **kwargs,
    )
    data.setup()
    return data


def test_splits_scene_ids_and_train_poses(tiny_root: Path) -> None:
    data = _data(tiny_root)
    assert data.scene_names == ["scene00", "scene01"]
    poses, scenes = data.train_poses()
    table = read_labels(tiny_root / "labels" / "all_train.csv")
    held_out = np.asarray(table.seq) == "seq-06"
    assert torch.allclose(poses, torch.as_tensor(table.poses[~held_out], dtype=torch.float32))
    assert torch.equal(scenes.bincount(), torch.tensor([20, 20]))
    assert data.tables["val"].seq == ["seq-06"] * 8 and len(data.datasets["test"]) == 24


def test_val_sequences_null_validates_on_test_with_a_warning(
    tiny_root: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from pae.core.run_context import start_run

    start_run()
    data = _data(tiny_root, val_sequences=None)
    poses, _ = data.train_poses()
    assert len(poses) == 48 and data.datasets["val"] is data.datasets["test"]
    warning = capsys.readouterr().err.strip()
    assert "\n" not in warning and "validation reads the test split" in warning


def test_cached_and_uncached_batches_are_identical(tiny_root: Path) -> None:
    cached, plain = _data(tiny_root, cache_images=True), _data(tiny_root)
    a = cached.datasets["train"].__getitems__([0, 5, 30])
    b = plain.datasets["train"].__getitems__([0, 5, 30])
    assert a["image"].dtype == torch.uint8 and a["image"].shape == (3, 3, 32, 32)
    assert torch.equal(a["image"], b["image"]) and torch.equal(a["scene"], torch.tensor([0, 0, 1]))


def test_loaders_and_preprocessing(tiny_root: Path) -> None:
    data = _data(tiny_root, cache_images=True, balance_scenes=True)
    batch = next(iter(data.train_dataloader()))
    assert batch["image"].shape == (8, 3, 32, 32)
    assert data.preprocess(batch["image"], train=True).shape == (8, 3, 28, 28)
    eval_batch = data.on_after_batch_transfer(next(iter(data.test_dataloader())), 0)
    assert eval_batch["image"].dtype == torch.float32 and eval_batch["image"].shape[-1] == 28


def test_balanced_sampling_equalises_scenes(tiny_root: Path, tmp_path: Path) -> None:
    table = read_labels(tiny_root / "labels" / "all_train.csv")
    keep = [i for i, s in enumerate(table.scene) if s == "scene00" or i % 6 == 0]
    write_labels(tmp_path / "labels" / "all_train.csv", table.select(keep))
    write_labels(
        tmp_path / "labels" / "all_test.csv", read_labels(tiny_root / "labels" / "all_test.csv")
    )
    for scene in ("scene00", "scene01"):
        (tmp_path / scene).symlink_to(tiny_root / scene)
    data = _data(tmp_path, balance_scenes=True)
    torch.manual_seed(0)
    counts = torch.zeros(2)
    for _ in range(20):
        for batch in data.train_dataloader():
            counts += batch["scene"].bincount(minlength=2)
    assert abs(counts[0] / counts.sum() - 0.5) < 0.05


def test_test_scene_missing_from_train_is_an_error(tiny_root: Path, tmp_path: Path) -> None:
    train = read_labels(tiny_root / "labels" / "scene00_train.csv")
    write_labels(tmp_path / "labels" / "all_train.csv", train)
    write_labels(
        tmp_path / "labels" / "all_test.csv", read_labels(tiny_root / "labels" / "all_test.csv")
    )
    with pytest.raises(LabelError, match=r"scene01.*do not occur in the train labels"):
        _data(tmp_path)


def test_teacher_latents_are_cached_once_in_train_order(tiny_root: Path) -> None:
    data = _data(tiny_root, cache_images=True)
    teacher = PoseNet(Backbone("small_cnn", pool="flatten", spatial=2), latent_dim=16).eval()
    cached = TeacherLatentDataModule(data, teacher)
    cached.setup("fit")
    latents = cached.latents
    assert latents is not None and len(latents) == 40  # the held-out seq-06 rows excluded
    images = data.preprocess(data.datasets["train"].images[:4], train=False)
    with torch.no_grad():
        pose, z = teacher(images)
    assert torch.allclose(latents.tensors["z_x"][:4], z.x, atol=1e-5)
    assert torch.allclose(latents.tensors["teacher_pose"][:4], pose, atol=1e-5)
    batch = next(iter(cached.train_dataloader()))
    assert set(batch) == {"pose", "scene", "z_x", "z_q", "teacher_pose"} and len(batch["pose"]) == 8


def test_the_image_fingerprint_sees_an_edit_the_sampled_hash_missed(
    tiny_root: Path, tmp_path: Path
) -> None:
    """An edit that keeps an image's size and lies outside the middle 4 KiB the older hash
    read changes the fingerprint of every byte."""
    import shutil

    from pae.data.fingerprint import SAMPLE_BYTES, images_blake2b, sampled_images_sha256

    root = tmp_path / "copy"
    shutil.copytree(tiny_root, root)
    table = read_labels(root / "labels" / "all_train.csv")
    image = root / table.img_path[3]
    image.write_bytes(bytes(range(256)) * 48)  # 12 KiB: larger than the sample
    before = images_blake2b(table, root), sampled_images_sha256(table, root)
    edited = bytearray(image.read_bytes())
    assert len(edited) // 2 - SAMPLE_BYTES // 2 > 100
    edited[100] ^= 0xFF
    image.write_bytes(bytes(edited))
    assert sampled_images_sha256(table, root) == before[1]
    assert images_blake2b(table, root) != before[0]


def test_a_checkpoint_with_the_sampled_fingerprint_is_checked_by_it_with_a_warning(
    tiny_root: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from omegaconf import OmegaConf

    from pae.core.errors import CheckpointError
    from pae.core.run_context import start_run
    from pae.runs.inputs import check_fingerprint

    data = _data(tiny_root)
    older = data.fingerprint()
    del older["train_images_blake2b"]
    older["train_images_sha256"] = data.sampled_images_sha256()
    cfg = OmegaConf.create({})
    start_run()
    with caplog.at_level("INFO"):
        check_fingerprint(cfg, "old.ckpt", older, data)
        check_fingerprint(cfg, "old.ckpt", older, data)
    warnings = [m for m in caplog.messages if m.startswith("data: warning: old.ckpt")]
    assert warnings == [
        "data: warning: old.ckpt records an older fingerprint of its train images (4 KiB of each "
        "file): its images are checked by that sample only, an edit elsewhere is not seen"
    ]
    older["train_images_sha256"] = "0" * 64
    with pytest.raises(CheckpointError, match=r"^old\.ckpt: trained on other train images than"):
        check_fingerprint(cfg, "old.ckpt", older, data)
