"""pae-export on a tiny teacher -> student run: onnxruntime gives the checkpoints' poses and
latents, pae-localize gives the same estimates from the export, and a layer that cannot be
exported is named in one line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from torch import nn

from pae import CONFIG_DIR
from pae.core.errors import ExportError
from pae.core.geometry import pose_errors
from pae.data.labels import read_labels
from tests.conftest import tiny_overrides

onnxruntime = pytest.importorskip("onnxruntime")

POSITION_M = 1e-4
ORIENTATION_DEG = 1e-3
"""How close onnxruntime's poses must come to the checkpoint's."""


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory: pytest.TempPathFactory, tiny_root: Path) -> Path:
    """A teacher and student run over the tiny dataset (2 scenes), with its saved config."""
    from pae.train import run

    run_dir = tmp_path_factory.mktemp("export") / "run"
    overrides = [
        *tiny_overrides(tiny_root),
        "student.max_epochs=1",
        "refine=none",
        "stage=pipeline",
        "stage.steps=[teacher,student]",
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    (run_dir / ".hydra").mkdir(parents=True)
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")  # what Hydra saves
    run(cfg, run_dir)
    return run_dir


@pytest.fixture(scope="module")
def exported(trained_run: Path) -> Path:
    """The run exported by pae-export into a folder beside it."""
    from pae.export import main

    out = trained_run.parent / "onnx"
    assert main([str(trained_run), str(out)]) == 0
    return out


def _session(path: Path) -> onnxruntime.InferenceSession:
    return onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def test_onnxruntime_gives_the_checkpoints_test_poses(trained_run: Path, exported: Path) -> None:
    from pae.apps.localization import data_module, read_run
    from pae.core.checkpoints import load_pae, load_teacher

    manifest = json.loads((exported / "pae_export.json").read_text())
    teacher = load_teacher(trained_run / "teacher" / "checkpoints" / "last.ckpt")
    pae = load_pae(trained_run / "student" / "checkpoints" / "last.ckpt")
    assert manifest["scenes"] == teacher.scene_names == ["scene00", "scene01"]
    assert manifest["fingerprint"] == teacher.data_fingerprint is not None
    data = data_module(read_run(trained_run))
    data.setup()
    steps = manifest["preprocessing"]
    assert (steps["center_crop_px"], steps["resize_shorter_edge_px"]) == (28, data.shorter_edge)
    images = torch.cat([data.preprocess(b["image"], False) for b in data.test_dataloader()])
    assert len(images) == 24

    found = _session(exported / manifest["teacher"]["file"]).run(None, {"image": images.numpy()})
    pose, latent, logits = (torch.from_numpy(array) for array in found)
    with torch.no_grad():
        expected = teacher.model.estimate(images, torch.zeros(len(images), dtype=torch.long))
    position, orientation = pose_errors(pose.double(), expected.pose.double())
    assert float(position.max()) <= POSITION_M
    assert float(orientation.max()) <= ORIENTATION_DEG
    assert torch.equal(logits.argmax(-1), expected.scene)
    assert torch.allclose(latent, expected.latents.joint(), atol=1e-4)

    scene = expected.scene
    pae_file = exported / manifest["pae"]["file"]
    given = {"pose": expected.pose.numpy(), "scene": scene.numpy()}
    (pae_latent,) = _session(pae_file).run(None, given)
    with torch.no_grad():
        assert np.allclose(pae_latent, pae.model(expected.pose, scene).joint().numpy(), atol=1e-4)


def test_pae_localize_from_the_export_gives_the_checkpoints_estimates(
    trained_run: Path, exported: Path, tiny_root: Path, tmp_path: Path, capsys
) -> None:
    from pae.localize import main

    labels = str(tiny_root / "labels" / "all_test.csv")
    out = {name: tmp_path / f"{name}.csv" for name in ("checkpoint", "onnx")}
    assert main([str(trained_run), labels, "--out", str(out["checkpoint"])]) == 0
    by_checkpoint = capsys.readouterr().out.splitlines()[0]
    for given in (exported, exported / "teacher.onnx"):
        argv = [str(trained_run), labels, "--onnx", str(given), "--batch-size", "5"]
        assert main([*argv, "--out", str(out["onnx"])]) == 0
        assert capsys.readouterr().out.splitlines()[0] == by_checkpoint  # the run's figures
        ours, theirs = read_labels(out["onnx"]), read_labels(out["checkpoint"])
        assert ours.img_path == theirs.img_path and ours.scene == theirs.scene
        position, orientation = pose_errors(
            torch.as_tensor(ours.poses), torch.as_tensor(theirs.poses)
        )
        assert float(position.max()) <= POSITION_M
        assert float(orientation.max()) <= ORIENTATION_DEG


def test_an_export_of_other_data_or_another_method_is_one_line(
    trained_run: Path, exported: Path, tiny_root: Path, tmp_path: Path, capsys
) -> None:
    from pae.localize import main

    other = tmp_path / "other"
    shutil.copytree(exported, other)
    manifest = json.loads((other / "pae_export.json").read_text())
    manifest["fingerprint"]["train_poses_sha256"] = "0" * 64
    (other / "pae_export.json").write_text(json.dumps(manifest))
    labels = str(tiny_root / "labels" / "all_test.csv")
    out = str(tmp_path / "poses.csv")
    cases = {
        "fingerprints differ": ["--onnx", str(other)],
        "runs the teacher only, not --refine student": [
            *("--onnx", str(exported), "--refine", "student")
        ],
        "no pae_export.json": ["--onnx", str(tmp_path)],
    }
    for message, extra in cases.items():
        with pytest.raises(SystemExit):
            main([str(trained_run), labels, "--out", out, *extra])
        errors = capsys.readouterr().err.splitlines()
        assert len([line for line in errors if "error:" in line]) == 1
        assert message in errors[-1]
    assert not Path(out).exists()


class Eigenvalues(nn.Module):
    """A layer whose operator (a symmetric eigendecomposition) ONNX has no function for."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.linalg.eigh(x[:, :, None] * x[:, None, :])[0]


