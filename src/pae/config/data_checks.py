"""The data config's checks (``data.*``), run when a run starts, before data is rendered or
read for training: paths, the synthetic benchmark's settings against what a given root holds,
sizes, the validation hold-out and batch sizes, each failure a ConfigError naming its key."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, open_dict

from pae.core.checks import check_record, existing_file, setting
from pae.core.errors import ConfigError
from pae.core.ranges import is_int
from pae.data.holdout import CALIBRATION_ON_TEST, validation_is_test
from pae.data.labels import read_labels
from pae.data.settings import PoseDataSettings
from pae.synthetic.settings import SyntheticSettings


def _is_synthetic(cfg: DictConfig) -> bool:
    return "train_frames" in cfg.data


def _renders(cfg: DictConfig) -> bool:
    """The synthetic benchmark without a data.root: rendered under data/synthetic/ on first
    use. A given data.root is only read."""
    return _is_synthetic(cfg) and cfg.data.get("root") is None


def _label_files(cfg: DictConfig) -> dict[str, Any]:
    """split -> the label file a run reads (synthetic data: ROOT/labels/all_{split}.csv)."""
    data = cfg.data
    if _is_synthetic(cfg):
        labels = Path(str(data.root)) / "labels"
        return {split: labels / f"all_{split}.csv" for split in ("train", "test")}
    return {split: data.get(f"{split}_labels") for split in ("train", "test", "val")}


def _check_root(cfg: DictConfig) -> None:
    """data.root is a folder that holds the label files; else one line naming it (synthetic
    data: and how to render a dataset there)."""
    root = Path(str(cfg.data.root))
    hint = ""
    if _is_synthetic(cfg):
        hint = (
            f"; `pae-data synth {root}` renders a dataset there (without data.root the "
            "default benchmark renders under data/synthetic/)"
        )
    if not root.is_dir():
        raise ConfigError(f"data.root={root}: no such directory{hint}")
    if not any(root.iterdir()):
        raise ConfigError(f"data.root={root}: empty folder{hint}")
    if _is_synthetic(cfg):
        for path in _label_files(cfg).values():
            if not path.is_file():
                raise ConfigError(f"data.root={root}: no label file {path}{hint}")
    else:
        from pae.data.raw import raw_download

        raw = raw_download(root)
        for key in ("train_labels", "test_labels", "val_labels"):
            value = setting(cfg, f"data.{key}")
            if raw and value is not None and not Path(str(value)).is_file():
                raise ConfigError(
                    f"data.{key}={value}: no such file; {root} holds a raw {raw[0]} download: "
                    f"`pae-data convert {raw[1]} {root} {root}/labels` writes its label files"
                )
            existing_file(cfg, f"data.{key}")


def _per_scene(table: Any) -> int | None:
    """Rows per scene of a label table, None when the scenes' counts differ."""
    counts = set(np.unique(np.asarray(table.scene), return_counts=True)[1].tolist())
    return counts.pop() if len(counts) == 1 else None


def match_synthetic_settings(cfg: DictConfig) -> list[str]:
    """Synthetic data read from a given data.root: set data.scenes, data.train_frames,
    data.test_frames (per scene; null where the scenes' counts differ) and data.size (the
    images' shorter side) to what the folder holds, so that the run's config and its saved
    copy describe the data it reads; -> the corrections, as `key: old -> new`."""
    from pae.data.transforms import image_size

    files = _label_files(cfg)
    train, test = read_labels(files["train"]), read_labels(files["test"])
    first_image = Path(str(cfg.data.root)) / train.img_path[0]
    on_disk = {
        "scenes": len(train.scene_names),
        "train_frames": _per_scene(train),
        "test_frames": _per_scene(test),
        "size": min(image_size(str(first_image))),
    }
    corrections = []
    with open_dict(cfg):
        for key, value in on_disk.items():
            if cfg.data.get(key) != value:
                corrections.append(f"data.{key}: {cfg.data.get(key)} -> {value}")
                cfg.data[key] = value
    if corrections:
        print(
            f"data: data.root={cfg.data.root} holds other data than the settings say; the "
            f"run's config now describes it ({', '.join(corrections)})"
        )
    return corrections


