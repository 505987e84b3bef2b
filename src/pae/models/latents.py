"""Teacher outputs for the PAE's training images, computed once so PAE epochs cost MLP time only.

With a cache folder they are computed once per (teacher checkpoint, training images,
pre-processing) and shared on disk by every job of a sweep: written atomically, built by one
job at a time (a file lock), and checked on every read (key and checksum): a corrupt or stale
file is rebuilt, never used.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Iterable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import lightning as L
import torch
from filelock import FileLock, Timeout
from lightning.pytorch.utilities import rank_zero_info
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from pae.core.atomic import atomic_write
from pae.data.datamodule import PoseDataModule
from pae.data.dataset import collate_batch
from pae.data.order import EpochOrder, trainer_epoch
from pae.models.base import PoseRegressor


class TeacherLatents(Dataset):
    """Per train row: pose [7], scene, teacher latents z_x, z_q [d], teacher estimate [7]."""

    def __init__(self, tensors: dict[str, Tensor]) -> None:
        self.tensors = tensors

    def __len__(self) -> int:
        return len(self.tensors["pose"])

    def __getitem__(self, index: int) -> dict[str, Tensor]:
        return {key: value[index] for key, value in self.tensors.items()}

    def __getitems__(self, indices: list[int]) -> dict[str, Tensor]:
        idx = torch.as_tensor(indices, dtype=torch.long)
        return {key: value[idx] for key, value in self.tensors.items()}


@torch.no_grad()
def teacher_latents_of(
    teacher: PoseRegressor,
    images: PoseDataModule,
    batches: Iterable[dict[str, Tensor]],
    device: torch.device | str = "cpu",
) -> TeacherLatents:
    """Run the frozen teacher over ``batches`` (uint8 ``image`` [B, 3, H, W], ``pose`` [B, 7],
    ``scene`` [B]) with ``images``' test pre-processing; a multi-scene teacher gives the
    latents of each image's true scene."""
    teacher = teacher.to(device).eval()
    parts: dict[str, list[Tensor]] = {k: [] for k in LATENT_KEYS}
    for batch in batches:
        pixels = images.preprocess(batch["image"].to(device), train=False)
        pose, latents = teacher(pixels, batch["scene"].to(device))
        parts["pose"].append(batch["pose"])
        parts["scene"].append(batch["scene"])
        parts["z_x"].append(latents.x.cpu())
        parts["z_q"].append(latents.q.cpu())
        parts["teacher_pose"].append(pose.cpu())
    return TeacherLatents({k: torch.cat(v) for k, v in parts.items()})


def compute_teacher_latents(
    teacher: PoseRegressor, images: PoseDataModule, device: torch.device | str = "cpu"
) -> TeacherLatents:
    """The teacher's latents of the train split (``teacher_latents_of``)."""
    return teacher_latents_of(teacher, images, images.train_eval_dataloader(), device)


def view_batches(views: dict[str, Tensor], size: int) -> Iterator[dict[str, Tensor]]:
    """Rendered views (``image`` [M, 3, H, W], ``pose`` [M, 7], ``scene`` [M]) in batches of
    ``size``."""
    for rows in torch.arange(len(views["pose"])).split(size):
        yield {key: views[key][rows] for key in ("image", "pose", "scene")}


LATENT_KEYS = ("pose", "scene", "z_x", "z_q", "teacher_pose")
CACHE_FORMAT = 1


def _sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _tensors_sha256(tensors: dict[str, Tensor]) -> str:
    digest = hashlib.sha256()
    for key in LATENT_KEYS:
        digest.update(key.encode())
        digest.update(tensors[key].contiguous().numpy().tobytes())
    return digest.hexdigest()


