"""Render-and-compare's two public calls, without a Trainer: :func:`refine` any starts, and
:func:`calibrate` the gate, the search's first steps and the scene decision on validation
queries with their true poses."""

from __future__ import annotations

import dataclasses
import functools
import itertools
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

from pae.core.geometry import pose_errors
from pae.core.shapes import check_shape
from pae.render_compare.calibration import (
    CONTRAST_PX,
    HIGHPASS_PX,
    LADDER,
    LADDER_DEG,
    RATIO_EPS_M,
    STEP_SHARES,
    SURFACE_SHARES,
    Calibration,
    choose_gate,
    ladder_starts,
    objective_value,
    steps_from_errors,
)
from pae.render_compare.correspondences import MatchQueries, MatchSettings
from pae.render_compare.gate import ACCEPT_ALL, RenderCompareResult, gate
from pae.render_compare.other_starts import with_other_starts
from pae.render_compare.refiner import FeatureExtractor, RenderCompareRefiner
from pae.render_compare.scene_decision import (
    PROBE_SCALES,
    SceneRule,
    apply,
    choose_scene_rule,
    decide_scenes,
    sharpness,
    try_scenes,
)
from pae.render_compare.sequences import (
    SequenceOptions,
    median_filter,
    propagate,
    vote_scenes,
)
from pae.render_compare.settings import RenderCompareSettings
from pae.scene_model.base import SceneModel

Settings = RenderCompareSettings | Mapping[str, Any] | None


class Refinement(NamedTuple):
    """poses [B, 7]: refined where the gate accepted, else the start (with a sequence window:
    then each the median over its frames); accepted [B] bool; result: the refiner's output
    before the gate (poses, scores) in the decided scenes, after any sequence passes;
    scenes [B]: the decided scene (the given one unless the scene decision or the sequence
    vote moved it);
    checked [B] bool: queries also refined in the other scenes; matched [B] bool: queries
    whose correspondences gave a pose (:mod:`pae.render_compare.correspondences`), None where
    the stage did not run; from_match [B] bool: those whose kept refinement started there."""

    poses: Tensor
    accepted: Tensor
    result: RenderCompareResult
    scenes: Tensor
    checked: Tensor
    matched: Tensor | None = None
    from_match: Tensor | None = None


def build_refiner(
    scene_model: SceneModel,
    settings: Settings = None,
    steps: Mapping[str, float] | None = None,
    features: FeatureExtractor | None = None,
) -> RenderCompareRefiner:
    """The refiner against ``scene_model``: the defaults, replaced by ``settings``, then by
    the calibrated first ``steps``."""
    if isinstance(settings, RenderCompareSettings):
        settings = dataclasses.asdict(settings)
    merged = dict(settings or {}) | dict(steps or {})
    return RenderCompareRefiner.configured(scene_model, features=features, **merged)


def _check(
    images: Tensor,
    intrinsics: Tensor,
    starts: Tensor,
    scenes: Tensor,
    scene_poses: Tensor | None,
    scene_logits: Tensor | None = None,
    sequences: Tensor | None = None,
    sequence: SequenceOptions | None = None,
) -> None:
    if sequences is None and sequence is not None and sequence.active:
        raise ValueError(
            f"render_compare: {sequence} uses the queries' sequences, but no sequences "
            "were given (sequences=: an id per query, each sequence's frames in row order)"
        )
    n = check_shape(images, "images", "B 3 H W")["B"]
    check_shape(intrinsics, "intrinsics", f"{n} 4")
    check_shape(starts, "starts", f"{n} 7")
    check_shape(scenes, "scenes", f"{n}")
    if sequences is not None:
        check_shape(sequences, "sequences", f"{n}")
    if scene_poses is not None:
        spec = f"{n} S 7" if scene_poses.dim() == 3 else f"{n} S K 7"
        s = check_shape(scene_poses, "scene_poses", spec)["S"]
        if scene_logits is not None:
            check_shape(scene_logits, "scene_logits", f"{n} {s}")


def _check_matching(matching: MatchQueries | None, n: int) -> None:
    if matching is not None:
        check_shape(matching.images, "matching.images", f"{n} 3 H W")
        check_shape(matching.intrinsics, "matching.intrinsics", f"{n} 4")


def _log_prior(scene_logits: Tensor | None) -> Tensor | None:
    return None if scene_logits is None else scene_logits.float().log_softmax(-1)


