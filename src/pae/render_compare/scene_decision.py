"""Render-and-compare's scene decision for multi-scene teachers. A query refined in the scene
the teacher predicted but explained poorly there (its refined score below a floor) is refined
in every other scene too, from the teacher's pose for that scene, and each scene's evidence
is weighed: the refined score itself or how sharply the scene model determines the refined
pose (its score minus the mean score of probe poses around it: a scene whose rendering only
happens to correlate with the query scores about as well a few centimetres and a degree away),
plus the teacher's own log-probability of the scene times a weight. The query moves to the
scene with the most evidence only where that beats its predicted scene's by a margin >= 0, so
no query moves to a scene with weaker evidence than its own. What the evidence is, the
weight, the margin and the floor are chosen on validation (:func:`choose_scene_rule`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from pae.core.pose_sampling import perturb
from pae.render_compare.gate import ACCEPT_ALL, RenderCompareResult
from pae.render_compare.refiner import RenderCompareRefiner

NEVER = ACCEPT_ALL
"""A score floor below every score (scores lie in [-2, 1]): no query is checked in the
other scenes."""
ALWAYS = 2.0
"""A score floor above every score: every query is checked in every scene."""
CHECK_QUANTILES = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9)
"""Candidate floors of :func:`choose_scene_rule` besides NEVER and ALWAYS: these quantiles of
the validation queries' scores in their predicted scenes."""
PROBE_M = 0.05
PROBE_DEG = 1.0
"""The probe poses' unit steps: each probe moves the refined pose by ``scale x PROBE_M``
(m) along one world axis or turns it by ``scale x PROBE_DEG`` (deg) about one camera axis,
both signs: 12 probes per scale."""
PROBE_SCALES = (1.0, 3.0)
"""The probe scales :func:`choose_scene_rule` tries (0 stands for the refined score)."""
PRIOR_WEIGHTS = (0.0, 0.01, 0.03, 0.1, 0.3)
"""Candidate weights (score units per nat) of the teacher's scene log-probabilities."""
MOVE_MARGINS = (0.0, 0.02, 0.05, 0.1, 0.2)
"""Candidate margins (score units) by which another scene's evidence must beat the
predicted scene's."""

Refine = Callable[..., RenderCompareResult]
"""``refine(images [B, 3, h, w], intrinsics [B, 4], starts [B, 7], scenes [B], keys=None)``;
``keys`` [B] (int64): each row's random draws from its key alone
(:meth:`pae.render_compare.refiner.RenderCompareRefiner.keyed_draws`)."""
Probe = Callable[[Tensor, Tensor, Tensor, Tensor, tuple[float, ...]], Tensor]
"""``probe(images, intrinsics, poses [B, 7], scenes [B], scales [K]) -> sharpness [B, K]``:
the score at each pose minus the mean score of its probes at each scale
(:func:`sharpness`)."""


@dataclasses.dataclass(frozen=True)
class SceneRule:
    """How a query's scene is decided: queries whose refined score in the predicted scene is
    below ``check_below`` (a ZNCC; ``NEVER``: none) are refined in the other scenes; a
    scene's evidence is its refined score (``probe_scale`` 0) or its sharpness at that probe
    scale, plus ``prior_weight`` x the teacher's log-probability of the scene; a query moves
    where another scene's evidence beats its predicted scene's by more than ``margin``."""

    check_below: float = NEVER
    probe_scale: float = 0.0
    prior_weight: float = 0.0
    margin: float = 0.0

    def __post_init__(self) -> None:
        if self.probe_scale < 0 or self.prior_weight < 0 or self.margin < 0:
            raise ValueError(f"a scene rule's scale, weight and margin must be >= 0: {self}")


class SceneDecision(NamedTuple):
    """result: the refinement in the decided scene (poses, score, initial_score [N]; the
    initial score of the teacher's pose in that scene); scene [N]: the decided scene;
    checked [N] bool: queries also refined in the other scenes."""

    result: RenderCompareResult
    scene: Tensor
    checked: Tensor


