"""A given data.root is read, never rendered into; a run says and records which dataset it
read, and its saved config describes that data."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from pae.config.validation import validate_train_config
from pae.core.errors import ConfigError, LabelError
from pae.core.provenance import dataset_line, flat_record, save_corrected_config
from pae.synthetic.datamodule import SyntheticDataModule
from tests.conftest import TINY


@pytest.mark.parametrize("case", ["missing", "empty", "no labels"])
def test_a_given_root_without_a_dataset_is_refused_in_one_line(
    compose_train, tmp_path: Path, case: str
) -> None:
    root = tmp_path / "mine"
    if case != "missing":
        root.mkdir()
    if case == "no labels":
        (root / "notes.txt").write_text("not a dataset")
    expected = {
        "missing": "no such directory",
        "empty": "empty folder",
        "no labels": "no label file",
    }[case]
    cfg = compose_train(f"data.root={root}")
    with pytest.raises(ConfigError, match=f"data.root={root}: {expected}") as error:
        validate_train_config(cfg)
    assert f"pae-data synth {root}" in str(error.value) and "\n" not in str(error.value)
    data = SyntheticDataModule(root=str(root), scenes=1, train_frames=2, test_frames=1, size=8)
    with pytest.raises(LabelError, match="never rendered into"):
        data.prepare_data()
    left = sorted(p.name for p in root.iterdir()) if root.exists() else None
    assert left == {"missing": None, "empty": [], "no labels": ["notes.txt"]}[case]


def test_only_the_default_root_renders_on_first_use(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.chdir(tmp_path)
    data = SyntheticDataModule(scenes=1, train_frames=4, test_frames=2, size=16)
    with caplog.at_level("INFO"):
        data.prepare_data()
    assert str(data.root).startswith("data/synthetic/scenes1_train4_test2_px16")
    assert (tmp_path / data.root / "labels" / "all_train.csv").is_file()
    progress = [r.getMessage() for r in caplog.records if "(first use)" in r.getMessage()]
    assert progress and progress[-1].endswith("elapsed")
    assert f"rendering {data.root} (first use): 6/6 frames (100 %)" in progress[-1]


def test_settings_of_a_given_root_follow_the_data_on_disk(
    compose_train, tiny_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    one_scene = tmp_path / "one"
    shutil.copytree(tiny_root, one_scene)
    for split in ("train", "test"):
        shutil.copy(
            one_scene / "labels" / f"scene00_{split}.csv", one_scene / "labels" / f"all_{split}.csv"
        )
    cfg = compose_train(f"data.root={one_scene}", "data.size=64", run_dir=tmp_path / "run")
    assert (cfg.data.scenes, cfg.data.size) == (2, 64)
    validate_train_config(cfg)
    assert (cfg.data.scenes, cfg.data.train_frames, cfg.data.test_frames) == (1, 24, 12)
    assert cfg.data.size == TINY["size"] == cfg.data.shorter_edge  # shorter_edge follows size
    note = capsys.readouterr().out
    assert "data.scenes: 2 -> 1" in note and "data.size: 64 -> 32" in note
    validate_train_config(cfg)  # checked again in the job: nothing left to correct
    assert capsys.readouterr().out == ""

    saved = tmp_path / "run" / ".hydra" / "config.yaml"
    saved.parent.mkdir(parents=True)
    stale = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    stale.data.scenes = 2
    OmegaConf.save(stale, saved)
    assert save_corrected_config(cfg, tmp_path / "run")
    assert OmegaConf.load(saved).data.scenes == 1
    assert not save_corrected_config(cfg, tmp_path / "run")


def test_the_dataset_record_names_root_scenes_frames_and_hashes(tiny_root: Path) -> None:
    data = SyntheticDataModule(root=str(tiny_root), **{k: v for k, v in TINY.items()})
    record = data.describe()
    assert record["root"] == str(tiny_root.resolve())
    assert record["scenes"] == ["scene00", "scene01"]
    train = record["splits"]["train"]
    assert train["frames"] == TINY["scenes"] * TINY["train_frames"]
    assert train["sha256"] == hashlib.sha256(Path(train["labels"]).read_bytes()).hexdigest()
    assert set(record["splits"]) == {"train", "test"}  # val reads the test file
    flat = flat_record(record)
    assert flat["data/scenes"] == "scene00,scene01"
    assert flat["data/test/frames"] == TINY["scenes"] * TINY["test_frames"]
    line = dataset_line(record)
    assert line.startswith(f"data: {tiny_root.resolve()}: 2 scenes (scene00, scene01); train 48")
    assert "labels/all_train.csv, sha256 " + train["sha256"][:12] in line