def _voted(
    scenes: Tensor,
    starts: Tensor,
    scene_poses: Tensor | None,
    sequences: Tensor | None,
    options: SequenceOptions | None,
) -> tuple[Tensor, Tensor]:
    """Scenes [B] voted by sequence where the options say so, and the starts [B, 7] in them:
    the multi-scene APR's pose for a query's new scene (its first start there)."""
    if sequences is None or options is None or not options.vote_scene:
        return scenes, starts
    voted = vote_scenes(scenes, sequences)
    if scene_poses is None:
        return voted, starts
    rows = torch.arange(len(voted), device=voted.device)
    there = scene_poses[rows, voted]
    there = there[:, 0] if there.dim() == 3 else there
    return voted, torch.where((voted != scenes)[:, None], there.to(starts), starts)


def _propagated(
    refiner: RenderCompareRefiner,
    images: Tensor,
    intrinsics: Tensor,
    scenes: Tensor,
    result: RenderCompareResult,
    sequences: Tensor | None,
    options: SequenceOptions | None,
) -> RenderCompareResult:
    if sequences is None or options is None or not options.passes:
        return result
    return propagate(refiner, images, intrinsics, scenes, result, sequences, options.passes)


def _filtered(
    poses: Tensor, scenes: Tensor, sequences: Tensor | None, options: SequenceOptions | None
) -> Tensor:
    if sequences is None or options is None:
        return poses
    return median_filter(poses, sequences, scenes, options.window)


def _refine_in_scenes(
    refiner: RenderCompareRefiner,
    images: Tensor,
    intrinsics: Tensor,
    starts: Tensor,
    scenes: Tensor,
    scene_poses: Tensor | None,
    scene_logits: Tensor | None,
    rule: SceneRule,
) -> tuple[RenderCompareResult, Tensor, Tensor]:
    first = refiner(images, intrinsics, starts, scenes)
    if scene_poses is None:
        return first, scenes, torch.zeros_like(scenes, dtype=torch.bool)
    probe = functools.partial(sharpness, refiner)
    decision = decide_scenes(
        refiner, probe, images, intrinsics, scene_poses, scenes, first, rule,
        _log_prior(scene_logits),
    )  # fmt: skip
    return decision.result, decision.scene, decision.checked


def refine(
    scene_model: SceneModel,
    images: Tensor,
    intrinsics: Tensor,
    starts: Tensor,
    scenes: Tensor,
    settings: Settings = None,
    calibration: Calibration | None = None,
    features: FeatureExtractor | None = None,
    scene_poses: Tensor | None = None,
    scene_logits: Tensor | None = None,
    sequences: Tensor | None = None,
    sequence: SequenceOptions | None = None,
    matching: MatchQueries | None = None,
) -> Refinement:
    """Refine starts [B, 7] (camera-to-world, unit quaternions) of query images [B, 3, H, W]
    (RGB in [0, 1]) with intrinsics [B, 4] (fx, fy, cx, cy in px at the images' size) in
    scenes [B] against ``scene_model``; ``settings`` replace the defaults
    (:class:`RenderCompareSettings`), ``calibration`` gives the gate, first steps and scene
    check chosen on validation (:func:`calibrate`; default: margin 0, no floor, the
    settings' steps, no scene check). With a multi-scene APR's poses for every scene
    ``scene_poses`` [B, S, 7] (or K starts per scene [B, S, K, 7]:
    :mod:`pae.render_compare.scene_starts`) and its scene logits ``scene_logits`` [B, S] (the
    prior),
    the calibration's scene rule decides each query's scene
    (:mod:`pae.render_compare.scene_decision`). With each query's sequence ``sequences``
    [B] (rows in frame order within each), ``sequence`` says how the refinement uses them
    (:mod:`pae.render_compare.sequences`; default: it does not). With the queries at their
    match width ``matching`` (:class:`MatchQueries`), the calibration's correspondence stage
    (``calibration.match``) gives each query a second start, refined too; the better-scoring
    refinement is kept (:mod:`pae.render_compare.correspondences`)."""
    _check(images, intrinsics, starts, scenes, scene_poses, scene_logits, sequences, sequence)
    _check_matching(matching, len(starts))
    scenes, starts = _voted(scenes, starts, scene_poses, sequences, sequence)
    calibration = calibration or Calibration()
    refiner = build_refiner(scene_model, settings, calibration.steps, features)
    result, decided, checked = _refine_in_scenes(
        refiner, images, intrinsics, starts, scenes, scene_poses, scene_logits,
        calibration.scene,
    )  # fmt: skip
    matched = with_other_starts(
        refiner, images, intrinsics, starts, scenes, decided, result, calibration.match, matching
    )
    result = _propagated(refiner, images, intrinsics, decided, matched.result, sequences, sequence)
    gated = gate(result, starts, calibration.accept_margin, calibration.accept_score)
    poses = _filtered(gated.poses, decided, sequences, sequence)
    return Refinement(
        poses, gated.accepted, result, decided, checked, matched.matched, matched.from_match
    )


