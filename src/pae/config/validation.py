"""Every configured value checked when a run starts, before data is rendered or read for
training: types, ranges and paths, each failure a ConfigError naming its key."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

from pae.config.data_checks import check_calibration_held_out, validate_data
from pae.config.novel_views import novel_view_needs
from pae.core.checks import (
    boolean,
    check_constructor,
    check_missing,
    check_record,
    existing_file,
    integer,
    setting,
)
from pae.core.errors import ConfigError
from pae.core.run_context import current_run
from pae.steps import CHECKPOINTS, GROUPS, MODELS, missing_checkpoints, steps_of

RENAMED_KEYS = {"pae_ckpt": "student_ckpt"}
"""Old key -> its new name. The old key is still read for one more release, with a one-line
deprecation warning."""


def apply_renamed_keys(cfg: DictConfig, program: str | None = None) -> None:
    """Move a value given under an old key (RENAMED_KEYS) to its new name; with `program`,
    say once per run that the old name is deprecated. Both names with different values
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
        if program is not None and current_run().first_time(f"renamed {old}"):
            print(
                f"{program}: warning: {old} is deprecated, use {new} (the old name is read "
                "for one more release)",
                file=sys.stderr,
            )


def validate_models(cfg: DictConfig) -> None:
    """Every model config a step builds (``pae.steps.MODELS``) against its own class."""
    for key, supplied in MODELS.items():
        check_constructor(cfg, key, supplied)


def _validate_common(cfg: DictConfig) -> None:
    """Seed, flags, the validation period and ``refine.*`` (its record, then its callback)."""
    integer(cfg, "seed", 0)
    boolean(cfg, "allow_other_data")
    if "check_val_every_n_epoch" in cfg.trainer:
        integer(cfg, "trainer.check_val_every_n_epoch", 1)
    if cfg.get("refine"):
        from pae.callbacks.settings import TestTimeRefinementSettings
        from pae.runs.trainer import refinement_callbacks

        check_record(cfg, "refine", TestTimeRefinementSettings)
        refinement_callbacks(cfg)


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


GROUP_CONSTRUCTORS: dict[str, tuple[str, ...]] = {
    "data": ("augment",),
    "trainer": ("max_epochs", "logger", "callbacks", "default_root_dir", "plugins"),
    "refine": (),
    "render_compare": (),
}
"""Groups built from their ``_target_`` besides the steps' models -> the constructor
arguments their builder fills in; each entry of ``callbacks`` and ``logger`` is checked too
(a logger's ``save_dir`` filled in). Nested ``_target_`` configs (the render-and-compare
refiner) are checked with their parent."""


def validate_groups(cfg: DictConfig) -> None:
    """Every key of the groups built from a ``_target_`` (``GROUP_CONSTRUCTORS``, callbacks,
    loggers) is an argument of its class, before any work: a misspelt or added key is a
    ConfigError naming it."""
    checks = dict(GROUP_CONSTRUCTORS)
    for group, supplied in (("callbacks", ()), ("logger", ("save_dir",))):
        node = setting(cfg, group)
        if isinstance(node, DictConfig):
            checks |= {f"{group}.{name}": supplied for name in node}
    for key, supplied in checks.items():
        node = setting(cfg, key)
        if isinstance(node, DictConfig) and "_target_" in node:
            check_constructor(cfg, key, supplied)


def validate_render_compare(cfg: DictConfig) -> None:
    """render_compare.*: its values and ranges as its classes check them (the callback and
    the refiner it builds; their keys: ``validate_groups``), by building the callback."""
    if setting(cfg, "render_compare") is None:
        return
    from pae.runs.trainer import render_compare_callback

    render_compare_callback(cfg)


def validate_train_config(cfg: DictConfig, overrides: list[str] | None = None) -> None:
    """All of pae-train's settings (conf/train.yaml), and the keys ``overrides`` (the command
    line's) add; raises ConfigError naming the key."""
    from hydra.utils import get_object

    from pae.steps.settings import STEP_SETTINGS, OptimizerSettings

    check_missing(cfg)
    check_added_keys(cfg, overrides or [])
    steps = list(cfg.stage.steps)
    try:
        steps_of(steps)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    validate_models(cfg)
    validate_groups(cfg)
    _validate_common(cfg)
    boolean(cfg, "resume")
    for group, record_type in STEP_SETTINGS.items():
        if setting(cfg, group) is not None:
            check_record(cfg, group, record_type)
        if setting(cfg, f"{group}.optimizer") is not None:
            check_record(cfg, f"{group}.optimizer", OptimizerSettings)
    for key in ("backbone.weights_path", *CHECKPOINTS):
        existing_file(cfg, key)
    validate_render_compare(cfg)
    if "scene_model" in steps:
        check_calibration_held_out(cfg)
    needs = _model_needs(cfg, steps)
    for step, keys in novel_view_needs(cfg, steps).items():
        needs[step] = (*needs[step], *keys)
    target = setting(cfg, "scene_model.model._target_")
    if "scene_fit" in steps and not getattr(get_object(target), "trains", False):
        raise ConfigError(f"scene_fit: scene_model.model._target_={target} does not train")
    fitting = {"scene_fit", "scene_model"} & set(steps)
    if (
        fitting
        and setting(cfg, "scene_model.depth_rays")
        and not getattr(get_object(target), "fits_depth", False)
    ):
        raise ConfigError(
            f"scene_model.depth_rays: scene_model.model._target_={target} fits no depth"
        )
    given = {key: setting(cfg, key) for key in CHECKPOINTS}
    missing = missing_checkpoints(steps, given, needs)
    if missing:
        raise ConfigError(f"stage={cfg.stage.name} needs {missing[0][1]}=PATH")
    from pae.core.checkpoints import check_checkpoint_kinds

    check_checkpoint_kinds(given)
    validate_data(cfg, train=True)


def _model_needs(cfg: DictConfig, steps: list[str]) -> dict[str, tuple[str, ...]]:
    """Step name -> the checkpoint keys its models' classes declare they need (``needs``)."""
    from hydra.utils import get_object

    return {
        step.name: tuple(
            key
            for model in step.models
            for key in getattr(get_object(setting(cfg, f"{model}._target_")), "needs", ())
        )
        for step in steps_of(steps)
    }


def validate_eval_config(cfg: DictConfig) -> None:
    """All of pae-eval's settings (conf/eval.yaml); raises ConfigError naming the key."""
    check_missing(cfg)
    validate_groups(cfg)
    _validate_common(cfg)
    if setting(cfg, "student_ckpt") is None and setting(cfg, "scene_model_ckpt") is None:
        raise ConfigError(
            "pae-eval needs student_ckpt=PATH (a checkpoint of stage=student) or "
            "scene_model_ckpt=PATH (a checkpoint of stage=render_compare)"
        )
    for key in ("student_ckpt", "teacher_ckpt", "scene_model_ckpt"):
        existing_file(cfg, key)
    if setting(cfg, "scene_model_ckpt") is not None:
        check_calibration_held_out(cfg)
    methods = setting(cfg, "method_ckpts")
    if methods is not None and not isinstance(methods, ListConfig):
        raise ConfigError(f"method_ckpts must be a list of checkpoint paths, got {methods!r}")
    for position, path in enumerate(methods or []):
        if not Path(str(path)).is_file():
            raise ConfigError(f"method_ckpts[{position}]={path}: no such file")
    if "iapr_iterations" in cfg:
        integer(cfg, "iapr_iterations", 1)
    validate_render_compare(cfg)
    validate_data(cfg, train=False)
