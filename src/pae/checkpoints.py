"""Loading pae checkpoints safely (weights_only) with clear one-line errors."""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any, NamedTuple

import torch
from hydra.utils import instantiate
from torch import nn


class CheckpointError(RuntimeError):
    """A missing, unreadable, wrong-kind or mismatched checkpoint; the message names the file."""


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """torch.load with weights_only=True: no pickled code is ever executed."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise CheckpointError(
            f"{path}: not a readable checkpoint (not a torch file, or it holds objects that "
            "weights-only loading refuses to unpickle)"
        ) from None
    except Exception as err:  # torch raises several types for corrupt/unsafe files
        first_line = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CheckpointError(f"{path}: not a readable checkpoint ({first_line})") from None


def _hparam(checkpoint: dict[str, Any], key: str, path: Path, kind: str) -> Any:
    hparams = checkpoint.get("hyper_parameters") or {}
    if key not in hparams:
        raise CheckpointError(
            f"{path}: not a {kind} checkpoint (no '{key}' in its hyper-parameters)"
        )
    return hparams[key]


def _load_submodule(model: nn.Module, checkpoint: dict[str, Any], prefix: str, path: Path) -> None:
    state = {
        k.removeprefix(prefix): v
        for k, v in checkpoint.get("state_dict", {}).items()
        if k.startswith(prefix)
    }
    try:
        model.load_state_dict(state)
    except RuntimeError as err:
        detail = " ".join(str(err).split())[:300]
        raise CheckpointError(f"{path}: weights do not match the model ({detail})") from None


class LoadedModel(NamedTuple):
    """A model rebuilt from a checkpoint: the model (eval mode), its scenes and architecture."""

    model: nn.Module
    scene_names: list[str]
    config: dict[str, Any]


def _load_model(path: str | Path, name: str, kind: str) -> LoadedModel:
    """Rebuild submodule `name` of a checkpoint from its `{name}_config` hyper-parameter."""
    path = Path(path)
    checkpoint = read_checkpoint(path)
    config = dict(_hparam(checkpoint, f"{name}_config", path, kind))
    model = instantiate(config)
    _load_submodule(model, checkpoint, f"{name}.", path)
    scenes = list(_hparam(checkpoint, "scene_names", path, kind))
    return LoadedModel(model.eval(), scenes, config)


def load_teacher(path: str | Path) -> LoadedModel:
    """A teacher or student checkpoint (students hold a copy of their teacher) -> the teacher
    (a PoseRegressor)."""
    return _load_model(path, "teacher", "teacher")


def load_pae(path: str | Path) -> LoadedModel:
    """A student checkpoint -> its PoseAutoEncoder."""
    return _load_model(path, "pae", "student")


def load_decoder(path: str | Path) -> LoadedModel:
    """A decoder checkpoint (stage=decoder) -> its ImageDecoder."""
    return _load_model(path, "decoder", "decoder")
