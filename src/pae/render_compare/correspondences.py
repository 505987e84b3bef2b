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

import dataclasses
import math
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from pae.core.camera import camera_rays
from pae.core.geometry import matrix_to_quaternion, normalize_quaternion, quaternion_to_matrix
from pae.core.threads import current_budget
from pae.scene_model.base import SceneModel

DETECTORS = ("sift", "orb")
MIN_DEPTH_M = 0.05
"""Rendered depths below this (m) lift no keypoint."""
STILL_M, STILL_DEG = 0.005, 0.1
"""The render -> match -> solve loop stops once no query's pose moves more than this."""
DESCRIPTOR_SIDE = 16
"""The classical global descriptor: a band-passed grey thumbnail this many px on its longer
side (:func:`thumbnail_descriptors`)."""

Describer = Callable[[Tensor], Tensor]
"""RGB images [B, 3, H, W] in [0, 1] -> global descriptors [B, G], unit length."""


@dataclasses.dataclass(frozen=True)
class MatchSettings:
    """The correspondence stage's settings (``render_compare.match``); ``width`` 0: off."""

    width: int = 0
    """The query's width (px) where keypoints are detected; 0: the stage is off."""
    detector: str = "sift"
    """OpenCV's ``sift`` or ``orb``."""
    contrast: float = 0.01
    """SIFT's contrast threshold (OpenCV's default 0.04 keeps few keypoints on soft images);
    ORB's FAST threshold is ``contrast`` × 500 grey levels."""
    keypoints: int = 1000
    """At most this many keypoints per image."""
    ratio: float = 0.85
    """Lowe's ratio test: a match's distance below this share of the second nearest's."""
    render_width: int = 128
    """The scene model's rendering at the start (px; 0: none), with ``render_fov_scale`` ×
    the query's field of view."""
    render_fov_scale: float = 1.3
    views: int = 0
    """Train views retrieved by global descriptor per query (0: none)."""
    near_views: int = 0
    """Train views whose cameras lie nearest the start per query (0: none)."""
    depth_width: int = 64
    """The train views' depth rendering (px) that lifts their keypoints."""
    iterations: int = 2
    """Render -> match -> solve rounds (the train views' matches are kept in each)."""
    reprojection_px: float = 1.5
    """The solver's inlier threshold, px at ``width``."""
    min_inliers: int = 15
    """Fewer inliers: no pose from correspondences (the query keeps its start)."""
    surface_share: float = 0.0
    """The depth that lifts a keypoint (:meth:`SceneModel.render`'s)."""

    def __post_init__(self) -> None:
        if self.detector not in DETECTORS:
            raise ValueError(
                f"render_compare.match.detector must be one of {DETECTORS}, not {self.detector!r}"
            )
        if self.width < 0 or (0 < self.width < 32):
            raise ValueError(f"render_compare.match.width must be 0 or >= 32, not {self.width}")
        if self.render_width < 0 or (0 < self.render_width < 32) or self.depth_width < 8:
            raise ValueError(
                "render_compare.match needs render_width 0 or >= 32 and depth_width >= 8, not "
                f"{self.render_width} and {self.depth_width}"
            )
        if min(self.views, self.near_views, self.iterations) < 0 or self.keypoints < 8:
            raise ValueError(
                "render_compare.match needs views, near_views, iterations >= 0 and keypoints "
                f">= 8, not {self.views}, {self.near_views}, {self.iterations}, {self.keypoints}"
            )
        if not 0 < self.ratio <= 1 or self.reprojection_px <= 0 or self.min_inliers < 4:
            raise ValueError(
                "render_compare.match needs 0 < ratio <= 1, reprojection_px > 0 and "
                f"min_inliers >= 4, not {self.ratio}, {self.reprojection_px}, {self.min_inliers}"
            )
        if self.render_fov_scale <= 0 or not 0 <= self.surface_share < 1:
            raise ValueError(
                "render_compare.match needs render_fov_scale > 0 and 0 <= surface_share < 1"
            )

    @property
    def active(self) -> bool:
        return self.width > 0 and bool(self.render_width or self.views or self.near_views)

    @property
    def uses_views(self) -> bool:
        return self.active and bool(self.views or self.near_views)


