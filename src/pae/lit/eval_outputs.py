"""The seam between an evaluating module and the callbacks that refine its queries: the
keys of each evaluation batch it keeps (``eval_outputs``), what a render-and-compare
callback needs of the module (:class:`SceneModelEvaluation`) and the epoch's queries joined
once each (:func:`collect_outputs`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import lightning as L
import torch
import torch.nn.functional as F
from torch import Tensor

from pae.core.errors import ConfigError
from pae.core.heap import release_free_heap
from pae.core.metrics import first_occurrences
from pae.data.holdout import CALIBRATION_ON_TEST
from pae.data.transforms import ImageTransform
from pae.render_compare.correspondences import Describer, MatchQueries, TrainImages
from pae.render_compare.sequences import SequenceOptions, Sequences
from pae.scene_model.base import SceneModel
from pae.scene_model.oracle import OracleSceneModel


@dataclass(frozen=True)
class EvalKeys:
    """The keys of one evaluation batch of ``eval_outputs``: the query ``image`` [B, 3, h, w]
    (RGB in [0, 1], at the compare width), its ``intrinsics`` [B, 4] (px, at that size), the
    teacher's pose ``estimate`` [B, 7] and ``scene_estimate`` [B], the true ``pose`` [B, 7]
    and ``scene`` [B], and the query's row ``index`` [B] in the split; for teachers that
    classify the scene, render-and-compare's starts in every scene ``scene_poses`` [B, S, K,
    7] (their pose for the scene first) and their scene logits ``scene_logits`` [B, S]."""

    image: str = "image"
    intrinsics: str = "intrinsics"
    estimate: str = "estimate"
    scene_estimate: str = "scene_estimate"
    pose: str = "pose"
    scene: str = "scene"
    index: str = "index"
    scene_poses: str = "scene_poses"
    scene_logits: str = "scene_logits"


EVAL = EvalKeys()


class EvalOutputs(Protocol):
    """A module that keeps its evaluation batches (dicts of tensors keyed by ``EVAL``'s
    names, and any of its own) for a callback to read at the epoch's end."""

    eval_outputs: list[dict[str, Tensor]]

    def all_gather(self, data: Any) -> Any: ...


class SceneModelEvaluation(EvalOutputs, Protocol):
    """What the render-and-compare callbacks need of the evaluated module
    (``pae.lit.scene_model.SceneModelModule`` is one): its queries, the scene model to
    render, the frozen teacher (whose backbone gives the compare features), the scene names
    and a place to log figures."""

    scene_model: SceneModel
    teacher: torch.nn.Module
    scene_names: list[str]

    def log_dict(self, dictionary: Any, *args: Any, **kwargs: Any) -> None: ...


TRIM_BYTES = 64 * 2**20
"""While batches are joined, the freed ones' heap pages are returned every this many bytes."""


def _join_consuming(batches: list[dict[str, Tensor]]) -> dict[str, Tensor]:
    """The batches joined along their first axis, each batch's tensors dropped as soon as they
    are copied and their pages returned every ``TRIM_BYTES``: the joined copy and the
    batches never both stay whole (``batches`` is emptied)."""
    rows = sum(len(batch[EVAL.index]) for batch in batches)
    joined = {}
    for key in list(batches[0]):
        first = batches[0][key]
        out = first.new_empty((rows, *first.shape[1:]))
        row, freed = 0, 0
        for batch in batches:
            part = batch.pop(key)
            out[row : row + len(part)] = part
            row += len(part)
            freed += part.nbytes
            del part
            if freed >= TRIM_BYTES:
                release_free_heap()
                freed = 0
        joined[key] = out
    batches.clear()
    return joined


def collect_outputs(
    trainer: L.Trainer, module: EvalOutputs, gather: bool = True
) -> dict[str, Tensor] | None:
    """The finished evaluation epoch's batches of ``module`` joined, each query once, in
    split order (a distributed sampler pads with repeats); with ``gather``, every rank's
    (so each rank sees all queries of the split). None where it kept none. In one process
    the joined batch replaces the batches in ``module.eval_outputs`` as they are copied: the
    queries are held once (the batches' freed pages returned to the system:
    :mod:`pae.core.heap`), and every later call returns them without a copy."""
    if not module.eval_outputs:
        return None
    release_free_heap()  # what the epoch freed, before the joined copy is allocated
    distributed = trainer.world_size > 1
    batches = module.eval_outputs
    if len(batches) == 1:
        outputs = dict(batches[0])
    elif distributed:
        outputs = {key: torch.cat([batch[key] for batch in batches]) for key in batches[0]}
    else:
        outputs = _join_consuming(batches)
    if gather and distributed:
        outputs = {k: module.all_gather(v).flatten(0, 1) for k, v in outputs.items()}
    keep = first_occurrences(outputs[EVAL.index])
    if len(keep) != len(outputs[EVAL.index]) or not bool((keep[1:] > keep[:-1]).all()):
        outputs = {key: value[keep] for key, value in outputs.items()}
    if not distributed:
        module.eval_outputs = [outputs]
        release_free_heap()
    return dict(outputs)


