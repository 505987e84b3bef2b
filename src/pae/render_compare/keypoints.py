"""Keypoints for the correspondence stage (:mod:`pae.render_compare.correspondences`): its
settings, its detector (OpenCV's classical ones, :mod:`pae.core.features`), and the lifting
of pixels to world points through a rendered depth."""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from pae.core import features
from pae.core.features import DETECTORS, Keypoints
from pae.core.geometry import quaternion_to_matrix

MIN_DEPTH_M = 0.05
"""Rendered depths below this (m) lift no keypoint."""


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
    start_views: int = 0
    """The poses of this many train views nearest the query by global descriptor, each
    refined as a start of its own beside the APR's (0: none)."""
    near_start_views: int = 0
    """And the poses of this many train cameras nearest the APR's start (0: none)."""
    near_best_rounds: int = 0
    """Then, this many times, the ``near_start_views`` train cameras nearest each query's
    best-scoring pose so far refined as starts too (a walk over the train cameras towards
    where the score points)."""
    screen_keep: int = 0
    """Refine only this many other starts per query in full, those a short search
    (``screen_rounds`` rounds at the coarsest level, no polish) scores highest, each from
    where that search ended (0: every other start in full)."""
    screen_rounds: int = 1
    """The short search's rounds (0: the other starts scored where they are)."""
    below_score: float = 2.0
    """Only queries whose refinement from the APR's start scores below this ZNCC get the
    other starts (2: every query): a query the scene model already explains keeps its own."""
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
        counts = (self.views, self.near_views, self.start_views, self.near_start_views)
        counts += (self.iterations, self.near_best_rounds, self.screen_keep, self.screen_rounds)
        if min(counts) < 0 or self.keypoints < 8:
            raise ValueError(
                "render_compare.match needs views, near_views, start_views, near_start_views, "
                "iterations, near_best_rounds, screen_keep, screen_rounds >= 0 and keypoints "
                f">= 8, not {counts}, {self.keypoints}"
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
    def solves(self) -> bool:
        """Whether poses are solved from keypoint correspondences."""
        return self.width > 0 and bool(self.render_width or self.views or self.near_views)

    @property
    def active(self) -> bool:
        return self.solves or (self.width > 0 and self.start_views + self.near_start_views > 0)

    @property
    def uses_views(self) -> bool:
        return self.width > 0 and bool(self.views or self.near_views)

    def described(self) -> str:
        """The stage in a table's words: the other starts refined, the rounds from the best
        pose, whether keypoints solve a pose (against a rendering how many px wide, or the
        train views alone), how many starts are refined in full after the screen and, where
        it is not every query's, the score below which a query gets the stage; ``none``
        where no stage runs."""
        if not self.active:
            return "none"
        parts = []
        if self.start_views + self.near_start_views:
            parts.append(f"{self.start_views + self.near_start_views} other starts")
        if self.near_best_rounds:
            parts.append(f"{self.near_best_rounds} round")
        if self.solves:
            against = f"{self.render_width} px" if self.render_width else "train views"
            parts.append(f"keypoints ({against})")
        described = " + ".join(parts)
        if self.screen_keep:
            described += f", {self.screen_keep} in full"
        if self.below_score < 1:
            described += f", below ZNCC {self.below_score:.2f}"
        return described


def detect(images: Tensor, settings: MatchSettings, masks: Tensor | None = None) -> Keypoints:
    """Keypoints of RGB images [B, 3, H, W] in [0, 1] with the stage's detector, contrast and
    count (:func:`pae.core.features.detect`); ``masks`` [B, H, W] bool: only where True."""
    return features.detect(images, settings.detector, settings.keypoints, settings.contrast, masks)


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
