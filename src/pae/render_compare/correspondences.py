"""Poses from keypoint correspondences: the query matched against the scene model's rendering
at its start and against the nearest train views, each match lifted to 3-D through the scene
model's depth, the absolute pose solved robustly (PnP in OpenCV's USAC with MAGSAC). Unlike
the photometric search it needs no start inside a basin: a start only says where to render
and (with ``near_views``) which train views to look at.

1. **Keypoints** on the query at its match size (the loader's full size where features
   exist, not the compare width) with OpenCV's SIFT or ORB (no weights).
2. **References**: the scene model rendered (colour and depth) at the start with a wider
   field of view; the ``views`` train views whose global descriptor is nearest the query's
   and the ``near_views`` train cameras nearest the start (:class:`TrainViews`: their
   keypoints lifted once through the depth the scene model renders at their poses).
3. **Matches**: mutual nearest neighbours passing Lowe's ratio test, batched over queries.
4. **Pose**: PnP in USAC (MAGSAC) on every match pooled; then rendered again at the solved
   pose and matched again, up to ``iterations`` times or until the pose stops moving.

Detection and the solver are OpenCV calls, one per image (no batched form exists); they run
on threads (OpenCV releases the GIL). Everything between them is batched."""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor

from pae.core.features import DETECTORS, Keypoints, mutual_matches, worker_threads
from pae.core.geometry import matrix_to_quaternion, normalize_quaternion
from pae.render_compare.keypoints import MIN_DEPTH_M, MatchSettings, detect, lift
from pae.render_compare.train_views import (
    Describer,
    MatchQueries,
    TrainImages,
    TrainViews,
    nearest_cameras,
    thumbnail_descriptors,
    train_views,
    unit_rgb,
)
from pae.scene_model.base import SceneModel

__all__ = [
    "DETECTORS",
    "Correspondences",
    "Describer",
    "Keypoints",
    "MatchQueries",
    "MatchSettings",
    "TrainImages",
    "TrainViews",
    "correspond",
    "detect",
    "lift",
    "mutual_matches",
    "thumbnail_descriptors",
    "train_views",
]

STILL_M, STILL_DEG = 0.005, 0.1
"""The render -> match -> solve loop stops once no query's pose moves more than this."""
MATCH_CHUNK = 64
"""Queries matched at once: bounds the renderings and the descriptor distances (a query's
1,000 × 1,000 SIFT distances are 4 MB) whatever the number of queries."""


class Correspondences(NamedTuple):
    """Poses [B, 7] solved from correspondences (the start where none was found), found [B]
    bool, inliers [B] (the last solve's), matches [B] (pooled in the last round)."""

    poses: Tensor
    found: Tensor
    inliers: Tensor
    matches: Tensor


def _wider(intrinsics: Tensor, width: int, height: int, fov_scale: float) -> Tensor:
    """Intrinsics [B, 4] of ``width × height`` renderings centred like ``intrinsics``' images
    (of the same aspect) with ``fov_scale`` × their field of view."""
    fx, fy, cx, _ = intrinsics.unbind(-1)
    scale = width / (2 * (cx + 0.5)) / fov_scale
    return torch.stack(
        [
            fx * scale,
            fy * scale,
            torch.full_like(fx, (width - 1) / 2),
            torch.full_like(fy, (height - 1) / 2),
        ],
        -1,
    )


def _retrieve(
    views: TrainViews, descriptors: Tensor, starts: Tensor, scenes: Tensor, settings: MatchSettings
) -> Tensor:
    """Rows [B, V] of the train views each query matches against: the ``views`` nearest by
    descriptor, then the ``near_views`` cameras nearest its start (in its scene)."""
    other = scenes[:, None] != views.scenes[None]
    chosen = []
    if settings.views:
        similarity = (descriptors @ views.descriptors.T).masked_fill(other, -math.inf)
        chosen.append(similarity.topk(min(settings.views, similarity.shape[1]), 1).indices)
    if settings.near_views:
        chosen.append(
            nearest_cameras(starts, scenes, views.poses, views.scenes, settings.near_views)
        )
    return torch.cat(chosen, 1)


class _Pooled(NamedTuple):
    xy: Tensor  # [B, M, 2] query px
    points: Tensor  # [B, M, 3] world
    valid: Tensor  # [B, M]