def latent_cache_key(teacher_ckpt: str | Path, images: PoseDataModule) -> dict[str, Any]:
    """What the cached latents depend on: the teacher checkpoint's bytes, the training data
    (scenes, train poses, each image's path, size and modification time) and the
    pre-processing (shorter edge, crop). JSON-able; its SHA-256 names the cache file."""
    table = images.tables["train"]
    files = hashlib.sha256()
    for relative in table.img_path:
        stat = (images.root / relative).stat()
        files.update(f"{relative}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return {
        "format": CACHE_FORMAT,
        "teacher_sha256": _sha256_file(Path(teacher_ckpt)),
        "data": images.fingerprint(),
        "root": str(images.root.resolve()),
        "images_sha256": files.hexdigest(),
        "shorter_edge": images.shorter_edge,
        "crop": images.eval_transform.crop,
    }


def _lock(path: Path) -> FileLock:
    """An exclusive OS lock on `path` (``filelock``; the file kept after release)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    return FileLock(path, thread_local=False, preserve_lock_file=True)


def _held_by_another(path: Path) -> bool:
    """Whether another process (or another lock object of this one) holds the lock on `path`."""
    if not path.is_file():
        return False
    lock = _lock(path)
    try:
        lock.acquire(timeout=0)
    except Timeout:
        return True
    lock.release()
    return False


class LatentCache:
    """Teacher latents on disk in `folder`, one file per key: `<sha256 of the key>.pt`."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    def path(self, key: dict[str, Any]) -> Path:
        name = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:32]
        return self.folder / f"{name}.pt"

    def _remove_dead_writes(self, own: Path) -> None:
        """Delete the temporary files that writers killed mid-write left (atomic_write's
        `.<name>.pt.*.tmp`). A writer holds its file's lock while it writes, so a temporary
        whose lock nobody holds is dead; `own` is the file whose lock this process holds."""
        for temporary in self.folder.glob(".*.pt.*.tmp"):
            name = temporary.name[1:].split(".pt.", 1)[0]
            if name == own.stem or not _held_by_another(self.folder / f"{name}.lock"):
                temporary.unlink(missing_ok=True)

    def _read(self, path: Path, key: dict[str, Any], rows: int) -> TeacherLatents | None:
        """The cached latents, or None (with the reason said once) when the file is missing,
        unreadable, for another key, of another length, or fails its checksum."""
        if not path.is_file():
            return None
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
            tensors = {name: payload["tensors"][name] for name in LATENT_KEYS}
            problem = None
            if payload["key"] != key:
                problem = "made for other settings"
            elif any(len(t) != rows for t in tensors.values()):
                problem = f"holds other than {rows} rows"
            elif payload["sha256"] != _tensors_sha256(tensors):
                problem = "fails its checksum"
        except Exception as err:  # any unreadable file is rebuilt
            problem = f"unreadable ({type(err).__name__})"
        if problem is not None:
            rank_zero_info(f"teacher latent cache {path}: {problem}; rebuilding it")
            return None
        return TeacherLatents(tensors)

    def load_or_compute(
        self, key: dict[str, Any], rows: int, compute: Callable[[], TeacherLatents]
    ) -> tuple[TeacherLatents, bool]:
        """(latents, whether they came from the cache). One job computes and writes while the
        others wait on the lock, then read its file."""
        path = self.path(key)
        with _lock(path.with_suffix(".lock")):
            self._remove_dead_writes(path)
            cached = self._read(path, key, rows)
            if cached is not None:
                return cached, True
            latents = compute()
            tensors = {name: latents.tensors[name].contiguous() for name in LATENT_KEYS}
            payload = {"key": key, "tensors": tensors, "sha256": _tensors_sha256(tensors)}
            with atomic_write(path, "wb") as handle:
                torch.save(payload, handle)
            rank_zero_info(f"teacher latents cached in {path} (pid {os.getpid()})")
            return latents, False


