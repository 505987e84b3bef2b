"""Other starts than the APR's for each query (:mod:`pae.render_compare.correspondences`):
the pose its keypoint correspondences give and the poses of the train views nearest it by
appearance, each refined, the best-scoring refinement kept."""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import NamedTuple

import torch
from torch import Tensor

from pae.render_compare.correspondences import MatchQueries, MatchSettings, correspond
from pae.render_compare.gate import RenderCompareResult
from pae.render_compare.refiner import RenderCompareRefiner
from pae.render_compare.train_views import nearest_cameras
from pae.scene_model.base import SceneModel


class OtherStarts(NamedTuple):
    """A refinement after the other starts: its result, which queries' correspondences gave
    a pose [B] and which kept a refinement from another start [B] (None: no stage ran)."""

    result: RenderCompareResult
    matched: Tensor | None
    from_match: Tensor | None


def _extra_starts(
    scene_model: SceneModel,
    starts: Tensor,
    scenes: Tensor,
    match: MatchSettings,
    matching: MatchQueries,
) -> tuple[Tensor, Tensor, Tensor]:
    """Each query's starts beside its APR's [B, H, 7], which of them to refine [B, H] and
    whether correspondences gave it a pose [B]: the pose its correspondences give, then the
    poses of its ``start_views`` train views nearest by descriptor and of the
    ``near_start_views`` train cameras nearest its start."""
    extra, usable = [], []
    found = torch.zeros(len(starts), dtype=torch.bool)
    if match.solves:
        solved = correspond(
            scene_model, matching.images, matching.intrinsics, starts, scenes, match,
            matching.views(scene_model, match), matching.describe,
        )  # fmt: skip
        found = solved.found
        extra.append(solved.poses[:, None])
        usable.append(found[:, None])
    if match.start_views or match.near_start_views:
        train = matching.train
        if train is None:
            raise ValueError(
                "render_compare.match.start_views and near_start_views need MatchQueries.train"
            )
        rows = []
        if match.start_views:
            rows.append(train.nearest(matching.images, scenes, match.start_views))
        rows.append(
            nearest_cameras(starts, scenes, train.poses, train.scenes, match.near_start_views)
        )
        chosen = torch.cat(rows, 1)
        extra.append(train.poses[chosen].to(starts))
        usable.append(torch.ones(chosen.shape, dtype=torch.bool))
    return torch.cat(extra, 1), torch.cat(usable, 1), found


def _refine_usable(
    refiner: RenderCompareRefiner,
    queries: tuple[Tensor, Tensor, Tensor],
    rows: Tensor,
    extra: Tensor,
    usable: Tensor,
) -> tuple[RenderCompareResult, Tensor]:
    """Refine the other starts extra [n, H, 7] of the queries at ``rows`` [n] (of images,
    intrinsics and scenes ``queries``) where ``usable`` [n, H], all in one call -> the
    refinements (in ``usable``'s row-major order) and their scores [n, H] (-inf where not
    usable)."""
    images, intrinsics, scenes = queries
    at = rows[usable.nonzero(as_tuple=True)[0]]
    refined = refiner(images[at], intrinsics[at], extra[usable], scenes[at])
    scores = torch.full(usable.shape, -math.inf)
    scores[usable] = refined.score.float()
    return refined, scores


def _screened(
    refiner: RenderCompareRefiner,
    queries: tuple[Tensor, Tensor, Tensor],
    rows: Tensor,
    extra: Tensor,
    usable: Tensor,
    match: MatchSettings,
) -> tuple[Tensor, Tensor]:
    """The ``match.screen_keep`` other starts of each query (extra [n, H, 7] where ``usable``
    [n, H]) that a short search (``match.screen_rounds`` rounds, no polish) scores highest,
    each moved to where that search ended -> starts [n, keep, 7] and which are usable."""
    short = copy.copy(refiner)
    short.rounds, short.polish_steps, short.final_reference_size = match.screen_rounds, 0, 0
    searched, scores = _refine_usable(short, queries, rows, extra, usable)
    poses = extra.clone()
    poses[usable] = searched.poses.to(poses)
    top, pick = scores.topk(match.screen_keep, dim=1)
    return poses.gather(1, pick[..., None].expand(-1, -1, poses.shape[-1])), top.isfinite()


def _keep_better(
    refiner: RenderCompareRefiner,
    queries: tuple[Tensor, Tensor, Tensor],
    rows: Tensor,
    extra: Tensor,
    usable: Tensor,
    best: RenderCompareResult,
    match: MatchSettings,
) -> tuple[RenderCompareResult, Tensor]:
    """Refine the other starts extra [n, H, 7] of the queries at ``rows`` [n] (of images,
    intrinsics and scenes ``queries``) where ``usable`` [n, H] (the ``match.screen_keep``
    best after a short search, where set: :func:`_screened`), and keep each query's
    best-scoring refinement where it beats ``best``'s score -> the result and which of the
    ``rows`` it moved [n]."""
    moved = torch.zeros(len(rows), dtype=torch.bool)
    if not usable.any():
        return best, moved
    if 0 < match.screen_keep < usable.shape[1]:
        extra, usable = _screened(refiner, queries, rows, extra, usable, match)
    refined, scores = _refine_usable(refiner, queries, rows, extra, usable)
    top, pick = scores.max(1)
    moved = top > best.score[rows].float()
    index = torch.full(usable.shape, -1, dtype=torch.long)
    index[usable] = torch.arange(int(usable.sum()))
    chosen = index[moved, pick[moved]]
    poses, score = best.poses.clone(), best.score.clone()
    poses[rows[moved]] = refined.poses[chosen].to(poses)
    score[rows[moved]] = refined.score[chosen].to(score)
    return RenderCompareResult(poses, score, best.initial_score), moved


def with_other_starts(
    refiner: RenderCompareRefiner,
    images: Tensor,
    intrinsics: Tensor,
    starts: Tensor,
    scenes: Tensor,
    decided: Tensor,
    result: RenderCompareResult,
    match: MatchSettings,
    matching: MatchQueries | None,
) -> OtherStarts:
    """The refinement from the APR's starts, or where one scores higher, a refinement from
    another start (:func:`_extra_starts`), for the queries whose scene the decision kept;
    then ``match.near_best_rounds`` times, from the ``near_start_views`` train cameras
    nearest each query's best pose so far."""
    if not match.active or matching is None:
        return OtherStarts(result, None, None)
    match = dataclasses.replace(match, surface_share=refiner.surface_share)
    found = torch.zeros(len(starts), dtype=torch.bool)
    from_match = torch.zeros_like(found)
    needy = ((decided == scenes) & (result.score < match.below_score)).nonzero().flatten()
    if not len(needy):
        return OtherStarts(result, found, from_match)
    subset = MatchQueries(matching.images[needy], matching.intrinsics[needy], matching.train)
    extra, usable, found[needy] = _extra_starts(
        refiner.scene_model, starts[needy], scenes[needy], match, subset
    )
    queries = (images, intrinsics, decided)
    result, moved = _keep_better(refiner, queries, needy, extra, usable, result, match)
    from_match[needy[moved]] = True
    train = matching.train
    for _ in range(match.near_best_rounds if train is not None else 0):
        rows = nearest_cameras(
            result.poses[needy], scenes[needy], train.poses, train.scenes, match.near_start_views
        )
        near = train.poses[rows].to(starts)
        usable = torch.ones(rows.shape, dtype=torch.bool)
        result, moved = _keep_better(refiner, queries, needy, near, usable, result, match)
        from_match[needy[moved]] = True
    return OtherStarts(result, found, from_match)