def _view_matches(
    query: Keypoints, views: TrainViews, rows: Tensor, settings: MatchSettings
) -> _Pooled:
    """Matches of each query against its retrieved views ``rows`` [B, V], pooled."""
    b, v = rows.shape
    k = query.xy.shape[1]
    flat = rows.flatten()
    repeated = Keypoints(
        query.xy.repeat_interleave(v, 0),
        query.descriptors.repeat_interleave(v, 0),
        query.count.repeat_interleave(v, 0),
    )
    reference = Keypoints(
        views.keypoints.xy[flat], views.keypoints.descriptors[flat], views.keypoints.count[flat]
    )
    index, matched = mutual_matches(
        repeated, reference, settings.ratio, settings.detector != "sift"
    )
    lifted = views.lifted[flat].gather(1, index)
    points = views.points[flat].gather(1, index[..., None].expand(-1, -1, 3))
    return _Pooled(
        repeated.xy.view(b, v * k, 2),
        points.view(b, v * k, 3),
        (matched & lifted).view(b, v * k),
    )


def _render_matches(
    scene_model: SceneModel,
    query: Keypoints,
    poses: Tensor,
    scenes: Tensor,
    intrinsics: Tensor,
    size: tuple[int, int],
    settings: MatchSettings,
) -> _Pooled:
    """Matches of each query against the scene model rendered at poses [B, 7]."""
    width, height = size
    render_w = settings.render_width
    render_h = max(4, round(height * render_w / width))
    wide = _wider(intrinsics, render_w, render_h, settings.render_fov_scale)
    rendering = scene_model.render(poses, scenes, wide, render_w, render_h, settings.surface_share)
    assert rendering.depth is not None and rendering.opacity is not None
    seen = (rendering.opacity > 0.5) & (rendering.depth > MIN_DEPTH_M)
    found = detect(rendering.rgb, settings, seen)
    index, matched = mutual_matches(query, found, settings.ratio, settings.detector != "sift")
    points, lifted = lift(found.xy, rendering.depth, rendering.opacity, poses, wide)
    gathered = points.gather(1, index[..., None].expand(-1, -1, 3))
    return _Pooled(query.xy, gathered, matched & lifted.gather(1, index))


def _solve(
    pooled: _Pooled, intrinsics: Tensor, starts: Tensor, settings: MatchSettings
) -> tuple[Tensor, Tensor]:
    """PnP in USAC (MAGSAC) per query -> camera-to-world poses [B, 7] (the start where it
    found fewer than ``min_inliers``) and inlier counts [B]."""
    xy, points = (t.double().cpu().numpy() for t in pooled[:2])
    valid = pooled.valid.cpu().numpy()
    k = intrinsics.double().cpu().numpy()

    def one(row: int) -> tuple[np.ndarray | None, int]:
        keep = valid[row]
        if keep.sum() < settings.min_inliers:
            return None, 0
        camera = np.array([[k[row, 0], 0, k[row, 2]], [0, k[row, 1], k[row, 3]], [0, 0, 1]])
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            points[row][keep],
            xy[row][keep],
            camera,
            None,
            iterationsCount=1000,
            reprojectionError=settings.reprojection_px,
            confidence=0.999,
            flags=cv2.USAC_MAGSAC,
        )
        count = 0 if inliers is None else len(inliers)
        if not ok or count < settings.min_inliers:
            return None, count
        rotation, _ = cv2.Rodrigues(rvec)
        to_world = rotation.T
        return np.concatenate([(-to_world @ tvec).ravel(), to_world.ravel()]), count

    with ThreadPoolExecutor(worker_threads()) as pool:
        solved = list(pool.map(one, range(len(xy))))
    poses = starts.clone().float()
    counts = torch.tensor([count for _, count in solved], dtype=torch.long)
    rows = [row for row, (pose, _) in enumerate(solved) if pose is not None]
    if rows:
        found = torch.from_numpy(np.stack([solved[row][0] for row in rows])).float()
        quaternion = matrix_to_quaternion(found[:, 3:].view(-1, 3, 3))
        poses[rows] = torch.cat([found[:, :3], quaternion], -1).to(poses)
    return poses, counts