class TeacherLatentDataModule(L.LightningDataModule):
    """Training batches of cached teacher latents; validation and test batches are the
    wrapped PoseDataModule's images (the teacher still runs on queries). With `cache` and
    `teacher_ckpt` the latents come from (or go to) that on-disk cache; `cache_hit` says
    which. `views` is called once the train split is read and gives rendered views
    (``pose`` [M, 7], ``scene`` [M], and with `train_on_views` ``image`` uint8
    [M, 3, H, W]): with `train_on_views` the teacher's latents of those views join the train
    rows (computed every run, never cached), with `store_views` their poses join the
    retrieval store (`store_poses`)."""

    def __init__(
        self,
        images: PoseDataModule,
        teacher: PoseRegressor,
        batch_size: int | None = None,
        cache: LatentCache | None = None,
        teacher_ckpt: str | Path | None = None,
        views: Callable[[], dict[str, Tensor]] | None = None,
        train_on_views: bool = False,
        store_views: bool = False,
    ) -> None:
        super().__init__()
        if (train_on_views or store_views) and views is None:
            raise ValueError("train_on_views and store_views need the views")
        if cache is not None and teacher_ckpt is None:
            raise ValueError("a latent cache needs the teacher checkpoint it keys on")
        self.images = images
        self.teacher = teacher
        self.batch_size = batch_size or images.batch_size
        self.cache = cache
        self.teacher_ckpt = teacher_ckpt
        self.views = views
        self.train_on_views = train_on_views
        self.store_views = store_views
        self.latents: TeacherLatents | None = None
        self.view_rows = 0
        self._view_store: tuple[Tensor, Tensor] | None = None
        self.cache_hit: bool | None = None

    def setup(self, stage: str | None = None) -> None:
        self.images.setup(stage)
        if self.latents is None and stage in (None, "fit"):
            device = self.trainer.strategy.root_device if self.trainer is not None else "cpu"

            def compute() -> TeacherLatents:
                return compute_teacher_latents(self.teacher, self.images, device)

            if self.cache is None:
                self.latents = compute()
            else:
                key = latent_cache_key(self.teacher_ckpt, self.images)
                rows = len(self.images.tables["train"])
                self.latents, self.cache_hit = self.cache.load_or_compute(key, rows, compute)
            if self.train_on_views or self.store_views:
                views = self.views()
                if self.store_views:
                    self._view_store = (views["pose"], views["scene"])
                if self.train_on_views:
                    batches = view_batches(views, self.images.eval_batch_size)
                    extra = teacher_latents_of(self.teacher, self.images, batches, device)
                    self.view_rows = len(extra)
                    tensors = self.latents.tensors
                    self.latents = TeacherLatents(
                        {k: torch.cat([tensors[k], extra.tensors[k]]) for k in LATENT_KEYS}
                    )

    def scenes_without_rows(self, split: str) -> list[str]:
        return self.images.scenes_without_rows(split)

    def train_poses(self) -> tuple[Tensor, Tensor]:
        return self.images.train_poses()

    def store_poses(self) -> tuple[Tensor, Tensor]:
        """The train poses [N, 7] and scene ids [N], with `store_views` followed by the
        rendered views' (their poses sampled from the train split alone)."""
        poses, scenes = self.images.train_poses()
        if self._view_store is None:
            return poses, scenes
        view_poses, view_scenes = self._view_store
        return (
            torch.cat([poses, view_poses.to(poses.dtype)]),
            torch.cat([scenes, view_scenes.to(scenes.dtype)]),
        )

    def fingerprint(self) -> dict[str, Any]:
        return self.images.fingerprint()

    def sampled_images_sha256(self) -> str:
        return self.images.sampled_images_sha256()

    @property
    def root(self) -> Path:
        return self.images.root

    def train_dataloader(self) -> DataLoader:
        assert self.latents is not None
        order = EpochOrder(len(self.latents), self.images.order_seed, partial(trainer_epoch, self))
        return DataLoader(
            self.latents,
            batch_size=self.batch_size,
            sampler=order,
            drop_last=True,
            collate_fn=collate_batch,
            generator=torch.Generator(),
        )

    def val_dataloader(self) -> DataLoader:
        return self.images.val_dataloader()

    def test_dataloader(self) -> DataLoader:
        return self.images.test_dataloader()

    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        if isinstance(batch, dict) and batch.get("image") is not None:
            batch = {**batch, "image": self.images.preprocess(batch["image"], train=False)}
        return batch
