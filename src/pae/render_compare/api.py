"""Render-and-compare's public calls, without a Trainer: :func:`refine` any starts, and
:func:`calibrate` the gate, the search's first steps and the scene decision on validation
queries with their true poses. Each takes a handful of arguments: the queries
(:class:`Queries`), their starts, the calibration or its options, the sequences
(:class:`Sequences`) and the refiner's settings."""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

from pae.core.geometry import pose_errors
from pae.core.shapes import check_shape
from pae.render_compare.calibration import (
    LADDER,
    LADDER_DEG,
    STAGE_SHARE_TOLERANCE,
    STEP_SHARES,
    AnyStartOptions,
    Calibration,
    CalibrationOptions,
    choose_gate,
    ladder_starts,
    objective_value,
    steps_from_errors,
)
from pae.render_compare.correspondences import MatchQueries, MatchSettings
from pae.render_compare.gate import RenderCompareResult, gate
from pae.render_compare.other_starts import with_other_starts
from pae.render_compare.refiner import RenderCompareRefiner
from pae.render_compare.scene_decision import (
    PROBE_SCALES,
    SceneRule,
    apply,
    choose_scene_rule,
    decide_scenes,
    sharpness,
    try_scenes,
)
from pae.render_compare.sequences import Sequences, propagate, vote_scenes, window_filter
from pae.render_compare.settings import RenderCompareSettings
from pae.scene_model.base import SceneModel

log = logging.getLogger(__name__)

Settings = RenderCompareSettings | Mapping[str, Any] | None
"""The refiner's settings replacing the defaults: a :class:`RenderCompareSettings`, or a
mapping of its fields, which may add ``features`` (the extractor behind
``score="features"``: :func:`pae.render_compare.calibration.teacher_features`)."""


class Queries(NamedTuple):
    """What render-and-compare reads of the queries besides their starts: ``images``
    [B, 3, H, W] (RGB in [0, 1]) with ``intrinsics`` [B, 4] (fx, fy, cx, cy in px at the
    images' size) in ``scenes`` [B]; a multi-scene APR's poses for every scene
    ``scene_poses`` [B, S, 7] (or K starts per scene [B, S, K, 7]:
    :mod:`pae.render_compare.scene_starts`) and its scene logits ``scene_logits`` [B, S] (the
    prior) for the scene decision (:mod:`pae.render_compare.scene_decision`); ``matching``:
    the queries at their match width for the correspondence stage
    (:mod:`pae.render_compare.correspondences`)."""

    images: Tensor
    intrinsics: Tensor
    scenes: Tensor
    scene_poses: Tensor | None = None
    scene_logits: Tensor | None = None
    matching: MatchQueries | None = None


class Validation(NamedTuple):
    """Validation queries with their ``starts`` [B, 7], true poses ``truth`` [B, 7] and,
    where a scene rule is chosen (``queries.scene_poses`` over several scenes), their true
    scenes ``true_scenes`` [B]."""

    queries: Queries
    starts: Tensor
    truth: Tensor
    true_scenes: Tensor | None = None


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
    scene_model: SceneModel, settings: Settings = None, steps: Mapping[str, float] | None = None
) -> RenderCompareRefiner:
    """The refiner against ``scene_model``: the defaults, replaced by ``settings``, then by
    the calibrated first ``steps``."""
    if isinstance(settings, RenderCompareSettings):
        settings = dataclasses.asdict(settings)
    merged = dict(settings or {}) | dict(steps or {})
    return RenderCompareRefiner.configured(scene_model, **merged)


def _check(queries: Queries, starts: Tensor, sequences: Sequences | None) -> None:
    n = check_shape(queries.images, "images", "B 3 H W")["B"]
    check_shape(queries.intrinsics, "intrinsics", f"{n} 4")
    check_shape(starts, "starts", f"{n} 7")
    check_shape(queries.scenes, "scenes", f"{n}")
    if sequences is not None:
        check_shape(sequences.ids, "sequences.ids", f"{n}")
    if queries.scene_poses is not None:
        spec = f"{n} S 7" if queries.scene_poses.dim() == 3 else f"{n} S K 7"
        s = check_shape(queries.scene_poses, "scene_poses", spec)["S"]
        if queries.scene_logits is not None:
            check_shape(queries.scene_logits, "scene_logits", f"{n} {s}")
    if queries.matching is not None:
        check_shape(queries.matching.images, "matching.images", f"{n} 3 H W")
        check_shape(queries.matching.intrinsics, "matching.intrinsics", f"{n} 4")


