"""Teacher outputs for the PAE's training images, computed once so PAE epochs cost MLP time only."""

from __future__ import annotations

from typing import Any

import lightning as L
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from pae.data.datamodule import PoseDataModule
from pae.data.dataset import collate_batch
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
def compute_teacher_latents(
    teacher: PoseRegressor, images: PoseDataModule, device: torch.device | str = "cpu"
) -> TeacherLatents:
    """Run the frozen teacher once over the train split with the test pre-processing; a
    multi-scene teacher gives the latents of each image's true scene."""
    teacher = teacher.to(device).eval()
    parts: dict[str, list[Tensor]] = {
        k: [] for k in ("pose", "scene", "z_x", "z_q", "teacher_pose")
    }
    for batch in images.train_eval_dataloader():
        pixels = images.preprocess(batch["image"].to(device), train=False)
        pose, latents = teacher(pixels, batch["scene"].to(device))
        parts["pose"].append(batch["pose"])
        parts["scene"].append(batch["scene"])
        parts["z_x"].append(latents.x.cpu())
        parts["z_q"].append(latents.q.cpu())
        parts["teacher_pose"].append(pose.cpu())
    return TeacherLatents({k: torch.cat(v) for k, v in parts.items()})


class TeacherLatentDataModule(L.LightningDataModule):
    """Training batches of cached teacher latents; validation and test batches are the
    wrapped PoseDataModule's images (the teacher still runs on queries)."""

    def __init__(
        self, images: PoseDataModule, teacher: PoseRegressor, batch_size: int | None = None
    ) -> None:
        super().__init__()
        self.images = images
        self.teacher = teacher
        self.batch_size = batch_size or images.batch_size
        self.latents: TeacherLatents | None = None

    def setup(self, stage: str | None = None) -> None:
        self.images.setup(stage)
        if self.latents is None and stage in (None, "fit"):
            device = self.trainer.strategy.root_device if self.trainer is not None else "cpu"
            self.latents = compute_teacher_latents(self.teacher, self.images, device)

    def train_poses(self) -> tuple[Tensor, Tensor]:
        return self.images.train_poses()

    def train_dataloader(self) -> DataLoader:
        assert self.latents is not None
        return DataLoader(
            self.latents,
            batch_size=self.batch_size,
            shuffle=True,
            drop_last=True,
            collate_fn=collate_batch,
        )

    def val_dataloader(self) -> DataLoader:
        return self.images.val_dataloader()

    def test_dataloader(self) -> DataLoader:
        return self.images.test_dataloader()

    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        if isinstance(batch, dict) and batch.get("image") is not None:
            batch = {**batch, "image": self.images.preprocess(batch["image"], train=False)}
        return batch
