"""Loading pae checkpoints safely (weights_only) with clear one-line errors."""

from __future__ import annotations

import pickle
import zipfile
import zlib
from pathlib import Path
from typing import Any, NamedTuple

import torch
from hydra.utils import instantiate
from lightning.fabric.plugins import TorchCheckpointIO
from torch import nn

from pae.core.atomic import atomic_write
from pae.core.errors import CheckpointError

DATA_FINGERPRINT_KEY = "pae_data_fingerprint"
"""Checkpoint entry with the fingerprint of the training data (see PoseDataModule.fingerprint)."""


DAMAGED_HINT = "copy it again, or retrain it"
"""What to do with a damaged checkpoint file."""


def verify_archive(path: Path) -> None:
    """A checkpoint in torch's zip format whose members all match their stored CRC-32; a
    file that is not a zip archive is left to torch.load (its error names it)."""
    if not zipfile.is_zipfile(path):
        return
    try:
        with zipfile.ZipFile(path) as archive:
            bad_member = archive.testzip()
        problem = None if bad_member is None else f"{bad_member} fails its CRC check"
    except (zipfile.BadZipFile, zlib.error, EOFError, ValueError):
        problem = "its zip directory is unreadable"
    if problem is not None:
        raise CheckpointError(f"{path}: damaged checkpoint file ({problem}): {DAMAGED_HINT}")


def first_non_finite_weight(checkpoint: Any) -> tuple[str, float] | None:
    """(key, value) of the first weight tensor holding NaN or inf in a checkpoint's state
    dict (in a plain state dict: its own tensors), or None when every weight is finite."""
    weights = checkpoint.get("state_dict", checkpoint) if isinstance(checkpoint, dict) else {}
    for key, value in weights.items() if isinstance(weights, dict) else ():
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            finite = torch.isfinite(value)
            if not bool(finite.all()):
                return str(key), float(value[~finite][0])
    return None


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """torch.load with weights_only=True (no pickled code is ever executed) of a checkpoint
    whose archive passes its CRC check and whose weights are all finite."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    verify_archive(path)
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
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
    bad_weight = first_non_finite_weight(checkpoint)
    if bad_weight is not None:
        key, value = bad_weight
        raise CheckpointError(
            f"{path}: damaged checkpoint file (weight {key} holds {value}): {DAMAGED_HINT}"
        )
    return checkpoint


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
    the fingerprint of the data it was trained on (None in checkpoints without one) and the
    checkpoint's hyper-parameters (the stored configs of every model in it)."""

    model: nn.Module
    scene_names: list[str]
    config: dict[str, Any]
    data_fingerprint: dict[str, Any] | None = None
    hparams: dict[str, Any] | None = None


KINDS_BY_CONFIG = (
    (("rpr_config", "decoder_config"), "rpr"),
    (("rpr_config",), "rpr_image"),
    (("iapr_config",), "iapr"),
    (("decoder_config",), "decoder"),
    (("scene_model_config",), "render_compare"),
    (("pae_config",), "student"),
    (("teacher_config",), "teacher"),
)
"""A checkpoint's kind (the stage that trained it) from the model configs it stores: the
first entry whose configs it has all."""
KEY_KINDS = {
    "teacher_ckpt": "teacher",
    "student_ckpt": "student",
    "decoder_ckpt": "decoder",
    "scene_model_ckpt": "render_compare",
}
"""The checkpoint kind each setting takes."""


def checkpoint_kind(checkpoint: dict[str, Any]) -> str | None:
    """The stage that wrote `checkpoint` (teacher, student, decoder, rpr, rpr_image, iapr,
    render_compare), or None for a checkpoint that pae did not write."""
    hparams = checkpoint.get("hyper_parameters") or {}
    for configs, kind in KINDS_BY_CONFIG:
        if all(name in hparams for name in configs):
            return kind
    return None


def _check_kind(checkpoint: dict[str, Any], path: Path, key: str) -> None:
    """`checkpoint` (read from `path`) is of the kind setting `key` takes (KEY_KINDS)."""
    expected, kind = KEY_KINDS[key], checkpoint_kind(checkpoint)
    if kind == expected:
        return
    found = f"a stage={kind} checkpoint" if kind else "not a checkpoint of a pae stage"
    hint = ""
    if key == "teacher_ckpt" and kind == "student":
        hint = "; a student checkpoint holds its teacher: pass it as student_ckpt"
    raise CheckpointError(
        f"{key}={path}: {found}, but {key} takes a stage={expected} checkpoint{hint}"
    )


