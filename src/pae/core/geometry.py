"""Quaternions, camera poses and pose errors, batched over leading dimensions.

Conventions (shared by the whole package):

- A pose tensor has shape ``[..., 7]``: position ``x, y, z`` in metres (world frame) followed by
  the orientation ``qw, qx, qy, qz``, a unit quaternion with the scalar part first.
- Poses are camera-to-world: ``X_world = R(q) @ X_camera + t``.
- A relative pose (``relative_pose``, inverted by ``compose_pose``) is the world-frame
  translation from the reference to the query camera, ``t_query − t_ref`` (m), and the
  rotation ``conj(q_ref) ⊗ q_query`` (the query's orientation in the reference camera's
  frame): the one relative-pose convention of the package; the RPRs and the iterative APR
  regress it.
- Quaternions are Hamilton quaternions; ``q`` and ``-q`` are the same rotation and stored poses
  are canonicalised to ``qw >= 0``.

Every function works for float32 and float64 and broadcasts over leading dimensions.
"""

from __future__ import annotations

import torch
from torch import Tensor

from pae.core.quaternion_sign import canonical_sign

__all__ = [
    "average_quaternions",
    "canonical_sign",
    "canonicalize_quaternion",
    "compose_pose",
    "matrix_to_quaternion",
    "normalize_quaternion",
    "orientation_error_deg",
    "pose_errors",
    "position_error",
    "quaternion_apply",
    "quaternion_conjugate",
    "quaternion_multiply",
    "quaternion_to_matrix",
    "relative_pose",
    "rotation_vector_to_quaternion",
]


def normalize_quaternion(q: Tensor, eps: float = 1e-12) -> Tensor:
    """Scale quaternions ``[..., 4]`` to unit norm (norms below ``eps`` are clamped to ``eps``)."""
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(eps)


def normalize_pose(pose: Tensor) -> Tensor:
    """Poses ``[..., 7]`` with their quaternion part scaled to unit norm."""
    return torch.cat([pose[..., :3], normalize_quaternion(pose[..., 3:])], dim=-1)


def canonicalize_quaternion(q: Tensor) -> Tensor:
    """Unit quaternions ``[..., 4]`` with the sign chosen so that ``qw >= 0``."""
    return canonical_sign(normalize_quaternion(q))


def quaternion_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a ⊗ b`` of quaternions ``[..., 4]`` (rotation ``b`` first, then ``a``)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quaternion_conjugate(q: Tensor) -> Tensor:
    """Conjugate ``(w, -x, -y, -z)`` of quaternions ``[..., 4]`` (the inverse rotation if unit)."""
    return q * q.new_tensor((1.0, -1.0, -1.0, -1.0))


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """Cross product of 3-vectors ``[..., 3]`` with broadcasting."""
    ax, ay, az = a.unbind(-1)
    bx, by, bz = b.unbind(-1)
    return torch.stack((ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx), dim=-1)


def quaternion_apply(q: Tensor, v: Tensor) -> Tensor:
    """Rotate 3-vectors ``v [..., 3]`` by quaternions ``q [..., 4]`` (normalised first)."""
    q = normalize_quaternion(q)
    w, u = q[..., :1], q[..., 1:]
    uv = 2.0 * _cross(u, v)
    return v + w * uv + _cross(u, uv)


def rotation_vector_to_quaternion(vector: Tensor) -> Tensor:
    """Axis-angle vectors [..., 3] (rad) -> unit quaternions [..., 4] (w first)."""
    angle = vector.norm(dim=-1, keepdim=True)
    half = angle / 2
    scale = torch.where(angle > 1e-9, torch.sin(half) / angle.clamp_min(1e-9), 0.5 - angle**2 / 48)
    return torch.cat([torch.cos(half), vector * scale], -1)


def quaternion_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrices ``[..., 3, 3]`` of quaternions ``[..., 4]`` (normalised first)."""
    w, x, y, z = normalize_quaternion(q).unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = (
        1 - 2 * (yy + zz),
        2 * (xy - wz),
        2 * (xz + wy),
        2 * (xy + wz),
        1 - 2 * (xx + zz),
        2 * (yz - wx),
        2 * (xz - wy),
        2 * (yz + wx),
        1 - 2 * (xx + yy),
    )
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quaternion(R: Tensor) -> Tensor:
    """Canonical unit quaternions ``[..., 4]`` of rotation matrices ``[..., 3, 3]``.

    Shepperd's method: each of the four candidate rows below equals ``4·q_i·q`` for one
    component ``q_i``; the row whose ``4·q_i²`` (its ``i``-th entry) is largest is normalised,
    which is accurate for every rotation, including angles near 180°. Slightly non-orthogonal
    inputs (e.g. matrices read from text files) give the nearest quaternion in this sense.
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"expected rotation matrices of shape [..., 3, 3], got {tuple(R.shape)}")
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    candidates = torch.stack(
        (
            torch.stack((1 + r00 + r11 + r22, r21 - r12, r02 - r20, r10 - r01), dim=-1),
            torch.stack((r21 - r12, 1 + r00 - r11 - r22, r01 + r10, r02 + r20), dim=-1),
            torch.stack((r02 - r20, r01 + r10, 1 - r00 + r11 - r22, r12 + r21), dim=-1),
            torch.stack((r10 - r01, r02 + r20, r12 + r21, 1 - r00 - r11 + r22), dim=-1),
        ),
        dim=-2,
    )  # [..., 4 candidates, 4]
    best = torch.diagonal(candidates, dim1=-2, dim2=-1).argmax(dim=-1)
    index = best[..., None, None].expand(*best.shape, 1, 4)
    chosen = torch.gather(candidates, -2, index).squeeze(-2)
    return canonicalize_quaternion(chosen)


