"""Render-and-compare pose refinement against a scene model learned from the train images,
callable without a Trainer:

- :func:`refine`: from any starts (an APR's estimates), the refined poses through the gate;
- :func:`calibrate`: the gate and the search's first steps chosen on validation queries
  with their true poses, for :func:`refine` to apply at test.

The refiner itself is :class:`pae.render_compare.refiner.RenderCompareRefiner`, its settings
:class:`pae.render_compare.settings.RenderCompareSettings`."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, NamedTuple

from torch import Tensor

from pae.core.geometry import pose_errors
from pae.core.shapes import check_shape
from pae.render_compare.calibration import Calibration, choose_gate, steps_from_errors
from pae.render_compare.gate import ACCEPT_ALL, RenderCompareResult, gate
from pae.render_compare.refiner import FeatureExtractor, RenderCompareRefiner
from pae.render_compare.settings import RenderCompareSettings
from pae.scene_model.base import SceneModel

__all__ = [
    "ACCEPT_ALL",
    "Calibration",
    "Refinement",
    "RenderCompareResult",
    "RenderCompareSettings",
    "calibrate",
    "refine",
]


class Refinement(NamedTuple):
    """poses [B, 7]: refined where the gate accepted, else the start; accepted [B] bool;
    result: the refiner's output before the gate (poses, scores)."""

    poses: Tensor
    accepted: Tensor
    result: RenderCompareResult


def _refiner(
    scene_model: SceneModel,
    settings: RenderCompareSettings | Mapping[str, Any] | None,
    steps: Mapping[str, float],
    features: FeatureExtractor | None,
) -> RenderCompareRefiner:
    if isinstance(settings, RenderCompareSettings):
        settings = dataclasses.asdict(settings)
    return RenderCompareRefiner.configured(
        scene_model, features=features, **(dict(settings or {}) | dict(steps))
    )


def _check(images: Tensor, intrinsics: Tensor, starts: Tensor, scenes: Tensor) -> None:
    n = check_shape(images, "images", "B 3 H W")["B"]
    check_shape(intrinsics, "intrinsics", f"{n} 4")
    check_shape(starts, "starts", f"{n} 7")
    check_shape(scenes, "scenes", f"{n}")


def refine(
    scene_model: SceneModel,
    images: Tensor,
    intrinsics: Tensor,
    starts: Tensor,
    scenes: Tensor,
    settings: RenderCompareSettings | Mapping[str, Any] | None = None,
    calibration: Calibration | None = None,
    features: FeatureExtractor | None = None,
) -> Refinement:
    """Refine starts [B, 7] (camera-to-world, unit quaternions) of query images [B, 3, H, W]
    (RGB in [0, 1]) with intrinsics [B, 4] (fx, fy, cx, cy in px at the images' size) in
    scenes [B] against ``scene_model``; ``settings`` replace the defaults
    (:class:`RenderCompareSettings`), ``calibration`` gives the gate and first steps chosen
    on validation (:func:`calibrate`; default: margin 0, no floor, the settings' steps)."""
    _check(images, intrinsics, starts, scenes)
    calibration = calibration or Calibration()
    refiner = _refiner(scene_model, settings, calibration.steps, features)
    result = refiner(images, intrinsics, starts, scenes)
    gated = gate(result, starts, calibration.accept_margin, calibration.accept_score)
    return Refinement(gated.poses, gated.accepted, result)


def calibrate(
    scene_model: SceneModel,
    images: Tensor,
    intrinsics: Tensor,
    starts: Tensor,
    scenes: Tensor,
    truth: Tensor,
    settings: RenderCompareSettings | Mapping[str, Any] | None = None,
    step_fractions: Mapping[str, float] | None = None,
    accept_margin: float | None = None,
    accept_score: float | None = ACCEPT_ALL,
    features: FeatureExtractor | None = None,
) -> tuple[Calibration, Refinement]:
    """The calibration chosen on validation queries (as :func:`refine`'s arguments, with
    their true poses ``truth`` [B, 7]): the search's first steps as ``step_fractions`` of the
    starts' median errors (None: the settings' own), and the gate's margin and floor that
    minimise the mean position error (None: chosen, :func:`choose_gate`; a number: kept) ->
    the calibration and the validation queries' refinement under it."""
    _check(images, intrinsics, starts, scenes)
    check_shape(truth, "truth", f"{len(starts)} 7")
    steps = {} if step_fractions is None else steps_from_errors(starts, truth, step_fractions)
    refiner = _refiner(scene_model, settings, steps, features)
    result = refiner(images, intrinsics, starts, scenes)
    refined_pos, _ = pose_errors(result.poses.float(), truth.float())
    start_pos, _ = pose_errors(starts.float(), truth.float())
    margin, floor = choose_gate(
        result.score - result.initial_score,
        result.score,
        refined_pos,
        start_pos,
        margin=accept_margin,
        floor=accept_score,
    )
    calibration = Calibration(margin, floor, steps)
    gated = gate(result, starts, margin, floor)
    return calibration, Refinement(gated.poses, gated.accepted, result)
