"""Render-and-compare's scene decision for multi-scene teachers: a query refined in the scene
the teacher predicted but explained poorly there (a low score) is refined in every other
scene too, from the teacher's pose for that scene, and moved to the scene whose scene model
explains it best. A wrong scene prediction is then not refined into a confident wrong pose
unless no other scene explains the query better."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from pae.render_compare.gate import ACCEPT_ALL, RenderCompareResult

NEVER = ACCEPT_ALL
"""A score floor below every score (scores lie in [-2, 1]): no query is checked in the
other scenes."""
ALWAYS = 2.0
"""A score floor above every score: every query is checked in every scene."""
CHECK_QUANTILES = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9)
"""Candidate floors of ``choose_scene_check`` besides NEVER and ALWAYS: these quantiles of
the validation queries' scores in their predicted scenes."""

Refine = Callable[[Tensor, Tensor, Tensor, Tensor], RenderCompareResult]
"""``refine(images [B, 3, h, w], intrinsics [B, 4], starts [B, 7], scenes [B])``."""


class SceneDecision(NamedTuple):
    """result: the refinement in the decided scene (poses, score, initial_score [N]; the
    initial score of the teacher's pose in that scene); scene [N]: the decided scene;
    checked [N] bool: queries also refined in the other scenes."""

    result: RenderCompareResult
    scene: Tensor
    checked: Tensor


def decide_scenes(
    refine: Refine,
    images: Tensor,
    intrinsics: Tensor,
    scene_poses: Tensor,
    predicted: Tensor,
    first: RenderCompareResult,
    below: float,
) -> SceneDecision:
    """Refine every query whose score in its ``predicted`` scene [N] (``first``, the
    refinement there) is below ``below`` in each other scene too, from the teacher's poses
    of every scene ``scene_poses`` [N, S, 7], in one batched call, and keep per query the
    scene with the highest refined score."""
    scenes = scene_poses.shape[1]
    checked = first.score < below
    if scenes < 2 or not bool(checked.any()):
        return SceneDecision(first, predicted, checked)
    query = checked.nonzero().flatten()
    others = torch.arange(scenes, device=predicted.device).expand(len(query), scenes)
    others = others[others != predicted[query, None]].reshape(len(query), scenes - 1)
    pair_query = query.repeat_interleave(scenes - 1)
    pair_scene = others.flatten()
    pair_start = scene_poses[pair_query, pair_scene]
    pairs = refine(images[pair_query], intrinsics[pair_query], pair_start, pair_scene)
    # per checked query: its predicted scene's refinement, then each other scene's
    score = torch.cat([first.score[query, None], pairs.score.view(len(query), -1)], 1)
    best = score.argmax(1)  # ties: the predicted scene
    chosen = torch.where(best > 0, others.gather(1, (best - 1).clamp(min=0)[:, None])[:, 0], -1)
    moved = chosen >= 0
    pair_rows = torch.arange(len(query), device=query.device) * (scenes - 1) + best - 1
    target = query[moved]
    source = pair_rows[moved]
    poses, final, initial = first.poses.clone(), first.score.clone(), first.initial_score.clone()
    poses[target] = pairs.poses[source].to(poses)
    final[target] = pairs.score[source].to(final)
    initial[target] = pairs.initial_score[source].to(initial)
    decided = predicted.clone()
    decided[target] = chosen[moved]
    return SceneDecision(RenderCompareResult(poses, final, initial), decided, checked)


def narrow(
    decision: SceneDecision, first: RenderCompareResult, predicted: Tensor, keep: Tensor
) -> SceneDecision:
    """``decision`` (made with every query checked) for only the queries ``keep`` [N] bool
    checked: the others keep ``first``, their refinement in their ``predicted`` scene [N]."""
    poses = torch.where(keep[:, None], decision.result.poses, first.poses)
    score = torch.where(keep, decision.result.score, first.score)
    initial = torch.where(keep, decision.result.initial_score, first.initial_score)
    scene = torch.where(keep, decision.scene, predicted)
    return SceneDecision(RenderCompareResult(poses, score, initial), scene, keep)


def choose_scene_check(
    scores: Tensor, predicted: Tensor, decided_if_checked: Tensor, truth: Tensor
) -> float:
    """The score floor below which queries are checked in the other scenes that maximises
    scene accuracy over queries with scores [N] in their predicted scenes [N], the scenes
    [N] they would be moved to if checked, and their true scenes [N]: NEVER, ALWAYS and
    ``CHECK_QUANTILES`` of the scores; the lowest floor wins ties (the fewest checks)."""
    if not len(scores):
        return NEVER
    quantiles = scores.float().quantile(scores.new_tensor(CHECK_QUANTILES, dtype=torch.float))
    floors = torch.cat([torch.tensor([NEVER, ALWAYS]), quantiles.cpu()]).sort().values
    checked = scores.float().cpu()[None, :] < floors[:, None]  # [F, N]
    decided = torch.where(checked, decided_if_checked.cpu(), predicted.cpu())
    accuracy = (decided == truth.cpu()).float().mean(1)
    return float(floors[int(accuracy.argmax())])
