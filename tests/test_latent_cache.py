"""The on-disk teacher-latent cache: reused, rebuilt when corrupt or stale, built once."""

import threading
import time
from pathlib import Path

import pytest
import torch

from pae.models.latents import LatentCache, TeacherLatents, latent_cache_key

KEY = {"format": 1, "teacher_sha256": "abc", "crop": 28}


class _Compute:
    """A teacher pass that counts its calls."""

    def __init__(self, rows: int = 6, delay_s: float = 0.0) -> None:
        self.rows, self.delay_s, self.calls = rows, delay_s, 0

    def __call__(self) -> TeacherLatents:
        self.calls += 1
        time.sleep(self.delay_s)
        generator = torch.Generator().manual_seed(self.calls)
        return TeacherLatents(
            {
                "pose": torch.randn(self.rows, 7, generator=generator),
                "scene": torch.zeros(self.rows, dtype=torch.long),
                "z_x": torch.randn(self.rows, 4, generator=generator),
                "z_q": torch.randn(self.rows, 4, generator=generator),
                "teacher_pose": torch.randn(self.rows, 7, generator=generator),
            }
        )


def test_second_read_comes_from_disk(tmp_path: Path) -> None:
    cache, compute = LatentCache(tmp_path), _Compute()
    first, hit = cache.load_or_compute(KEY, 6, compute)
    assert not hit and compute.calls == 1
    again, hit = cache.load_or_compute(KEY, 6, compute)
    assert hit and compute.calls == 1
    for name, value in first.tensors.items():
        assert torch.equal(again.tensors[name], value), name
    assert [p.suffix for p in sorted(tmp_path.iterdir())] == [".lock", ".pt"]


@pytest.mark.parametrize("damage", ["truncated", "garbage", "tampered", "other_key", "rows"])
def test_corrupt_or_stale_files_are_rebuilt(tmp_path: Path, damage: str) -> None:
    cache, compute = LatentCache(tmp_path), _Compute()
    cache.load_or_compute(KEY, 6, compute)
    path = cache.path(KEY)
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[:100])
    elif damage == "garbage":
        path.write_bytes(b"not a checkpoint")
    else:
        payload = torch.load(path, weights_only=True)
        if damage == "tampered":
            payload["tensors"]["z_x"][0, 0] += 1.0
        elif damage == "other_key":
            payload["key"] = {**KEY, "teacher_sha256": "def"}
        torch.save(payload, path)
    rows = 5 if damage == "rows" else 6
    _, hit = cache.load_or_compute(KEY, rows, _Compute(rows))
    assert not hit
    _, hit = cache.load_or_compute(KEY, rows, compute)
    assert hit  # the rebuilt file is whole and trusted again


def test_concurrent_jobs_compute_once(tmp_path: Path) -> None:
    compute = _Compute(delay_s=0.3)
    hits: list[bool] = []

    def job() -> None:
        hits.append(LatentCache(tmp_path).load_or_compute(KEY, 6, compute)[1])

    threads = [threading.Thread(target=job) for _ in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert compute.calls == 1 and sorted(hits) == [False, True, True]


def test_key_follows_teacher_bytes_and_preprocessing(tiny_root: Path, tmp_path: Path) -> None:
    from pae.data.datamodule import PoseDataModule

    def data(crop: int) -> PoseDataModule:
        module = PoseDataModule(
            root=str(tiny_root),
            train_labels=str(tiny_root / "labels" / "all_train.csv"),
            test_labels=str(tiny_root / "labels" / "all_test.csv"),
            shorter_edge=32,
            crop=crop,
        )
        module.setup()
        return module

    teacher = tmp_path / "teacher.ckpt"
    teacher.write_bytes(b"weights one")
    key = latent_cache_key(teacher, data(28))
    assert latent_cache_key(teacher, data(28)) == key
    assert latent_cache_key(teacher, data(24)) != key
    teacher.write_bytes(b"weights two")
    assert latent_cache_key(teacher, data(28))["teacher_sha256"] != key["teacher_sha256"]


def test_unwritable_cache_folder_is_refused_before_the_run(tmp_path: Path) -> None:
    from omegaconf import OmegaConf

    from pae.config.preflight import _check_latent_cache
    from pae.core.errors import ConfigError

    blocker = tmp_path / "file"
    blocker.write_text("")
    config = OmegaConf.create({"student": {"latent_cache_dir": str(blocker / "cache")}})
    with pytest.raises(ConfigError, match=r"student\.latent_cache_dir"):
        _check_latent_cache(config)
    _check_latent_cache(OmegaConf.create({"student": {"latent_cache_dir": None}}))


def test_a_cache_hit_reads_no_train_image_and_runs_no_teacher(
    tiny_root: Path, tmp_path: Path
) -> None:
    from pae.data.datamodule import PoseDataModule
    from pae.models.backbones import Backbone
    from pae.models.latents import TeacherLatentDataModule
    from pae.models.posenet import PoseNet

    teacher = PoseNet(Backbone("small_cnn", pool="flatten", spatial=2), latent_dim=16).eval()
    checkpoint = tmp_path / "teacher.ckpt"
    torch.save(teacher.state_dict(), checkpoint)
    passes: list[int] = []
    teacher.register_forward_pre_hook(lambda module, args: passes.append(len(args[0])))

    def job() -> tuple[TeacherLatentDataModule, PoseDataModule]:
        images = PoseDataModule(
            root=str(tiny_root),
            train_labels=str(tiny_root / "labels" / "all_train.csv"),
            test_labels=str(tiny_root / "labels" / "all_test.csv"),
            shorter_edge=32,
            crop=28,
            cache_images=True,
        )
        latents = TeacherLatentDataModule(
            images, teacher, cache=LatentCache(tmp_path / "cache"), teacher_ckpt=checkpoint
        )
        latents.setup("fit")
        return latents, images

    first, images = job()
    assert first.cache_hit is False and sum(passes) == 40  # the train rows left after seq-06
    assert images.datasets["train"]._cached is not None
    passes.clear()
    second, images = job()
    assert second.cache_hit is True and passes == []
    assert images.datasets["train"]._cached is None  # never decoded
    assert images.datasets["test"]._cached is not None  # read at setup, before training
    assert torch.equal(second.latents.tensors["z_x"], first.latents.tensors["z_x"])