def _log_prior(scene_logits: Tensor | None) -> Tensor | None:
    return None if scene_logits is None else scene_logits.float().log_softmax(-1)


def _voted(queries: Queries, starts: Tensor, sequences: Sequences | None) -> tuple[Tensor, Tensor]:
    """Scenes [B] voted by sequence where the options say so, and the starts [B, 7] in them:
    the multi-scene APR's pose for a query's new scene (its first start there)."""
    scenes, scene_poses = queries.scenes, queries.scene_poses
    if sequences is None or not sequences.options.vote_scene:
        return scenes, starts
    voted = vote_scenes(scenes, sequences.ids)
    if scene_poses is None:
        return voted, starts
    rows = torch.arange(len(voted), device=voted.device)
    there = scene_poses[rows, voted]
    there = there[:, 0] if there.dim() == 3 else there
    return voted, torch.where((voted != scenes)[:, None], there.to(starts), starts)


def _propagated(
    refiner: RenderCompareRefiner,
    queries: Queries,
    scenes: Tensor,
    result: RenderCompareResult,
    sequences: Sequences | None,
) -> RenderCompareResult:
    if sequences is None or not sequences.options.passes:
        return result
    return propagate(
        refiner, queries.images, queries.intrinsics, scenes, result, sequences.ids,
        sequences.options.passes,
    )  # fmt: skip


def _filtered(poses: Tensor, scenes: Tensor, sequences: Sequences | None) -> Tensor:
    if sequences is None:
        return poses
    return window_filter(poses, sequences.ids, scenes, sequences.options)


def _refine_in_scenes(
    refiner: RenderCompareRefiner,
    queries: Queries,
    starts: Tensor,
    scenes: Tensor,
    rule: SceneRule,
) -> tuple[RenderCompareResult, Tensor, Tensor]:
    first = refiner(queries.images, queries.intrinsics, starts, scenes)
    if queries.scene_poses is None:
        return first, scenes, torch.zeros_like(scenes, dtype=torch.bool)
    probe = functools.partial(sharpness, refiner)
    decision = decide_scenes(
        refiner, probe, queries.images, queries.intrinsics, queries.scene_poses, scenes, first,
        rule, _log_prior(queries.scene_logits),
    )  # fmt: skip
    return decision.result, decision.scene, decision.checked


def _finish(
    refiner: RenderCompareRefiner,
    queries: Queries,
    starts: Tensor,
    sequences: Sequences | None,
    decided: tuple[RenderCompareResult, Tensor, Tensor],
    match: MatchSettings,
    gate_for: Callable[[RenderCompareResult], tuple[float, float]],
) -> tuple[Calibration, Refinement]:
    """After the scene decision (``decided``: result, scenes, checked): the other starts of
    the correspondence stage ``match``, the sequence passes, the gate whose margin and floor
    ``gate_for`` gives for the result, and the sequence window."""
    result, scenes, checked = decided
    matched = with_other_starts(
        refiner, queries.images, queries.intrinsics, starts, queries.scenes, scenes, result,
        match, queries.matching,
    )  # fmt: skip
    result = _propagated(refiner, queries, scenes, matched.result, sequences)
    margin, floor = gate_for(result)
    gated = gate(result, starts, margin, floor)
    poses = _filtered(gated.poses, scenes, sequences)
    refinement = Refinement(
        poses, gated.accepted, result, scenes, checked, matched.matched, matched.from_match
    )
    return Calibration(margin, floor), refinement


