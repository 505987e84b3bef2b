"""Pose index, affine weight fitting, orientation combination and the position refiner."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from pae.core.geometry import orientation_error_deg
from pae.models.base import Latents
from pae.refine import (
    PoseIndex,
    PositionRefiner,
    closed_form_weights,
    combine_orientations,
    init_weight_regressor,
    perturb_positions,
    refine_affine,
)
from pae.refine.fused import FUSED_KERNEL
from pae.refine.reference import first_layer_gain_direct, refine_affine_per_query
from pae.refine.regressor import FirstLayerGain


@pytest.fixture(autouse=True)
def single_thread() -> Iterator[None]:
    """Run on one intra-op thread: these tensors are small, and on a busy machine waiting for
    a second thread costs far more than it saves."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def random_poses(n: int, generator: torch.Generator, spread_m: float = 10.0) -> Tensor:
    """[n, 7] poses with uniform positions in a cube and random unit quaternions (any sign)."""
    positions = spread_m * torch.rand(n, 3, generator=generator, dtype=torch.float64)
    quaternions = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    quaternions = quaternions / quaternions.norm(dim=1, keepdim=True)
    return torch.cat([positions, quaternions], dim=1)


def brute_force(
    stored: np.ndarray,
    stored_scenes: np.ndarray,
    queries: np.ndarray,
    query_scenes: np.ndarray,
    k: int,
    distance: str,
    rot_weight: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Reference kNN by a loop over queries, in float64 numpy."""
    stored_q = stored[:, 3:] / np.linalg.norm(stored[:, 3:], axis=1, keepdims=True)
    indices, distances = [], []
    for pose, scene in zip(queries, query_scenes, strict=True):
        members = np.flatnonzero(stored_scenes == scene)
        position = np.linalg.norm(stored[members, :3] - pose[:3], axis=1)
        q = pose[3:] / np.linalg.norm(pose[3:])
        cosine = np.clip(np.abs(stored_q[members] @ q), 0.0, 1.0)
        angle = np.degrees(2.0 * np.arccos(cosine))
        if distance == "normalized":
            total = position / position.max() + angle / angle.max()
        else:
            total = position + rot_weight * angle
        order = np.argsort(total)[:k]
        indices.append(members[order])
        distances.append(total[order])
    return np.stack(indices), np.stack(distances)


@pytest.fixture
def multi_scene_store() -> tuple[Tensor, Tensor]:
    generator = torch.Generator().manual_seed(0)
    sizes = (40, 70, 90)
    poses = torch.cat([random_poses(n, generator) for n in sizes])
    scenes = torch.cat(
        [torch.full((n,), s, dtype=torch.long) for s, n in zip((3, 0, 7), sizes, strict=True)]
    )
    order = torch.randperm(len(poses), generator=generator)  # scenes interleaved in the store
    return poses[order], scenes[order]


@pytest.mark.parametrize("engine", ["numba", "torch"])
@pytest.mark.parametrize("distance", ["normalized", "fixed"])
def test_index_matches_brute_force(
    multi_scene_store: tuple[Tensor, Tensor], distance: str, engine: str
) -> None:
    poses, scenes = multi_scene_store
    generator = torch.Generator().manual_seed(1)
    queries = random_poses(60, generator)
    query_scenes = torch.tensor([3, 0, 7])[torch.randint(0, 3, (60,), generator=generator)]
    index = PoseIndex(
        poses, scenes, distance=distance, rot_weight=0.05, chunk_size=7, engine=engine
    )
    indices, distances = index.query(queries, query_scenes, k=5)
    expected_indices, expected_distances = brute_force(
        index.poses.double().numpy(),
        scenes.numpy(),
        queries.numpy(),
        query_scenes.numpy(),
        5,
        distance,
        0.05,
    )
    assert indices.dtype == torch.long and indices.shape == (60, 5)
    np.testing.assert_array_equal(indices.numpy(), expected_indices)
    np.testing.assert_allclose(distances.numpy(), expected_distances, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("distance", ["normalized", "fixed"])
def test_index_engines_agree_on_a_dense_trajectory(distance: str) -> None:
    """Poses along a walked path, a few centimetres and degrees apart, queried from near the
    path: the fused search (which skips poses by a lower bound) finds what the tensor search
    finds."""
    generator = torch.Generator().manual_seed(11)
    t = torch.linspace(0, 6 * math.pi, 3000, dtype=torch.float64)
    path = torch.stack([3 * torch.cos(t), 3 * torch.sin(t), 0.2 * t], dim=1)
    yaw = t / 2 + 0.05 * torch.randn(3000, generator=generator, dtype=torch.float64)
    zeros = torch.zeros_like(yaw)
    stored = torch.cat([path, torch.stack([yaw.cos(), zeros, zeros, yaw.sin()], 1)], dim=1)
    rows = torch.randint(0, 3000, (200,), generator=generator)
    queries = stored[rows] + 0.05 * torch.randn(200, 7, generator=generator, dtype=torch.float64)
    found = [
        PoseIndex(stored, distance=distance, engine=engine).query(queries, k=5)
        for engine in ("numba", "torch")
    ]
    assert torch.equal(found[0][0], found[1][0])
    torch.testing.assert_close(found[0][1], found[1][1], rtol=1e-6, atol=1e-7)


def test_index_rejects_an_unknown_engine() -> None:
    with pytest.raises(ValueError, match="engine must be one of"):
        PoseIndex(torch.tensor([[0.0, 0, 0, 1, 0, 0, 0]]), engine="gpu")


def test_index_never_returns_another_scene(multi_scene_store: tuple[Tensor, Tensor]) -> None:
    poses, scenes = multi_scene_store
    index = PoseIndex(poses, scenes)
    # Query with the exact poses of scene 0 while claiming scenes 3 and 7.
    queries = poses[scenes == 0]
    for claimed in (3, 7):
        found, _ = index.query(queries, torch.full((len(queries),), claimed), k=3)
        assert bool((scenes[found] == claimed).all())
    found, distances = index.query(queries, torch.zeros(len(queries), dtype=torch.long), k=1)
    assert torch.equal(found[:, 0], torch.nonzero(scenes == 0).squeeze(1))
    assert float(distances.abs().max()) < 1e-4


def test_index_validates_inputs(multi_scene_store: tuple[Tensor, Tensor]) -> None:
    poses, scenes = multi_scene_store
    with pytest.raises(ValueError, match="NaN"):
        PoseIndex(torch.where(torch.arange(7) == 2, math.nan, poses))
    with pytest.raises(ValueError, match=r"\[N, 7\]"):
        PoseIndex(poses[:, :6])
    with pytest.raises(ValueError, match="zero norm"):
        PoseIndex(torch.cat([poses[:, :3], torch.zeros(len(poses), 4, dtype=poses.dtype)], 1))
    with pytest.raises(ValueError, match="scenes must have shape"):
        PoseIndex(poses, scenes[:-1])
    index = PoseIndex(poses, scenes)
    with pytest.raises(ValueError, match="fewer than k"):
        index.query(poses[:2], torch.tensor([3, 3]), k=41)
    with pytest.raises(ValueError, match="no stored poses"):
        index.query(poses[:2], torch.tensor([3, 5]), k=3)
    with pytest.raises(ValueError, match="pass the queries' scenes"):
        index.query(poses[:2], None, k=3)


def test_single_scene_index_and_memory() -> None:
    poses = random_poses(30, torch.Generator().manual_seed(2)).float()
    index = PoseIndex(poses)
    found, _ = index.query(poses[:4], None, k=1)
    assert found[:, 0].tolist() == [0, 1, 2, 3]
    assert index.poses.dtype == torch.float32 and index.poses.shape == (30, 7)
    assert bool((index.poses[:, 3] >= 0).all())
    assert index.memory_bytes == 30 * 7 * 4  # float32 poses, nothing else


def test_interleaved_scenes_keep_their_order(multi_scene_store: tuple[Tensor, Tensor]) -> None:
    poses, scenes = multi_scene_store
    index = PoseIndex(poses, scenes)
    assert index.memory_bytes == len(poses) * (7 * 4 + 4)  # poses and an int32 permutation
    torch.testing.assert_close(index.poses, PoseIndex(poses).poses)
    assert torch.equal(index.scenes, scenes)


@pytest.mark.parametrize("weight_model", ["mlp", "softmax_logits", "closed_form"])
def test_weights_sum_to_one(weight_model: str) -> None:
    generator = torch.Generator().manual_seed(3)
    query = torch.randn(9, 16, generator=generator)
    neighbours = query.unsqueeze(1) + 0.5 * torch.randn(9, 4, 16, generator=generator)
    poses = torch.randn(9, 4, 7, generator=generator)
    fit = refine_affine(
        query, neighbours, poses, weight_model=weight_model, lr=0.05, generator=generator
    )
    assert fit.weights.shape == (9, 4) and fit.positions.shape == (9, 3)
    torch.testing.assert_close(fit.weights.sum(dim=1), torch.ones(9))
    expected = (fit.weights.unsqueeze(-1) * poses[..., :3]).sum(dim=1)
    torch.testing.assert_close(fit.positions, expected)


def test_closed_form_recovers_exact_affine_weights() -> None:
    generator = torch.Generator().manual_seed(4)
    neighbours = torch.randn(6, 4, 32, generator=generator, dtype=torch.float64)
    weights = torch.randn(6, 4, generator=generator, dtype=torch.float64)
    weights[:, -1] = 1.0 - weights[:, :-1].sum(dim=1)
    assert bool((weights < 0).any())
    query = (weights.unsqueeze(-1) * neighbours).sum(dim=1)
    recovered = closed_form_weights(query, neighbours, ridge=1e-12)
    torch.testing.assert_close(recovered, weights, atol=1e-8, rtol=0)
    coincident = closed_form_weights(query, neighbours[:, :1].expand(-1, 4, -1))
    torch.testing.assert_close(coincident, torch.full((6, 4), 0.25, dtype=torch.float64))


@pytest.mark.parametrize("objective", ["l2", "mse"])
@pytest.mark.parametrize(
    ("weight_model", "engine"),
    [
        ("mlp", "numba"),
        ("mlp", "torch"),
        ("softmax_logits", "auto"),
        ("closed_form", "auto"),
    ],
)
def test_batched_equals_per_query(weight_model: str, engine: str, objective: str) -> None:
    generator = torch.Generator().manual_seed(5)
    batch, k, dim = 7, 3, 24
    query = torch.randn(batch, dim, generator=generator, dtype=torch.float64)
    query[:, ::5] = 0.0  # exact zeros, as after a ReLU
    neighbours = query.unsqueeze(1) + 0.3 * torch.randn(
        batch, k, dim, generator=generator, dtype=torch.float64
    )
    poses = torch.randn(batch, k, 7, generator=generator, dtype=torch.float64)
    if weight_model == "mlp":
        init = init_weight_regressor(batch, k, dim, generator=generator, dtype=torch.float64)
    elif weight_model == "softmax_logits":
        init = torch.randn(batch, k, generator=generator, dtype=torch.float64)
    else:
        init = None
    options = {"weight_model": weight_model, "objective": objective, "init": init}
    batched = refine_affine(
        query, neighbours, poses, lr=0.02, chunk_size=3, engine=engine, **options
    )
    reference = refine_affine_per_query(query, neighbours, poses, lr=0.02, **options)
    untrained = refine_affine(query, neighbours, poses, iterations=0, **options)
    torch.testing.assert_close(batched.positions, reference.positions, atol=1e-10, rtol=0)
    torch.testing.assert_close(batched.weights, reference.weights, atol=1e-10, rtol=0)
    if weight_model != "closed_form":
        assert float((batched.weights - untrained.weights).abs().max()) > 1e-3


@pytest.mark.parametrize("hidden", [None, (8,), (12, 6, 5, 4)])
def test_fused_loop_equals_tensor_ops_on_drawn_regressors(hidden: tuple[int, ...] | None) -> None:
    """The compiled per-query loop and the batched tensor path start from the same drawn
    regressors (one later-layer draw shared by every query) and end at the same weights, in
    float64 exactly up to rounding and in float32 on the benchmark's sizes (k = 3, D = 512)."""
    generator = torch.Generator().manual_seed(9)
    query = torch.randn(40, 16, generator=generator, dtype=torch.float64).relu()
    neighbours = query.unsqueeze(1) + 0.3 * torch.randn(
        40, 3, 16, generator=generator, dtype=torch.float64
    )
    poses = torch.randn(40, 3, 7, generator=generator, dtype=torch.float64)
    fits = [
        refine_affine(
            query,
            neighbours,
            poses,
            lr=0.05,
            iterations=4,
            hidden=hidden,
            engine=engine,
            generator=torch.Generator().manual_seed(3),
        )
        for engine in ("numba", "torch")
    ]
    torch.testing.assert_close(fits[0].weights, fits[1].weights, atol=1e-9, rtol=0)
    assert float((fits[0].weights - 1 / 3).abs().max()) > 1e-2  # the fit moved the weights

    query = torch.randn(24, 512, generator=generator)
    neighbours = query.unsqueeze(1) + 0.3 * torch.randn(24, 3, 512, generator=generator)
    poses = torch.randn(24, 3, 7, generator=generator)
    fused, tensor_ops = (
        refine_affine(
            query, neighbours, poses, engine=engine, generator=torch.Generator().manual_seed(4)
        )
        for engine in ("numba", "torch")
    )
    assert fused.weights.dtype == torch.float32
    torch.testing.assert_close(fused.weights, tensor_ops.weights, atol=2e-4, rtol=0)


def test_fused_loop_follows_units_that_switch_off_and_on() -> None:
    """The compiled loop skips the AdamW arithmetic of weight rows whose input unit is off
    and whose moments are still zero; units that switch off and back on between steps (a
    large learning rate) must still give the per-query oracle's weights. The oracle's ReLU
    outputs are recorded to show that such switches happen here."""
    generator = torch.Generator().manual_seed(12)
    batch, k, dim = 30, 3, 8
    query = torch.randn(batch, dim, generator=generator, dtype=torch.float64)
    neighbours = query.unsqueeze(1) + torch.randn(
        batch, k, dim, generator=generator, dtype=torch.float64
    )
    poses = torch.randn(batch, k, 7, generator=generator, dtype=torch.float64)
    init = init_weight_regressor(
        batch, k, dim, hidden=(6, 5, 4), generator=generator, dtype=torch.float64
    )
    options = {"init": init, "lr": 0.3, "iterations": 6}
    masks: dict[nn.Module, list[Tensor]] = {}  # keyed by the module itself, kept alive

    def record(module: nn.Module, _: object, output: Tensor) -> None:
        if isinstance(module, nn.ReLU):
            masks.setdefault(module, []).append(output.detach().reshape(-1) > 0)

    handle = nn.modules.module.register_module_forward_hook(record)
    try:
        reference = refine_affine_per_query(query, neighbours, poses, **options)
    finally:
        handle.remove()
    history = [torch.stack(steps) for steps in masks.values()]  # per ReLU: [steps, width]
    assert len(history) == 3 * batch
    # units off at the first step and on later, and units that switch off
    assert sum(int(((~steps[0]) & steps[1:].any(dim=0)).sum()) for steps in history) > 0
    assert sum(int((steps[:-1] & ~steps[1:]).sum()) for steps in history) > 0
    fused = refine_affine(query, neighbours, poses, engine="numba", **options)
    torch.testing.assert_close(fused.weights, reference.weights, atol=1e-10, rtol=0)


@pytest.mark.parametrize("activation", ["tanh", "gelu"])
def test_an_activation_the_kernel_lacks_takes_the_tensor_path(activation: str) -> None:
    """The autograd model defines the weight regressor: with an activation the compiled loop
    does not declare, ``auto`` gives the tensor path's (and the per-query oracle's) weights,
    which differ from ReLU's, and ``fused`` refuses in one line."""
    generator = torch.Generator().manual_seed(8)
    batch, k, dim = 6, 3, 16
    query = torch.randn(batch, dim, generator=generator, dtype=torch.float64)
    neighbours = query.unsqueeze(1) + 0.3 * torch.randn(
        batch, k, dim, generator=generator, dtype=torch.float64
    )
    poses = torch.randn(batch, k, 7, generator=generator, dtype=torch.float64)
    init = init_weight_regressor(batch, k, dim, generator=generator, dtype=torch.float64)
    options = {"init": init, "lr": 0.05, "iterations": 4}
    auto = refine_affine(query, neighbours, poses, activation=activation, **options)
    batched = refine_affine(
        query, neighbours, poses, activation=activation, engine="torch", **options
    )
    oracle = refine_affine_per_query(query, neighbours, poses, activation=activation, **options)
    relu = refine_affine(query, neighbours, poses, **options)
    torch.testing.assert_close(auto.weights, batched.weights, atol=1e-12, rtol=0)
    torch.testing.assert_close(auto.weights, oracle.weights, atol=1e-10, rtol=0)
    assert float((auto.weights - relu.weights).abs().max()) > 1e-4
    with pytest.raises(ValueError, match=f"implements activation relu, not '{activation}'"):
        refine_affine(query, neighbours, poses, activation=activation, engine="numba", **options)
    assert activation not in FUSED_KERNEL.activations and "relu" in FUSED_KERNEL.activations


def test_an_unknown_activation_is_refused() -> None:
    query, neighbours = torch.zeros(2, 4), torch.zeros(2, 3, 4)
    with pytest.raises(ValueError, match="unknown activation 'swish'; choose one of"):
        refine_affine(query, neighbours, torch.zeros(2, 3, 7), activation="swish")


def test_refine_affine_rejects_an_unknown_engine() -> None:
    query, neighbours = torch.zeros(2, 4), torch.randn(2, 3, 4)
    with pytest.raises(ValueError, match="engine must be one of"):
        refine_affine(query, neighbours, torch.zeros(2, 3, 7), engine="gpu")
    with pytest.raises(ValueError, match="float32 or float64 CPU tensors"):
        refine_affine(query.bfloat16(), neighbours, torch.zeros(2, 3, 7), engine="numba")


def test_first_layer_gain_matches_direct_sum() -> None:
    generator = torch.Generator().manual_seed(6)
    inputs = torch.randn(5, 300, generator=generator, dtype=torch.float64).abs()
    inputs[:, ::4] = 0.0
    inputs[1] = 0.0
    inputs[2, :10] = 1e-9
    for scale_size in (1e-12, 1e-9, 1e-7, 1e-5, 1e-3, 1e-1, 10.0):
        scale = scale_size * torch.rand(5, 40, generator=generator, dtype=torch.float64)
        scale[:, 0] = 0.0
        direct = first_layer_gain_direct(inputs, scale, 1e-8)
        loop = [
            [sum(a * a / (a * s + 1e-8) for a in row.tolist()) for s in scales.tolist()]
            for row, scales in zip(inputs[:2], scale[:2], strict=True)
        ]
        loop[0][0] = loop[1][0] = 0.0
        torch.testing.assert_close(direct[:2], torch.tensor(loop, dtype=torch.float64))
        for ratio, tolerance in ((1e3, 1e-13), (30.0, 5e-8)):
            gain = FirstLayerGain(inputs, 1e-8, ratio)(scale)
            torch.testing.assert_close(gain, direct, rtol=tolerance, atol=0)


def test_softmax_logits_favour_the_matching_neighbour() -> None:
    generator = torch.Generator().manual_seed(7)
    neighbours = torch.randn(5, 3, 64, generator=generator)
    match = torch.tensor([0, 1, 2, 1, 0])
    query = neighbours[torch.arange(5), match]
    poses = torch.randn(5, 3, 7, generator=generator)
    fit = refine_affine(
        query, neighbours, poses, weight_model="softmax_logits", iterations=60, lr=0.1
    )
    assert bool((fit.weights.argmax(dim=1) == match).all())
    assert float(fit.weights[torch.arange(5), match].min()) > 0.9


def test_markley_orientation_of_identical_neighbours() -> None:
    generator = torch.Generator().manual_seed(8)
    q = torch.randn(4, 4, generator=generator)
    q = q / q.norm(dim=1, keepdim=True)
    neighbours = torch.stack([q, -q, q], dim=1)  # same rotation, mixed signs
    weights = torch.tensor([[0.2, 0.3, 0.5], [1.0, 0.0, 0.0], [0.6, 0.6, -0.2], [0.1, 0.1, 0.8]])
    combined = combine_orientations(neighbours, weights, torch.zeros(4, 4) + 1, "markley")
    assert float(orientation_error_deg(combined, q).max()) < 1e-2
    assert bool((combined[:, 0] >= 0).all())


def test_affine_orientation_is_the_weighted_midpoint() -> None:
    axis_angle = torch.tensor([0.0, 40.0])
    half = torch.deg2rad(axis_angle) / 2
    about_z = torch.stack([torch.cos(half), torch.zeros(2), torch.zeros(2), torch.sin(half)], dim=1)
    neighbours = torch.stack([about_z[0], -about_z[1]]).unsqueeze(0)  # second one sign-flipped
    combined = combine_orientations(neighbours, torch.tensor([[0.5, 0.5]]), about_z[:1], "affine")
    expected = torch.tensor([[math.cos(math.radians(10)), 0.0, 0.0, math.sin(math.radians(10))]])
    torch.testing.assert_close(combined, expected)
    teacher = combine_orientations(
        neighbours, torch.tensor([[0.5, 0.5]]), -2 * about_z[1:], "teacher"
    )
    torch.testing.assert_close(teacher, about_z[1:])
    with pytest.raises(ValueError, match="orientation mode"):
        combine_orientations(neighbours, torch.tensor([[0.5, 0.5]]), about_z[:1], "mean")


def test_perturb_positions_moves_positions_only() -> None:
    poses = random_poses(2000, torch.Generator().manual_seed(9)).float()
    moved = perturb_positions(poses, 1.5, torch.Generator().manual_seed(10))
    again = perturb_positions(poses, 1.5, torch.Generator().manual_seed(10))
    assert torch.equal(moved, again)
    assert torch.equal(moved[:, 3:], poses[:, 3:])
    offsets = moved[:, :3] - poses[:, :3]
    assert abs(float(offsets.std()) - 1.5) < 0.1 and abs(float(offsets.mean())) < 0.1


class TinyPae(nn.Module):
    """A random pose encoder: pose [B, 7] -> Latents with d = 8."""

    def __init__(self) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(7, 32), nn.ReLU(), nn.Linear(32, 16))

    def forward(self, poses: Tensor, scenes: Tensor | None = None) -> Latents:
        latents = self.net(poses.float())
        return Latents(latents[:, :8], latents[:, 8:])