class SceneTrials(NamedTuple):
    """Every query of a set refined in every scene: result fields [Q, S] (poses [Q, S, 7]);
    sharpness [Q, S, K] at each probe scale of ``scales`` [K]."""

    result: RenderCompareResult
    sharpness: Tensor
    scales: tuple[float, ...]

    def rows(self, keep: Tensor) -> SceneTrials:
        """The trials of the queries ``keep`` (indices or a mask over Q)."""
        result = RenderCompareResult(*(field[keep] for field in self.result))
        return SceneTrials(result, self.sharpness[keep], self.scales)


def probe_steps(scale: float, device: torch.device | str = "cpu") -> Tensor:
    """The 12 probe steps [12, 6] (:func:`pae.core.pose_sampling.perturb`'s: m, rad) at
    ``scale``."""
    eye = torch.eye(3, dtype=torch.float64)
    move = torch.cat([eye, -eye]) * PROBE_M * scale
    turn = torch.cat([eye, -eye]) * math.radians(PROBE_DEG * scale)
    zeros = torch.zeros(6, 3, dtype=torch.float64)
    steps = torch.cat([torch.cat([move, zeros], 1), torch.cat([zeros, turn], 1)])
    return steps.to(device)


def sharpness(
    refiner: RenderCompareRefiner,
    images: Tensor,
    intrinsics: Tensor,
    poses: Tensor,
    scenes: Tensor,
    scales: tuple[float, ...] = PROBE_SCALES,
) -> Tensor:
    """How sharply ``refiner``'s scene model determines poses [B, 7] of query images [B, 3,
    h, w] (RGB in [0, 1], intrinsics [B, 4] px) in scenes [B]: at the finest pyramid level,
    against a rendering at each pose, the score of the pose minus the mean score of its 12
    probes at each of ``scales`` (:func:`probe_steps`) -> [B, K] (score units)."""
    parts = []
    poses = poses.float()
    steps = torch.cat([probe_steps(s) for s in scales]).to(poses)  # [12 K, 6]
    chunk = refiner.chunk_for(poses.device)
    for rows in torch.arange(len(poses), device=poses.device).split(chunk):
        level = refiner.pyramid(images[rows].float(), intrinsics[rows], scenes[rows])[-1]
        surface = None
        if refiner.scene_model.has_depth:
            size = refiner.final_reference_size or refiner.reference_size
            reference = refiner.reference(poses[rows], level, size, refiner.final_fov_scale)
            surface = refiner.surface(reference, level)
        centre = poses[rows, None]
        probes = perturb(centre.expand(-1, len(steps), -1), steps.expand(len(rows), -1, -1))
        scores = refiner.score_poses(torch.cat([centre, probes], 1), level, surface)
        probe_mean = scores[:, 1:].view(len(rows), len(scales), -1).mean(-1)
        parts.append(scores[:, :1] - probe_mean)
    return torch.cat(parts)


def _pairs(query: Tensor, scenes: int, exclude: Tensor | None) -> tuple[Tensor, Tensor]:
    """Rows and scenes of every (query, scene) pair, scene-major within a query; without
    each query's ``exclude`` scene where given."""
    grid = torch.arange(scenes, device=query.device).expand(len(query), scenes)
    if exclude is not None:
        grid = grid[grid != exclude[:, None]].reshape(len(query), scenes - 1)
    return query.repeat_interleave(grid.shape[1]), grid.flatten()


