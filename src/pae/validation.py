"""Every configured value checked when a run starts, before data is rendered or read for
training: types, ranges and paths, each failure a ConfigError naming its key."""

from __future__ import annotations

import inspect
import math
import sys
import typing
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

from pae.data.labels import read_labels
from pae.errors import ConfigError
from pae.steps import CHECKPOINTS, GROUPS, MODELS, missing_checkpoints, steps_of

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
(``pae.data.synthetic.NUISANCE_BOUNDS``)."""

RENAMED_KEYS = {"pae_ckpt": "student_ckpt"}
"""Old key -> its new name. The old key is still read for one more release, with a one-line
deprecation warning."""
_WARNED: set[str] = set()


def apply_renamed_keys(cfg: DictConfig, program: str | None = None) -> None:
    """Move a value given under an old key (RENAMED_KEYS) to its new name; with `program`,
    say once per process that the old name is deprecated. Both names with different values
    are a ConfigError."""
    for old, new in RENAMED_KEYS.items():
        value = OmegaConf.select(cfg, old, default=None, throw_on_missing=False)
        if value is None:
            continue
        current = OmegaConf.select(cfg, new, default=None, throw_on_missing=False)
        if current is not None and current != value:
            raise ConfigError(f"{old}={value} and {new}={current}: {old} is the old name of {new}")
        with open_dict(cfg):
            cfg[new], cfg[old] = value, None
        if program is not None and old not in _WARNED:
            _WARNED.add(old)
            print(
                f"{program}: warning: {old} is deprecated, use {new} (the old name is read "
                "for one more release)",
                file=sys.stderr,
            )


def _value(cfg: DictConfig, key: str) -> Any:
    return OmegaConf.select(cfg, key, default=None)


def _present(cfg: DictConfig, key: str) -> bool:
    """Whether the config has ``key`` (dotted), whatever its value."""
    parent, _, name = key.rpartition(".")
    node = _value(cfg, parent) if parent else cfg
    return isinstance(node, DictConfig) and name in node


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _integer(cfg: DictConfig, key: str, low: int) -> int:
    value = _value(cfg, key)
    if not _is_int(value) or value < low:
        raise ConfigError(f"{key} must be an integer >= {low}, got {value!r}")
    return value


def _number(cfg: DictConfig, key: str, low: float, strict: bool, optional: bool = False) -> None:
    value = _value(cfg, key)
    if value is None and optional:
        return
    number = _is_int(value) or isinstance(value, float)
    if not number or value != value or (value <= low if strict else value < low):
        bound = f"> {low:g}" if strict else f">= {low:g}"
        raise ConfigError(f"{key} must be a number {bound}, got {value!r}")


def _boolean(cfg: DictConfig, key: str) -> None:
    value = _value(cfg, key)
    if not isinstance(value, bool):
        raise ConfigError(f"{key} must be true or false, got {value!r}")


def _choice(cfg: DictConfig, key: str, choices: tuple[str, ...]) -> None:
    value = _value(cfg, key)
    if value not in choices:
        raise ConfigError(f"unknown {key} {value!r}; choose one of {list(choices)}")


def _file(cfg: DictConfig, key: str) -> None:
    value = _value(cfg, key)
    if value is not None and not Path(str(value)).is_file():
        raise ConfigError(f"{key}={value}: no such file")


INSTANTIATE_KEYS = ("_target_", "_partial_", "_recursive_", "_convert_", "_args_")
"""Keys of a model config that Hydra reads itself, not constructor arguments."""
_ANNOTATED_TYPES = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}


def _constructor_types(target: Any) -> dict[str, Any]:
    """The constructor's annotated argument types (empty where they cannot be resolved)."""
    try:
        return typing.get_type_hints(target.__init__ if inspect.isclass(target) else target)
    except Exception:  # annotations naming what the module does not import: unchecked
        return {}


def _matches(value: Any, annotation: Any) -> bool:
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return _is_int(value)
    if annotation is float:
        return _is_int(value) or isinstance(value, float)
    return isinstance(value, str)


