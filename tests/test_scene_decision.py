"""Render-and-compare's scene decision: queries explained poorly in their predicted scene are
refined in the others and moved to the one that explains them."""

from __future__ import annotations

import torch
from torch import Tensor

from pae.render_compare.gate import RenderCompareResult
from pae.render_compare.scene_decision import (
    ALWAYS,
    NEVER,
    choose_scene_check,
    decide_scenes,
    narrow,
)

SCENES = 3


def _queries(n: int = 12) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Images carrying each query's id, intrinsics, the teacher's poses for every scene
    [N, S, 7] (position x = 10 × scene + query id), and the true scenes [N]."""
    ids = torch.arange(n, dtype=torch.float)
    images = ids[:, None, None, None].expand(n, 3, 4, 4).clone()
    intrinsics = torch.ones(n, 4)
    scene_poses = torch.zeros(n, SCENES, 7)
    scene_poses[..., 3] = 1
    scene_poses[..., 0] = 10 * torch.arange(SCENES)[None, :] + ids[:, None]
    truth = torch.arange(n) % SCENES
    return images, intrinsics, scene_poses, truth


def _refiner(truth: Tensor, calls: list[int]):
    """A stand-in refiner: a query (its id in its image) scores 0.9 in its true scene and 0.2
    elsewhere; the refined pose is the start moved by 0.5 m along y."""

    def refine(images: Tensor, intrinsics: Tensor, starts: Tensor, scenes: Tensor):
        calls.append(len(images))
        query = images[:, 0, 0, 0].long()
        right = scenes == truth[query]
        score = torch.where(right, torch.tensor(0.9), torch.tensor(0.2))
        poses = starts.clone()
        poses[:, 1] += 0.5
        return RenderCompareResult(poses, score, score - 0.1)

    return refine


def test_a_wrongly_predicted_query_is_moved_to_the_scene_that_explains_it() -> None:
    images, intrinsics, scene_poses, truth = _queries()
    predicted = truth.clone()
    wrong = torch.tensor([1, 5, 7])
    predicted[wrong] = (truth[wrong] + 1) % SCENES
    calls: list[int] = []
    refine = _refiner(truth, calls)
    rows = torch.arange(len(truth))
    first = refine(images, intrinsics, scene_poses[rows, predicted], predicted)
    decision = decide_scenes(refine, images, intrinsics, scene_poses, predicted, first, 0.5)
    assert torch.equal(decision.scene, truth)
    assert torch.equal(decision.checked.nonzero().flatten(), wrong)
    assert calls == [len(truth), len(wrong) * (SCENES - 1)], "one batched call for the pairs"
    # moved queries: refined from the teacher's pose for their true scene
    expected = scene_poses[wrong, truth[wrong]].clone()
    expected[:, 1] += 0.5
    assert torch.equal(decision.result.poses[wrong], expected)
    assert torch.allclose(decision.result.score[wrong], torch.full((3,), 0.9))
    kept = torch.ones(len(truth), dtype=torch.bool)
    kept[wrong] = False
    assert torch.equal(decision.result.poses[kept], first.poses[kept])

    never = decide_scenes(refine, images, intrinsics, scene_poses, predicted, first, NEVER)
    assert torch.equal(never.scene, predicted) and not never.checked.any()
    assert len(calls) == 2, "no query checked: no second call"


def test_the_check_floor_is_chosen_for_scene_accuracy_and_narrowing_equals_deciding() -> None:
    images, intrinsics, scene_poses, truth = _queries()
    predicted = truth.clone()
    predicted[[2, 4]] = (truth[[2, 4]] + 2) % SCENES
    refine = _refiner(truth, [])
    rows = torch.arange(len(truth))
    first = refine(images, intrinsics, scene_poses[rows, predicted], predicted)
    every = decide_scenes(refine, images, intrinsics, scene_poses, predicted, first, ALWAYS)
    floor = choose_scene_check(first.score, predicted, every.scene, truth)
    assert 0.2 < floor <= 0.9, "the lowest floor that checks the two wrong queries"
    narrowed = narrow(every, first, predicted, first.score < floor)
    decided = decide_scenes(refine, images, intrinsics, scene_poses, predicted, first, floor)
    assert torch.equal(narrowed.scene, decided.scene)
    assert torch.equal(narrowed.checked, decided.checked)
    for ours, theirs in zip(narrowed.result, decided.result, strict=True):
        assert torch.equal(ours, theirs)
    assert torch.equal(decided.scene, truth)
    right = choose_scene_check(first.score, truth, truth, truth)
    assert right == NEVER, "every prediction right: nothing is checked"