def refine(
    scene_model: SceneModel,
    queries: Queries,
    starts: Tensor,
    calibration: Calibration | None = None,
    sequences: Sequences | None = None,
    settings: Settings = None,
) -> Refinement:
    """Refine starts [B, 7] (camera-to-world, unit quaternions) of ``queries``
    (:class:`Queries`) against ``scene_model``; ``calibration`` gives the gate, first steps,
    scene rule and correspondence stage chosen on validation (:func:`calibrate`; default:
    margin 0, no floor, the settings' steps, no scene check, no stage); with the queries'
    ``sequences`` (:class:`Sequences`) their options say how the refinement uses the frame
    order (:mod:`pae.render_compare.sequences`); ``settings`` replace the refiner's defaults
    (:data:`Settings`). With ``queries.scene_poses`` the calibration's scene rule decides each
    query's scene; with ``queries.matching`` the calibration's correspondence stage gives
    each query other starts, refined too, the best-scoring refinement kept."""
    _check(queries, starts, sequences)
    scenes, starts = _voted(queries, starts, sequences)
    calibration = calibration or Calibration()
    refiner = build_refiner(scene_model, settings, calibration.steps)
    decided = _refine_in_scenes(refiner, queries, starts, scenes, calibration.scene)
    kept = (calibration.accept_margin, calibration.accept_score)
    voted = queries._replace(scenes=scenes)
    return _finish(refiner, voted, starts, sequences, decided, calibration.match, lambda _: kept)[1]


class _Trial(NamedTuple):
    """One calibration tried on val: a filter (refiner settings), a correspondence stage and
    the sequences (None: each query on its own)."""

    filter: Mapping[str, float]
    match: Mapping[str, Any]
    sequences: Sequences | None


def _calibrate_once(
    scene_model: SceneModel,
    val: Validation,
    options: CalibrationOptions,
    settings: Settings,
    trial: _Trial,
) -> tuple[Calibration, Refinement]:
    """The calibration under one filter, stage and sequences: the first steps, the scene
    rule, then the gate that minimises the options' objective."""
    queries, truth = val.queries, val.truth
    scenes, starts = _voted(queries, val.starts, trial.sequences)
    fractions = options.step_from_val
    steps = {} if fractions is None else steps_from_errors(starts, truth, fractions)
    steps |= dict(trial.filter)
    refiner = build_refiner(scene_model, settings, steps)
    first = refiner(queries.images, queries.intrinsics, starts, scenes)
    decided = first, scenes, torch.zeros_like(scenes, dtype=torch.bool)
    rule = SceneRule()
    scene_poses = queries.scene_poses
    if scene_poses is not None and scene_poses.shape[1] > 1:
        if val.true_scenes is None:
            raise ValueError("calibrate: choosing the scene rule needs Validation.true_scenes")
        every = torch.arange(len(scenes), device=scenes.device)
        probe = functools.partial(sharpness, refiner)
        trials = try_scenes(
            refiner, probe, queries.images, queries.intrinsics, scene_poses, scenes, first,
            every, PROBE_SCALES,
        )  # fmt: skip
        prior = _log_prior(queries.scene_logits)
        below = options.fixed("scene_check_below")
        rule = choose_scene_rule(trials, prior, scenes, val.true_scenes, below)
        keep = (first.score < rule.check_below).nonzero().flatten()
        decision = apply(first, scenes, keep, trials.rows(keep), prior, rule)
        decided = decision.result, decision.scene, decision.checked
    start_pos, _ = pose_errors(starts.float(), truth.float())

    def chosen_gate(result: RenderCompareResult) -> tuple[float, float]:
        refined_pos, _ = pose_errors(result.poses.float(), truth.float())
        return choose_gate(
            result.score - result.initial_score, result.score, refined_pos, start_pos,
            options.fixed("accept_margin"), options.fixed("accept_score"),
            options.gate_objective,
        )  # fmt: skip

    match = MatchSettings(**trial.match)
    gated, refinement = _finish(
        refiner, queries._replace(scenes=scenes), starts, trial.sequences, decided, match,
        chosen_gate,
    )  # fmt: skip
    calibration = dataclasses.replace(gated, steps=steps, scene=rule, match=match)
    return calibration, refinement


