"""The config groups' schemas, made from the settings records that hold their defaults, and
registered with Hydra's ConfigStore in the groups ``schema/<group>``: a config file starts
from its schema (``defaults: [/schema/data@_here_: pose_data, _self_]``) and sets only what
differs. Every key is typed, and a key the schema lacks is refused by Hydra at compose time;
``~key`` and ``+key`` still work, so a group's ``_target_`` can be a user's own class
(checked against its own constructor when the run starts).
Imports neither numpy nor torch: a sweep's launching process composes configs without them."""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from omegaconf import MISSING, DictConfig, OmegaConf

from pae.callbacks.settings import TestTimeRefinementSettings
from pae.config.signatures import source_fields
from pae.data.settings import PoseDataSettings
from pae.models.settings import PoseAutoEncoderSettings
from pae.synthetic.settings import SYNTHETIC_LOADING, SyntheticSettings

Field = tuple[str, Any, Any]
"""A schema field: its name, type and ``dataclasses.field``."""


BUILDER_FILLED = ("order_seed",)
"""Settings a run fills in (the data order's seed: the run's ``seed``), not configured."""
DESCRIBED_COUNTS = ("train_frames", "test_frames")
"""The frame counts of ``data=synthetic``: with a given ``root`` they only describe it, None
where its scenes hold different counts."""


def settings_fields(
    settings: type,
    defaults: dict[str, Any] | None = None,
    leave_out: tuple[str, ...] = (),
    nullable: tuple[str, ...] = (),
) -> list[Field]:
    """The fields of the dataclass ``settings`` (but ``leave_out``) as schema fields, their
    types resolved (optional where the default is None or the name is ``nullable``) and
    ``defaults`` replacing theirs."""
    types = typing.get_type_hints(settings)
    defaults = defaults or {}
    fields = []
    for spec in dataclasses.fields(settings):
        if spec.name in leave_out:
            continue
        if spec.name in defaults:
            default = defaults[spec.name]
        elif spec.default_factory is not dataclasses.MISSING:
            default = spec.default_factory()
        else:
            default = spec.default
        kind = types[spec.name]
        optional = default is None or spec.name in nullable
        if optional and type(None) not in typing.get_args(kind):
            kind = kind | None
        fields.append((spec.name, kind, _field(default)))
    return fields


def _field(default: Any) -> Any:
    """A ``dataclasses.field`` of ``default`` (copied for each config where mutable)."""
    if isinstance(default, list | dict):
        return dataclasses.field(default_factory=lambda: type(default)(default))
    return dataclasses.field(default=default)


def schema(name: str, target: str, fields: list[Field], partial: bool = False) -> type:
    """A dataclass ``name`` of ``fields`` built by ``target`` (its ``_target_``; with
    ``partial``, built as a ``functools.partial`` that the run completes)."""
    built = [("_target_", str, _field(target))]
    if partial:
        built.append(("_partial_", bool, _field(True)))
    return dataclasses.make_dataclass(name, [*built, *fields])


def label_files_fields() -> list[Field]:
    """The images' folder and the train and test label files: no default."""
    return [(name, str, _field(MISSING)) for name in ("root", "train_labels", "test_labels")]


SCHEMAS: dict[tuple[str, str], type] = {
    ("data", "pose_data"): schema(
        "PoseDataSchema",
        "pae.data.datamodule.PoseDataModule",
        [*label_files_fields(), *settings_fields(PoseDataSettings, leave_out=BUILDER_FILLED)],
    ),
    ("data", "synthetic"): schema(
        "SyntheticDataSchema",
        "pae.synthetic.datamodule.SyntheticDataModule",
        [
            ("root", str | None, _field(None)),
            ("poses", list[str] | None, _field(None)),
            ("render_seed", int, _field(0)),
            *settings_fields(SyntheticSettings, leave_out=("seed",), nullable=DESCRIBED_COUNTS),
            *settings_fields(
                PoseDataSettings,
                {**SYNTHETIC_LOADING, "shorter_edge": "${.size}"},
                leave_out=(*BUILDER_FILLED, "scenes"),
            ),
        ],
    ),
    ("pae", "pose_auto_encoder"): schema(
        "PoseAutoEncoderSchema",
        "pae.models.pae.PoseAutoEncoder",
        settings_fields(PoseAutoEncoderSettings),
    ),
    **{
        (group, name): schema(f"{target.rsplit('.', 1)[1]}Schema", target, source_fields(target))
        for group, name, target in (
            ("backbone", "backbone", "pae.models.backbones.Backbone"),
            ("teacher", "posenet", "pae.models.posenet.PoseNet"),
            ("teacher", "ms_transformer", "pae.models.ms_transformer.MSTransformer"),
            ("rpr", "siamese", "pae.models.rpr.SiameseRPR"),
            ("iapr", "iterative_apr", "pae.models.iapr.IterativeAPR"),
            ("decoder", "image_decoder", "pae.models.decoder.ImageDecoder"),
            ("loss", "learned_pose", "pae.core.losses.LearnedPoseLoss"),
        )
    },
    ("render_compare", "callback"): schema(
        "RenderCompareCallbackSchema",
        "pae.callbacks.render_compare.RenderCompareCallback",
        source_fields("pae.callbacks.render_compare.RenderCompareCallback"),
    ),
    ("render_compare", "refiner"): schema(
        "RenderCompareRefinerSchema",
        "pae.render_compare.refiner.RenderCompareRefiner",
        source_fields("pae.render_compare.settings.RenderCompareSettings"),
        partial=True,
    ),
    ("novel_views", "default"): dataclasses.make_dataclass(
        "NovelViewSchema",
        [
            ("enabled", bool, _field(False)),
            *source_fields("pae.scene_model.novel_views.NovelViewSettings"),
        ],
    ),
    ("refine", "test_time_refinement"): schema(
        "TestTimeRefinementSchema",
        "pae.callbacks.refinement.TestTimeRefinement",
        [
            *settings_fields(TestTimeRefinementSettings),
            ("alternatives", dict[str, Any], _field({})),
        ],
    ),
}
"""(group, name) -> the schema registered there: the settings records', and the models'
read from their constructors' signatures (:mod:`pae.config.signatures`; ``n_scenes``, which
the steps fill in, is left out). ``data=synthetic`` shows the loaders'
``shorter_edge`` as the benchmark's ``size`` (SYNTHETIC_LOADING's None)."""


def open_schema(schema_type: type) -> DictConfig:
    """The config of ``schema_type`` with each value typed as the schema types it, but not
    the node itself: Hydra deletes its keys (``~key``) and adds others (``+key``), as for a
    user's own ``_target_`` class, while a misspelt key (without ``+``) and a value of
    another type are still refused when composing."""
    typed = OmegaConf.structured(schema_type)
    node = OmegaConf.create({})
    for key in typed:
        node[key] = typed._get_node(key)
    return node


def register_schemas() -> None:
    """Store every schema of ``SCHEMAS`` in Hydra's ConfigStore (again: the same), each in
    the group ``schema/<its group>``, apart from the options users choose."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for (group, name), schema_type in SCHEMAS.items():
        store.store(group=f"schema/{group}", name=name, node=open_schema(schema_type))


def compose_config(config_name: str, overrides: list[str] | None = None) -> DictConfig:
    """pae's config ``config_name`` (``train`` or ``eval``) with command-line ``overrides``,
    composed as its entry point composes it, outside a run."""
    from hydra import compose, initialize_config_dir

    from pae import CONFIG_DIR

    register_schemas()
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config_name, overrides=list(overrides or []))