def try_scenes(
    refine: Refine,
    probe: Probe,
    images: Tensor,
    intrinsics: Tensor,
    scene_poses: Tensor,
    predicted: Tensor,
    first: RenderCompareResult,
    query: Tensor,
    scales: tuple[float, ...],
) -> SceneTrials:
    """The queries ``query`` [Q] refined in every scene: their ``first`` refinement in the
    ``predicted`` scene [N] kept, every other scene refined from each start for it
    (``scene_poses`` [N, S, 7], the teacher's pose, or [N, S, K, 7], K starts:
    :mod:`pae.render_compare.scene_starts`) in one batched call, keeping the best-scoring
    start's (ties: the first), and every scene's sharpness at ``scales`` ->
    :class:`SceneTrials` of the Q queries. Each (query, scene, start) draws from its own key,
    so a query's trials do not depend on which other queries are tried beside it."""
    q, s = len(query), scene_poses.shape[1]
    starts = scene_poses if scene_poses.dim() == 4 else scene_poses[:, :, None]
    k = starts.shape[2]
    pair_query, pair_scene = _pairs(query, s, predicted[query])
    keys = ((pair_query * s + pair_scene) * k)[:, None] + torch.arange(k, device=query.device)
    tried = refine(
        images[pair_query].repeat_interleave(k, 0),
        intrinsics[pair_query].repeat_interleave(k, 0),
        starts[pair_query, pair_scene].reshape(-1, 7),
        pair_scene.repeat_interleave(k),
        keys=keys.flatten(),
    )
    best = tried.score.view(len(pair_query), k).argmax(1)
    pick = torch.arange(len(pair_query), device=best.device) * k + best
    pairs = RenderCompareResult(*(field[pick] for field in tried))
    own = predicted[query]
    fields = []
    for mine, theirs in zip(first, pairs, strict=True):
        whole = mine.new_zeros((q, s, *mine.shape[1:]))
        whole[torch.arange(q, device=query.device), own] = mine[query]
        others = torch.ones(q, s, dtype=torch.bool, device=query.device)
        others[torch.arange(q, device=query.device), own] = False
        whole[others] = theirs.to(whole).reshape(-1, *mine.shape[1:])
        fields.append(whole)
    trials = RenderCompareResult(*fields)
    if not scales:
        return SceneTrials(trials, trials.score.new_zeros(q, s, 0), scales)
    every_query, every_scene = _pairs(query, s, None)
    sharp = probe(
        images[every_query],
        intrinsics[every_query],
        trials.poses.reshape(-1, 7),
        every_scene,
        scales,
    )
    return SceneTrials(trials, sharp.reshape(q, s, len(scales)), scales)


def evidence(
    trials: SceneTrials, log_prior: Tensor | None, probe_scale: float, prior_weight: float
) -> Tensor:
    """Every trial's evidence [Q, S]: its refined score (``probe_scale`` 0) or its sharpness
    at ``probe_scale`` (one of those in ``trials``), plus ``prior_weight`` x the teacher's
    scene log-probabilities ``log_prior`` [Q, S] (None: no prior)."""
    if probe_scale == 0:
        base = trials.result.score.float()
    elif probe_scale in trials.scales:
        base = trials.sharpness[..., trials.scales.index(probe_scale)].float()
    else:
        raise ValueError(f"probe scale {probe_scale} was not tried: {trials.scales}")
    if log_prior is None or prior_weight == 0:
        return base
    return base + prior_weight * log_prior.float()


def moves(values: Tensor, own: Tensor, margin: float) -> Tensor:
    """Per query of evidence [Q, S] and predicted scene [Q]: the scene with the most evidence
    where it beats the predicted scene's by more than ``margin``, else the predicted scene
    [Q] (ties: the predicted scene)."""
    rows = torch.arange(len(own), device=own.device)
    mine = values[rows, own]
    others = values.clone()
    others[rows, own] = -math.inf
    best, scene = others.max(1)
    return torch.where(best > mine + margin, scene, own)


def decide_scenes(
    refine: Refine,
    probe: Probe,
    images: Tensor,
    intrinsics: Tensor,
    scene_poses: Tensor,
    predicted: Tensor,
    first: RenderCompareResult,
    rule: SceneRule,
    log_prior: Tensor | None = None,
) -> SceneDecision:
    """Decide the scene of every query under ``rule``: those whose score in their
    ``predicted`` scene [N] (``first``, the refinement there) is below ``rule.check_below``
    are tried in every scene (:func:`try_scenes`, from the starts of every scene
    ``scene_poses`` [N, S, 7] or [N, S, K, 7]) and moved where the evidence says (:func:`moves`; the
    teacher's scene log-probabilities ``log_prior`` [N, S], None: no prior)."""
    checked = first.score < rule.check_below
    if scene_poses.shape[1] < 2 or not bool(checked.any()):
        return SceneDecision(first, predicted, checked)
    query = checked.nonzero().flatten()
    scales = (rule.probe_scale,) if rule.probe_scale else ()
    trials = try_scenes(
        refine, probe, images, intrinsics, scene_poses, predicted, first, query, scales
    )
    return apply(first, predicted, query, trials, log_prior, rule)