@pytest.mark.parametrize("weight_model", ["mlp", "softmax_logits"])
def test_refiner_under_inference_mode(
    multi_scene_store: tuple[Tensor, Tensor], weight_model: str
) -> None:
    torch.manual_seed(11)
    poses, scenes = multi_scene_store
    index = PoseIndex(poses, scenes)
    pae = TinyPae()
    targets = index.poses[:12]  # query images taken at train poses
    target_scenes = scenes[:12]
    initial = perturb_positions(targets, 1.0, torch.Generator().manual_seed(12))
    refiner = PositionRefiner(
        index, pae, k=3, iterations=40, lr=0.1, weight_model=weight_model, seed=0
    )
    with torch.inference_mode():
        query_latents = pae(targets, target_scenes)
        result = refiner(query_latents, initial, target_scenes)
    assert result.poses.shape == (12, 7) and result.neighbour_indices.shape == (12, 3)
    assert not result.poses.requires_grad
    torch.testing.assert_close(result.weights.sum(dim=1), torch.ones(12))
    assert bool((scenes[result.neighbour_indices] == target_scenes[:, None]).all())
    neighbour_positions = index.poses[result.neighbour_indices, :3]
    expected = (result.weights.unsqueeze(-1) * neighbour_positions).sum(dim=1)
    torch.testing.assert_close(result.poses[:, :3], expected)
    torch.testing.assert_close(result.poses[:, 3:], initial[:, 3:])
    # Queries whose own train pose is among the neighbours move towards it.
    hit = (result.neighbour_indices == torch.arange(12)[:, None]).any(dim=1)
    assert int(hit.sum()) >= 4
    before = (initial[hit, :3] - targets[hit, :3]).norm(dim=1)
    after = (result.poses[hit, :3] - targets[hit, :3]).norm(dim=1)
    assert float(after.median()) < float(before.median())
    # Scenes come from PoseRegressor.estimate, never guessed here: a multi-scene index needs them.
    with_logits = Latents(query_latents.x, query_latents.q, nn.functional.one_hot(target_scenes, 8))
    with pytest.raises(ValueError, match="pass the queries' scenes"):
        refiner(with_logits, initial)