def calibrate(
    scene_model: SceneModel,
    images: Tensor,
    intrinsics: Tensor,
    starts: Tensor,
    scenes: Tensor,
    truth: Tensor,
    settings: Settings = None,
    step_fractions: Mapping[str, float] | None = None,
    accept_margin: float | None = None,
    accept_score: float | None = ACCEPT_ALL,
    features: FeatureExtractor | None = None,
    scene_poses: Tensor | None = None,
    true_scenes: Tensor | None = None,
    scene_check_below: float | None = None,
    scene_logits: Tensor | None = None,
    filters: Sequence[Mapping[str, float]] | None = None,
    sequences: Tensor | None = None,
    sequence: SequenceOptions | None = None,
    gate_objective: str = "mean",
    matching: MatchQueries | None = None,
    matches: Sequence[Mapping[str, Any]] | None = None,
) -> tuple[Calibration, Refinement]:
    """The calibration chosen on validation queries (as :func:`refine`'s arguments, with
    their true poses ``truth`` [B, 7]): with ``filters`` (refiner settings of
    ``pae.render_compare.calibration.FILTER_KEYS``), each tried and the one whose gated
    refinement has the lowest mean position error kept in the calibration's steps; the
    search's first steps as
    ``step_fractions`` of the starts' median errors (None: the settings' own); with
    ``scene_poses``, every query tried in every scene and the scene rule that maximises
    accuracy against ``true_scenes`` [B]
    (:func:`pae.render_compare.scene_decision.choose_scene_rule`; its check floor
    ``scene_check_below`` chosen where None, else kept); then the gate's margin and floor
    that minimise the ``gate_objective`` (:func:`choose_gate`: the mean position error by
    default; None: chosen; a number: kept) -> the calibration and the validation queries'
    refinement under it. With ``sequences`` and ``sequence`` (as :func:`refine`'s), the
    filter is chosen on the queries refined each on its own (the sequences multiply the
    refiner's work), and the gate on the refinement that uses the sequences. With
    ``matching`` (as :func:`refine`'s) and ``matches`` (correspondence stages, each a mapping
    of :class:`MatchSettings`; ``{}``: none), each is tried with the chosen filter and the one
    whose gated refinement minimises the ``gate_objective`` is kept in the calibration's
    ``match``."""
    arguments = dict(locals())  # every argument as given, before any local variable
    _check(images, intrinsics, starts, scenes, scene_poses, scene_logits, sequences, sequence)
    check_shape(truth, "truth", f"{len(starts)} 7")
    _check_matching(matching, len(starts))
    by_sequence = sequences is not None and sequence is not None and sequence.active
    chooses_match = matching is not None and matches is not None and len(matches) > 1
    if filters is not None and len(filters) > 1:
        alone = {"sequences": None, "sequence": None, "matches": None}
        tried = [calibrate(**arguments | alone | {"filters": [chosen]}) for chosen in filters]
        errors = [pose_errors(r.poses.float(), truth.float())[0].mean() for _, r in tried]
        best = min(range(len(tried)), key=lambda i: float(errors[i]))
        if not by_sequence and not chooses_match:
            return tried[best]
        return calibrate(**arguments | {"filters": [filters[best]]})
    if chooses_match:
        alone = {"sequences": None, "sequence": None}
        tried = [calibrate(**arguments | alone | {"matches": [chosen]}) for chosen in matches]
        values = [objective_value(r.poses, starts, truth, gate_objective) for _, r in tried]
        best = min(range(len(tried)), key=lambda i: values[i])
        if not by_sequence:
            return tried[best]
        return calibrate(**arguments | {"matches": [matches[best]]})
    match = MatchSettings(**(matches[0] if matches else {}))
    scenes, starts = _voted(scenes, starts, scene_poses, sequences, sequence)
    steps = {} if step_fractions is None else steps_from_errors(starts, truth, step_fractions)
    steps |= dict(filters[0]) if filters else {}
    refiner = build_refiner(scene_model, settings, steps, features)
    first = refiner(images, intrinsics, starts, scenes)
    result, decided, checked = first, scenes, torch.zeros_like(scenes, dtype=torch.bool)
    rule = SceneRule()
    if scene_poses is not None and scene_poses.shape[1] > 1:
        if true_scenes is None:
            raise ValueError("calibrate: choosing the scene rule needs true_scenes")
        every = torch.arange(len(scenes), device=scenes.device)
        probe = functools.partial(sharpness, refiner)
        trials = try_scenes(
            refiner, probe, images, intrinsics, scene_poses, scenes, first, every, PROBE_SCALES
        )
        prior = _log_prior(scene_logits)
        rule = choose_scene_rule(trials, prior, scenes, true_scenes, scene_check_below)
        keep = (first.score < rule.check_below).nonzero().flatten()
        decision = apply(first, scenes, keep, trials.rows(keep), prior, rule)
        result, decided, checked = decision.result, decision.scene, decision.checked
    matched = with_other_starts(
        refiner, images, intrinsics, starts, scenes, decided, result, match, matching
    )
    result = _propagated(refiner, images, intrinsics, decided, matched.result, sequences, sequence)
    refined_pos, _ = pose_errors(result.poses.float(), truth.float())
    start_pos, _ = pose_errors(starts.float(), truth.float())
    margin, floor = choose_gate(
        result.score - result.initial_score,
        result.score,
        refined_pos,
        start_pos,
        margin=accept_margin,
        floor=accept_score,
        objective=gate_objective,
    )
    calibration = Calibration(margin, floor, steps, rule, match)
    gated = gate(result, starts, margin, floor)
    poses = _filtered(gated.poses, decided, sequences, sequence)
    refinement = Refinement(
        poses, gated.accepted, result, decided, checked, matched.matched, matched.from_match
    )
    return calibration, refinement


