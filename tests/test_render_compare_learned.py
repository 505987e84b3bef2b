"""Render-and-compare against a voxel grid learned from the train images alone (not the
benchmark's own renderer): it must beat the estimate it starts from on unseen test views."""

from __future__ import annotations

import functools
from pathlib import Path

import lightning as L
import pytest
import torch
from omegaconf import OmegaConf

from pae import CONFIG_DIR
from pae.core.geometry import pose_errors
from pae.core.pose_sampling import perturb
from pae.data.transforms import ImageTransform
from pae.lit.scene_model import SceneModelModule
from pae.render_compare.refiner import RenderCompareRefiner
from pae.scene_model.base import SceneModelInputs
from pae.scene_model.rays import RayLoader
from pae.scene_model.voxel_grid import VoxelGridSceneModel
from pae.synthetic import write_synthetic_dataset
from pae.synthetic.datamodule import SyntheticDataModule

BENCHMARK = {"scenes": 1, "train_frames": 48, "test_frames": 12, "size": 32}
START_SIGMA = (0.2, 0.06)
"""Per-axis spread of the start's position (m) and rotation vector (rad, 3.4°): starts 0.27 m
off (median), the scale of a teacher's error (the demo's teacher: 0.42 m / 7°)."""
PINNED_RATIO = 0.6
"""The refined median position error must be below this share of the start's (measured:
0.48)."""


def _no_checkpoint(key: str) -> None:
    raise AssertionError(f"the voxel grid reads no checkpoint, asked for {key}")


@pytest.mark.filterwarnings("ignore")
def test_a_learned_grid_halves_the_start_error_on_unseen_views(tmp_path: Path) -> None:
    root = tmp_path / "data"
    write_synthetic_dataset(root, seed=0, **BENCHMARK)
    size = BENCHMARK["size"]
    data = SyntheticDataModule(
        root=str(root), **BENCHMARK, crop=size, shorter_edge=size, cache_images=True
    )
    data.setup()
    conf = Path(CONFIG_DIR)
    grid = OmegaConf.to_container(OmegaConf.load(conf / "scene_model" / "voxel_grid.yaml").model)
    grid.pop("_target_")
    grid |= {"num_voxels": 30_000, "samples_per_ray": 24}
    model, _ = VoxelGridSceneModel.build(grid, SceneModelInputs(data, "sequence", _no_checkpoint))
    module = SceneModelModule(
        model,
        torch.nn.Linear(1, 1),  # no teacher: the start is the truth moved by START_SIGMA
        functools.partial(torch.optim.Adam, lr=0.1, betas=(0.9, 0.99)),
        data.scene_names,
        {},
    )
    L.seed_everything(0)
    trainer = L.Trainer(
        max_epochs=3,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
    )
    data.train_batches = RayLoader(rays_per_batch=2048, batches=40)
    trainer.fit(module, datamodule=data)
    assert len(trainer.train_dataloader.dataset.images) == 0  # released when the fit ended

    test = data.datasets["test"]
    batch = test.__getitems__(list(range(len(test))))
    images = ImageTransform.unnormalize_batch(data.preprocess(batch["image"], train=False))
    truth = test.poses
    generator = torch.Generator().manual_seed(0)
    steps = torch.cat([s * torch.randn(len(truth), 3, generator=generator) for s in START_SIGMA], 1)
    start = perturb(truth, steps)
    refiner = RenderCompareRefiner.configured(model.eval())  # the shipped defaults
    result = refiner(images, data.intrinsics("test"), start, test.scenes)
    before, _ = pose_errors(start, truth)
    after, _ = pose_errors(result.poses, truth)
    assert after.median() < PINNED_RATIO * before.median()
    assert (after < before).float().mean() >= 2 / 3