def check_held_out(data: Any, stage: str) -> None:
    """Before a ``fit`` or ``validate`` (``stage``) that calibrates render-and-compare on the
    validation split: ConfigError where ``data`` (a data module) validates on its test split
    (``val_is_test``), whose labels would choose the gate, filters and scene rule."""
    if stage in ("fit", "validate") and getattr(data, "val_is_test", False):
        raise ConfigError(CALIBRATION_ON_TEST)


def oracle_scenes(data: Any) -> list[Any] | None:
    """The true scenes of a data module that knows them (the synthetic benchmark), else None."""
    source = getattr(data, "images", data)
    scenes = getattr(source, "oracle_scenes", None)
    return scenes() if callable(scenes) else None


def query_sequences(
    options: SequenceOptions, data: Any, split: str, rows: Tensor
) -> Sequences | None:
    """The queries' sequences for :func:`pae.render_compare.refine` and ``calibrate`` under
    ``options`` (None where inactive): the recording [B] of each of ``split``'s queries at
    ``rows`` [B] of the data module's split (its label rows: each recording's frames in
    order; the data module's ``recording_ids``, from where each frame came from, never a
    label) and the options."""
    if not options.active:
        return None
    recordings = getattr(data, "recording_ids", None)
    if recordings is None:
        raise ConfigError(
            f"render_compare.sequence_*: the data module {type(data).__name__} does not say "
            "which sequence each query belongs to"
        )
    return Sequences(recordings(split).to(rows.device)[rows], options)


DESCRIPTORS = ("teacher", "thumbnail")
"""The train views' global descriptor for the correspondence stage: the teacher backbone's
pooled features, or the classical band-passed thumbnail."""


def match_width(matches: Sequence[Mapping[str, Any]] | None) -> int:
    """The one match width (px) of the correspondence stages tried on val (0: none); a
    ConfigError where two differ."""
    widths = {int(m.get("width", 0)) for m in matches or ()} - {0}
    if len(widths) > 1:
        raise ConfigError(
            f"render_compare.matches_from_val: one width for every stage, not {sorted(widths)}"
        )
    return widths.pop() if widths else 0


def teacher_descriptor(teacher: torch.nn.Module, size: int) -> Describer:
    """The teacher backbone's pooled features as a global descriptor: RGB images
    [B, 3, H, W] in [0, 1] area-resized to ``size`` px on their shorter edge, normalised as
    the teacher's inputs -> unit vectors [B, G]."""

    @torch.no_grad()
    def describe(rgb: Tensor) -> Tensor:
        h, w = rgb.shape[-2:]
        scale = size / min(h, w)
        small = F.interpolate(rgb, size=(round(h * scale), round(w * scale)), mode="area")
        return F.normalize(teacher.backbone(ImageTransform.normalize_batch(small)), dim=1)

    return describe


def train_images(data: Any, width: int, describe: Describer | None) -> TrainImages:
    """The data module's train views at ``width`` px for the correspondence stage."""
    images, intrinsics = data.images_at("train", width)
    poses, scenes = data.train_poses()
    return TrainImages(images, intrinsics, poses, scenes, describe)


class MatchInputs:
    """What a render-and-compare callback gives the correspondence stages it tries on val
    (``matches``: mappings of ``MatchSettings``): the queries at their one match width and
    the train views, retrieved by ``descriptor`` (``DESCRIPTORS``), read once per run."""

    def __init__(self, matches: Sequence[Mapping[str, Any]] | None, descriptor: str) -> None:
        if descriptor not in DESCRIPTORS:
            raise ValueError(
                f"render_compare.match_descriptor: unknown {descriptor!r}; choose one of "
                f"{list(DESCRIPTORS)}"
            )
        self.width, self.descriptor = match_width(matches), descriptor
        self.train: TrainImages | None = None
        self.loaded: dict[str, tuple[Tensor, Tensor]] = {}  # split -> its images, intrinsics

    def queries(
        self, data: Any, teacher: torch.nn.Module, split: str, rows: Tensor
    ) -> MatchQueries | None:
        """``split``'s queries at ``rows`` [B] at the match width (None without a stage)."""
        if not self.width:
            return None
        if self.train is None:
            size = int(getattr(data, "shorter_edge", 64))
            describe = teacher_descriptor(teacher, size) if self.descriptor == "teacher" else None
            self.train = train_images(data, self.width, describe)
        if split not in self.loaded:  # each validation reads the same files: once a run
            self.loaded[split] = data.images_at(split, self.width)
        images, intrinsics = self.loaded[split]
        at = rows.cpu()
        return MatchQueries(images[at], intrinsics[at], self.train)


HONEST = "render_compare"
"""The method refining against the scene model learned from the train images."""
ORACLE = "render_compare_oracle"
"""The method refining against the benchmark's own renderer (a bound)."""


def scene_models(scene_model: SceneModel, data: Any, oracle: bool) -> dict[str, SceneModel]:
    """The scene models a render-and-compare callback refines against, by method: the run's
    (an oracle scene model under ``ORACLE``), and with ``oracle`` on data that knows its
    scenes the benchmark's own renderer."""
    if isinstance(scene_model, OracleSceneModel):
        return {ORACLE: scene_model}
    scenes = oracle_scenes(data) if oracle else None
    return {HONEST: scene_model} | ({} if scenes is None else {ORACLE: OracleSceneModel(scenes)})
