"""Render-and-compare's scene decision: queries explained poorly in their predicted scene are
tried in every scene and moved where the evidence (score or sharpness, with the teacher's
prior) beats their own; the rule is chosen on validation."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
from torch import Tensor

from pae.core.geometry import matrix_to_quaternion, quaternion_to_matrix
from pae.core.pose_sampling import perturb
from pae.render_compare import CalibrationOptions, Queries, Validation, calibrate, refine
from pae.render_compare.api import build_refiner
from pae.render_compare.confusion import confusion_markdown, scene_confusion
from pae.render_compare.gate import RenderCompareResult
from pae.render_compare.scene_decision import (
    ALWAYS,
    NEVER,
    PROBE_SCALES,
    SceneRule,
    choose_scene_rule,
    decide_scenes,
    moves,
    probe_steps,
    sharpness,
    try_scenes,
)
from pae.render_compare.scene_starts import HEADINGS, LATENT_STARTS, heading_starts, latent_starts
from pae.scene_model.oracle import OracleSceneModel
from pae.synthetic import Appearance, PinholeCamera, make_scene, render_batch

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


def _stand_ins(truth: Tensor, calls: list[int], lucky: Tensor | None = None):
    """A stand-in refiner and probe: a query (its id in its image) scores 0.6 in its true
    scene and 0.3 elsewhere, except ``lucky`` queries, which score 0.3 in their true scene
    and 0.8 in the one after it (a wrong room that happens to correlate); the sharpness is
    0.4 in the true
    scene and 0.05 elsewhere. The refined pose is the start moved by 0.5 m along y."""

    def refine(images: Tensor, intrinsics: Tensor, starts: Tensor, scenes: Tensor, keys=None):
        calls.append(len(images))
        query = images[:, 0, 0, 0].long()
        right = scenes == truth[query]
        score = torch.where(right, torch.tensor(0.6), torch.tensor(0.3))
        if lucky is not None:
            fooled = lucky[query] & (scenes == (truth[query] + 1) % SCENES)
            score = torch.where(fooled, torch.tensor(0.8), score)
            score = torch.where(lucky[query] & right, torch.tensor(0.3), score)
        poses = starts.clone()
        poses[:, 1] += 0.5
        return RenderCompareResult(poses, score, score - 0.1)

    def probe(images: Tensor, intrinsics: Tensor, poses: Tensor, scenes: Tensor, scales):
        query = images[:, 0, 0, 0].long()
        right = (scenes == truth[query]).float()
        return (0.05 + 0.35 * right)[:, None].expand(-1, len(scales))

    return refine, probe


def _first(refine, images, intrinsics, scene_poses, predicted) -> RenderCompareResult:
    rows = torch.arange(len(predicted))
    return refine(images, intrinsics, scene_poses[rows, predicted], predicted)


def test_a_wrongly_predicted_query_is_moved_to_the_scene_that_explains_it() -> None:
    images, intrinsics, scene_poses, truth = _queries()
    predicted = truth.clone()
    wrong = torch.tensor([1, 5, 7])
    predicted[wrong] = (truth[wrong] + 1) % SCENES
    calls: list[int] = []
    refine, probe = _stand_ins(truth, calls)
    first = _first(refine, images, intrinsics, scene_poses, predicted)
    rule = SceneRule(check_below=0.5)
    decision = decide_scenes(refine, probe, images, intrinsics, scene_poses, predicted, first, rule)
    assert torch.equal(decision.scene, truth)
    assert torch.equal(decision.checked.nonzero().flatten(), wrong)
    assert calls == [len(truth), len(wrong) * (SCENES - 1)], "one batched call for the pairs"
    # moved queries: refined from the teacher's pose for their true scene
    expected = scene_poses[wrong, truth[wrong]].clone()
    expected[:, 1] += 0.5
    assert torch.equal(decision.result.poses[wrong], expected)
    assert torch.allclose(decision.result.score[wrong], torch.full((3,), 0.6))
    kept = torch.ones(len(truth), dtype=torch.bool)
    kept[wrong] = False
    assert torch.equal(decision.result.poses[kept], first.poses[kept])

    never = decide_scenes(
        refine, probe, images, intrinsics, scene_poses, predicted, first, SceneRule(NEVER)
    )
    assert torch.equal(never.scene, predicted) and not never.checked.any()
    assert len(calls) == 2, "no query checked: no second call"


def test_sharpness_is_chosen_where_a_wrong_room_scores_higher_and_no_right_query_moves() -> None:
    """Two right queries score higher in a wrong room (the raw score would move them); the
    rule chosen on these queries weighs sharpness, fixes the wrong ones and moves no right
    one, and a margin never lets weaker evidence win."""
    images, intrinsics, scene_poses, truth = _queries()
    predicted = truth.clone()
    wrong = torch.tensor([2, 4])
    predicted[wrong] = (truth[wrong] + 2) % SCENES
    lucky = torch.zeros(len(truth), dtype=torch.bool)
    lucky[[0, 6]] = True
    refine, probe = _stand_ins(truth, [], lucky)
    first = _first(refine, images, intrinsics, scene_poses, predicted)
    every = torch.arange(len(truth))
    trials = try_scenes(
        refine, probe, images, intrinsics, scene_poses, predicted, first, every, PROBE_SCALES
    )
    by_score = moves(trials.result.score, predicted, 0.0)
    assert not torch.equal(by_score, truth), "the raw score moves the lucky queries"
    rule = choose_scene_rule(trials, None, predicted, truth)
    assert rule.probe_scale in PROBE_SCALES
    decision = decide_scenes(refine, probe, images, intrinsics, scene_poses, predicted, first, rule)
    assert torch.equal(decision.scene, truth)
    right = predicted == truth
    assert torch.equal(decision.scene[right], predicted[right]), "no right query moved"
    # nothing to fix on these queries: the evidence that alone names every true scene
    # (sharpness, not the lucky raw scores), checking every query, moving none of them
    quiet = choose_scene_rule(trials, None, truth, truth)
    assert quiet.probe_scale in PROBE_SCALES and quiet.check_below == ALWAYS
    first_right = _first(refine, images, intrinsics, scene_poses, truth)
    kept = decide_scenes(refine, probe, images, intrinsics, scene_poses, truth, first_right, quiet)
    assert torch.equal(kept.scene, truth)
    fixed = choose_scene_rule(trials, None, predicted, truth, check_below=ALWAYS)
    assert fixed.check_below == ALWAYS, "a given floor is kept"


def test_no_query_moves_to_weaker_evidence_than_its_own() -> None:
    generator = torch.Generator().manual_seed(0)
    values = torch.rand(500, 4, generator=generator)
    own = torch.randint(4, (500,), generator=generator)
    rows = torch.arange(500)
    for margin in (0.0, 0.05, 0.2):
        decided = moves(values, own, margin)
        moved = decided != own
        assert moved.any()
        assert (values[rows, decided][moved] > values[rows, own][moved] + margin).all()
        stays = values.clone()
        stays[rows, own] = -math.inf
        assert (stays.max(1).values[~moved] <= values[rows, own][~moved] + margin).all()


def test_a_scene_rule_refuses_negative_settings_and_probes_are_symmetric() -> None:
    with pytest.raises(ValueError, match="must be >= 0"):
        SceneRule(margin=-0.1)
    steps = probe_steps(2.0)
    assert steps.shape == (12, 6)
    assert torch.allclose(steps.sum(0), torch.zeros(6, dtype=steps.dtype))
    assert torch.allclose(steps[:3, :3].diagonal(), torch.full((3,), 0.1, dtype=steps.dtype))


def test_the_confusion_table_counts_queries_by_true_and_assigned_scene() -> None:
    truth = torch.tensor([0, 0, 1, 1, 2, 2])
    assigned = torch.tensor([0, 2, 1, 1, 2, 0])
    table = scene_confusion(assigned, truth, 3)
    assert table.tolist() == [[1, 0, 1], [0, 2, 0], [1, 0, 1]]
    text = confusion_markdown({"teacher": table}, ["a", "b", "c"])
    assert "scene accuracy 66.7 %" in text and "| b | 0 | 2 | 0 |" in text
    with pytest.raises(ValueError, match=r"scene ids must lie in \[0, 2\)"):
        scene_confusion(assigned, truth, 2)


def _look(position: list[float], yaw: float) -> Tensor:
    """A camera-to-world pose [7] at ``position`` (m) looking horizontally at ``yaw`` (rad;
    world z up; camera x right, y down, z forward)."""
    forward = torch.tensor([math.cos(yaw), math.sin(yaw), 0.0], dtype=torch.float64)
    down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    rotation = torch.stack([torch.linalg.cross(down, forward), down, forward], 1)
    return torch.cat([torch.tensor(position, dtype=torch.float64), matrix_to_quaternion(rotation)])


def _three_scenes(per_scene: int, seed: int):
    """Queries of the benchmark's scenes 0-2 (32 px) at random poses near each room's
    centre, their intrinsics, true poses and scenes, and the teacher's poses for every scene
    [N, 3, 7]: the true pose moved by about 0.1 m and 2 degrees (the same for every scene)."""
    scenes = [make_scene(i) for i in range(SCENES)]
    camera = PinholeCamera(32)
    rng = np.random.default_rng(seed)
    images, poses, labels = [], [], []
    for index, scene in enumerate(scenes):
        pose = torch.stack(
            [
                _look([*rng.uniform(-0.4, 0.4, 2), 1.4], rng.uniform(0, 2 * math.pi))
                for _ in range(per_scene)
            ]
        )
        rendered = render_batch(scene, pose.numpy(), camera, Appearance(), supersample=1)
        images.append(torch.from_numpy(rendered).float().div(255).permute(0, 3, 1, 2))
        poses.append(pose.float())
        labels += [index] * per_scene
    truth = torch.cat(poses)
    f, c = camera.focal_px, camera.principal_point
    intrinsics = torch.tensor([f, f, c, c]).expand(len(truth), 4)
    generator = torch.Generator().manual_seed(seed)
    steps = torch.cat(
        [0.06 * torch.randn(len(truth), 3, generator=generator),
         0.02 * torch.randn(len(truth), 3, generator=generator)], 1,
    )  # fmt: skip
    start = perturb(truth, steps)
    scene_poses = start[:, None].expand(-1, SCENES, -1).contiguous()
    model = OracleSceneModel(scenes)
    return model, torch.cat(images), intrinsics, truth, torch.tensor(labels), scene_poses


SMALL = {
    "rounds": 3,
    "candidates": 8,
    "hypotheses": 2,
    "resolution": 32,
    "levels": 2,
    "reference_size": 16,
    "final_reference_size": 16,
    "position_sigma_m": 0.08,
    "orientation_sigma_deg": 2.0,
}


def test_a_wrong_scene_on_a_three_scene_benchmark_is_moved_to_the_right_one() -> None:
    """Chosen on validation queries (two of them predicted in a wrong scene), the scene
    rule moves a test query predicted in a wrong scene to its true scene against the
    benchmark's own renderer, and moves no correctly predicted query."""
    model, images, intrinsics, truth, scenes, scene_poses = _three_scenes(3, seed=1)
    predicted = scenes.clone()
    predicted[[1, 5]] = (scenes[[1, 5]] + 1) % SCENES
    start = scene_poses[:, 0]
    queries = Queries(images, intrinsics, predicted, scene_poses)
    calibration, val = calibrate(
        model, Validation(queries, start, truth, scenes), CalibrationOptions(), settings=SMALL
    )
    assert torch.equal(val.scenes, scenes)
    model, images, intrinsics, truth, scenes, scene_poses = _three_scenes(3, seed=2)
    predicted = scenes.clone()
    predicted[4] = 0
    queries = Queries(images, intrinsics, predicted, scene_poses)
    refined = refine(model, queries, scene_poses[:, 0], calibration, settings=SMALL)
    assert int(refined.scenes[4]) == int(scenes[4]), "the wrong prediction is moved"
    right = predicted == scenes
    assert torch.equal(refined.scenes[right], scenes[right]), "no right prediction moved"