def _moved(a: Tensor, b: Tensor) -> Tensor:
    """Whether poses a, b [B, 7] differ by more than STILL_M or STILL_DEG."""
    position = (a[:, :3] - b[:, :3]).norm(dim=-1)
    dot = (normalize_quaternion(a[:, 3:]) * normalize_quaternion(b[:, 3:])).sum(-1).abs()
    angle = torch.rad2deg(2 * torch.acos(dot.clamp(max=1.0)))
    return (position > STILL_M) | (angle > STILL_DEG)


@torch.no_grad()
def correspond(
    scene_model: SceneModel,
    images: Tensor,
    intrinsics: Tensor,
    starts: Tensor,
    scenes: Tensor,
    settings: MatchSettings,
    views: TrainViews | None = None,
    describe: Describer | None = None,
    chunk: int = MATCH_CHUNK,
) -> Correspondences:
    """Poses of query images [B, 3, H, W] (RGB, uint8 or float in [0, 1], at the match
    width) with intrinsics [B, 4] (px of those images) from correspondences with the scene
    model's renderings at starts [B, 7] (camera-to-world) in scenes [B] and with ``views``
    (the train views, :func:`train_views`; needed where ``settings.views`` or
    ``near_views``). Queries without ``min_inliers`` inliers keep their starts (``found``
    False). Each round renders, matches and solves ``chunk`` queries at a time (the
    renderings and descriptor distances stay that size), and another round follows while any
    query's pose moved: the chunking changes no result."""
    if settings.uses_views and views is None:
        raise ValueError(
            "render_compare.match.views and near_views need the train views (train_views())"
        )
    if chunk < 1:
        raise ValueError(f"correspond: chunk must be >= 1 query, not {chunk}")
    starts = torch.cat([starts[:, :3], normalize_quaternion(starts[:, 3:])], -1).float()
    intrinsics = intrinsics.float()
    size = (images.shape[-1], images.shape[-2])
    chunks = [
        _keypoints(rows, unit_rgb(images[rows]), starts, scenes, settings, views, describe)
        for rows in torch.arange(len(starts)).split(chunk)
    ]
    poses, found = starts.clone(), torch.zeros(len(starts), dtype=torch.bool)
    inliers, matches = (torch.zeros(len(starts), dtype=torch.long) for _ in range(2))
    rounds = max(1, settings.iterations) if settings.render_width else 1
    for _ in range(rounds):
        moved = False
        for rows, query, fixed in chunks:
            parts = [] if fixed is None else [fixed]
            if settings.render_width:
                where = poses[rows], scenes[rows], intrinsics[rows]
                parts.append(_render_matches(scene_model, query, *where, size, settings))
            pooled = _Pooled(*(torch.cat(column, 1) for column in zip(*parts, strict=True)))
            solved, counts = _solve(pooled, intrinsics[rows], starts[rows], settings)
            now = counts >= settings.min_inliers
            better = now & (counts >= inliers[rows])
            moved |= bool((_moved(solved, poses[rows]) & better).any())
            poses[rows] = torch.where(better[:, None], solved, poses[rows])
            inliers[rows] = torch.where(better, counts, inliers[rows])
            matches[rows] = torch.where(better, pooled.valid.sum(1), matches[rows])
            found[rows] |= now
        if not settings.render_width or not moved:
            break
    return Correspondences(poses, found, inliers, matches)


class _Chunk(NamedTuple):
    rows: Tensor  # [C] the chunk's queries
    query: Keypoints  # their keypoints
    fixed: _Pooled | None  # their matches with the train views (kept in every round)


def _keypoints(
    rows: Tensor,
    images: Tensor,
    starts: Tensor,
    scenes: Tensor,
    settings: MatchSettings,
    views: TrainViews | None,
    describe: Describer | None,
) -> _Chunk:
    """The keypoints of one chunk's query images [C, 3, H, W] (float in [0, 1]), rows [C] of
    ``starts`` and ``scenes``, and their matches with the train views where the settings
    retrieve any."""
    query = detect(images, settings)
    if not settings.uses_views:
        return _Chunk(rows, query, None)
    assert views is not None
    descriptors = (describe or thumbnail_descriptors)(images)
    chosen = _retrieve(views, descriptors, starts[rows], scenes[rows], settings)
    return _Chunk(rows, query, _view_matches(query, views, chosen, settings))
