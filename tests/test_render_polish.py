"""The analytic polish of render-and-compare: its geometry, its two engines, its effect."""

from __future__ import annotations

import torch

from pae.core.geometry import (
    matrix_to_quaternion,
    pose_errors,
    quaternion_to_matrix,
    rotation_vector_to_quaternion,
)
from pae.core.pose_sampling import perturb
from pae.render_compare.kernels.numba_polish import polish_compiled
from pae.render_compare.kernels.numba_score import compiled_zncc_scores
from pae.render_compare.kernels.reference import (
    PolishProblem,
    PolishSettings,
    image_gradients,
    polish_tensor,
    rotation_vector_to_matrix,
    score_tensor,
)
from pae.render_compare.refiner import RenderCompareRefiner, pyramid_widths
from tests.test_render_compare import _oracle_queries


def test_rodrigues_matches_the_quaternion_of_the_same_rotation_vector() -> None:
    vectors = torch.randn(16, 3, generator=torch.Generator().manual_seed(0)).double()
    vectors[0] = 0.0
    vectors[1] = 1e-12
    expected = quaternion_to_matrix(rotation_vector_to_quaternion(vectors))
    torch.testing.assert_close(rotation_vector_to_matrix(vectors), expected)


def test_image_gradients_are_central_differences() -> None:
    u = torch.arange(6.0).view(1, 1, 6).expand(1, 5, 6)
    grad_u, grad_v = image_gradients(3 * u + 2 * torch.arange(5.0).view(1, 5, 1))
    torch.testing.assert_close(grad_u[0, :, 1:-1], torch.full((5, 4), 3.0))
    torch.testing.assert_close(grad_v[0, 1:-1], torch.full((3, 6), 2.0))


def test_pyramid_widths_halve_from_the_finest_never_above_the_query() -> None:
    assert pyramid_widths(64, 3, 56) == [14, 28, 56]
    assert pyramid_widths(64, 3, 128) == [16, 32, 64]
    assert pyramid_widths(32, 1, 64) == [32]
    assert pyramid_widths(16, 4, 64) == [8, 8, 8, 16]


def _polish_inputs(n: int = 4) -> tuple[PolishProblem, torch.Tensor]:
    """The polish's inputs at the finest level for oracle queries moved off their truth."""
    model, images, intrinsics, truth, start = _oracle_queries(n)
    refiner = RenderCompareRefiner.configured(
        model, resolution=48, levels=1, final_reference_size=0
    )
    level = refiner.pyramid(images, intrinsics, torch.zeros(n, dtype=torch.long))[-1]
    surface = refiner.surface(refiner.reference(start, level, 32, 1.3), level)
    hypotheses = torch.stack([start, perturb(start, torch.full((n, 6), 0.02))], 1)
    scores = refiner.score_poses(hypotheses, level, surface)
    inputs = PolishProblem(
        surface.points,
        surface.values[:, 0],
        surface.valid,
        quaternion_to_matrix(hypotheses[..., 3:]),
        hypotheses[..., :3],
        scores,
        level.intrinsics,
        level.target[:, 0],
    )
    return inputs, truth


def test_compiled_and_tensor_polish_take_the_same_steps() -> None:
    inputs, _ = _polish_inputs()
    for trim_sigma in (0.0, 2.0):
        settings = PolishSettings(6, 1e-3, 0.4, trim_sigma)
        compiled = polish_compiled(inputs, settings)
        tensor = polish_tensor(inputs, settings)
        for a, b in zip(compiled, tensor, strict=True):
            torch.testing.assert_close(a, b.to(a.dtype), atol=2e-4, rtol=0)
        assert (compiled[2] > inputs[5]).any()  # the steps moved something


def test_the_tensor_score_equals_the_compiled_score() -> None:
    inputs, _ = _polish_inputs()
    points, values, valid, rotations, positions, _, intrinsics, target = inputs
    poses = torch.cat([positions, matrix_to_quaternion(rotations)], -1)
    compiled = compiled_zncc_scores(points, values, valid, poses, intrinsics, target, 0.4, 2.0)
    rows = torch.arange(len(points)).repeat_interleave(rotations.shape[1])
    cameras = (rotations.flatten(0, 1), positions.flatten(0, 1))
    per_row = (points[rows], values[rows], valid[rows])
    tensor = score_tensor(*per_row, *cameras, intrinsics[rows], target[rows], 0.4, 2.0, 2)
    torch.testing.assert_close(tensor.view_as(compiled), compiled, atol=1e-4, rtol=0)


def test_the_polish_raises_every_score_and_moves_towards_the_truth() -> None:
    """Every hypothesis's score rises by a clear step, the score returned is that of the pose
    returned, and the median position error halves."""
    inputs, truth = _polish_inputs(6)
    rotation, position, scores = polish_compiled(inputs, PolishSettings(10, 1e-3, 0.4))
    assert (scores > inputs[5] + 0.1).all(), (inputs[5], scores)
    points, values, valid, _, _, _, intrinsics, target = inputs
    poses = torch.cat([position, matrix_to_quaternion(rotation)], -1)
    rescored = compiled_zncc_scores(points, values, valid, poses, intrinsics, target, 0.4)
    torch.testing.assert_close(rescored, scores.to(rescored.dtype), atol=1e-5, rtol=0)
    start = torch.cat([inputs[4][:, 0], matrix_to_quaternion(inputs[3][:, 0])], -1)
    after = torch.cat([position[:, 0], matrix_to_quaternion(rotation[:, 0])], -1)
    before_m, _ = pose_errors(start, truth)
    after_m, _ = pose_errors(after, truth)
    assert after_m.median() < 0.5 * before_m.median()


def test_the_counted_work_is_the_candidates_and_steps_the_settings_ask_for() -> None:
    """One level, no final rendering: per query the start, two rounds of hypotheses ×
    candidates and the start again at the end are scored, against the same reference; each
    hypothesis takes polish_steps steps over it."""
    model, images, intrinsics, _, start = _oracle_queries(3)
    scenes = torch.zeros(3, dtype=torch.long)
    settings = {"resolution": 24, "levels": 1, "final_reference_size": 0, "reference_size": 16}
    refiner = RenderCompareRefiner.configured(
        model, rounds=2, candidates=3, hypotheses=2, polish_steps=4, **settings
    )
    refiner(images, intrinsics, start, scenes)
    level = refiner.pyramid(images, intrinsics, scenes)[-1]
    valid = int(refiner.reference(start, level, 16, 1.3).valid.sum())
    assert refiner.work.score_points == valid * (1 + 2 * 2 * 3 + 1)
    assert refiner.work.polish_point_steps == valid * 2 * 4
    assert refiner.work.rendered_rays == 2 * 3 * 16 * 16
