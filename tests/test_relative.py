"""Relative regressors that read the query image: the image RPR, the iterative APR, their
training data (train poses and images only), the relative-pose convention, decoder PSNR."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
import torch
from torch import Tensor

from pae.core.geometry import (
    canonicalize_quaternion,
    compose_pose,
    orientation_error_deg,
    position_error,
    relative_pose,
)
from pae.core.losses import LearnedPoseLoss
from pae.core.pose_sampling import perturb_poses
from pae.data.datamodule import PoseDataModule
from pae.lit.decoder import mean_train_image, psnr_db
from pae.lit.iapr import IAPRModule
from pae.lit.rpr_image import ImageRPRModule
from pae.models.backbones import Backbone
from pae.models.base import TeacherEstimate
from pae.models.iapr import IterativeAPR
from pae.models.pae import PoseAutoEncoder
from pae.models.posenet import PoseNet
from pae.models.rpr import SiameseRPR
from pae.relative.refiners import ImageRPR, IterativeAPRRefiner


def random_poses(n: int, generator: torch.Generator) -> Tensor:
    position = 5 * torch.randn(n, 3, generator=generator)
    q = canonicalize_quaternion(torch.randn(n, 4, generator=generator))
    return torch.cat([position, q], dim=-1)


class Forbidden:
    """Stands in for the test (and val) split: any read fails the test."""

    def __getattr__(self, name: str) -> None:
        raise AssertionError(f"the test split was read ({name})")

    def __len__(self) -> int:
        raise AssertionError("the test split was read (len)")


class RecordingReads:
    """Wraps the train dataset and records the rows read through it."""

    def __init__(self, dataset) -> None:
        self.dataset = dataset
        self.poses, self.scenes = dataset.poses, dataset.scenes
        self.rows: list[int] = []

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitems__(self, rows: list[int]) -> dict[str, Tensor]:
        self.rows += list(rows)
        return self.dataset.__getitems__(rows)


@pytest.fixture
def tiny_data(tiny_root: Path) -> PoseDataModule:
    data = PoseDataModule(
        root=str(tiny_root),
        train_labels=str(tiny_root / "labels" / "all_train.csv"),
        test_labels=str(tiny_root / "labels" / "all_test.csv"),
        shorter_edge=32,
        crop=28,
        batch_size=8,
        cache_images=True,
    )
    data.setup()
    return data


def train_batch(data: PoseDataModule) -> dict[str, Tensor]:
    batch = next(iter(data.train_dataloader()))
    return {**batch, "image": data.preprocess(batch["image"], train=True)}


def hide_test_split(data: PoseDataModule) -> tuple[Tensor, RecordingReads]:
    """Test poses (for comparisons), then the test split replaced by Forbidden and the train
    dataset by a recorder of the rows read."""
    test_poses = data.datasets["test"].poses.clone()
    recorder = RecordingReads(data.datasets["train"])
    data.datasets = {"train": recorder, "val": Forbidden(), "test": Forbidden()}
    return test_poses, recorder


def small_backbone() -> Backbone:
    return Backbone("small_cnn", pool="flatten", spatial=2)


def test_relative_convention_round_trips() -> None:
    generator = torch.Generator().manual_seed(0)
    query, reference = random_poses(64, generator), random_poses(64, generator)
    moved = compose_pose(reference, relative_pose(reference, query))
    assert torch.allclose(moved[:, :3], query[:, :3], atol=1e-5)
    assert orientation_error_deg(moved[:, 3:], query[:, 3:]).max() < 1e-2
    # the stored-quaternion convention holds for the result
    assert (moved[:, 3] >= 0).all()


class ExactRPR(torch.nn.Module):
    """An RPR that regresses given relative poses, whatever the images."""

    def __init__(self, relative: Tensor) -> None:
        super().__init__()
        self.relative = relative

    def forward(self, query: Tensor, reference: Tensor) -> Tensor:
        return self.relative


def image_rpr_module(data: PoseDataModule, **options: Any) -> ImageRPRModule:
    """An image RPR step with small untrained networks for ``data``'s scenes."""
    return ImageRPRModule(
        SiameseRPR(small_backbone(), latent_dim=16),
        PoseNet(small_backbone(), latent_dim=16, n_scenes=2),
        LearnedPoseLoss(),
        torch.optim.Adam,
        data.scene_names,
        configs={},
        **options,
    )


