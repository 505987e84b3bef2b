"""Depth at the train images' keypoints, triangulated between train views whose poses are
known (what a structure-from-motion model's sparse points give a NeRF's fit): SIFT keypoints
(OpenCV, no weights) of each train image matched to those of its two partner views (mutual
nearest neighbours, Lowe's ratio test), each match triangulated, and a keypoint kept only
where both partners agree on its depth. The scene model's fit draws rays through these
keypoints and asks each ray's light to end at their depth
(:meth:`pae.scene_model.voxel_grid.VoxelGrid.depth_error`)."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from pae.core.camera import directions_through
from pae.core.features import Keypoints, detect, mutual_matches
from pae.core.geometry import quaternion_to_matrix
from pae.scene_model.voxel_layout import camera_extent_m

KEYPOINTS = 500
"""SIFT keypoints per train image at most (contrast 0.01)."""
RATIO = 0.8
"""Lowe's ratio test."""
MIN_BASELINE = 0.15
"""A partner view's camera lies at least this share of the scene's camera extent away."""
MAX_AXIS_DEG = 30.0
"""And its optical axis within this angle of the image's."""
MAX_REPROJECTION_PX = 1.0
"""A triangulated point reprojects within this many px in both views."""
MIN_PARALLAX_DEG = 1.5
"""Its two rays meet at this angle at least."""
AGREE_LOG = 0.05
"""Both partners' depths agree within this (natural log: 5 %)."""
PAIRS_PER_CHUNK = 64
DETECT_ROWS = 256
SIFT_BYTES = 128


class SparseDepths(NamedTuple):
    """Keypoints with a triangulated depth: the train image's row [P], its pixel u, v [P]
    (px of the images triangulated on; column, row) and the depth [P] (m along the optical
    axis)."""

    row: Tensor
    u: Tensor
    v: Tensor
    depth: Tensor


def partner_views(
    poses: Tensor, scenes: Tensor, count: int = 2, min_baseline: float = MIN_BASELINE
) -> Tensor:
    """Rows [N, count] of each train camera's partners among poses [N, 7] of scenes [N]: the
    nearest cameras of its scene at least ``min_baseline`` × the scene's camera extent away
    whose optical axes lie within ``MAX_AXIS_DEG``; -1 where fewer exist."""
    positions = poses[:, :3].double()
    axes = quaternion_to_matrix(poses[:, 3:].double())[:, :, 2]
    extent = torch.zeros(len(poses), dtype=torch.float64)
    for scene in scenes.unique():
        mine = scenes == scene
        extent[mine] = camera_extent_m(positions[mine])
    distance = torch.cdist(positions, positions)
    allowed = (
        (scenes[:, None] == scenes[None])
        & (distance >= (min_baseline * extent)[:, None].clamp_min(1e-6))
        & (axes @ axes.T >= math.cos(math.radians(MAX_AXIS_DEG)))
    )
    cost = distance.masked_fill(~allowed, math.inf)
    k = min(count, len(poses))
    best = cost.topk(k, 1, largest=False)
    rows = best.indices.masked_fill(best.values.isinf(), -1)
    if k < count:
        rows = torch.cat([rows, rows.new_full((len(poses), count - k), -1)], 1)
    return rows


def triangulate(
    xy_a: Tensor,
    xy_b: Tensor,
    poses_a: Tensor,
    poses_b: Tensor,
    intr_a: Tensor,
    intr_b: Tensor,
    min_parallax_deg: float = MIN_PARALLAX_DEG,
) -> tuple[Tensor, Tensor]:
    """Matched pixels xy [B, K, 2] of cameras a and b (poses [B, 7] camera-to-world,
    intrinsics [B, 4]) -> the depth [B, K] (m along a's optical axis) of the midpoint of
    their rays' closest approach, and whether it holds [B, K]: in front of both cameras,
    reprojecting within ``MAX_REPROJECTION_PX`` in both, rays meeting at
    ``min_parallax_deg`` or more."""
    rot_a = quaternion_to_matrix(poses_a[:, 3:].double())
    rot_b = quaternion_to_matrix(poses_b[:, 3:].double())
    local_a = directions_through(xy_a[..., 0], xy_a[..., 1], intr_a[:, None].double())
    local_b = directions_through(xy_b[..., 0], xy_b[..., 1], intr_b[:, None].double())
    d_a = torch.einsum("bij,bkj->bki", rot_a, local_a)  # camera z = 1: t is the depth
    d_b = torch.einsum("bij,bkj->bki", rot_b, local_b)
    w = (poses_a[:, None, :3] - poses_b[:, None, :3]).double()
    aa, bb, ab = (d_a * d_a).sum(-1), (d_b * d_b).sum(-1), (d_a * d_b).sum(-1)
    wa, wb = (w * d_a).sum(-1), (w * d_b).sum(-1)
    denominator = (aa * bb - ab * ab).clamp_min(1e-12)
    t_a = (ab * wb - bb * wa) / denominator
    t_b = (aa * wb - ab * wa) / denominator
    point = (poses_a[:, None, :3] + t_a[..., None] * d_a + poses_b[:, None, :3]) / 2
    point = point + t_b[..., None] * d_b / 2

    def reprojection(pose: Tensor, rot: Tensor, intr: Tensor, xy: Tensor) -> Tensor:
        local = torch.einsum("bji,bkj->bki", rot, point - pose[:, None, :3].double())
        fx, fy, cx, cy = intr.double()[:, None].unbind(-1)
        z = local[..., 2].clamp_min(1e-9)
        u, v = fx * local[..., 0] / z + cx, fy * local[..., 1] / z + cy
        return torch.hypot(u - xy[..., 0], v - xy[..., 1])

    cosine = ab / (aa * bb).sqrt()
    holds = (
        (t_a > 0)
        & (t_b > 0)
        & (reprojection(poses_a, rot_a, intr_a, xy_a) < MAX_REPROJECTION_PX)
        & (reprojection(poses_b, rot_b, intr_b, xy_b) < MAX_REPROJECTION_PX)
        & (cosine <= math.cos(math.radians(min_parallax_deg)))
    )
    return t_a.float(), holds