def test_a_querys_trials_do_not_depend_on_the_queries_tried_beside_it() -> None:
    """The calibration tries every validation query in every scene, the test only those
    below the floor: each (query, scene, start) draws from its own key, so a query's trials
    are the same either way."""
    model, images, intrinsics, _, scenes, scene_poses = _three_scenes(2, seed=3)
    refiner = build_refiner(model, SMALL)
    first = refiner(images, intrinsics, scene_poses[:, 0], scenes)
    probe = functools.partial(sharpness, refiner)
    tried = (images, intrinsics, scene_poses, scenes, first)
    every = try_scenes(refiner, probe, *tried, torch.arange(len(scenes)), PROBE_SCALES)
    some = torch.tensor([4, 1])
    alone = try_scenes(refiner, probe, *tried, some, PROBE_SCALES)
    for whole, part in zip(every.result, alone.result, strict=True):
        assert torch.equal(whole[some], part)
    assert torch.equal(every.sharpness[some], alone.sharpness)


def test_heading_starts_turn_the_pose_about_its_camera_vertical_evenly() -> None:
    poses = torch.tensor([[1.0, 2.0, 3.0, 1.0, 0.0, 0.0, 0.0]])
    turned = heading_starts(poses, 4)  # [1, 4, 7]
    assert torch.equal(turned[:, :, :3], poses[:, None, :3].expand(1, 4, 3)), "positions kept"
    axes = quaternion_to_matrix(turned[0, :, 3:])  # camera-to-world rotations [4, 3, 3]
    assert torch.allclose(axes[:, :, 1], torch.tensor([0.0, 1.0, 0.0]).expand(4, 3), atol=1e-6)
    optical = axes[:, :, 2]  # the camera's z axis turns by 90° per heading
    expected = torch.tensor([[0.0, 0, 1], [1, 0, 0], [0, 0, -1], [-1, 0, 0]])
    assert torch.allclose(optical, expected, atol=1e-6)


