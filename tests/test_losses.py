import math

import pytest
import torch

from pae.core.losses import LearnedPoseLoss, latent_distance


def test_learned_pose_loss_hand_computed() -> None:
    loss = LearnedPoseLoss(s_x=-3.0, s_q=-6.5)
    target = torch.tensor([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
    pred = torch.tensor([[3.0, 4.0, 0.0, 2.0, 0.0, 0.0, 0.0]])  # |Δx| = 5, q normalises to target
    terms = loss(pred, target)
    assert terms.position.item() == pytest.approx(5.0)
    assert terms.orientation.item() == pytest.approx(0.0, abs=1e-7)
    assert terms.total.item() == pytest.approx(5.0 * math.exp(3.0) - 3.0 - 6.5, rel=1e-6)


def test_learned_pose_loss_orientation_term() -> None:
    loss = LearnedPoseLoss(s_x=0.0, s_q=0.0)
    target = torch.tensor([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
    pred = torch.tensor([[0.0, 0.0, 0.0, 0.0, 5.0, 0.0, 0.0]])  # unit (0,1,0,0): distance √2
    assert loss(pred, target).total.item() == pytest.approx(math.sqrt(2), rel=1e-6)


def test_learned_weights_receive_gradient_unless_fixed() -> None:
    target = torch.zeros(2, 7)
    target[:, 3] = 1
    pred = torch.randn(2, 7)
    learned = LearnedPoseLoss()
    learned(pred, target).total.backward()
    assert learned.s_x.grad is not None and learned.s_x.grad != 0
    fixed = LearnedPoseLoss(learnable=False)
    assert not fixed.s_x.requires_grad and not fixed.s_q.requires_grad


def test_latent_distance_kinds() -> None:
    a, b = torch.zeros(2, 4), torch.tensor([[3.0, 4.0, 0, 0], [0, 0, 0, 0]])
    assert latent_distance(a, b, "l2").item() == pytest.approx(2.5)
    assert latent_distance(a, b, "mse").item() == pytest.approx(25 / 8)
    with pytest.raises(ValueError, match="unknown latent loss"):
        latent_distance(a, b, "cosine")
