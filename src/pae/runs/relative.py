"""The models of the relative regressors' steps (rpr, rpr_image, iapr): built from their
group's config, their backbone optionally copied from the teacher's, stored in a checkpoint
without pretrained weights, and how an RPR draws its training references."""

from __future__ import annotations

from typing import Any

import torch
from hydra.utils import instantiate
from lightning.pytorch.utilities import rank_zero_info
from omegaconf import DictConfig, OmegaConf

from pae.core.errors import ConfigError
from pae.models.base import PoseRegressor


def init_backbone_from_teacher(model: torch.nn.Module, teacher: PoseRegressor, key: str) -> None:
    """Copy the teacher's backbone weights into `model.backbone` (same backbone config);
    a ConfigError naming `key` when they do not fit."""
    source = getattr(teacher, "backbone", None)
    try:
        model.backbone.load_state_dict(source.state_dict())
    except (AttributeError, RuntimeError):
        raise ConfigError(
            f"{key}=teacher: the teacher's backbone does not match this model's backbone "
            f"(use {key}=null)"
        ) from None
    rank_zero_info(f"{key}: backbone initialised from the teacher's")


def stored_model_config(model_config: DictConfig) -> dict[str, Any]:
    """A model config as stored in a checkpoint: the weights come from the state dict, so
    no pretrained download and no weights file (for a backbone that takes them)."""
    config = OmegaConf.to_container(model_config, resolve=True)
    backbone = config["backbone"]
    for key, value in (("pretrained", False), ("weights_path", None)):
        if key in backbone:
            backbone[key] = value
    return config


def relative_model(cfg: DictConfig, group: str, teacher: PoseRegressor) -> torch.nn.Module:
    """The model of a relative regressor's group (`rpr`, `iapr`), its backbone copied from
    the teacher's when `{group}.init_backbone` is `teacher`."""
    settings = cfg[group]
    model = instantiate(settings.model)
    if settings.get("init_backbone") == "teacher":
        init_backbone_from_teacher(model, teacher, f"{group}.init_backbone")
    return model


def rpr_pairs(cfg: DictConfig) -> dict[str, Any]:
    """How an RPR draws its training references: `pair_k` and `pair_offset` (None: around
    the true pose)."""
    offset = cfg.rpr.get("pair_offset")
    return {
        "pair_k": cfg.rpr.pair_k,
        "pair_offset": OmegaConf.to_container(offset, resolve=True) if offset else None,
    }