class Keypoints(NamedTuple):
    """Keypoints of ``B`` images, padded to ``K``: xy [B, K, 2] px, descriptors [B, K, D]
    (float; binary ones as 0/1 bits), count [B]."""

    xy: Tensor
    descriptors: Tensor
    count: Tensor

    @property
    def mask(self) -> Tensor:  # [B, K] real keypoints
        return torch.arange(self.xy.shape[1])[None] < self.count[:, None]


class TrainViews(NamedTuple):
    """The train views the stage retrieves: keypoints [N, K, ...] lifted to world points
    [N, K, 3] (``lifted`` [N, K] where the scene model saw a surface), global descriptors
    [N, G], poses [N, 7] and scenes [N]."""

    keypoints: Keypoints
    points: Tensor
    lifted: Tensor
    descriptors: Tensor
    poses: Tensor
    scenes: Tensor


class Correspondences(NamedTuple):
    """Poses [B, 7] solved from correspondences (the start where none was found), found [B]
    bool, inliers [B] (the last solve's), matches [B] (pooled in the last round)."""

    poses: Tensor
    found: Tensor
    inliers: Tensor
    matches: Tensor


def _grey_uint8(images: Tensor) -> np.ndarray:
    """RGB [B, 3, H, W] in [0, 1] -> uint8 grey [B, H, W]."""
    grey = 0.299 * images[:, 0] + 0.587 * images[:, 1] + 0.114 * images[:, 2]
    return (grey.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()


def _detector(settings: MatchSettings) -> cv2.Feature2D:
    if settings.detector == "sift":
        return cv2.SIFT_create(settings.keypoints, contrastThreshold=settings.contrast)
    fast = max(1, round(settings.contrast * 500))
    return cv2.ORB_create(settings.keypoints, edgeThreshold=15, patchSize=15, fastThreshold=fast)


def _workers() -> int:
    return max(1, current_budget().threads)


def detect(
    images: Tensor, settings: MatchSettings, masks: Tensor | None = None
) -> Keypoints:
    """Keypoints of RGB images [B, 3, H, W] in [0, 1], at most ``settings.keypoints`` each
    (the strongest); ``masks`` [B, H, W] bool: only where True."""
    grey = _grey_uint8(images)
    allowed = None if masks is None else masks.to(torch.uint8).mul(255).cpu().numpy()
    binary = settings.detector != "sift"

    def one(index: int) -> tuple[np.ndarray, np.ndarray]:
        detector = _detector(settings)
        mask = None if allowed is None else allowed[index]
        found, described = detector.detectAndCompute(grey[index], mask)
        if described is None or not found:
            return np.zeros((0, 2), np.float32), np.zeros((0, 0), np.float32)
        strength = np.array([k.response for k in found], np.float32)
        keep = np.argsort(-strength, kind="stable")[: settings.keypoints]
        xy = np.array([found[i].pt for i in keep], np.float32)
        chosen = described[keep]
        if binary:
            chosen = np.unpackbits(chosen, axis=1)
        return xy, chosen.astype(np.float32)

    with ThreadPoolExecutor(_workers()) as pool:
        found = list(pool.map(one, range(len(grey))))
    size = max([len(xy) for xy, _ in found] + [1])
    dim = max([d.shape[1] for _, d in found] + [1])
    xy = torch.zeros(len(found), size, 2)
    descriptors = torch.zeros(len(found), size, dim)
    count = torch.zeros(len(found), dtype=torch.long)
    for row, (points, described) in enumerate(found):
        xy[row, : len(points)] = torch.from_numpy(points)
        if len(points):
            descriptors[row, : len(points), : described.shape[1]] = torch.from_numpy(described)
        count[row] = len(points)
    return Keypoints(xy, descriptors, count)


def mutual_matches(
    query: Keypoints, reference: Keypoints, ratio: float, binary: bool
) -> tuple[Tensor, Tensor]:
    """For each query keypoint [B, K] the index [B, K] of its match among the reference's
    (mutual nearest neighbours passing the ratio test) and whether it has one [B, K]."""
    a, b = query.descriptors, reference.descriptors
    if binary:  # Hamming distances of 0/1 bits
        distance = a.sum(-1)[..., None] + b.sum(-1)[:, None] - 2 * a @ b.transpose(1, 2)
    else:
        distance = torch.cdist(a, b)
    far = torch.finfo(distance.dtype).max
    distance = distance.masked_fill(~reference.mask[:, None], far)
    distance = distance.masked_fill(~query.mask[..., None], far)
    if distance.shape[2] < 2:
        empty = torch.zeros(query.xy.shape[:2], dtype=torch.bool)
        return torch.zeros_like(empty, dtype=torch.long), empty
    two, nearest = distance.topk(2, dim=2, largest=False)
    back = distance.argmin(1)  # [B, M]: each reference keypoint's nearest query keypoint
    mutual = back.gather(1, nearest[..., 0]) == torch.arange(distance.shape[1])[None]
    passes = two[..., 0] < ratio * two[..., 1]
    return nearest[..., 0], mutual & passes & query.mask & (two[..., 0] < far)


def lift(xy: Tensor, depth: Tensor, opacity: Tensor, poses: Tensor, intrinsics: Tensor):
    """World points [B, K, 3] of pixels xy [B, K, 2] (px of ``depth`` [B, H, W]) and where
    the model saw a surface there [B, K] (opacity [B, H, W] > 0.5, depth > MIN_DEPTH_M);
    poses [B, 7] camera-to-world, intrinsics [B, 4] of the depth images."""
    h, w = depth.shape[-2:]
    column = xy[..., 0].round().long().clamp(0, w - 1)
    row = xy[..., 1].round().long().clamp(0, h - 1)
    at = row * w + column
    z = depth.flatten(1).gather(1, at)
    seen = (opacity.flatten(1).gather(1, at) > 0.5) & (z > MIN_DEPTH_M)
    fx, fy, cx, cy = intrinsics[:, None].unbind(-1)
    local = torch.stack([(xy[..., 0] - cx) / fx * z, (xy[..., 1] - cy) / fy * z, z], -1)
    rotation = quaternion_to_matrix(poses[:, 3:])
    return torch.einsum("bij,bkj->bki", rotation, local) + poses[:, None, :3], seen


def thumbnail_descriptors(images: Tensor) -> Tensor:
    """The classical global descriptor of RGB images [B, 3, H, W]: the grey image's
    band-pass (a blurred copy subtracted) area-downsampled to ``DESCRIPTOR_SIDE`` px on its
    longer side, zero-mean and unit length -> [B, G]."""
    grey = (0.299 * images[:, 0] + 0.587 * images[:, 1] + 0.114 * images[:, 2])[:, None]
    h, w = grey.shape[-2:]
    scale = DESCRIPTOR_SIDE / max(h, w)
    small = F.interpolate(
        grey, size=(max(2, round(h * scale)), max(2, round(w * scale))), mode="area"
    )
    smooth = F.avg_pool2d(F.pad(small, (2, 2, 2, 2), mode="replicate"), 5, stride=1)
    flat = (small - smooth).flatten(1)
    flat = flat - flat.mean(1, keepdim=True)
    return F.normalize(flat, dim=1)


def _lift_views(
    scene_model: SceneModel,
    keypoints: Keypoints,
    poses: Tensor,
    scenes: Tensor,
    intrinsics: Tensor,
    size: tuple[int, int],
    settings: MatchSettings,
    chunk: int = 64,
) -> tuple[Tensor, Tensor]:
    """The views' keypoints (px at ``size`` = (width, height)) lifted through the scene
    model's depth rendered at their poses, ``settings.depth_width`` px wide."""
    width, height = size
    depth_w = settings.depth_width
    depth_h = max(4, round(height * depth_w / width))
    scale = torch.tensor([depth_w / width, depth_h / height])
    small = intrinsics.clone()
    small[:, [0, 2]] = (intrinsics[:, [0, 2]] + torch.tensor([0.0, 0.5])) * scale[0]
    small[:, [1, 3]] = (intrinsics[:, [1, 3]] + torch.tensor([0.0, 0.5])) * scale[1]
    small[:, 2:] -= 0.5
    points, lifted = [], []
    for rows in torch.arange(len(poses)).split(chunk):
        rendering = scene_model.render(
            poses[rows], scenes[rows], small[rows], depth_w, depth_h, settings.surface_share
        )
        assert rendering.depth is not None and rendering.opacity is not None
        xy = (keypoints.xy[rows] + 0.5) * scale - 0.5
        world, seen = lift(xy, rendering.depth, rendering.opacity, poses[rows], small[rows])
        points.append(world)
        lifted.append(seen & keypoints.mask[rows])
    return torch.cat(points), torch.cat(lifted)


@torch.no_grad()
def train_views(
    scene_model: SceneModel,
    images: Tensor,
    intrinsics: Tensor,
    poses: Tensor,
    scenes: Tensor,
    settings: MatchSettings,
    describe: Describer | None = None,
) -> TrainViews:
    """The database of train views: their images [N, 3, H, W] (RGB in [0, 1], at the match
    width) with intrinsics [N, 4] (px of those images), poses [N, 7] and scenes [N] ->
    keypoints lifted through the scene model's depth, global descriptors (``describe``, else
    :func:`thumbnail_descriptors`)."""
    describe = describe or thumbnail_descriptors
    found = detect(images, settings)
    size = (images.shape[-1], images.shape[-2])
    points, lifted = _lift_views(
        scene_model, found, poses.float(), scenes, intrinsics.float(), size, settings
    )
    descriptors = torch.cat([describe(part) for part in images.split(256)])
    return TrainViews(found, points, lifted, descriptors, poses.float(), scenes)


def _wider(intrinsics: Tensor, width: int, height: int, fov_scale: float) -> Tensor:
    """Intrinsics [B, 4] of ``width × height`` renderings centred like ``intrinsics``' images
    (of the same aspect) with ``fov_scale`` × their field of view."""
    fx, fy, cx, cy = intrinsics.unbind(-1)
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
        distance = torch.cdist(starts[:, :3], views.poses[:, :3])
        facing = quaternion_to_matrix(starts[:, 3:])[:, :, 2] @ (
            quaternion_to_matrix(views.poses[:, 3:])[:, :, 2].T
        )  # cos of the angle between the optical axes
        cost = (distance + (1 - facing) * 2.0).masked_fill(other, math.inf)
        k = min(settings.near_views, cost.shape[1])
        chosen.append(cost.topk(k, 1, largest=False).indices)
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
    index, matched = mutual_matches(repeated, reference, settings.ratio, settings.detector != "sift")
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
    rendering = scene_model.render(
        poses, scenes, wide, render_w, render_h, settings.surface_share
    )
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

    with ThreadPoolExecutor(_workers()) as pool:
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
) -> Correspondences:
    """Poses of query images [B, 3, H, W] (RGB in [0, 1], at the match width) with
    intrinsics [B, 4] (px of those images) from correspondences with the scene model's
    renderings at starts [B, 7] (camera-to-world) in scenes [B] and with ``views`` (the
    train views, :func:`train_views`; needed where ``settings.views`` or ``near_views``).
    Queries without ``min_inliers`` inliers keep their starts (``found`` False)."""
    if settings.uses_views and views is None:
        raise ValueError(
            "render_compare.match.views and near_views need the train views (train_views())"
        )
    starts = torch.cat([starts[:, :3], normalize_quaternion(starts[:, 3:])], -1).float()
    intrinsics = intrinsics.float()
    images = images.float()
    size = (images.shape[-1], images.shape[-2])
    query = detect(images, settings)
    fixed = None
    if settings.uses_views:
        assert views is not None
        descriptors = (describe or thumbnail_descriptors)(images)
        rows = _retrieve(views, descriptors, starts, scenes, settings)
        fixed = _view_matches(query, views, rows, settings)
    poses, found = starts, torch.zeros(len(starts), dtype=torch.bool)
    inliers = matches = torch.zeros(len(starts), dtype=torch.long)
    rounds = max(1, settings.iterations) if settings.render_width else 1
    for _ in range(rounds):
        parts = [] if fixed is None else [fixed]
        if settings.render_width:
            parts.append(
                _render_matches(scene_model, query, poses, scenes, intrinsics, size, settings)
            )
        pooled = _Pooled(*(torch.cat(column, 1) for column in zip(*parts, strict=True)))
        solved, counts = _solve(pooled, intrinsics, starts, settings)
        now = counts >= settings.min_inliers
        better = now & (counts >= inliers)
        moved = _moved(solved, poses) & better
        poses = torch.where(better[:, None], solved, poses)
        inliers = torch.where(better, counts, inliers)
        matches = torch.where(better, pooled.valid.sum(1), matches)
        found |= now
        if not settings.render_width or not bool(moved.any()):
            break
    return Correspondences(poses, found, inliers, matches)


