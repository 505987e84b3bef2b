import math
from pathlib import Path

import pytest
import torch

from pae.models.backbones import Backbone, BackboneError
from pae.models.pae import FourierFeatures, PoseAutoEncoder
from pae.models.posenet import PoseNet


@pytest.mark.parametrize(
    ("L", "include_input", "expected"), [(0, True, 3), (3, True, 21), (6, True, 39), (6, False, 36)]
)
def test_fourier_feature_dimensions(L: int, include_input: bool, expected: int) -> None:
    features = FourierFeatures(L, include_input)
    out = features(torch.randn(5, 3))
    assert out.shape == (5, expected) == (5, features.out_dim(3))


def test_fourier_features_values() -> None:
    p = torch.tensor([[0.5]])
    out = FourierFeatures(2)(p)[0]
    expected = [
        0.5,
        torch.sin(torch.tensor(0.5)),
        torch.cos(torch.tensor(0.5)),
        torch.sin(torch.tensor(1.0)),
        torch.cos(torch.tensor(1.0)),
    ]
    assert torch.allclose(out, torch.tensor(expected))


def test_fourier_features_order_on_several_coordinates() -> None:
    x, y, z = 0.5, -1.0, 2.0
    out = FourierFeatures(2)(torch.tensor([[x, y, z]], dtype=torch.float64))[0]
    expected = [x, y, z]  # the input, then per band, per coordinate: sin, cos
    for frequency in (1.0, 2.0):
        for value in (x, y, z):
            expected += [math.sin(frequency * value), math.cos(frequency * value)]
    torch.testing.assert_close(out, torch.tensor(expected, dtype=torch.float64))
    without_input = FourierFeatures(2, include_input=False)(torch.tensor([[x, y, z]]))[0]
    torch.testing.assert_close(without_input, torch.tensor(expected[3:], dtype=torch.float32))


def test_fourier_features_rejects_negative_bands() -> None:
    with pytest.raises(ValueError, match="L must be"):
        FourierFeatures(-1)


@pytest.mark.parametrize("hidden", [(64,), (64, 128, 256)])
def test_pae_shapes_single_and_multi_scene(hidden: tuple[int, ...]) -> None:
    poses = torch.randn(6, 7)
    single = PoseAutoEncoder(latent_dim=32, hidden=hidden, L=6)
    assert single(poses).x.shape == (6, 32) and single(poses).q.shape == (6, 32)
    multi = PoseAutoEncoder(latent_dim=32, hidden=hidden, L=6, n_scenes=3)
    scenes = torch.tensor([0, 1, 2, 0, 1, 2])
    a, b = multi(poses, scenes), multi(poses, torch.zeros(6, dtype=torch.long))
    assert a.x.shape == (6, 32)
    assert not torch.allclose(a.x[1:3], b.x[1:3]), "the scene index must change the encoding"
    with pytest.raises(ValueError, match="scene index"):
        multi(poses)


def test_pae_size_matches_paper_table() -> None:
    pae = PoseAutoEncoder(latent_dim=256, hidden=(64, 128, 256), L=6, n_scenes=2)
    size_mb = sum(p.numel() for p in pae.parameters()) * 4 / 1e6
    assert 0.8 < size_mb < 1.0  # paper Table 5: 0.89 MB


def test_posenet_interface_and_scene_logits() -> None:
    model = PoseNet(Backbone("small_cnn", pool="flatten", spatial=2), latent_dim=16, n_scenes=3)
    images = torch.randn(4, 3, 56, 56)
    latents = model.encode(images)
    assert latents.x.shape == (4, 16) and latents.q.shape == (4, 16)
    assert latents.scene_logits is not None and latents.scene_logits.shape == (4, 3)
    pose, _ = model(images)
    assert pose.shape == (4, 7)
    assert (
        PoseNet(Backbone("small_cnn", pool="flatten", spatial=2), 16).encode(images).scene_logits
        is None
    )


@pytest.mark.parametrize("name", ["mobilenet_v2", "efficientnet_b0"])
def test_torchvision_backbones_build_without_weights(name: str) -> None:
    backbone = Backbone(name, pretrained=False)
    assert backbone(torch.randn(1, 3, 64, 64)).shape == (1, backbone.out_dim)


def test_backbone_errors_are_clear(tmp_path: Path) -> None:
    with pytest.raises(BackboneError, match="unknown backbone 'vgg'"):
        Backbone("vgg")
    with pytest.raises(BackboneError, match="no ImageNet weights"):
        Backbone("small_cnn", pretrained=True)
    with pytest.raises(BackboneError, match="does not exist"):
        Backbone("small_cnn", weights_path=str(tmp_path / "missing.pt"))
    bad = tmp_path / "other.pt"
    torch.save({"something.else": torch.zeros(1)}, bad)
    with pytest.raises(BackboneError, match="holds no weights"):
        Backbone("small_cnn", weights_path=str(bad))


def test_backbone_loads_local_weights(tmp_path: Path) -> None:
    source = Backbone("small_cnn", pool="flatten", spatial=2)
    path = tmp_path / "weights.pt"
    torch.save(source.state_dict(), path)
    loaded = Backbone("small_cnn", weights_path=str(path), pool="flatten", spatial=2).eval()
    images = torch.randn(2, 3, 32, 32)
    assert torch.allclose(loaded(images), source.eval()(images))


def test_unreachable_imagenet_weights_are_one_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    import torchvision

    def offline(weights=None):
        raise OSError("<urlopen error [Errno -2] Name or service not known>")

    monkeypatch.setattr(torchvision.models, "mobilenet_v2", offline)
    with pytest.raises(BackboneError, match=r"ImageNet weights could not be loaded.*weights_path"):
        Backbone("mobilenet_v2", pretrained=True)


def test_estimate_normalises_and_assigns_scenes() -> None:
    images = torch.randn(3, 3, 32, 32)
    given = torch.tensor([1, 1, 1])
    multi = PoseNet(Backbone("small_cnn", pool="flatten", spatial=2), 8, n_scenes=3).eval()
    answer = multi.estimate(images, given)
    assert torch.allclose(answer.pose[:, 3:].norm(dim=-1), torch.ones(3))
    assert torch.equal(answer.pose[:, :3], answer.raw_pose[:, :3])
    assert torch.equal(answer.scene, answer.latents.scene_logits.argmax(-1))
    single = PoseNet(Backbone("small_cnn", pool="flatten", spatial=2), 8).eval()
    assert torch.equal(single.estimate(images, given).scene, given)