def calibrate(
    scene_model: SceneModel,
    val: Validation,
    options: CalibrationOptions | None = None,
    sequences: Sequences | None = None,
    settings: Settings = None,
) -> tuple[Calibration, Refinement]:
    """The calibration chosen on validation queries with their true poses (``val``,
    :class:`Validation`) under ``options`` (:class:`CalibrationOptions`; default: margin
    chosen, no floor, the settings' steps, scene check floor chosen) -> the calibration and
    the validation queries' refinement under it. One objective, the options'
    ``gate_objective`` (:func:`pae.render_compare.calibration.objective_value`), chooses
    everything: each of ``filters_from_val`` is tried on the queries each refined on its own
    and without a correspondence stage (the sequences multiply the refiner's work), the one
    that minimises the objective kept in the calibration's steps; then each of
    ``matches_from_val`` with that filter (where ``val.queries.matching`` is given), the same
    way; then, with the chosen filter and stage and the ``sequences`` (as :func:`refine`'s),
    the first steps as ``step_from_val`` of the starts' median errors, the scene rule that
    maximises accuracy against ``val.true_scenes``
    (:func:`pae.render_compare.scene_decision.choose_scene_rule`, where
    ``val.queries.scene_poses`` hold several scenes) and the gate's margin and floor
    (:func:`pae.render_compare.calibration.choose_gate`; a fixed one kept)."""
    options = options or CalibrationOptions()
    _check(val.queries, val.starts, sequences)
    check_shape(val.truth, "truth", f"{len(val.starts)} 7")
    filters = list(options.filters_from_val or [{}])
    matches = list(options.matches_from_val or [{}])
    if val.queries.matching is None:
        matches = matches[:1]
    staged = len(matches) > 1 or bool(matches[0])
    by_sequence = sequences is not None and sequences.options.active

    def best(trials: list[_Trial]) -> tuple[_Trial, tuple[Calibration, Refinement]]:
        tried = [_calibrate_once(scene_model, val, options, settings, t) for t in trials]
        values = [
            objective_value(r.poses, val.starts, val.truth, options.gate_objective)
            for _, r in tried
        ]
        chosen = min(range(len(tried)), key=values.__getitem__)
        for trial, value in zip(trials, values, strict=True):
            kept = "kept" if trial is trials[chosen] else "tried"
            log.info(
                "calibrate on val: %s %s objective %.4f, filter %s, stage %s",
                kept, options.gate_objective, value, dict(trial.filter), dict(trial.match),
            )  # fmt: skip
        return trials[chosen], tried[chosen]

    found = None  # the chosen trial's calibration, where it ran as it is to be kept
    chosen = _Trial(filters[0], matches[0], sequences)
    if len(filters) > 1:  # each query on its own, without a stage
        chosen, found = best([_Trial(f, {}, None) for f in filters])
        if staged or by_sequence:
            chosen, found = chosen._replace(match=matches[0], sequences=sequences), None
    if len(matches) > 1:  # with the chosen filter, each query on its own
        chosen, found = best([chosen._replace(match=m, sequences=None) for m in matches])
        if by_sequence:
            chosen, found = chosen._replace(sequences=sequences), None
    return found or _calibrate_once(scene_model, val, options, settings, chosen)