def check_constructor(cfg: DictConfig, key: str, supplied: tuple[str, ...] = ()) -> None:
    """The model config at ``key`` (with ``_target_``) fits its class's constructor: every key
    is an argument of it, every argument without a default is given (or in ``supplied``, the
    ones its step fills in), values annotated as a plain int, float, bool or str are one; the
    same for nested model configs (a backbone). A ConfigError naming the key otherwise."""
    node = _value(cfg, key)
    if not isinstance(node, DictConfig) or "_target_" not in node:
        raise ConfigError(f"{key}: no model configured (a group with a _target_ class)")
    target_name = node["_target_"]
    try:
        from hydra.utils import get_object

        target = get_object(target_name)
        parameters = inspect.signature(target).parameters
    except Exception as err:
        line = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise ConfigError(f"{key}._target_={target_name}: cannot be loaded ({line})") from None
    named = [
        name
        for name, p in parameters.items()
        if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
    ]
    any_keyword = any(p.kind == p.VAR_KEYWORD for p in parameters.values())
    types = _constructor_types(target)
    for name in node:
        if name in INSTANTIATE_KEYS:
            continue
        if name not in named and not any_keyword:
            raise ConfigError(
                f"{key}.{name}: not an argument of {target_name} (it takes {', '.join(named)})"
            )
        value = _value(cfg, f"{key}.{name}")
        annotation = types.get(name)
        if annotation in _ANNOTATED_TYPES and not _matches(value, annotation):
            raise ConfigError(f"{key}.{name} must be {_ANNOTATED_TYPES[annotation]}, got {value!r}")
        if isinstance(value, DictConfig) and "_target_" in value:
            check_constructor(cfg, f"{key}.{name}")
    for name in named:
        p = parameters[name]
        if p.default is p.empty and name not in node and name not in supplied:
            raise ConfigError(f"{key}.{name}: required by {target_name}, not set")


def validate_models(cfg: DictConfig) -> None:
    """The ranges a constructor's signature cannot state (for the keys the config has), then
    every model config a step builds (``pae.steps.MODELS``) against its class's constructor."""
    for key, low in (("teacher.model.latent_dim", 1), ("pae.latent_dim", 1), ("pae.L", 0)):
        if _present(cfg, key):
            _integer(cfg, key, low)
    if _present(cfg, "pae.hidden"):
        hidden = _value(cfg, "pae.hidden")
        if not isinstance(hidden, ListConfig) or not all(_is_int(h) and h >= 1 for h in hidden):
            raise ConfigError(f"pae.hidden must be a list of layer widths >= 1, got {hidden!r}")
    for key, supplied in MODELS.items():
        check_constructor(cfg, key, supplied)


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
        for key in ("train_labels", "test_labels", "val_labels"):
            _file(cfg, f"data.{key}")


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


def _train_set_size(cfg: DictConfig) -> int:
    """Rows of the train split: from the synthetic data's settings when it renders on first
    use (it may not be rendered yet), otherwise from the train label file (its chosen
    scenes)."""
    data = cfg.data
    if _is_synthetic(cfg):
        for key, high in {**SYNTHETIC_LAYOUT_BOUNDS, **SYNTHETIC_NUISANCE_BOUNDS}.items():
            if key in data:
                _number(cfg, f"data.{key}", 0, strict=False)
                if data[key] > high:
                    raise ConfigError(f"data.{key} must be <= {high:g}, got {data[key]!r}")
        on = [f"data.{key}" for key in SYNTHETIC_NUISANCE_BOUNDS if data.get(key)]
        if data.get("poses") and on:
            raise ConfigError(
                f"data.poses renders the given rows without nuisances: set {', '.join(on)} to 0"
            )
    if _renders(cfg):
        _integer(cfg, "data.scenes", 1)
        _integer(cfg, "data.train_frames", 1)
        _integer(cfg, "data.test_frames", 1)
        _integer(cfg, "data.size", 8)
        _integer(cfg, "data.render_seed", 0)
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
    sequences = _value(cfg, "data.val_sequences")
    names = isinstance(sequences, ListConfig) and all(isinstance(s, str) for s in sequences)
    names = names and len(sequences) > 0
    if not (sequences is None or (_is_int(sequences) and sequences >= 1) or names):
        raise ConfigError(
            "data.val_sequences must be null, an integer >= 1 (the last n train sequences of "
            f"each scene) or a list of sequence names, got {sequences!r}"
        )
    fraction = _value(cfg, "data.val_fraction")
    if fraction is not None and not (
        isinstance(fraction, int | float) and not isinstance(fraction, bool) and 0 < fraction < 1
    ):
        raise ConfigError(f"data.val_fraction must be null or a number in (0, 1), got {fraction!r}")


def validate_data(cfg: DictConfig, train: bool = True) -> None:
    """data.*: paths (a given data.root holds label files; synthetic data read from one
    gets the settings of what it holds), sizes, batch sizes (train: at most the train set),
    workers."""
    n_train = _train_set_size(cfg)
    crop = _integer(cfg, "data.crop", 1)
    shorter_edge = _integer(cfg, "data.shorter_edge", 1)
    if crop > shorter_edge:
        raise ConfigError(
            f"data.crop={crop} is larger than data.shorter_edge={shorter_edge} (the images' "
            "shorter edge after resizing)"
        )
    _integer(cfg, "data.eval_batch_size", 1)
    _integer(cfg, "data.num_workers", 0)
    for key in ("augment", "cache_images", "balance_scenes"):
        _boolean(cfg, f"data.{key}")
    _validate_holdout(cfg)
    batch_size = _integer(cfg, "data.batch_size", 1)
    if train and batch_size > n_train:
        raise ConfigError(
            f"data.batch_size={batch_size} is larger than the train set ({n_train} rows): "
            "training would get no full batch"
        )


