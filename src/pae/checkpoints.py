"""Loading pae checkpoints safely (weights_only) with clear one-line errors."""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path
from typing import Any, NamedTuple

import torch
from hydra.utils import instantiate
from lightning.fabric.plugins import TorchCheckpointIO
from torch import nn

from pae.atomic import atomic_write
from pae.errors import CheckpointError

DATA_FINGERPRINT_KEY = "pae_data_fingerprint"
"""Checkpoint entry with the fingerprint of the training data (see PoseDataModule.fingerprint)."""


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """torch.load with weights_only=True: no pickled code is ever executed."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        if not zipfile.is_zipfile(path):
            raise CheckpointError(
                f"{path}: not a readable checkpoint (not a complete torch file: truncated, "
                f"or not a checkpoint at all; {path.stat().st_size} bytes)"
            ) from None
        if not isinstance(err, pickle.UnpicklingError):
            first_line = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise CheckpointError(f"{path}: not a readable checkpoint ({first_line})") from None
        raise CheckpointError(
            f"{path}: not a readable checkpoint (not a torch file, or it holds objects that "
            "weights-only loading refuses to unpickle)"
        ) from None


def newest_readable_checkpoint(folder: str | Path) -> tuple[Path | None, list[str]]:
    """The most recently written `*.ckpt` in `folder` that loads (weights-only) -> (its path or
    None, one line per newer checkpoint that could not be read). Resuming uses it, so that a
    damaged `last.ckpt` falls back to the checkpoint before it."""
    candidates = sorted(
        Path(folder).glob("*.ckpt"), key=lambda p: (p.stat().st_mtime_ns, p.name), reverse=True
    )
    skipped = []
    for path in candidates:
        try:
            read_checkpoint(path)
        except CheckpointError as err:
            skipped.append(str(err))
            continue
        return path, skipped
    return None, skipped


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning checkpoint I/O that writes each checkpoint whole: a temporary file in the
    checkpoint's folder, then a rename (a full disk or a kill never leaves half a file)."""

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: str | Path, storage_options: Any | None = None
    ) -> None:
        with atomic_write(path, "wb") as handle:
            torch.save(checkpoint, handle)


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
    """A model rebuilt from a checkpoint: the model (eval mode), its scenes and architecture,
    and the fingerprint of the data it was trained on (None in checkpoints without one)."""

    model: nn.Module
    scene_names: list[str]
    config: dict[str, Any]
    data_fingerprint: dict[str, Any] | None = None


def _load_model(path: str | Path, name: str, kind: str) -> LoadedModel:
    """Rebuild submodule `name` of a checkpoint from its `{name}_config` hyper-parameter."""
    path = Path(path)
    checkpoint = read_checkpoint(path)
    config = dict(_hparam(checkpoint, f"{name}_config", path, kind))
    model = instantiate(config)
    _load_submodule(model, checkpoint, f"{name}.", path)
    scenes = list(_hparam(checkpoint, "scene_names", path, kind))
    return LoadedModel(model.eval(), scenes, config, checkpoint.get(DATA_FINGERPRINT_KEY))


def load_teacher(path: str | Path) -> LoadedModel:
    """A teacher or student checkpoint (students hold a copy of their teacher) -> the teacher
    (a PoseRegressor)."""
    return _load_model(path, "teacher", "teacher")


def load_pae(path: str | Path) -> LoadedModel:
    """A student checkpoint -> its PoseAutoEncoder."""
    return _load_model(path, "pae", "student")


def load_scene_model(path: str | Path) -> LoadedModel:
    """A scene-model checkpoint (the scene_model step with scene_model=voxel_grid) -> its
    scene model (it also holds a copy of its teacher: load_teacher reads it)."""
    return _load_model(path, "scene_model", "scene model")


def load_decoder(path: str | Path) -> LoadedModel:
    """A decoder checkpoint (stage=decoder) -> its ImageDecoder."""
    return _load_model(path, "decoder", "decoder")