def test_latent_starts_are_the_teachers_pose_then_the_nearest_train_poses_of_each_scene() -> None:
    generator = torch.Generator().manual_seed(0)
    store_latents = torch.randn(12, 4, generator=generator)
    store_poses = torch.zeros(12, 7)
    store_poses[:, 0] = torch.arange(12.0)  # x = the row
    store_scenes = torch.arange(12) % SCENES
    scene_poses = torch.zeros(2, SCENES, 7)
    scene_poses[..., 0], scene_poses[..., 3] = -1.0, 1.0
    # query 0's latent for scene 1 is train row 7's (scene 1), query 1's for scene 2 row 5's
    scene_latents = torch.full((2, SCENES, 4), 50.0)
    scene_latents[0, 1] = store_latents[7]
    scene_latents[1, 2] = store_latents[5]
    starts = latent_starts(scene_poses, scene_latents, store_latents, store_poses, store_scenes)
    assert starts.shape == (2, SCENES, HEADINGS + LATENT_STARTS, 7)
    assert torch.equal(starts[:, :, :HEADINGS], heading_starts(scene_poses)), "teacher's first"
    assert torch.allclose(starts[:, :, 0], scene_poses), "its own heading first"
    near = starts[:, :, HEADINGS:]
    assert near[0, 1, 0, 0] == 7 and near[1, 2, 0, 0] == 5, "the nearest by latent next"
    assert (near[..., 0] % SCENES == torch.arange(SCENES)[None, :, None]).all()
    with pytest.raises(ValueError, match="5 latent starts per scene, but a scene has 4"):
        latent_starts(scene_poses, scene_latents, store_latents, store_poses, store_scenes, 5)


def test_a_scene_tried_from_several_starts_keeps_the_best_scoring_one() -> None:
    images, intrinsics, scene_poses, truth = _queries(6)
    predicted = truth.clone()
    starts = torch.stack([scene_poses, scene_poses.clone()], 2)  # [N, S, 2, 7]
    starts[:, :, 1, 2] = 1.0  # the second start of every scene lies at z = 1

    def refine(images: Tensor, intrinsics: Tensor, poses: Tensor, scenes: Tensor, keys=None):
        score = torch.where(poses[:, 2] == 1.0, torch.tensor(0.9), torch.tensor(0.1))
        return RenderCompareResult(poses.clone(), score, score)

    first = refine(images, intrinsics, scene_poses[torch.arange(6), predicted], predicted)
    trials = try_scenes(
        refine, None, images, intrinsics, starts, predicted, first, torch.arange(6), ()
    )
    others = torch.ones(6, SCENES, dtype=torch.bool)
    others[torch.arange(6), predicted] = False
    assert (trials.result.poses[others][:, 2] == 1.0).all(), "the better start kept"
    assert (trials.result.score[others] == 0.9).all()
    assert (trials.result.score[~others] == 0.1).all(), "the predicted scene's own refinement"
