"""Convolutional backbones by name: image [B, 3, H, W] -> feature vector [B, out_dim]."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch
import torchvision
from torch import Tensor, nn

from pae.core.errors import BackboneError


def _small_cnn() -> tuple[nn.Module, int]:
    """A five-stage stride-2 CNN for CPU work: 64 px in -> [B, 256, 2, 2] out."""
    widths = (32, 64, 96, 128, 256)
    layers: list[nn.Module] = []
    in_ch = 3
    for width in widths:
        layers += [
            nn.Conv2d(in_ch, width, 3, stride=2, padding=1, bias=False),
            nn.BatchNorm2d(width),
            nn.ReLU(inplace=True),
            nn.Conv2d(width, width, 3, padding=1, bias=False),
            nn.BatchNorm2d(width),
            nn.ReLU(inplace=True),
        ]
        in_ch = width
    return nn.Sequential(*layers), in_ch


def _torchvision(name: str, pretrained: bool) -> tuple[nn.Module, int]:
    weights = "DEFAULT" if pretrained else None
    try:
        model = getattr(torchvision.models, name)(weights=weights)
    except (OSError, RuntimeError, ValueError) as err:  # no network, broken cache
        raise BackboneError(
            f"backbone {name}: ImageNet weights could not be loaded ({err}); "
            "set backbone.weights_path to a local state-dict file or backbone.pretrained=false"
        ) from None
    if name.startswith("resnet"):
        return nn.Sequential(*list(model.children())[:-2]), model.fc.in_features
    return model.features, model.classifier[-1].in_features


BACKBONES: dict[str, Callable[[bool], tuple[nn.Module, int]]] = {
    "small_cnn": lambda pretrained: _small_cnn(),
    "mobilenet_v2": lambda pretrained: _torchvision("mobilenet_v2", pretrained),
    "resnet50": lambda pretrained: _torchvision("resnet50", pretrained),
    "efficientnet_b0": lambda pretrained: _torchvision("efficientnet_b0", pretrained),
}


class Backbone(nn.Module):
    """A named feature extractor followed by pooling.

    pool="avg": global average pooling -> [B, C]; pool="flatten": keeps the spatial layout
    of the final map -> [B, C * h * w] (`spatial` gives h = w, needed to size the next layer).
    """

    def __init__(
        self,
        name: str = "small_cnn",
        pretrained: bool = False,
        weights_path: str | None = None,
        pool: str = "avg",
        spatial: int = 1,
    ) -> None:
        super().__init__()
        if name not in BACKBONES:
            raise BackboneError(f"unknown backbone {name!r}; choose one of {sorted(BACKBONES)}")
        if pool not in ("avg", "flatten"):
            raise BackboneError(f"unknown backbone.pool {pool!r}; choose 'avg' or 'flatten'")
        if pretrained and name == "small_cnn" and weights_path is None:
            raise BackboneError("backbone small_cnn has no ImageNet weights; set pretrained=false")
        self.name = name
        self.features, channels = BACKBONES[name](pretrained and weights_path is None)
        if weights_path is not None:
            self._load_local(Path(weights_path))
        self.pool = pool
        self.out_dim = channels if pool == "avg" else channels * spatial * spatial
        self.spatial = spatial

    def _load_local(self, path: Path) -> None:
        if not path.is_file():
            raise BackboneError(f"backbone.weights_path {path} does not exist")
        state = torch.load(path, map_location="cpu", weights_only=True)
        prefix = "features."
        own = {k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix)}
        weights = own or state
        if not set(weights) & set(self.features.state_dict()):
            raise BackboneError(f"backbone.weights_path {path} holds no weights for {self.name}")
        try:
            self.features.load_state_dict(weights)
        except RuntimeError as err:
            detail = " ".join(str(err).split())[:200]
            raise BackboneError(
                f"backbone.weights_path {path} does not fit {self.name}: {detail}"
            ) from None

    def forward(self, images: Tensor) -> Tensor:
        """images [B, 3, H, W] -> features [B, out_dim]."""
        fmap = self.features(images)
        if self.pool == "avg":
            return fmap.mean(dim=(2, 3))
        if fmap.shape[-2:] != (self.spatial, self.spatial):
            fmap = nn.functional.adaptive_avg_pool2d(fmap, self.spatial)
        return fmap.flatten(1)
