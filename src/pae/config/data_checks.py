"""The data config's checks (``data.*``), run when a run starts, before data is rendered or
read for training: paths, the synthetic benchmark's settings against what a given root holds,
sizes, the validation hold-out and batch sizes, each failure a ConfigError naming its key."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, ListConfig, open_dict

from pae.core.checks import (
    boolean,
    existing_file,
    integer,
    is_int,
    number,
    setting,
)
from pae.core.errors import ConfigError
from pae.data.holdout import CALIBRATION_ON_TEST, validation_is_test
from pae.data.labels import read_labels

SYNTHETIC_LAYOUT_BOUNDS = {
    "test_offset_m": 1.0,
    "train_lane_m": 1.0,
    "stray_m": 1.0,
    "yaw_stray_rad": math.pi / 2,
}
"""Upper bounds of the synthetic camera layout's settings (all >= 0), as rendering checks."""
SYNTHETIC_NUISANCE_BOUNDS = {
    "lighting_change": 1.0,
    "occluder_fraction": 1.0,
    "sensor_noise_std": 0.5,
    "motion_blur_px": 64.0,
}
"""Upper bounds of the synthetic nuisances' settings (all >= 0, 0: off), as rendering checks
(``pae.synthetic.NUISANCE_BOUNDS``)."""
SYNTHETIC_SURFACE_BOUNDS = {
    "plain_surface_share": 1.0,
    "repeated_surface_share": 1.0,
    "glossy_surface_share": 1.0,
    "camera_pipeline": 1.0,
}
"""Upper bounds of the synthetic surface and camera pipeline settings (all >= 0, 0: off), as
rendering checks (``pae.synthetic.SURFACE_BOUNDS``, ``CaptureOptions``)."""


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


def _check_val_walks(cfg: DictConfig) -> None:
    """data.val_walks: a count of validation walks, held out on top of an integer
    data.val_sequences, of the benchmark's own layout (not data.poses)."""
    data = cfg.data
    if not data.get("val_walks"):
        return
    integer(cfg, "data.val_walks", 0)
    held = data.get("val_sequences")
    if not is_int(held) or data.get("val_labels") or data.get("poses"):
        raise ConfigError(
            f"data.val_walks={data.val_walks} holds its walks out on top of "
            f"data.val_sequences: set it to an integer (got {held!r}), data.val_labels and "
            f"data.poses to null"
        )


def _check_capture(cfg: DictConfig) -> None:
    """data.jpeg_quality: 0 or an integer in [1, 100]; data.render_scale: an integer in
    [1, 8] (``pae.synthetic.CaptureOptions``)."""
    data = cfg.data
    if "jpeg_quality" in data:
        integer(cfg, "data.jpeg_quality", 0)
        if data.jpeg_quality > 100:
            raise ConfigError(
                f"data.jpeg_quality must be 0 (off) or an integer in [1, 100], "
                f"got {data.jpeg_quality!r}"
            )
    if "render_scale" in data:
        integer(cfg, "data.render_scale", 1)
        if data.render_scale > 8:
            raise ConfigError(
                f"data.render_scale must be an integer in [1, 8], got {data.render_scale!r}"
            )