def check_checkpoint_kinds(paths: dict[str, Any]) -> None:
    """Each checkpoint setting given (a key of ``KEY_KINDS`` -> its path, or None) names a
    checkpoint of the kind that setting takes, read and checked as loading it would: before
    any data is read, a one-line error naming the setting and the file."""
    for key, path in paths.items():
        if path is not None and key in KEY_KINDS:
            _check_kind(read_checkpoint(path), Path(path), key)


def _load_model(path: str | Path, name: str, kind: str, key: str | None) -> LoadedModel:
    """Rebuild submodule `name` of a checkpoint from its `{name}_config` hyper-parameter;
    with `key`, the checkpoint must be of the kind that setting takes."""
    path = Path(path)
    checkpoint = read_checkpoint(path)
    if key is not None:
        _check_kind(checkpoint, path, key)
    config = dict(_hparam(checkpoint, f"{name}_config", path, kind))
    model = instantiate(config)
    _load_submodule(model, checkpoint, f"{name}.", path)
    scenes = list(_hparam(checkpoint, "scene_names", path, kind))
    hparams = dict(checkpoint.get("hyper_parameters") or {})
    fingerprint = checkpoint.get(DATA_FINGERPRINT_KEY)
    return LoadedModel(model.eval(), scenes, config, fingerprint, hparams)


def load_teacher(path: str | Path, key: str | None = None) -> LoadedModel:
    """A checkpoint that holds a teacher (a teacher's, or a later stage's: students hold a
    copy of their teacher) -> the teacher (a PoseRegressor). `key`: the setting that named
    the file (teacher_ckpt, student_ckpt), whose kind of checkpoint it must be."""
    return _load_model(path, "teacher", "teacher", key)


def load_pae(path: str | Path, key: str | None = None) -> LoadedModel:
    """A student checkpoint (or a later stage's) -> its PoseAutoEncoder (`key` as above)."""
    return _load_model(path, "pae", "student", key)


def load_scene_model(path: str | Path, key: str | None = None) -> LoadedModel:
    """A scene-model checkpoint (the scene_model step with scene_model=voxel_grid) -> its
    scene model (it also holds a copy of its teacher: load_teacher reads it; `key` as
    above)."""
    return _load_model(path, "scene_model", "scene model", key)


def load_decoder(path: str | Path, key: str | None = None) -> LoadedModel:
    """A decoder checkpoint (stage=decoder) -> its ImageDecoder (`key` as above)."""
    return _load_model(path, "decoder", "decoder", key)


ARCHITECTURE_NEUTRAL = ("dropout",)
"""Model settings that do not change what a trained model computes at test time."""


def architecture_differences(stored: dict[str, Any], other: dict[str, Any]) -> list[str]:
    """`key: stored -> other` for each setting two stored model configs disagree on
    (nested keys dotted), ARCHITECTURE_NEUTRAL ones aside."""

    def flat(config: dict[str, Any], prefix: str = "") -> dict[str, Any]:
        items: dict[str, Any] = {}
        for key, value in config.items():
            if isinstance(value, dict):
                items |= flat(value, f"{prefix}{key}.")
            elif key not in ARCHITECTURE_NEUTRAL:
                items[f"{prefix}{key}"] = value
        return items

    before, after = flat(stored), flat(other)
    return [
        f"{key}: {before.get(key, '(unset)')} -> {after.get(key, '(unset)')}"
        for key in sorted(before.keys() | after.keys())
        if before.get(key) != after.get(key)
    ]


def load_rpr(path: str | Path, key: str | None = None) -> LoadedModel:
    """An RPR checkpoint (stage=rpr or rpr_image) -> its SiameseRPR (`key` as above)."""
    return _load_model(path, "rpr", "rpr", key)


def load_iapr(path: str | Path, key: str | None = None) -> LoadedModel:
    """An iterative-APR checkpoint (stage=iapr) -> its IterativeAPR (`key` as above)."""
    return _load_model(path, "iapr", "iapr", key)
