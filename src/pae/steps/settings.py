"""The steps' own settings (``teacher.*``, ``student.*``, ``rpr.*``, ``iapr.*``,
``scene_model.*`` besides their models) as records whose ``__post_init__`` checks their
ranges, each a one-line ValueError naming the setting: the one home of those ranges, built
by :mod:`pae.config.validation` from a run's config. A record's defaults stand in only for a
key its group lacks (``conf/<group>/*.yaml`` hold the configured values). Imports neither
numpy nor torch."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pae.core.ranges import check_boolean, check_choice, check_integer, check_number, is_number

INIT_BACKBONES = ("teacher", None)
"""Where a step's backbone starts: the teacher's weights, or its own initialisation."""


@dataclass
class OptimizerSettings:
    """A step's ``optimizer``: its learning rate and weight decay (others: its class's)."""

    lr: float = 1e-3
    weight_decay: float | None = None

    def __post_init__(self) -> None:
        check_number("lr", self.lr, 0, strict=True)
        check_number("weight_decay", self.weight_decay, 0, optional=True)


@dataclass
class StepSettings:
    """What every trained step has: its epochs."""

    max_epochs: int = 0

    def __post_init__(self) -> None:
        check_integer("max_epochs", self.max_epochs, 0)


@dataclass
class TeacherSettings(StepSettings):
    scene_loss_weight: float = 1.0
    """The weight of the scene classification loss (multi-scene teachers)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_number("scene_loss_weight", self.scene_loss_weight, 0)


@dataclass
class StudentSettings(StepSettings):
    input: str = "gt"
    """The pose the PAE encodes: gt (the paper) or teacher (the teacher's estimate)."""
    latent_loss: str = "l2"
    cache_latents: bool = True

    def __post_init__(self) -> None:
        from pae.core.losses import LATENT_LOSSES

        super().__post_init__()
        check_choice("input", self.input, ("gt", "teacher"))
        check_choice("latent_loss", self.latent_loss, LATENT_LOSSES)
        check_boolean("cache_latents", self.cache_latents)


def _check_offset(name: str, offset: Any) -> None:
    """An offset ``{position_m, orientation_deg}``, both >= 0."""
    for key in ("position_m", "orientation_deg"):
        value = offset.get(key) if isinstance(offset, dict) else None
        if not (is_number(value) and value >= 0):
            raise ValueError(f"{name}.{key} must be a number >= 0, got {value!r}")


@dataclass
class RPRSettings(StepSettings):
    pair_k: int = 5
    """The training reference: one of the pair_k nearest train poses of the query."""
    pair_offset: dict[str, float] | None = None
    """Or a reference this far from the query (``position_m``, ``orientation_deg``)."""
    init_backbone: str | None = "teacher"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_integer("pair_k", self.pair_k, 1)
        if self.pair_offset is not None:
            _check_offset("pair_offset", self.pair_offset)
        check_choice("init_backbone", self.init_backbone, INIT_BACKBONES)


@dataclass
class IAPRSettings(StepSettings):
    iterations: int = 3
    start: dict[str, float] | None = None
    """How far the training starts lie from the labels (``position_m``, ``orientation_deg``)."""
    refine_orientation: bool = True
    init_backbone: str | None = "teacher"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_integer("iterations", self.iterations, 1)
        if self.start is not None:
            _check_offset("start", self.start)
        check_boolean("refine_orientation", self.refine_orientation)
        check_choice("init_backbone", self.init_backbone, INIT_BACKBONES)


@dataclass
class SceneModelStepSettings(StepSettings):
    """The scene_model step's settings shared by every scene model
    (``conf/scene_model/base.yaml`` says what each does)."""

    batches_per_epoch: int = 50
    rays_per_batch: int = 4096
    image_size: int | None = 64
    tv_weight: float = 1e-3
    appearance: str = "sequence"
    appearance_lr: float | None = None
    fit_trim: float = 0.0
    fit_trim_from_epoch: int = 1
    depth_rays: int = 0
    depth_weight: float = 0.05
    quality_size: int = 24
    quality_images: int = 128

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("batches_per_epoch", "rays_per_batch", "quality_size", "quality_images"):
            check_integer(name, getattr(self, name), 1)
        check_integer("image_size", self.image_size, 4, optional=True)
        check_number("tv_weight", self.tv_weight, 0)
        check_choice("appearance", self.appearance, ("sequence", "image"))
        check_number("appearance_lr", self.appearance_lr, 0, strict=True, optional=True)
        if not (is_number(self.fit_trim) and 0 <= self.fit_trim < 1):
            raise ValueError(f"fit_trim must be a number in [0, 1), got {self.fit_trim!r}")
        check_integer("fit_trim_from_epoch", self.fit_trim_from_epoch, 0)
        check_integer("depth_rays", self.depth_rays, 0)
        check_number("depth_weight", self.depth_weight, 0)


STEP_SETTINGS: dict[str, type] = {
    "teacher": TeacherSettings,
    "student": StudentSettings,
    "decoder": StepSettings,
    "iapr": IAPRSettings,
    "rpr": RPRSettings,
    "scene_model": SceneModelStepSettings,
}
"""Each step group -> its settings record (``iapr`` before ``rpr``, whose ``pair_offset`` is
``${iapr.start}``: a bad start is named where it is set)."""