def calibrate_any_start(
    scene_model: SceneModel,
    images: Tensor,
    intrinsics: Tensor,
    scenes: Tensor,
    truth: Tensor,
    size_m: float,
    settings: Settings = None,
    features: FeatureExtractor | None = None,
    seed: int = 0,
    highpass_px: Sequence[float] = (HIGHPASS_PX,),
    contrast_px: Sequence[float] = CONTRAST_PX,
    surface_shares: Sequence[float] = SURFACE_SHARES,
) -> tuple[Calibration, Refinement, Tensor]:
    """The calibration for starts from any APR, whose error scale the run cannot know: on
    validation queries (as :func:`calibrate`'s) with starts at every scale of the ladder
    (:func:`pae.render_compare.calibration.ladder_starts`, ``size_m``: the scene's size, m),
    the first steps among ``STEP_SHARES`` of the size, the filter among the settings' own and
    each of ``highpass_px`` (px) at every level or the finest only, with no local contrast or
    each of ``contrast_px`` (px, ``contrast_sigma_px``), then with those the references'
    ``surface_share`` among the settings' own and ``surface_shares``, and the gate that
    minimise the mean log of each query's error over its start's
    (``choose_gate(objective="log_ratio")``), so that a good start is kept rather than
    refined to the refiner's floor -> the calibration (its ``steps`` holding the chosen steps,
    filter and surface share), the validation refinement under it and its starts [N, 7]."""
    _check(images, intrinsics, truth, scenes, None)
    starts = ladder_starts(truth, size_m, torch.Generator().manual_seed(seed))
    start_pos, _ = pose_errors(starts.float(), truth.float())
    deg_per_share = LADDER_DEG[0] / LADDER[0]
    own = build_refiner(scene_model, settings, None, features)
    filters = dict.fromkeys(
        [(own.highpass_sigma_px, own.highpass_levels, own.contrast_sigma_px)]
        + [
            (sigma, levels, contrast)
            for sigma in highpass_px
            for levels in (0, 1)
            for contrast in (0.0, *contrast_px)
        ]
    )

    def evaluate(steps: dict[str, float]) -> tuple[float, Calibration, Refinement]:
        result = build_refiner(scene_model, settings, steps, features)(
            images, intrinsics, starts, scenes
        )
        refined_pos, _ = pose_errors(result.poses.float(), truth.float())
        gains = result.score - result.initial_score
        margin, floor = choose_gate(
            gains, result.score, refined_pos, start_pos, objective="log_ratio"
        )
        gated = gate(result, starts, margin, floor)
        final = torch.where(gated.accepted, refined_pos, start_pos)
        value = float(((final + RATIO_EPS_M) / (start_pos + RATIO_EPS_M)).log().mean())
        refinement = Refinement(gated.poses, gated.accepted, result, scenes, gated.accepted & False)
        return value, Calibration(margin, floor, steps), refinement

    best = min(
        (
            evaluate(
                {
                    "position_sigma_m": share * size_m,
                    "orientation_sigma_deg": share * deg_per_share,
                    "highpass_sigma_px": highpass,
                    "highpass_levels": levels,
                    "contrast_sigma_px": contrast,
                }
            )
            for (highpass, levels, contrast), share in itertools.product(filters, STEP_SHARES)
        ),
        key=lambda tried: tried[0],
    )
    chosen = dict(best[1].steps)
    for surface in dict.fromkeys(surface_shares):
        if surface != own.surface_share:
            tried = evaluate(chosen | {"surface_share": surface})
            best = tried if tried[0] < best[0] else best
    return best[1], best[2], starts