def test_latent_retrieval_finds_the_pose_that_encodes_the_query() -> None:
    from pae.models.pae import PoseAutoEncoder
    from pae.refine import LatentRetrievalRefiner

    generator = torch.Generator().manual_seed(3)
    store = PoseIndex(random_poses(200, generator, spread_m=3.0).float()).poses  # qw >= 0
    scenes = torch.arange(200) % 2
    torch.manual_seed(0)  # the PAE's weights, whatever ran before
    pae = PoseAutoEncoder(latent_dim=32, L=3, n_scenes=2).eval()
    picked = torch.tensor([5, 17, 80, 151])
    with torch.no_grad():
        query = pae(store[picked], scenes[picked])
    far_estimates = store[picked].clone()
    far_estimates[:, :3] += 5.0
    refiner = LatentRetrievalRefiner(PoseIndex(store, scenes), pae, k=1)
    result = refiner(query, far_estimates, scenes[picked])
    assert torch.equal(result.neighbour_indices[:, 0], picked)
    torch.testing.assert_close(result.poses[:, :3], store[picked, :3])
    from pae.core.geometry import canonicalize_quaternion

    torch.testing.assert_close(result.poses[:, 3:], canonicalize_quaternion(far_estimates[:, 3:]))


@pytest.mark.parametrize("refine", ["position", "pose"])
def test_pose_descent_moves_towards_the_encoded_pose(refine: str) -> None:
    from pae.models.pae import PoseAutoEncoder
    from pae.refine import PoseDescentRefiner

    generator = torch.Generator().manual_seed(4)
    truth = random_poses(16, generator, spread_m=2.0).float()
    pae = PoseAutoEncoder(latent_dim=32, L=0).eval()
    with torch.no_grad():
        query = pae(truth)
    start = truth.clone()
    start[:, :3] += 0.3 * torch.randn(16, 3, generator=generator)
    result = PoseDescentRefiner(None, pae, iterations=200, lr=0.01, refine=refine)(query, start)
    before = (start[:, :3] - truth[:, :3]).norm(dim=1).median()
    after = (result.poses[:, :3] - truth[:, :3]).norm(dim=1).median()
    assert after < 0.5 * before
    assert all(p.grad is None for p in pae.parameters())
    if refine == "position":
        assert torch.equal(result.poses[:, 3:], start[:, 3:])
    else:
        torch.testing.assert_close(result.poses[:, 3:].norm(dim=1), torch.ones(16))