def _pair_depths(
    keypoints: Keypoints,
    rows: Tensor,
    partners: Tensor,
    poses: Tensor,
    intrinsics: Tensor,
    min_parallax_deg: float,
) -> tuple[Tensor, Tensor]:
    """Depth [B, K] of the keypoints of images ``rows`` [B] triangulated with their
    ``partners`` [B] (>= 0), and where it holds [B, K]."""
    query = Keypoints(*(part[rows] for part in keypoints))
    reference = Keypoints(*(part[partners] for part in keypoints))
    nearest, matched = mutual_matches(query, reference, RATIO, binary=False)
    other = reference.xy.gather(1, nearest[..., None].expand(-1, -1, 2))
    depth, holds = triangulate(
        query.xy, other, poses[rows], poses[partners], intrinsics[rows], intrinsics[partners],
        min_parallax_deg,
    )  # fmt: skip
    return depth, holds & matched


def _keypoints(images: Tensor) -> Keypoints:
    """SIFT keypoints of uint8 images [N, 3, H, W], detected ``DETECT_ROWS`` at a time."""
    found = [
        detect(images[start : start + DETECT_ROWS].float() / 255, "sift", KEYPOINTS)
        for start in range(0, len(images), DETECT_ROWS)
    ]
    size = max(part.xy.shape[1] for part in found)

    def padded(t: Tensor, last: int | None = None) -> Tensor:  # [n, k, d] -> [n, size, last]
        return F.pad(t, (0, (last or t.shape[2]) - t.shape[2], 0, size - t.shape[1]))

    return Keypoints(
        torch.cat([padded(part.xy) for part in found]),
        torch.cat([padded(part.descriptors, SIFT_BYTES) for part in found]),
        torch.cat([part.count for part in found]),
    )


def sparse_depths(
    images: Tensor,
    poses: Tensor,
    intrinsics: Tensor,
    scenes: Tensor,
    min_baseline: float = MIN_BASELINE,
    min_parallax_deg: float = MIN_PARALLAX_DEG,
) -> SparseDepths:
    """Triangulated keypoints of train images uint8 [N, 3, H, W] (poses [N, 7], intrinsics
    [N, 4] of those images, scenes [N]): each image's keypoints matched to its two
    :func:`partner_views` (``min_baseline``), kept where both triangulations hold
    (``min_parallax_deg``: :func:`triangulate`) and their depths agree within ``AGREE_LOG``,
    at the two depths' geometric mean."""
    keypoints = _keypoints(images)
    partners = partner_views(poses, scenes, min_baseline=min_baseline)
    usable = (partners >= 0).all(1).nonzero().squeeze(1)
    parts: list[SparseDepths] = []
    for chunk in usable.split(PAIRS_PER_CHUNK):
        both = partners[chunk].T.flatten()  # each image's first partners, then its second
        depth, holds = _pair_depths(
            keypoints, chunk.repeat(2), both, poses, intrinsics, min_parallax_deg
        )
        (first, second), (holds_first, holds_second) = depth.chunk(2), holds.chunk(2)
        gap = (first.clamp_min(1e-9).log() - second.clamp_min(1e-9).log()).abs()
        keep = holds_first & holds_second & (gap < AGREE_LOG)
        image, slot = keep.nonzero(as_tuple=True)
        xy = keypoints.xy[chunk[image], slot]
        depth = (first[image, slot] * second[image, slot]).sqrt()
        parts.append(SparseDepths(chunk[image], xy[:, 0], xy[:, 1], depth))
    if not parts:
        empty = torch.zeros(0)
        return SparseDepths(torch.zeros(0, dtype=torch.long), empty, empty, empty)
    return SparseDepths(*(torch.cat(column) for column in zip(*parts, strict=True)))
