import pytest
import torch

from pae.core.losses import LearnedPoseLoss
from pae.lit.student import StudentModule
from pae.models.backbones import Backbone
from pae.models.pae import PoseAutoEncoder
from pae.models.posenet import PoseNet


def _student(latent_dim: int = 16, pae_dim: int = 16) -> StudentModule:
    teacher = PoseNet(Backbone("small_cnn", pool="flatten", spatial=2), latent_dim=latent_dim)
    pae = PoseAutoEncoder(latent_dim=pae_dim, hidden=(32,), L=2)
    return StudentModule(teacher, pae, LearnedPoseLoss(), torch.optim.Adam, ["scene"], {}, {})


def _batch(b: int = 4, d: int = 16) -> dict[str, torch.Tensor]:
    pose = torch.randn(b, 7)
    pose[:, 3:] = torch.nn.functional.normalize(pose[:, 3:], dim=-1)
    return {
        "pose": pose,
        "scene": torch.zeros(b, dtype=torch.long),
        "z_x": torch.randn(b, d),
        "z_q": torch.randn(b, d),
        "teacher_pose": torch.randn(b, 7),
    }


def test_pose_term_alone_trains_the_pae_through_frozen_heads() -> None:
    module = _student()
    module.train()
    assert not module.teacher.training, "the teacher stays in eval mode"
    terms = module.student_loss(_batch())
    terms["pose"].backward()  # the pose-loss term only
    pae_grads = [p.grad for p in module.pae.parameters()]
    assert all(g is not None for g in pae_grads)
    assert sum(g.abs().sum() for g in pae_grads) > 0
    assert all(p.grad is None for p in module.teacher.parameters())
    assert all(not p.requires_grad for p in module.teacher.parameters())


def test_student_runs_teacher_on_image_batches() -> None:
    module = _student()
    batch = {
        "image": torch.randn(3, 3, 32, 32),
        "pose": _batch(3)["pose"],
        "scene": torch.zeros(3, dtype=torch.long),
    }
    terms = module.student_loss(batch)
    assert torch.isfinite(terms["loss"]) and terms["latent_x"] > 0


def test_latent_size_mismatch_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="does not match the teacher's latent size 16"):
        _student(latent_dim=16, pae_dim=32)