class TrainImages:
    """The train views a correspondence stage retrieves: images [N, 3, H, W] (uint8, or RGB
    in [0, 1]) at the match width with intrinsics [N, 4] (px of those images), poses [N, 7]
    and scenes [N]; ``describe``: their global descriptor (None:
    :func:`thumbnail_descriptors`). Their keypoints and lifted points (:func:`train_views`)
    are made on first use for each scene model and each detector setting, then kept."""

    def __init__(
        self,
        images: Tensor,
        intrinsics: Tensor,
        poses: Tensor,
        scenes: Tensor,
        describe: Describer | None = None,
    ) -> None:
        self.images, self.intrinsics = images, intrinsics
        self.poses, self.scenes, self.describe = poses, scenes, describe
        self._made: dict[tuple, TrainViews] = {}

    def views(self, scene_model: SceneModel, settings: MatchSettings) -> TrainViews:
        key = (
            id(scene_model), settings.detector, settings.keypoints, settings.contrast, settings.depth_width,
            settings.surface_share,
        )  # fmt: skip
        if key not in self._made:
            parts = [
                train_views(
                    scene_model, self._float(rows), self.intrinsics[rows], self.poses[rows],
                    self.scenes[rows], settings, self.describe,
                )  # fmt: skip
                for rows in torch.arange(len(self.poses)).split(512)
            ]
            self._made[key] = _joined(parts)
        return self._made[key]

    def _float(self, rows: Tensor) -> Tensor:
        images = self.images[rows]
        return images.float() / 255 if images.dtype == torch.uint8 else images.float()


