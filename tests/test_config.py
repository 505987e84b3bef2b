"""Every config group option composes and instantiates; bad options fail with clear messages."""

import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from pae import CONFIG_DIR

GROUPS = {
    name: sorted(p.stem for p in (Path(CONFIG_DIR) / name).glob("*.yaml"))
    for name in (
        "data",
        "backbone",
        "teacher",
        "pae",
        "student",
        "decoder",
        "rpr",
        "iapr",
        "refine",
        "trainer",
        "logger",
        "callbacks",
        "stage",
        "experiment",
    )
}


def _compose(config: str, overrides: list[str]):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config, overrides=overrides)


@pytest.mark.parametrize(
    ("group", "option"), [(g, o) for g, options in GROUPS.items() for o in options]
)
def test_every_group_option_composes(group: str, option: str) -> None:
    overrides = [f"{group}={option}"]
    if group == "data" and option != "synthetic":
        overrides.append("data.root=/data/somewhere")
    cfg = _compose("train", overrides)
    assert group == "experiment" or cfg[group] is not None


@pytest.mark.parametrize("option", GROUPS["pae"])
def test_pae_options_instantiate_with_teacher_latent_size(option: str) -> None:
    cfg = _compose("train", [f"pae={option}", "teacher.model.latent_dim=32"])
    pae = instantiate(cfg.pae)
    assert pae.latent_dim == 32


@pytest.mark.parametrize("option", GROUPS["backbone"])
def test_backbone_options_instantiate(option: str) -> None:
    cfg = _compose("train", [f"backbone={option}"])
    assert instantiate(cfg.backbone).out_dim > 0


def test_pae_bands_override_reaches_the_model() -> None:
    cfg = _compose("train", ["pae.L=3"])
    assert instantiate(cfg.pae).fourier.L == 3


def test_eval_config_composes() -> None:
    cfg = _compose("eval", ["pae_ckpt=/x.ckpt", "refine=knn_closed_form"])
    assert cfg.refine.weight_model == "closed_form"


def test_unknown_group_option_lists_valid_choices(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "pae.train", "pae=transformer", f"hydra.run.dir={tmp_path}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode != 0
    assert "fourier_mlp4" in result.stderr and "mlp2" in result.stderr