def position_error(x_hat: Tensor, x: Tensor) -> Tensor:
    """Euclidean distance ``[...]`` between positions ``[..., 3]`` (metres)."""
    return torch.linalg.vector_norm(x_hat - x, dim=-1)


def orientation_error_deg(q_hat: Tensor, q: Tensor) -> Tensor:
    """Rotation angle ``[...]`` in degrees between quaternions ``[..., 4]`` (any norm and sign).

    Equals ``2·acos(|⟨q̂/‖q̂‖, q/‖q‖⟩|)`` but is evaluated as ``4·atan2(‖a − b‖, ‖a + b‖)`` with
    ``a, b`` the normalised quaternions on the same hemisphere, which keeps small angles accurate
    in float32 (``acos`` near 1 loses about half the significant digits) and is never NaN.
    """
    a = normalize_quaternion(q_hat)
    b = normalize_quaternion(q)
    same_hemisphere = (a * b).sum(dim=-1, keepdim=True) >= 0
    b = torch.where(same_hemisphere, b, -b)
    half_chord = torch.linalg.vector_norm(a - b, dim=-1)
    half_sum = torch.linalg.vector_norm(a + b, dim=-1)
    return torch.rad2deg(4.0 * torch.atan2(half_chord, half_sum))


def pose_errors(pred: Tensor, gt: Tensor) -> tuple[Tensor, Tensor]:
    """Position error (m) and orientation error (deg), each ``[...]``, of poses ``[..., 7]``."""
    pos_m = position_error(pred[..., :3], gt[..., :3])
    rot_deg = orientation_error_deg(pred[..., 3:], gt[..., 3:])
    return pos_m, rot_deg


def relative_pose(p_ref: Tensor, p_query: Tensor) -> Tensor:
    """Pose ``[..., 7]`` of the query camera relative to the reference camera.

    ``t = t_query − t_ref`` (world frame, m) and ``q = conj(q_ref) ⊗ q_query`` (canonicalised).
    """
    q_ref_inv = quaternion_conjugate(normalize_quaternion(p_ref[..., 3:]))
    t = p_query[..., :3] - p_ref[..., :3]
    q = quaternion_multiply(q_ref_inv, normalize_quaternion(p_query[..., 3:]))
    return torch.cat(_broadcast_leading(t, canonicalize_quaternion(q)), dim=-1)


def compose_pose(p_ref: Tensor, p_rel: Tensor) -> Tensor:
    """World pose ``[..., 7]`` of a camera at relative pose ``p_rel`` from ``p_ref``.

    Inverse of :func:`relative_pose`: ``compose_pose(p_ref, relative_pose(p_ref, p)) == p``.
    """
    q_ref = normalize_quaternion(p_ref[..., 3:])
    t = p_ref[..., :3] + p_rel[..., :3]
    q = quaternion_multiply(q_ref, normalize_quaternion(p_rel[..., 3:]))
    return torch.cat(_broadcast_leading(t, canonicalize_quaternion(q)), dim=-1)


def _broadcast_leading(t: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
    """Broadcast ``t [..., 3]`` and ``q [..., 4]`` to common leading dimensions."""
    leading = torch.broadcast_shapes(t.shape[:-1], q.shape[:-1])
    return t.expand(*leading, 3), q.expand(*leading, 4)


def average_quaternions(q: Tensor, weights: Tensor | None = None) -> Tensor:
    """Weighted average ``[..., 4]`` of ``k`` quaternions ``q [..., k, 4]`` (Markley et al. 2007).

    The average is the eigenvector of the largest eigenvalue of ``Σ wᵢ qᵢ qᵢᵀ`` (quaternions
    normalised first), so it does not depend on the signs of the inputs. ``weights [..., k]``
    should be non-negative; ``None`` means equal weights. The result is canonicalised.
    """
    q = normalize_quaternion(q)
    if weights is None:
        scatter = q.transpose(-1, -2) @ q
    else:
        scatter = (q * weights[..., None]).transpose(-1, -2) @ q
    _, eigenvectors = torch.linalg.eigh(scatter)  # eigenvalues ascending
    return canonicalize_quaternion(eigenvectors[..., -1])


def transfer_error(truth: Tensor, estimate: Tensor, target: Tensor) -> Tensor:
    """An estimate's error moved to another world frame: ``estimate`` [..., 7] of a camera whose
    true pose is ``truth`` [..., 7] has the error ``dt = R^T (t_est - t)``, ``dR = R^T R_est``
    in the true camera's frame, which no world frame changes; applied to the same camera's pose
    ``target`` [..., 7] in another frame it gives the estimate there (camera-to-world, unit
    quaternions)."""
    q_inverse = quaternion_conjugate(normalize_quaternion(truth[..., 3:]))
    dt = quaternion_apply(q_inverse, estimate[..., :3] - truth[..., :3])
    dq = quaternion_multiply(q_inverse, normalize_quaternion(estimate[..., 3:]))
    q_target = normalize_quaternion(target[..., 3:])
    t = target[..., :3] + quaternion_apply(q_target, dt)
    q = canonicalize_quaternion(normalize_quaternion(quaternion_multiply(q_target, dq)))
    return torch.cat([t, q], dim=-1)
