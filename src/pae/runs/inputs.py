"""What a step reads: the configured data, and the checkpoints it needs, checked to have been
trained on that data."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from hydra.utils import instantiate
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, OmegaConf

from pae.core.checkpoints import CheckpointError, LoadedModel, load_scene_model
from pae.core.console import say
from pae.core.errors import ConfigError
from pae.core.provenance import dataset_line, flat_record, save_record
from pae.core.run_context import current_run
from pae.data.datamodule import PoseDataModule
from pae.scene_model.base import SceneModel
from pae.scene_model.novel_views import NovelViewSettings


def build_data(cfg: DictConfig, **overrides: Any) -> PoseDataModule:
    """Instantiate and set up the configured data module (renders synthetic data if needed);
    its train order is drawn from the run's ``seed``."""
    data = instantiate(cfg.data, order_seed=cfg.get("seed", 0), **overrides)
    data.setup()
    return data


def record_dataset(cfg: DictConfig, run_dir: Path) -> dict[str, str | int]:
    """Prepare the configured data (the default synthetic benchmark renders on first use),
    print which dataset the run reads and record it in `run_dir/.hydra/data.yaml` -> its
    `data/...` keys for metrics.json (pae.core.provenance)."""
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


SAMPLED_IMAGES_KEY = "train_images_sha256"
"""The fingerprint entry of older checkpoints: a hash of 4 KiB of each train image."""
IDENTITY = (
    ("scenes", "scenes"),
    ("train_poses_sha256", "train poses"),
    ("train_images_blake2b", "train images"),
    (SAMPLED_IMAGES_KEY, "train images"),
)
"""The entries of a data fingerprint (PoseDataModule.fingerprint, and the sampled hash of older
checkpoints) and what each names."""


def other_data_record(cfg: DictConfig) -> dict[str, int]:
    """With allow_other_data=true, ``data/other_data_checkpoints``: how many checkpoints the
    run read were trained on other data than its own (0: none); no key otherwise."""
    if not cfg.get("allow_other_data"):
        return {}
    return {"data/other_data_checkpoints": len(current_run().other_data)}


def check_fingerprint(
    cfg: DictConfig, path: str | Path, trained: dict[str, Any], data: Any
) -> None:
    """A checkpoint trained on other data than ``data`` (a data module: its scene names, train
    poses and train images, those the checkpoint records) is an error naming the checkpoint and
    the data root, unless allow_other_data=true: then a warning line says so and
    other_data_record counts it. A checkpoint that records only the older, sampled hash of its
    train images is checked by that hash, with a warning line; one that records no train images
    (written before pae did) is used with a warning line."""
    current, root = data.fingerprint(), data.root.resolve()
    sampled_only = SAMPLED_IMAGES_KEY in trained and "train_images_blake2b" not in trained
    if sampled_only:
        current[SAMPLED_IMAGES_KEY] = data.sampled_images_sha256()
    differs = [
        name
        for key, name in IDENTITY
        if key in trained and key in current and trained[key] != current[key]
    ]
    if differs:
        if differs[0] == "scenes":
            what = f"scenes {trained['scenes']}, but the data at {root} has {current['scenes']}"
        else:
            what = f"other {' and '.join(differs)} than those of the data at {root}"
        if not cfg.get("allow_other_data"):
            raise CheckpointError(
                f"{path}: trained on {what} (allow_other_data=true uses it anyway)"
            )
        other_data = current_run().other_data
        if str(path) not in other_data:
            other_data[str(path)] = what
            say(f"data: warning: allow_other_data=true: {path} was trained on {what}; used anyway")
    if sampled_only and current_run().first_time(f"sampled train images fingerprint {path}"):
        say(
            f"data: warning: {path} records an older fingerprint of its train images (4 KiB of "
            "each file): its images are checked by that sample only, an edit elsewhere is not seen"
        )
    unchecked = not any(key in trained for key, name in IDENTITY if name == "train images")
    if unchecked and current_run().first_time(f"no train images fingerprint {path}"):
        say(
            f"data: warning: {path} records no fingerprint of its train images (written before pae "
            f"recorded one): its images are not checked against those of the data at {root}"
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
    check_fingerprint(cfg, path, trained, data)


def novel_view_source(
    cfg: DictConfig, data: PoseDataModule, scene_model_ckpt: str | Path | None, stage: str
) -> tuple[SceneModel, NovelViewSettings]:
    """What renders a step's novel views: the scene model of ``scene_model_ckpt`` (needed by
    ``stage``; checked to have been fitted to ``data``) and ``teacher.novel_views``' settings."""
    path = required(scene_model_ckpt, "scene_model_ckpt", stage)
    loaded = load_scene_model(path, "scene_model_ckpt")
    check_data(cfg, path, loaded, data)
    settings = OmegaConf.to_container(cfg.teacher.novel_views, resolve=True)
    settings.pop("enabled")
    if "between_share" in settings:
        settings["between_share"] = tuple(settings["between_share"])
    return loaded.model, NovelViewSettings(**settings)