def calibrate_any_start(
    scene_model: SceneModel,
    queries: Queries,
    truth: Tensor,
    size_m: float,
    settings: Settings = None,
    options: AnyStartOptions | None = None,
) -> tuple[Calibration, Refinement, Tensor]:
    """The calibration for starts from any APR, whose error scale the run cannot know: on
    validation ``queries`` (their images, intrinsics and scenes) with true poses ``truth``
    [N, 7] and starts at every scale of the ladder
    (:func:`pae.render_compare.calibration.ladder_starts`, ``size_m``: the scene's size, m),
    the first steps among ``STEP_SHARES`` of the size, the filter among the settings' own and
    each of ``options.highpass_px`` (px) at every level or the finest only, with no local
    contrast or each of ``options.contrast_px`` (px, ``contrast_sigma_px``) or each of
    ``options.filters`` (over the settings' own), then with those the references'
    ``surface_share`` among the settings' own and ``options.surface_shares``,
    then, where ``queries.matching`` is given, the correspondence stage among none and
    ``options.matches`` (:class:`AnyStartOptions`; where one is kept, the fewest queries it
    goes to among ``options.stage_shares``), and the gate that minimise the mean log
    of each query's error over its start's (``choose_gate(objective="log_ratio")``), so that
    a good start is kept rather than refined to the refiner's floor -> the calibration (its
    ``steps`` holding the chosen steps, filter and surface share, its ``match`` the stage),
    the validation refinement under it and its starts [N, 7]."""
    options = options or AnyStartOptions()
    _check(queries, truth, None)
    starts = ladder_starts(truth, size_m, torch.Generator().manual_seed(options.seed))
    start_pos, _ = pose_errors(starts.float(), truth.float())
    deg_per_share = LADDER_DEG[0] / LADDER[0]
    own = build_refiner(scene_model, settings)
    grid = [(own.highpass_sigma_px, own.highpass_levels, own.contrast_sigma_px)] + [
        (sigma, levels, contrast)
        for sigma in options.highpass_px
        for levels in (0, 1)
        for contrast in (0.0, *options.contrast_px)
    ]
    keys = ("highpass_sigma_px", "highpass_levels", "contrast_sigma_px")
    filters = dict.fromkeys(
        tuple(dict(zip(keys, chosen, strict=True)).items()) for chosen in grid
    ) | dict.fromkeys(
        tuple((dict(zip(keys, grid[0], strict=True)) | dict(extra)).items())
        for extra in options.filters
    )

    def evaluate(
        steps: dict[str, float],
        match: MatchSettings | None = None,
        first: RenderCompareResult | None = None,
    ) -> tuple[float, Calibration, Refinement]:
        """The objective, calibration and val refinement under ``steps`` and ``match``;
        ``first``: the refinement from the starts under those steps, where already made."""
        match = match or MatchSettings()
        refiner = build_refiner(scene_model, settings, steps)
        if first is None:
            first = refiner(queries.images, queries.intrinsics, starts, queries.scenes)
        decided = first, queries.scenes, torch.zeros_like(queries.scenes, dtype=torch.bool)

        def chosen_gate(result: RenderCompareResult) -> tuple[float, float]:
            refined_pos, _ = pose_errors(result.poses.float(), truth.float())
            gains = result.score - result.initial_score
            return choose_gate(gains, result.score, refined_pos, start_pos, objective="log_ratio")

        gated, refinement = _finish(
            refiner, queries, starts, None, decided, match, chosen_gate
        )  # fmt: skip
        value = objective_value(refinement.poses, starts, truth, "log_ratio")
        log.info(
            "calibrate for any start on val: log_ratio objective %.4f, steps %s, stage %s",
            value, steps, dataclasses.asdict(match) if match.active else {},
        )  # fmt: skip
        return value, dataclasses.replace(gated, steps=steps, match=match), refinement

    best = min(
        (
            evaluate(
                {
                    "position_sigma_m": share * size_m,
                    "orientation_sigma_deg": share * deg_per_share,
                    **dict(chosen),
                }
            )
            for chosen, share in itertools.product(filters, STEP_SHARES)
        ),
        key=lambda tried: tried[0],
    )
    chosen = dict(best[1].steps)
    for surface in dict.fromkeys(options.surface_shares):
        if surface != own.surface_share:
            tried = evaluate(chosen | {"surface_share": surface})
            best = tried if tried[0] < best[0] else best
    if queries.matching is not None:
        chosen, plain = dict(best[1].steps), best[2].result  # no stage: the search made once
        for match in options.stages()[1:]:
            tried = evaluate(chosen, match, plain)
            best = tried if tried[0] < best[0] else best
        if best[1].match.active:
            fewer = functools.partial(evaluate, chosen, first=plain)
            best = _fewest_staged(best, options.stage_shares, plain.score, fewer)
    return best[1], best[2], starts


def _fewest_staged(
    best: tuple[float, Calibration, Refinement],
    shares: Sequence[float],
    scores: Tensor,
    evaluate: Callable[[MatchSettings], tuple[float, Calibration, Refinement]],
) -> tuple[float, Calibration, Refinement]:
    """``best`` (its objective, calibration and val refinement, its stage as listed) or,
    trying ``shares`` from the smallest, the first whose stage goes only to the queries
    scoring below that quantile of ``scores`` [N] (the refinements from their starts) and
    whose objective stays within ``STAGE_SHARE_TOLERANCE`` of ``best``'s."""
    match = best[1].match
    for share in sorted(shares):
        below = float(torch.quantile(scores.float(), share))
        tried = evaluate(dataclasses.replace(match, below_score=below))
        kept = tried[0] <= best[0] + STAGE_SHARE_TOLERANCE
        log.info(
            "calibrate for any start on val: the stage for the %.0f %% scoring below %.3f: "
            "objective %.4f against %.4f as listed, %s",
            100 * share, below, tried[0], best[0], "kept" if kept else "not kept",
        )  # fmt: skip
        if kept:
            return tried
    return best
