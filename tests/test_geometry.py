"""Quaternion and pose helpers against scipy's Rotation (scalar-last) and hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from pae.core.geometry import (
    average_quaternions,
    canonicalize_quaternion,
    compose_pose,
    matrix_to_quaternion,
    normalize_quaternion,
    orientation_error_deg,
    pose_errors,
    position_error,
    quaternion_apply,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_to_matrix,
    relative_pose,
)

DTYPES = [torch.float32, torch.float64]
TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


def scalar_first(quat_xyzw: np.ndarray) -> np.ndarray:
    """scipy's ``x, y, z, w`` → ``w, x, y, z``."""
    return np.roll(quat_xyzw, 1, axis=-1)


def scalar_last(quat_wxyz: np.ndarray) -> np.ndarray:
    """``w, x, y, z`` → scipy's ``x, y, z, w``."""
    return np.roll(quat_wxyz, -1, axis=-1)


def random_rotations(n: int, seed: int) -> Rotation:
    """Random rotations plus rotations by 180° and near it (the hard cases for Shepperd)."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(6, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.array([math.pi, math.pi, math.pi - 1e-7, math.pi - 1e-3, 1e-9, 0.0])[:, None]
    special = Rotation.from_rotvec(axes * angles)
    return Rotation.concatenate([Rotation.random(n, random_state=seed), special])


def as_tensor(array: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
    return torch.as_tensor(array, dtype=dtype)


def equal_up_to_sign(a: torch.Tensor, b: torch.Tensor, atol: float) -> bool:
    dot = (a * b).sum(-1, keepdim=True)
    return torch.allclose(torch.where(dot < 0, -a, a), b, atol=atol)


@pytest.mark.parametrize("dtype", DTYPES)
def test_quaternion_to_matrix_matches_scipy(dtype: torch.dtype) -> None:
    rotations = random_rotations(64, seed=1)
    q = as_tensor(scalar_first(rotations.as_quat()), dtype)
    R = quaternion_to_matrix(q)
    assert R.shape == (70, 3, 3) and R.dtype == dtype
    np.testing.assert_allclose(R.numpy(), rotations.as_matrix(), atol=TOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
def test_matrix_to_quaternion_matches_scipy_and_is_canonical(dtype: torch.dtype) -> None:
    rotations = random_rotations(64, seed=2)
    q = matrix_to_quaternion(as_tensor(rotations.as_matrix(), dtype))
    expected = as_tensor(scalar_first(rotations.as_quat()), dtype)
    assert q.dtype == dtype
    assert equal_up_to_sign(q, expected, atol=10 * TOL[dtype])
    assert (q[:, 0] >= 0).all()
    torch.testing.assert_close(torch.linalg.vector_norm(q, dim=-1), torch.ones(len(q), dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_matrix_quaternion_round_trip_batched(dtype: torch.dtype) -> None:
    q = canonicalize_quaternion(
        torch.randn(3, 5, 4, dtype=dtype, generator=torch.Generator().manual_seed(0))
    )
    round_trip = matrix_to_quaternion(quaternion_to_matrix(q))
    assert round_trip.shape == (3, 5, 4)
    torch.testing.assert_close(round_trip, q, atol=10 * TOL[dtype], rtol=0)


def test_matrix_to_quaternion_rejects_wrong_shape() -> None:
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, 3\]"):
        matrix_to_quaternion(torch.eye(4))


@pytest.mark.parametrize("dtype", DTYPES)
def test_multiply_and_apply_match_scipy(dtype: torch.dtype) -> None:
    a, b = random_rotations(32, seed=3), random_rotations(32, seed=4)
    qa = as_tensor(scalar_first(a.as_quat()), dtype)
    qb = as_tensor(scalar_first(b.as_quat()), dtype)
    expected = as_tensor(scalar_first((a * b).as_quat()), dtype)
    assert equal_up_to_sign(quaternion_multiply(qa, qb), expected, atol=TOL[dtype])

    v = np.random.default_rng(5).normal(size=(len(a), 3))
    rotated = quaternion_apply(qa, as_tensor(v, dtype))
    np.testing.assert_allclose(rotated.numpy(), a.apply(v), atol=10 * TOL[dtype])


def test_conjugate_is_inverse_and_apply_broadcasts() -> None:
    q = normalize_quaternion(torch.randn(8, 4, dtype=torch.float64))
    identity = quaternion_multiply(q, quaternion_conjugate(q))
    expected = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64).expand(8, 4)
    torch.testing.assert_close(identity, expected)

    quarter_turn_z = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    points = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 5.0]])
    rotated = quaternion_apply(quarter_turn_z, points)
    torch.testing.assert_close(rotated, torch.tensor([[0.0, 1.0, 0.0], [-2.0, 0.0, 5.0]]))


def test_normalize_and_canonicalize() -> None:
    q = torch.tensor([[-2.0, 0.0, 0.0, 0.0], [0.0, 0.0, 3.0, 4.0]])
    torch.testing.assert_close(
        canonicalize_quaternion(q), torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.6, 0.8]])
    )
    assert torch.isfinite(normalize_quaternion(torch.zeros(4))).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_orientation_error_hand_cases(dtype: torch.dtype) -> None:
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype)
    half = math.sqrt(0.5)
    quarter_z = torch.tensor([half, 0.0, 0.0, half], dtype=dtype)
    half_turn_x = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=dtype)
    q = torch.stack([quarter_z, -quarter_z, 3.0 * quarter_z, half_turn_x, identity])
    expected = torch.tensor([90.0, 90.0, 90.0, 180.0, 0.0], dtype=dtype)
    torch.testing.assert_close(orientation_error_deg(q, identity), expected, atol=1e-4, rtol=0)


def test_orientation_error_matches_scipy_and_is_accurate_for_small_angles() -> None:
    a, b = random_rotations(50, seed=6), random_rotations(50, seed=7)
    expected = np.degrees((a.inv() * b).magnitude())
    error = orientation_error_deg(
        as_tensor(scalar_first(a.as_quat()), torch.float64),
        as_tensor(scalar_first(b.as_quat()), torch.float64),
    )
    np.testing.assert_allclose(error.numpy(), expected, atol=1e-8)

    tiny = 1e-3  # degrees
    q_tiny = torch.tensor(
        [math.cos(math.radians(tiny) / 2), math.sin(math.radians(tiny) / 2), 0, 0]
    )
    error32 = orientation_error_deg(q_tiny, torch.tensor([1.0, 0.0, 0.0, 0.0]))
    assert abs(error32.item() - tiny) < 1e-6


def test_position_and_pose_errors() -> None:
    gt = torch.tensor([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
    pred = torch.tensor([[3.0, 4.0, 0.0, math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]])
    assert position_error(pred[:, :3], gt[:, :3]).tolist() == [5.0]
    pos_m, rot_deg = pose_errors(pred, gt)
    assert pos_m.shape == rot_deg.shape == (1,)
    assert pos_m.item() == pytest.approx(5.0)
    assert rot_deg.item() == pytest.approx(90.0, abs=1e-4)


def random_poses(n: int, seed: int, dtype: torch.dtype) -> torch.Tensor:
    rotations = Rotation.random(n, random_state=seed)
    positions = np.random.default_rng(seed).normal(scale=10.0, size=(n, 3))
    quats = scalar_first(rotations.as_quat())
    quats *= np.where(quats[:, :1] < 0, -1.0, 1.0)
    return as_tensor(np.concatenate([positions, quats], axis=1), dtype)


@pytest.mark.parametrize("dtype", DTYPES)
def test_relative_then_compose_is_identity(dtype: torch.dtype) -> None:
    p_ref, p = random_poses(40, 8, dtype), random_poses(40, 9, dtype)
    rel = relative_pose(p_ref, p)
    assert rel.shape == (40, 7)
    torch.testing.assert_close(compose_pose(p_ref, rel), p, atol=100 * TOL[dtype], rtol=0)


def test_relative_pose_matches_matrices() -> None:
    p_ref, p = random_poses(20, 10, torch.float64), random_poses(20, 11, torch.float64)

    def homogeneous(pose: torch.Tensor) -> np.ndarray:
        T = np.tile(np.eye(4), (len(pose), 1, 1))
        T[:, :3, :3] = Rotation.from_quat(scalar_last(pose[:, 3:].numpy())).as_matrix()
        T[:, :3, 3] = pose[:, :3].numpy()
        return T

    # rotation: the query's in the reference camera's frame; translation: world frame
    expected = np.linalg.inv(homogeneous(p_ref)) @ homogeneous(p)
    relative = homogeneous(relative_pose(p_ref, p))
    np.testing.assert_allclose(relative[:, :3, :3], expected[:, :3, :3], atol=1e-10)
    np.testing.assert_allclose(relative[:, :3, 3], (p[:, :3] - p_ref[:, :3]).numpy(), atol=1e-12)


def test_relative_pose_broadcasts_one_reference() -> None:
    p_ref = random_poses(1, 12, torch.float64)[0]
    p = random_poses(5, 13, torch.float64)
    assert relative_pose(p_ref, p).shape == (5, 7)
    torch.testing.assert_close(compose_pose(p_ref, relative_pose(p_ref, p)), p)


@pytest.mark.parametrize("dtype", DTYPES)
def test_average_of_identical_quaternions_is_that_quaternion(dtype: torch.dtype) -> None:
    q = canonicalize_quaternion(torch.randn(6, 1, 4, dtype=dtype)).expand(6, 3, 4)
    torch.testing.assert_close(average_quaternions(q), q[:, 0], atol=10 * TOL[dtype], rtol=0)


def test_average_is_invariant_to_sign_flips() -> None:
    q = canonicalize_quaternion(torch.randn(10, 4, 4, dtype=torch.float64))
    weights = torch.rand(10, 4, dtype=torch.float64)
    signs = torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64)[:, None]
    torch.testing.assert_close(
        average_quaternions(q * signs, weights), average_quaternions(q, weights)
    )


def test_average_of_two_rotations_about_one_axis_is_the_mid_angle() -> None:
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    angles = np.radians([[10.0, 50.0], [-20.0, 100.0]])
    quats = scalar_first(Rotation.from_rotvec(angles.reshape(-1, 1) * axis).as_quat())
    average = average_quaternions(as_tensor(quats.reshape(2, 2, 4), torch.float64))
    expected = scalar_first(Rotation.from_rotvec(angles.mean(-1)[:, None] * axis).as_quat())
    np.testing.assert_allclose(average.numpy(), expected, atol=1e-12)


def test_weighted_average_follows_the_weights() -> None:
    axis = np.array([0.0, 0.0, 1.0])
    quats = scalar_first(Rotation.from_rotvec(np.radians([[0.0], [60.0]]) * axis).as_quat())
    q = as_tensor(quats, torch.float64)
    heavy_second = average_quaternions(q, torch.tensor([0.1, 0.9], dtype=torch.float64))
    only_first = average_quaternions(q, torch.tensor([1.0, 0.0], dtype=torch.float64))
    angle_to_second = orientation_error_deg(heavy_second, q[1]).item()
    assert angle_to_second < 10.0
    torch.testing.assert_close(only_first, q[0])


def test_one_sign_convention_for_numpy_and_torch() -> None:
    import numpy as np

    from pae.core.quaternion_sign import canonical_sign

    q = [[-0.5, 0.5, 0.5, 0.5], [0.0, -1.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0]]
    expected = [[0.5, -0.5, -0.5, -0.5], [0.0, -1.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0]]
    np.testing.assert_array_equal(canonical_sign(np.array(q)), expected)  # norms kept
    assert torch.equal(canonical_sign(torch.tensor(q)), torch.tensor(expected))
    assert torch.equal(canonicalize_quaternion(torch.tensor(q))[2], torch.tensor([1.0, 0, 0, 0]))


def test_transfer_error_keeps_the_error_in_the_camera_frame() -> None:
    """transfer_error: the same cameras in two world frames (one turned and moved rigidly);
    an estimate's error applied in the second frame is the estimate moved by that transform,
    with the position and orientation error it had in the first."""
    from pae.core.geometry import quaternion_apply, quaternion_multiply, transfer_error

    generator = torch.Generator().manual_seed(0)

    def unit(q: torch.Tensor) -> torch.Tensor:
        return q / q.norm(dim=-1, keepdim=True)

    truth = torch.cat([torch.randn(5, 3, generator=generator), unit(torch.randn(5, 4))], 1)
    estimate = truth + torch.cat([0.1 * torch.randn(5, 3), 0.05 * torch.randn(5, 4)], 1)
    estimate[:, 3:] = unit(estimate[:, 3:])
    shift, turn = torch.tensor([1.0, -2.0, 0.5]), unit(torch.tensor([0.8, 0.2, -0.5, 0.26]))

    def moved(poses: torch.Tensor) -> torch.Tensor:
        q = quaternion_multiply(turn.expand(5, 4), poses[:, 3:])
        return torch.cat([shift + quaternion_apply(turn.expand(5, 4), poses[:, :3]), q], 1)

    target = moved(truth.double())
    result = transfer_error(truth.double(), estimate.double(), target)
    expected = moved(estimate.double())
    torch.testing.assert_close(result[:, :3], expected[:, :3], atol=1e-6, rtol=0)
    errors = pose_errors(result, target), pose_errors(estimate.double(), truth.double())
    for a, b in zip(*errors, strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=0)