def test_image_rpr_refines_exactly_with_an_exact_relative_pose(tiny_data: PoseDataModule) -> None:
    module = image_rpr_module(tiny_data)
    module.use_data(tiny_data)
    truth = tiny_data.datasets["test"].poses[:6]
    scene = tiny_data.datasets["test"].scenes[:6]
    images = tiny_data.preprocess(
        tiny_data.datasets["test"].__getitems__(list(range(6)))["image"], False
    )
    estimate = torch.cat([truth[:, :3] + 0.3, truth[:, 3:]], dim=-1)
    rows = module.index.query(estimate, scene, 1)[0][:, 0]
    exact = relative_pose(module.index.poses[rows], truth)
    module.method = ImageRPR(ExactRPR(exact), module.index, module.images)
    refined, reference = module.method(images, TeacherEstimate(estimate, estimate, None, scene))
    assert torch.equal(reference, module.index.poses[rows])
    assert position_error(refined[:, :3], truth[:, :3]).max() < 1e-5
    assert torch.equal(refined[:, 3:], estimate[:, 3:])  # position only: orientation kept


def test_image_rpr_training_pairs_use_train_poses_and_images_only(
    tiny_data: PoseDataModule,
) -> None:
    module = image_rpr_module(tiny_data, pair_k=3)
    train_poses = tiny_data.datasets["train"].poses.clone()
    batch = train_batch(tiny_data)
    test_poses, recorder = hide_test_split(tiny_data)
    module.use_data(tiny_data)
    for _ in range(5):
        rows, reference = module.training_pairs(batch)
        assert not (rows == batch["index"]).any()  # never the query itself
        assert torch.equal(reference, module.index.poses[rows])
        assert torch.allclose(reference[:, :3], train_poses[rows, :3])
        assert (torch.cdist(reference[:, :3], test_poses[:, :3]) > 1e-6).all()
        same_scene = module.index.scenes[rows] == batch["scene"]
        assert same_scene.all()
    recorder.rows.clear()
    loss = module.training_step(batch, 0)
    assert torch.isfinite(loss)
    assert recorder.rows and max(recorder.rows) < len(train_poses)


def test_iapr_starting_poses_lie_around_the_train_poses(tiny_data: PoseDataModule) -> None:
    pae = PoseAutoEncoder(latent_dim=16, n_scenes=2)
    module = IAPRModule(
        IterativeAPR(small_backbone(), latent_dim=16, hidden=32),
        PoseNet(small_backbone(), latent_dim=16, n_scenes=2),
        pae,
        LearnedPoseLoss(),
        torch.optim.Adam,
        tiny_data.scene_names,
        configs={},
        position_m=0.4,
        orientation_deg=6.0,
        iterations=2,
    )
    batch = train_batch(tiny_data)
    hide_test_split(tiny_data)
    start = module.starting_poses(batch)
    distance = position_error(start[:, :3], batch["pose"][:, :3])
    angle = orientation_error_deg(start[:, 3:], batch["pose"][:, 3:])
    assert (distance <= 0.8 + 1e-5).all() and (angle <= 12.0 + 1e-3).all()
    assert (distance > 0).all()
    assert torch.isfinite(module.training_step(batch, 0))


def test_perturbed_poses_have_the_configured_medians() -> None:
    generator = torch.Generator().manual_seed(0)
    poses = random_poses(4000, generator)
    start = perturb_poses(poses, 0.5, 8.0, generator)
    distance = position_error(start[:, :3], poses[:, :3])
    angle = orientation_error_deg(start[:, 3:], poses[:, 3:])
    assert distance.median().item() == pytest.approx(0.5, rel=0.05)
    assert angle.median().item() == pytest.approx(8.0, rel=0.05)
    assert distance.max() <= 1.0 + 1e-5 and angle.max() <= 16.0 + 1e-2