class SignBranch(nn.Module):
    """A layer whose Python branch depends on the values (one trace would keep one branch)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 2 * x if x.sum() > 0 else x


class FixedBatch(nn.Module):
    """A layer that reads the batch size as a Python number (exported as a constant)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.arange(len(x))[:, None]


@pytest.mark.parametrize(
    ("layer", "message"),
    [
        (Eigenvalues(), "layer 1.1 (Eigenvalues) cannot be exported to ONNX: No ONNX function"),
        (SignBranch(), "layer 1.1 (SignBranch) cannot be exported to ONNX: Could not guard"),
        (FixedBatch(), "the exported graph fails at a batch of 3 (exported at 2"),
    ],
)
def test_a_layer_that_cannot_be_exported_is_named_in_one_line(
    layer: nn.Module, message: str
) -> None:
    from pae.apps.export import onnx_bytes

    model = nn.Sequential(nn.Linear(4, 4), nn.Sequential(nn.ReLU(), layer))
    with pytest.raises(ExportError) as raised:
        onnx_bytes(model, (torch.randn(2, 4),), ["x"], ["y"], "teacher")
    text = str(raised.value)
    assert text.startswith("teacher: ") and message in text
    assert "\n" not in text


def test_pae_export_names_the_teachers_layer_and_writes_nothing(
    trained_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    from pae.apps import export
    from pae.core.checkpoints import load_teacher
    from pae.export import main

    def broken(path: Path):
        loaded = load_teacher(path)
        loaded.model.encoder_x.append(Eigenvalues())
        return loaded

    monkeypatch.setattr(export, "load_teacher", broken)
    out = tmp_path / "onnx"
    with pytest.raises(SystemExit):
        main([str(trained_run), str(out)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[-1].startswith(
        "pae-export: error: teacher: layer teacher.encoder_x.2 (Eigenvalues) cannot be exported"
    )
    assert not out.exists() or not any(out.iterdir())


SLOW_BACKBONES = ("mobilenet_v2", "efficientnet_b0", "resnet50")
"""Backbones whose export takes 5-40 s each here."""


@pytest.mark.parametrize(
    ("teacher", "backbone"),
    [
        ("posenet", "small_cnn"),
        ("ms_transformer_small", "small_cnn"),
        *(
            pytest.param(teacher, backbone, marks=pytest.mark.slow)
            for teacher in ("posenet", "ms_transformer_small")
            for backbone in SLOW_BACKBONES
        ),
    ],
)
def test_every_shipped_teacher_exports_with_a_dynamic_batch(teacher: str, backbone: str) -> None:
    """Each teacher config on each backbone config (untrained, 2 scenes, 64 px), exported,
    gives onnxruntime's poses, latents and scene logits at batches of 1 and 5 (MS-Transformer
    picks each image's scene with a gather: indexing by arange(len(images)) fixed the
    batch)."""
    from hydra.utils import instantiate

    from pae.apps.export import TeacherGraph, onnx_bytes

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=[f"teacher={teacher}", f"backbone={backbone}"])
    if teacher.startswith("ms_transformer"):  # one layer each: the graph's kinds of node
        cfg.teacher.model.encoder_layers = cfg.teacher.model.decoder_layers = 1
    model = instantiate(cfg.teacher.model, n_scenes=2).eval()
    graph = TeacherGraph(model).eval()
    outputs = ["pose", "latent", "scene_logits"]
    onnx = onnx_bytes(graph, (torch.zeros(2, 3, 64, 64),), ["image"], outputs, teacher)
    session = onnxruntime.InferenceSession(onnx, providers=["CPUExecutionProvider"])
    for batch in (1, 5):
        images = torch.randn(batch, 3, 64, 64)
        found = session.run(None, {"image": images.numpy()})
        with torch.no_grad():
            expected = graph(images)
        for ours, theirs in zip(expected, found, strict=True):
            assert np.allclose(theirs, ours.numpy(), atol=1e-4, rtol=1e-4)