def validate_refine(cfg: DictConfig) -> None:
    """refine.*: ranges here (for the keys the configured refinement has); the choices
    (weight model, orientation, distance) are checked by building its callback."""
    refine = cfg.get("refine")
    if not refine:
        return
    for key, low in (("k", 1), ("iterations", 0), ("every_n_val_epochs", 1)):
        if key in refine:
            _integer(cfg, f"refine.{key}", low)
    if "lr" in refine:
        _number(cfg, "refine.lr", 0, strict=True)
    if "rot_weight" in refine:
        _number(cfg, "refine.rot_weight", 0, strict=False)
    if "guess_sigma_m" in refine:
        _number(cfg, "refine.guess_sigma_m", 0, strict=False, optional=True)
    from pae.runs.trainer import refinement_callbacks

    refinement_callbacks(cfg)


def _validate_common(cfg: DictConfig) -> None:
    _integer(cfg, "seed", 0)
    _boolean(cfg, "allow_other_data")
    if "check_val_every_n_epoch" in cfg.trainer:
        _integer(cfg, "trainer.check_val_every_n_epoch", 1)
    validate_refine(cfg)


ADDED_KEY_GROUPS = GROUPS
"""The steps' groups, whose settings are exactly their YAML's: a key added to one with ``+``
is a typo, unless it lies in a model config (those are checked against their
constructors)."""


def check_added_keys(cfg: DictConfig, overrides: list[str]) -> None:
    """Command-line overrides that add a key (``+group.key=value``) to a group of
    ``ADDED_KEY_GROUPS`` outside its model configs (a node with ``_target_``): pae reads no
    such setting, so it is refused, naming the key and the group's nearest setting."""
    import difflib

    for override in overrides:
        if not override.startswith("+") or override.startswith("++") or "=" not in override:
            continue
        key = override[1:].split("=", 1)[0]
        parts = key.split(".")
        if parts[0] not in ADDED_KEY_GROUPS or len(parts) < 2:
            continue
        node: Any = cfg
        inside_model = False
        for part in parts[:-1]:
            node = node.get(part) if isinstance(node, DictConfig) else None
            if isinstance(node, DictConfig) and "_target_" in node:
                inside_model = True
        if inside_model or not isinstance(node, DictConfig):
            continue
        known = [name for name in node if name != parts[-1]]
        near = difflib.get_close_matches(parts[-1], known, n=1)
        hint = f"; did you mean {'.'.join([*parts[:-1], near[0]])}?" if near else ""
        raise ConfigError(f"{key}: not a setting of {'.'.join(parts[:-1])} (added with +){hint}")


def validate_train_config(cfg: DictConfig, overrides: list[str] | None = None) -> None:
    """All of pae-train's settings (conf/train.yaml), and the keys ``overrides`` (the command
    line's) add; raises ConfigError naming the key."""
    from pae.losses import LATENT_LOSSES

    check_added_keys(cfg, overrides or [])
    steps = list(cfg.stage.steps)
    try:
        steps_of(steps)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    validate_models(cfg)
    _validate_common(cfg)
    _boolean(cfg, "resume")
    for group in GROUPS:
        _integer(cfg, f"{group}.max_epochs", 0)
        _number(cfg, f"{group}.optimizer.lr", 0, strict=True)
        _number(cfg, f"{group}.optimizer.weight_decay", 0, strict=False, optional=True)
    _number(cfg, "teacher.scene_loss_weight", 0, strict=False)
    _choice(cfg, "student.input", ("gt", "teacher"))
    _choice(cfg, "student.latent_loss", LATENT_LOSSES)
    _boolean(cfg, "student.cache_latents")
    _integer(cfg, "rpr.pair_k", 1)
    _integer(cfg, "iapr.iterations", 1)
    _number(cfg, "iapr.start.position_m", 0, strict=False)
    _number(cfg, "iapr.start.orientation_deg", 0, strict=False)
    _boolean(cfg, "iapr.refine_orientation")
    _choice(cfg, "iapr.init_backbone", ("teacher", None))
    _choice(cfg, "rpr.init_backbone", ("teacher", None))
    if _value(cfg, "rpr.pair_offset") is not None:
        _number(cfg, "rpr.pair_offset.position_m", 0, strict=False)
        _number(cfg, "rpr.pair_offset.orientation_deg", 0, strict=False)
    _boolean(cfg, "backbone.pretrained")
    _file(cfg, "backbone.weights_path")
    for key in CHECKPOINTS:
        _file(cfg, key)
    _validate_scene_model(cfg)
    missing = missing_checkpoints(steps, {key: _value(cfg, key) for key in CHECKPOINTS})
    if missing:
        raise ConfigError(f"stage={cfg.stage.name} needs {missing[0][1]}=PATH")
    validate_data(cfg, train=True)