def _synthetic_settings(cfg: DictConfig) -> SyntheticSettings:
    """data.* of the synthetic benchmark as its record (its ranges; counts a given data.root
    only describes may be null), then what ``data.poses`` (the given rows, no layout of its
    own) and ``data.val_walks`` need: a ConfigError naming the key."""
    data, counts = cfg.data, ("scenes", "train_frames", "test_frames")
    unset = [] if _renders(cfg) else [name for name in counts if data.get(name) is None]
    described = {name: getattr(SyntheticSettings, name) for name in unset}
    renamed = {"seed": "render_seed"}
    settings = check_record(cfg, "data", SyntheticSettings, renamed, **described)
    if data.get("poses") and data.get("val_lane_m") is not None:
        raise ConfigError("data.poses renders the given rows: set data.val_lane_m to null")
    held = data.get("val_sequences")
    if settings.val_walks and (not is_int(held) or data.get("val_labels") or data.get("poses")):
        raise ConfigError(
            f"data.val_walks={settings.val_walks} holds its walks out on top of "
            f"data.val_sequences: set it to an integer (got {held!r}), data.val_labels and "
            f"data.poses to null"
        )
    return settings


def _train_set_size(cfg: DictConfig) -> int:
    """Rows of the train split: from the synthetic data's settings when it renders on first
    use (it may not be rendered yet), otherwise from the train label file (its chosen
    scenes)."""
    data = cfg.data
    if _renders(cfg):
        settings = _synthetic_settings(cfg)
        return settings.scenes * settings.train_frames
    if _is_synthetic(cfg):
        _synthetic_settings(cfg)
    _check_root(cfg)
    table = read_labels(_label_files(cfg)["train"])
    if _is_synthetic(cfg):
        match_synthetic_settings(cfg)
        return len(table)
    scenes = data.get("scenes")
    if scenes is None:
        return len(table)
    missing = [scene for scene in scenes if scene not in table.scene_names]
    if missing:
        raise ConfigError(
            f"data.scenes={list(scenes)}: no rows of {', '.join(missing)} in "
            f"data.train_labels={data.train_labels}, which has the scenes {table.scene_names}"
        )
    return int(np.isin(np.asarray(table.scene), list(scenes)).sum())


def validate_data(cfg: DictConfig, train: bool = True) -> None:
    """data.*: paths (a given data.root holds label files; synthetic data read from one
    gets the settings of what it holds), the loaders' record, the crop and batch sizes."""
    n_train = _train_set_size(cfg)
    scenes = {"scenes": None} if _is_synthetic(cfg) else {}
    loading = check_record(cfg, "data", PoseDataSettings, **scenes)
    if loading.crop > loading.shorter_edge:
        raise ConfigError(
            f"data.crop={loading.crop} is larger than the images' shorter edge after resizing "
            f"(data.shorter_edge={loading.shorter_edge})"
        )
    if train and loading.batch_size > n_train:
        raise ConfigError(
            f"data.batch_size={loading.batch_size} is larger than the train set ({n_train} "
            "rows): training would get no full batch"
        )


def check_calibration_held_out(cfg: DictConfig) -> None:
    """A run whose render-and-compare calibrates on the validation split (its
    ``render_compare`` group set) holds one out of the train labels: ConfigError
    (CALIBRATION_ON_TEST) where the validation split is the test split."""
    if setting(cfg, "render_compare") is None:
        return
    held = setting(cfg, "data.val_sequences"), setting(cfg, "data.val_labels")
    if validation_is_test(*held, None if _renders(cfg) else _label_files(cfg)["test"]):
        raise ConfigError(CALIBRATION_ON_TEST)
