"""A teacher exported by `pae-export`, run by onnxruntime where pae runs a teacher
(`pae-localize --onnx`): read back with its manifest and checked against the run."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from pae.apps.export import MANIFEST, TEACHER_FILE
from pae.apps.localization import Run, data_module
from pae.core.checkpoints import DATA_FINGERPRINT_KEY, LoadedModel, read_checkpoint
from pae.core.errors import ConfigError
from pae.models.base import Latents, PoseRegressor


class OnnxTeacher(PoseRegressor):
    """An exported teacher's graph (``pae.apps.export.TeacherGraph``) in an onnxruntime
    session on the CPU with ``threads`` threads: images [B, 3, crop, crop] -> (pose [B, 7]
    with unit quaternions, Latents of [B, d] and, multi-scene, scene logits [B, S])."""

    def __init__(self, path: str | Path, threads: int | None = None) -> None:
        super().__init__()
        import onnxruntime

        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = threads or torch.get_num_threads()
        self.session = onnxruntime.InferenceSession(
            str(path), options, providers=["CPUExecutionProvider"]
        )
        self.outputs = [entry.name for entry in self.session.get_outputs()]
        self.latent_dim = int(self.session.get_outputs()[1].shape[-1]) // 2

    def forward(self, images: Tensor, scene: Tensor | None = None) -> tuple[Tensor, Latents]:
        found = self.session.run(self.outputs, {"image": images.detach().float().cpu().numpy()})
        named = {
            name: torch.from_numpy(value).to(images.device)
            for name, value in zip(self.outputs, found, strict=True)
        }
        latent = named["latent"]
        d = latent.shape[-1] // 2
        return named["pose"], Latents(latent[:, :d], latent[:, d:], named.get("scene_logits"))


def read_manifest(path: str | Path) -> tuple[dict[str, Any], Path]:
    """The manifest of an export and the folder it lies in, from the export folder, its
    manifest or its teacher file; ConfigError naming ``path`` where there is none."""
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    manifest = folder / MANIFEST
    if not manifest.is_file():
        raise ConfigError(f"--onnx {path}: no {MANIFEST} in {folder} (write it with pae-export)")
    try:
        return json.loads(manifest.read_text()), folder
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ConfigError(f"{manifest}: not a pae-export manifest ({err})") from None


def load_onnx_teacher(path: str | Path, run: Run, teacher_checkpoint: Path) -> LoadedModel:
    """The teacher exported at ``path`` (see :func:`read_manifest`) as pae-localize takes a
    checkpoint's, after checking that it is ``run``'s: trained on the data of
    ``teacher_checkpoint`` (the fingerprint) and pre-processed as the run's data is."""
    manifest, folder = read_manifest(path)
    given = folder / manifest.get("teacher", {}).get("file", TEACHER_FILE)
    if not given.is_file():
        raise ConfigError(f"--onnx {path}: {given} is missing")
    fingerprint = read_checkpoint(teacher_checkpoint).get(DATA_FINGERPRINT_KEY)
    if manifest.get("fingerprint") != fingerprint:
        raise ConfigError(
            f"--onnx {path}: exported from a teacher trained on other data than {run.folder}'s "
            f"({teacher_checkpoint}): their fingerprints differ"
        )
    data = data_module(run)
    steps = manifest.get("preprocessing", {})
    expected = {"resize_shorter_edge_px": data.shorter_edge, "center_crop_px": data.crop}
    for key, value in expected.items():
        if steps.get(key) != value:
            raise ConfigError(
                f"--onnx {path}: preprocessing.{key} is {steps.get(key)}, the run's data "
                f"takes {value}"
            )
    return LoadedModel(OnnxTeacher(given), list(manifest["scenes"]), {}, fingerprint)