def _joined(parts: Sequence[TrainViews]) -> TrainViews:
    """Views made in parts -> one record (keypoints padded to the longest)."""
    size = max(part.points.shape[1] for part in parts)
    dim = max(part.keypoints.descriptors.shape[2] for part in parts)

    def padded(t: Tensor, last: int | None = None) -> Tensor:  # [n, k, ...] -> [n, size, ...]
        rest = list(t.shape[2:])
        if last is not None:
            rest[-1] = last
        out = t.new_zeros(t.shape[0], size, *rest)
        out[(slice(None), *(slice(0, n) for n in t.shape[1:]))] = t
        return out

    keypoints = Keypoints(
        torch.cat([padded(p.keypoints.xy) for p in parts]),
        torch.cat([padded(p.keypoints.descriptors, dim) for p in parts]),
        torch.cat([p.keypoints.count for p in parts]),
    )
    return TrainViews(
        keypoints,
        torch.cat([padded(p.points) for p in parts]),
        torch.cat([padded(p.lifted) for p in parts]),
        torch.cat([p.descriptors for p in parts]),
        torch.cat([p.poses for p in parts]),
        torch.cat([p.scenes for p in parts]),
    )


class MatchQueries(NamedTuple):
    """What the correspondence stage reads of the queries beyond the refiner's: their images
    [B, 3, H, W] (RGB in [0, 1]) at the match width with intrinsics [B, 4] (px of those
    images), and the train views to retrieve (None: the rendering at the start only)."""

    images: Tensor
    intrinsics: Tensor
    train: TrainImages | None = None

    def views(self, scene_model: SceneModel, settings: MatchSettings) -> TrainViews | None:
        if not settings.uses_views:
            return None
        if self.train is None:
            raise ValueError(
                "render_compare.match.views and near_views need the train views "
                "(MatchQueries.train)"
            )
        return self.train.views(scene_model, settings)

    @property
    def describe(self) -> Describer | None:
        return None if self.train is None else self.train.describe