def test_untrained_iapr_keeps_the_estimate_and_can_keep_orientation() -> None:
    generator = torch.Generator().manual_seed(1)
    model = IterativeAPR(small_backbone(), latent_dim=16, hidden=32).eval()
    pae = PoseAutoEncoder(latent_dim=16)
    start = random_poses(4, generator)
    images = torch.randn(4, 3, 28, 28, generator=generator)
    scene = torch.zeros(4, dtype=torch.long)
    steps = IterativeAPRRefiner(model, pae, 3).iterates(images, start, scene)
    assert len(steps) == 3
    for pose in steps:  # identity correction at initialisation
        assert torch.allclose(pose, start, atol=1e-6)
    with torch.no_grad():
        model.head_x.bias.fill_(0.1)
        model.head_q.bias.copy_(torch.tensor([1.0, 0.2, 0.0, 0.0]))
    steps = IterativeAPRRefiner(model, pae, 2, refine_orientation=False).iterates(
        images, start, scene
    )
    assert torch.allclose(steps[1][:, :3], start[:, :3] + 0.2, atol=1e-5)
    assert torch.equal(steps[1][:, 3:], start[:, 3:])


class ConstantImages:
    """A train dataset stub: images of constant value `values[i]` (uint8)."""

    def __init__(self, values: list[int], size: int = 8) -> None:
        self.images = torch.stack(
            [torch.full((3, size, size), v, dtype=torch.uint8) for v in values]
        )

    def __len__(self) -> int:
        return len(self.images)

    def __getitems__(self, rows: list[int]) -> dict[str, Tensor]:
        return {"image": self.images[torch.as_tensor(rows)]}


class StubData:
    def __init__(self, values: list[int]) -> None:
        from pae.data.transforms import ImageTransform

        self.datasets = {"train": ConstantImages(values)}
        self.transform = ImageTransform(8)

    def preprocess(self, images: Tensor, train: bool) -> Tensor:
        return self.transform(images)


def test_psnr_baseline_is_the_mean_train_image() -> None:
    data = StubData([64, 192, 64, 192, 128])
    mean = mean_train_image(data, size=4, chunk=2)  # chunks: the mean over all rows
    assert mean.shape == (3, 4, 4)
    assert torch.allclose(mean, torch.full_like(mean, 128 / 255), atol=1e-5)
    targets = torch.zeros(2, 3, 4, 4)
    expected = -20 * math.log10(128 / 255)
    baseline = psnr_db(mean.expand_as(targets), targets)
    assert baseline == pytest.approx(torch.full((2,), expected), abs=1e-3)
    # an image off by 0.1 everywhere: 20 dB; a perfect one: capped at 100 dB
    assert psnr_db(targets + 0.1, targets) == pytest.approx(torch.full((2,), 20.0), abs=1e-3)
    assert psnr_db(targets, targets) == pytest.approx(torch.full((2,), 100.0))


def test_bench_reports_storage_and_time_per_method() -> None:
    from pae.bench.methods import bench_methods

    figures = bench_methods(scenes=1, train_frames=16, size=32, crop=28, queries=2)
    for method in ("teacher", "refined", "vrpr", "rpr_image", "iapr_3"):
        assert figures[f"bench/deploy/{method}/ms_per_query"] > 0
        parts = ("networks", "poses", "images")
        total = sum(figures[f"bench/deploy/{method}/{p}_bytes"] for p in parts)
        assert figures[f"bench/deploy/{method}/total_bytes"] == total
    assert figures["bench/deploy/rpr_image/images_bytes"] == 16 * 3 * 32 * 32
    for method in ("teacher", "iapr_3"):  # keep nothing but networks
        assert figures[f"bench/deploy/{method}/poses_bytes"] == 0
        assert figures[f"bench/deploy/{method}/images_bytes"] == 0
    assert figures["bench/deploy/vrpr/images_bytes"] == 0


def test_siamese_rpr_can_give_each_head_its_own_encoder() -> None:
    shared = SiameseRPR(small_backbone(), latent_dim=16)
    separate = SiameseRPR(small_backbone(), latent_dim=16, separate_encoders=True)
    assert shared.encoder_q is None and separate.encoder_q is not None
    extra = sum(p.numel() for p in separate.parameters()) - sum(
        p.numel() for p in shared.parameters()
    )
    assert extra == sum(p.numel() for p in separate.encoder_q.parameters())
    images = torch.randn(2, 3, 28, 28)
    with torch.no_grad():
        separate.encoder_q[0].weight.zero_()
        separate.encoder_q[0].bias.zero_()
        out = separate.eval()(images, images)
    # the rotation head sees only its own (zeroed) encoder: its bias alone
    assert torch.allclose(out[:, 3:], separate.head_q.bias.expand(2, 4))