def apply(
    first: RenderCompareResult,
    predicted: Tensor,
    query: Tensor,
    trials: SceneTrials,
    log_prior: Tensor | None,
    rule: SceneRule,
) -> SceneDecision:
    """``first`` (the refinement in the ``predicted`` scenes [N]) with the queries ``query``
    [Q] (tried in every scene: ``trials``; log-probabilities ``log_prior`` [N, S] or None)
    taking their trial in the scene ``rule`` decides on."""
    prior = None if log_prior is None else log_prior[query]
    values = evidence(trials, prior, rule.probe_scale, rule.prior_weight)
    decided = moves(values, predicted[query], rule.margin)
    rows = torch.arange(len(query), device=query.device)
    fields = [f.clone() for f in first]
    for field, tried in zip(fields, trials.result, strict=True):
        field[query] = tried[rows, decided].to(field)
    scene = predicted.clone()
    scene[query] = decided
    checked = torch.zeros_like(predicted, dtype=torch.bool)
    checked[query] = True
    return SceneDecision(RenderCompareResult(*fields), scene, checked)


def choose_scene_rule(
    trials: SceneTrials,
    log_prior: Tensor | None,
    predicted: Tensor,
    truth: Tensor,
    check_below: float | None = None,
) -> SceneRule:
    """The rule that maximises scene accuracy over validation queries tried in every scene
    (``trials`` of all N queries; teacher's log-probabilities ``log_prior`` [N, S] or None;
    predicted [N] and true scenes [N]): the evidence (score, or sharpness at each of
    ``PROBE_SCALES``), ``PRIOR_WEIGHTS``, ``MOVE_MARGINS`` and floors (NEVER, ALWAYS and
    ``CHECK_QUANTILES`` of the predicted scenes' scores; a given ``check_below`` is kept).
    Ties: the fewest queries moved; then the evidence and weight that alone (every query's
    scene its argmax) name the most queries' true scene, over all N queries rather than the
    few mispredicted ones; then the highest floor and the smallest margin, which fix the
    most mispredictions among rules that move no more validation queries."""
    if not len(predicted):
        return SceneRule(NEVER if check_below is None else check_below)
    rows = torch.arange(len(predicted), device=predicted.device)
    own_score = trials.result.score[rows, predicted].float().cpu()
    quantiles = own_score.quantile(torch.tensor(CHECK_QUANTILES))
    floors = torch.cat([torch.tensor([NEVER, ALWAYS]), quantiles]).sort().values
    if check_below is not None:
        floors = torch.tensor([float(check_below)])
    checked = own_score[None, :] < floors[:, None]  # [F, N]
    weights = PRIOR_WEIGHTS if log_prior is not None else (0.0,)
    best: tuple[tuple[float, ...], SceneRule] | None = None
    for scale in (0.0, *trials.scales):
        for weight in weights:
            values = evidence(trials, log_prior, scale, weight)
            alone = float((values.argmax(1) == truth).float().mean())
            for margin in MOVE_MARGINS:
                target = moves(values, predicted, margin).cpu()
                decided = torch.where(checked, target, predicted.cpu())  # [F, N]
                accuracy = (decided == truth.cpu()).float().mean(1)
                moved = (decided != predicted.cpu()).sum(1).float()
                for f in range(len(floors)):
                    key = (-float(accuracy[f]), float(moved[f]), -alone, -float(floors[f]), margin)
                    if best is None or key < best[0]:
                        best = (key, SceneRule(float(floors[f]), scale, weight, margin))
    assert best is not None
    return best[1]
