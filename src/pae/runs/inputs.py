"""What a step reads: the configured data, and the checkpoints it needs, checked to have been
trained on that data."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from hydra.utils import instantiate
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig

from pae.checkpoints import CheckpointError, LoadedModel
from pae.console import say
from pae.data.datamodule import PoseDataModule
from pae.errors import ConfigError
from pae.provenance import dataset_line, flat_record, save_record


def build_data(cfg: DictConfig, **overrides: Any) -> PoseDataModule:
    """Instantiate and set up the configured data module (renders synthetic data if needed)."""
    data = instantiate(cfg.data, **overrides)
    data.setup()
    return data


def record_dataset(cfg: DictConfig, run_dir: Path) -> dict[str, str | int]:
    """Prepare the configured data (the default synthetic benchmark renders on first use),
    print which dataset the run reads and record it in `run_dir/.hydra/data.yaml` -> its
    `data/...` keys for metrics.json (pae.provenance)."""
    data = instantiate(cfg.data)
    data.prepare_data()
    record = data.describe()
    if rank_zero_only.rank == 0:
        say(dataset_line(record))
        save_record(record, run_dir)
    return flat_record(record)


def required(path: str | Path | None, key: str, stage: str) -> str | Path:
    """The checkpoint ``path`` a step (``stage``) needs as ``key``; a ConfigError when none is
    given."""
    if path is None:
        raise ConfigError(f"stage={stage} needs {key}=PATH")
    return path


def load_frozen(
    cfg: DictConfig,
    path: str | Path | None,
    key: str,
    stage: str,
    load: Callable[[str | Path, str], LoadedModel],
) -> tuple[str | Path, LoadedModel, PoseDataModule]:
    """The checkpoint a step needs (`key`), its model and the step's data (no augmentation),
    checked to belong together."""
    path = required(path, key, stage)
    loaded = load(path, key)
    data = build_data(cfg, augment=False)
    check_data(cfg, path, loaded, data)
    return path, loaded, data


def check_fingerprint(
    cfg: DictConfig, path: str | Path, trained: dict[str, Any], data: dict[str, Any]
) -> None:
    """A checkpoint trained on other data (scene names, or train poses when it records them)
    is an error unless allow_other_data=true."""
    if cfg.get("allow_other_data"):
        return
    if trained["scenes"] != data["scenes"]:
        raise CheckpointError(
            f"{path}: trained on scenes {trained['scenes']}, but the data has scenes "
            f"{data['scenes']} (allow_other_data=true uses it anyway)"
        )
    if trained.get("train_poses_sha256", data["train_poses_sha256"]) != data["train_poses_sha256"]:
        raise CheckpointError(
            f"{path}: trained on other train poses than those of {data['scenes']} in this "
            "data's train labels (allow_other_data=true uses it anyway)"
        )


def check_data(
    cfg: DictConfig, path: str | Path, loaded: LoadedModel, data: PoseDataModule
) -> None:
    """The checkpoint was trained on this data, and its models fit this data's scene count."""
    if len(loaded.scene_names) != data.n_scenes:
        raise CheckpointError(
            f"{path}: trained on scenes {loaded.scene_names}, but the data has scenes "
            f"{data.scene_names}"
        )
    trained = loaded.data_fingerprint or {"scenes": loaded.scene_names}
    check_fingerprint(cfg, path, trained, data.fingerprint())
