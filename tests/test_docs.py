"""The docs name what conf/ holds, and the commands they show compose."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[1]
CONF = REPO / "conf"
CONFIGURATION = REPO / "docs" / "configuration.md"
USAGE = REPO / "docs" / "usage.md"


def _quoted(text: str) -> set[str]:
    """Every `...` span of a Markdown text, and each such span without a trailing slash."""
    spans = set(re.findall(r"`([^`\n]+)`", text))
    return spans | {span.rstrip("/") for span in spans}


def _groups() -> list[Path]:
    return sorted(path for path in CONF.iterdir() if path.is_dir())


def _section(text: str, title: str) -> str:
    """The text of the Markdown section headed ``title`` (up to the next heading)."""
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end != -1 else None]


@pytest.mark.parametrize("doc", [CONFIGURATION, USAGE], ids=lambda path: path.name)
def test_docs_name_every_config_group(doc: Path) -> None:
    named = _quoted(doc.read_text(encoding="utf-8"))
    missing = [group.name for group in _groups() if group.name not in named]
    assert not missing, f"{doc.name} does not name the conf groups {missing}"


def test_configuration_names_every_option_of_a_group() -> None:
    """Each option file of a group (experiment/ and hydra/ aside) is in the groups table."""
    table = _section(CONFIGURATION.read_text(encoding="utf-8"), "Config groups")
    rows = {
        match.group(1): match.group(0)
        for match in re.finditer(r"^\| `([a-z_]+)/` \|.*$", table, re.MULTILINE)
    }
    missing = []
    for group in _groups():
        if group.name in ("experiment", "hydra", "stage"):
            continue
        named = _quoted(rows.get(group.name, ""))
        missing += [f"{group.name}/{f.stem}" for f in group.glob("*.yaml") if f.stem not in named]
    assert not missing, f"the groups table of docs/configuration.md lacks {missing}"


@pytest.mark.parametrize("doc", [CONFIGURATION, USAGE], ids=lambda path: path.name)
def test_docs_name_every_stage(doc: Path) -> None:
    named = _quoted(doc.read_text(encoding="utf-8"))
    missing = [f.stem for f in sorted((CONF / "stage").glob("*.yaml")) if f.stem not in named]
    assert not missing, f"{doc.name} does not name the stages {missing}"


def test_stage_table_lists_each_stage_s_steps() -> None:
    """Each row of the stages table gives the steps of conf/stage/<name>.yaml, in order."""
    section = _section(CONFIGURATION.read_text(encoding="utf-8"), "Stages and steps")
    for path in sorted((CONF / "stage").glob("*.yaml")):
        row = re.search(rf"^\| `{path.stem}` \| ([^|]+) \|", section, re.MULTILINE)
        assert row, f"no row for stage {path.stem} in docs/configuration.md"
        documented = re.findall(r"`([a-z_]+)`", row.group(1))
        assert documented == list(OmegaConf.load(path).steps), path.stem


# Commands of docs/usage.md: the pae-data ones as written there, the pae-train ones as their
# overrides (one value per swept axis) with the values the docs say they set.
COMMANDS = [
    "pae-data convert 7scenes /data/7Scenes /data/7Scenes/labels",
    "pae-data convert cambridge /data/CambridgeLandmarks /data/CambridgeLandmarks/labels",
    "pae-data convert colmap scene/undistorted/sparse scene/undistorted/images "
    "scene/undistorted/images/labels --scale 0.37",
]
OVERRIDES = {
    "seven_scenes_default": (
        "data=seven_scenes data.root=/data/7Scenes",
        {"data.scenes": ["chess"], "data.camera.fx": 585.0},
    ),
    "cambridge_default": (
        "data=cambridge data.root=/data/CambridgeLandmarks",
        {"data.scenes": ["KingsCollege"], "data.camera.fx": 1674.84375},
    ),
    "walkthrough_teacher": (
        "stage=teacher data=seven_scenes data.root=/data/7Scenes 'data.scenes=[chess,fire]' "
        "backbone=efficientnet_b0 backbone.pretrained=true trainer=gpu "
        "hydra.run.dir=outputs/7scenes/teacher",
        {"data.scenes": ["chess", "fire"], "stage.steps": ["teacher"]},
    ),
    "walkthrough_student": (
        "stage=student data=seven_scenes data.root=/data/7Scenes 'data.scenes=[chess,fire]' "
        "trainer=gpu teacher_ckpt=outputs/7scenes/teacher/checkpoints/last.ckpt "
        "hydra.run.dir=outputs/7scenes/student",
        {"stage.steps": ["student"]},
    ),
    "walkthrough_render_compare": (
        "stage=render_compare data=seven_scenes data.root=/data/7Scenes "
        "'data.scenes=[chess,fire]' trainer=gpu "
        "teacher_ckpt=outputs/7scenes/teacher/checkpoints/last.ckpt "
        "hydra.run.dir=outputs/7scenes/render_compare",
        {
            "stage.steps": ["scene_model"],
            "scene_model.model._target_": ("pae.scene_model.voxel_grid.VoxelGridSceneModel"),
        },
    ),
    "own_scene_teacher": (
        "stage=teacher data=converted data.root=scene/undistorted/images "
        "'data.camera={fx: 1210.4, fy: 1210.4, cx: 959.5, cy: 539.5, width: 1920, height: 1080}' "
        "backbone=efficientnet_b0 backbone.pretrained=true trainer=gpu "
        "hydra.run.dir=outputs/scene/teacher",
        {
            "data.train_labels": "scene/undistorted/images/labels/all_train.csv",
            "data.camera.fx": 1210.4,
            "data.scenes": None,
            "stage.steps": ["teacher"],
        },
    ),
    "all_scenes": (
        "stage=teacher data=cambridge data.root=/data/CambridgeLandmarks data.scenes=null",
        {"data.scenes": None},
    ),
    "gpu": (
        "stage=pipeline data=seven_scenes data.root=/data/7Scenes trainer=gpu",
        {"trainer.precision": "16-mixed", "trainer.accelerator": "gpu"},
    ),
    "render_compare_torch": (
        "stage=render_compare data=seven_scenes data.root=/data/7Scenes trainer=gpu "
        "render_compare.refiner.engine=torch teacher_ckpt=T",
        {"render_compare.refiner.engine": "torch", "stage.steps": ["scene_model"]},
    ),
    "ddp": (
        "stage=pipeline data=seven_scenes data.root=/data/7Scenes trainer=ddp",
        {"trainer.strategy": "ddp", "trainer.devices": -1},
    ),
    "grid_teachers": (
        "experiment=ablation_backbone stage=teacher backbone=mobilenet_v2 "
        "hydra.sweep.dir=outputs/grid/teachers 'hydra.sweep.subdir=${backbone.name}'",
        {"hydra.sweep.subdir": "mobilenet_v2", "stage.steps": ["teacher"]},
    ),
    "grid_students": (
        "experiment=ablation_fourier_L backbone=mobilenet_v2 pae.L=3 "
        "'teacher_ckpt=outputs/grid/teachers/${backbone.name}/checkpoints/last.ckpt' "
        "hydra.sweep.dir=outputs/grid/students",
        {
            "teacher_ckpt": "outputs/grid/teachers/mobilenet_v2/checkpoints/last.ckpt",
            "pae.L": 3,
            "stage.steps": ["student"],
        },
    ),
}


@pytest.mark.parametrize("command", COMMANDS)
def test_usage_shows_the_command(command: str) -> None:
    assert command in " ".join(USAGE.read_text(encoding="utf-8").split())


@pytest.mark.parametrize("name", sorted(OVERRIDES))
def test_usage_commands_compose(name: str) -> None:
    """The overrides compose and resolve to the values the docs describe."""
    import shlex

    overrides, expected = OVERRIDES[name]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=shlex.split(overrides), return_hydra_config=True)
    HydraConfig.instance().set_config(cfg)
    for key, value in expected.items():
        found = OmegaConf.select(cfg, key)
        found = OmegaConf.to_container(found) if OmegaConf.is_config(found) else found
        assert found == value, f"{name}: {key} = {found!r}, expected {value!r}"
