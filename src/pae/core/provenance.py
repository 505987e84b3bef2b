"""What a run read and with which settings: the dataset (one printed line,
`<run>/.hydra/data.yaml` and the `data/...` keys of metrics.json) and the run's saved config,
kept equal to the settings the run used."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pae.core.atomic import write_text_atomic

DATA_RECORD = "data.yaml"
"""The dataset record's file name in a run's `.hydra/` folder."""


def _shown_path(path: str, root: str) -> str:
    """`path` relative to `root` when it lies below it."""
    try:
        return str(Path(path).relative_to(root))
    except ValueError:
        return path


def dataset_line(record: dict[str, Any]) -> str:
    """``data: ROOT: 2 scenes (a, b); train 3200 frames (labels/all_train.csv, sha256
    1a2b3c4d5e6f), test ...`` for a record of ``PoseDataModule.describe``."""
    scenes = record["scenes"]
    splits = ", ".join(
        f"{split} {info['frames']} frames ({_shown_path(info['labels'], record['root'])}, "
        f"sha256 {info['sha256'][:12]})"
        for split, info in record["splits"].items()
    )
    noun = "scene" if len(scenes) == 1 else "scenes"
    return f"data: {record['root']}: {len(scenes)} {noun} ({', '.join(scenes)}); {splits}"


def flat_record(record: dict[str, Any]) -> dict[str, str | int]:
    """The record as metrics.json keys: `data/root`, `data/scenes` (comma-separated),
    `data/{split}/labels`, `data/{split}/frames`, `data/{split}/labels_sha256`."""
    flat: dict[str, str | int] = {
        "data/root": record["root"],
        "data/scenes": ",".join(record["scenes"]),
    }
    for split, info in record["splits"].items():
        flat[f"data/{split}/labels"] = info["labels"]
        flat[f"data/{split}/frames"] = info["frames"]
        flat[f"data/{split}/labels_sha256"] = info["sha256"]
    return flat


def save_record(record: dict[str, Any], run_dir: Path) -> None:
    """Write the record to `run_dir/.hydra/data.yaml`, atomically."""
    write_text_atomic(run_dir / ".hydra" / DATA_RECORD, OmegaConf.to_yaml(record))


def save_corrected_config(cfg: DictConfig, run_dir: Path) -> bool:
    """Rewrite `run_dir/.hydra/config.yaml` when it differs from the settings the run uses
    (the start-up checks correct some, e.g. a given data.root's scene and frame counts);
    -> whether it was rewritten. Runs without a saved config are left alone."""
    saved = run_dir / ".hydra" / "config.yaml"
    if not saved.is_file():
        return False
    used = OmegaConf.masked_copy(cfg, [key for key in cfg if key != "hydra"])
    if OmegaConf.to_container(OmegaConf.load(saved)) == OmegaConf.to_container(used):
        return False
    write_text_atomic(saved, OmegaConf.to_yaml(used))
    return True