def _train_set_size(cfg: DictConfig) -> int:
    """Rows of the train split: from the synthetic data's settings when it renders on first
    use (it may not be rendered yet), otherwise from the train label file (its chosen
    scenes)."""
    data = cfg.data
    if _is_synthetic(cfg):
        bounds = {
            **SYNTHETIC_LAYOUT_BOUNDS,
            **SYNTHETIC_NUISANCE_BOUNDS,
            **SYNTHETIC_SURFACE_BOUNDS,
        }
        for key, high in bounds.items():
            if key in data:
                number(cfg, f"data.{key}", 0, strict=False)
                if data[key] > high:
                    raise ConfigError(f"data.{key} must be <= {high:g}, got {data[key]!r}")
        shares = [data.get(key, 0) for key in ("plain_surface_share", "repeated_surface_share")]
        if sum(shares) > 1:
            raise ConfigError(
                "data.plain_surface_share + data.repeated_surface_share must be <= 1, got "
                f"{shares[0]:g} + {shares[1]:g}"
            )
        _check_capture(cfg)
        val_lane, lane = data.get("val_lane_m"), data.get("train_lane_m", 0.5)
        if val_lane is not None and not (
            (is_int(val_lane) or isinstance(val_lane, float)) and abs(val_lane) <= lane
        ):
            raise ConfigError(
                f"data.val_lane_m must be null or a number no farther from 0 than "
                f"data.train_lane_m={lane:g}, got {val_lane!r}"
            )
        if data.get("poses") and val_lane is not None:
            raise ConfigError("data.poses renders the given rows: set data.val_lane_m to null")
        _check_val_walks(cfg)
    if _renders(cfg):
        integer(cfg, "data.scenes", 1)
        integer(cfg, "data.train_frames", 1)
        integer(cfg, "data.test_frames", 1)
        integer(cfg, "data.size", 8)
        integer(cfg, "data.render_seed", 0)
        return data.scenes * data.train_frames
    _check_root(cfg)
    table = read_labels(_label_files(cfg)["train"])
    if _is_synthetic(cfg):
        match_synthetic_settings(cfg)
        return len(table)
    scenes = data.get("scenes")
    if scenes is not None and not (
        isinstance(scenes, ListConfig) and scenes and all(isinstance(s, str) for s in scenes)
    ):
        raise ConfigError(f"data.scenes must be null or a list of scene names, got {scenes!r}")
    if scenes is None:
        return len(table)
    missing = [scene for scene in scenes if scene not in table.scene_names]
    if missing:
        raise ConfigError(
            f"data.scenes={list(scenes)}: no rows of {', '.join(missing)} in "
            f"data.train_labels={data.train_labels}, which has the scenes {table.scene_names}"
        )
    return int(np.isin(np.asarray(table.scene), list(scenes)).sum())


def _validate_holdout(cfg: DictConfig) -> None:
    """data.val_sequences: null, an integer >= 1 or a list of sequence names;
    data.val_fraction: null or a number in (0, 1)."""
    sequences = setting(cfg, "data.val_sequences")
    names = isinstance(sequences, ListConfig) and all(isinstance(s, str) for s in sequences)
    names = names and len(sequences) > 0
    if not (sequences is None or (is_int(sequences) and sequences >= 1) or names):
        raise ConfigError(
            "data.val_sequences must be null, an integer >= 1 (the last n train sequences of "
            f"each scene) or a list of sequence names, got {sequences!r}"
        )
    fraction = setting(cfg, "data.val_fraction")
    if fraction is not None and not (
        isinstance(fraction, int | float) and not isinstance(fraction, bool) and 0 < fraction < 1
    ):
        raise ConfigError(f"data.val_fraction must be null or a number in (0, 1), got {fraction!r}")


def validate_data(cfg: DictConfig, train: bool = True) -> None:
    """data.*: paths (a given data.root holds label files; synthetic data read from one
    gets the settings of what it holds), sizes, batch sizes (train: at most the train set),
    workers."""
    n_train = _train_set_size(cfg)
    crop = integer(cfg, "data.crop", 1)
    shorter_edge = integer(cfg, "data.shorter_edge", 1)
    if crop > shorter_edge:
        raise ConfigError(
            f"data.crop={crop} is larger than data.shorter_edge={shorter_edge} (the images' "
            "shorter edge after resizing)"
        )
    integer(cfg, "data.eval_batch_size", 1)
    integer(cfg, "data.num_workers", 0)
    for key in ("augment", "cache_images", "balance_scenes", "crop_turns_camera"):
        boolean(cfg, f"data.{key}")
    _validate_holdout(cfg)
    batch_size = integer(cfg, "data.batch_size", 1)
    if train and batch_size > n_train:
        raise ConfigError(
            f"data.batch_size={batch_size} is larger than the train set ({n_train} rows): "
            "training would get no full batch"
        )


def check_calibration_held_out(cfg: DictConfig) -> None:
    """A run whose render-and-compare calibrates on the validation split (its
    ``render_compare`` group set) holds one out of the train labels: ConfigError
    (CALIBRATION_ON_TEST) where the validation split is the test split."""
    if setting(cfg, "render_compare") is None:
        return
    test = None if _renders(cfg) else _label_files(cfg)["test"]
    if validation_is_test(
        setting(cfg, "data.val_sequences"), setting(cfg, "data.val_labels"), test
    ):
        raise ConfigError(CALIBRATION_ON_TEST)