def _validate_scene_model(cfg: DictConfig) -> None:
    """scene_model.* and render_compare.refiner.*: ranges; names and options are checked
    when the step builds them."""
    if _value(cfg, "scene_model") is None:
        return
    _choice(cfg, "scene_model.name", ("voxel_grid", "pae_decoder", "oracle"))
    for key in ("batches_per_epoch", "rays_per_batch", "quality_size", "quality_images"):
        _integer(cfg, f"scene_model.{key}", 1)
    _integer(cfg, "scene_model.model.num_voxels", 8)
    _integer(cfg, "scene_model.model.samples_per_ray", 1)
    _number(cfg, "scene_model.tv_weight", 0, strict=False)
    _choice(cfg, "scene_model.appearance", ("sequence", "image"))
    _number(cfg, "scene_model.appearance_lr", 0, strict=True, optional=True)
    _integer(cfg, "scene_model.fit_trim_from_epoch", 0)
    fit_trim = _value(cfg, "scene_model.fit_trim")
    if not (_is_int(fit_trim) or isinstance(fit_trim, float)) or not 0 <= fit_trim < 1:
        raise ConfigError(f"scene_model.fit_trim must be a number in [0, 1), got {fit_trim!r}")
    if _value(cfg, "scene_model.model.contract") != "auto":
        _boolean(cfg, "scene_model.model.contract")
    if _value(cfg, "scene_model.image_size") is not None:
        _integer(cfg, "scene_model.image_size", 4)
    for key in ("margin_floor_m", "margin_fraction", "contract_above_m"):
        _number(cfg, f"scene_model.auto_scale.{key}", 0, strict=False)
    margin = _value(cfg, "scene_model.model.margin_m")
    values = list(margin) if isinstance(margin, ListConfig) else [margin]
    if margin != "auto" and (
        len(values) not in (1, 3)
        or not all((_is_int(v) or isinstance(v, float)) and v >= 0 for v in values)
    ):
        raise ConfigError(
            f"scene_model.model.margin_m must be auto, one number >= 0 or three, got {margin!r}"
        )
    if _value(cfg, "render_compare") is not None:
        for key in ("rounds", "polish_steps", "final_reference_size"):
            _integer(cfg, f"render_compare.refiner.{key}", 0)
        for key in ("candidates", "hypotheses", "levels", "chunk"):
            _integer(cfg, f"render_compare.refiner.{key}", 1)
        for key in ("resolution", "reference_size"):
            _integer(cfg, f"render_compare.refiner.{key}", 8)
        _choice(cfg, "render_compare.refiner.score", ("zncc", "features"))
        _number(cfg, "render_compare.refiner.trim_sigma", 0, strict=False, optional=True)
        _number(cfg, "render_compare.refiner.highpass_sigma_px", 0, strict=False, optional=True)
        for key in ("accept_margin", "accept_score"):
            value = _value(cfg, f"render_compare.{key}")
            if value != "auto" and not (_is_int(value) or isinstance(value, float)):
                raise ConfigError(f"render_compare.{key} must be auto or a number, got {value!r}")


def validate_eval_config(cfg: DictConfig) -> None:
    """All of pae-eval's settings (conf/eval.yaml); raises ConfigError naming the key."""
    _validate_common(cfg)
    if _value(cfg, "student_ckpt") is None and _value(cfg, "scene_model_ckpt") is None:
        raise ConfigError(
            "pae-eval needs student_ckpt=PATH (a checkpoint of stage=student) or "
            "scene_model_ckpt=PATH (a checkpoint of stage=render_compare)"
        )
    for key in ("student_ckpt", "teacher_ckpt", "scene_model_ckpt"):
        _file(cfg, key)
    methods = _value(cfg, "method_ckpts")
    if methods is not None and not isinstance(methods, ListConfig):
        raise ConfigError(f"method_ckpts must be a list of checkpoint paths, got {methods!r}")
    for position, path in enumerate(methods or []):
        if not Path(str(path)).is_file():
            raise ConfigError(f"method_ckpts[{position}]={path}: no such file")
    if "iapr_iterations" in cfg:
        _integer(cfg, "iapr_iterations", 1)
    validate_data(cfg, train=False)
