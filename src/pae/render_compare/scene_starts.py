"""Where render-and-compare starts in the scenes a multi-scene teacher did not predict: its
own pose for each scene, turned to ``HEADINGS`` headings about the camera's vertical axis, and
the poses of the train images of that scene whose teacher latents lie nearest to the query's
latent for that scene. A teacher that took the query for another room regresses a poor pose
for the right one: a metre off, and often facing another way (up to more than a quarter
turn where it erred on the synthetic benchmark), from which the search, whose steps are sized to
the teacher's errors in its predicted room, does not reach the true pose; the headings and
the nearest train images by latent give starts it can reach."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from pae.core.pose_sampling import perturb
from pae.core.shapes import check_shape

LATENT_STARTS = 2
"""Train poses per scene added to the teacher's pose as starts."""
HEADINGS = 8
"""Headings of the teacher's pose tried per scene, evenly spaced (45° apart: within about
20° of any true heading, where the search's turns reach), the teacher's own first."""


def heading_starts(poses: Tensor, headings: int = HEADINGS) -> Tensor:
    """Poses [..., 7] turned about their camera's y axis (the vertical of a level camera) by
    ``k · 360° / headings``, k = 0 .. headings - 1 -> [..., headings, 7] (k = 0: the pose
    itself)."""
    turns = poses.new_zeros(headings, 6)
    turns[:, 4] = torch.arange(headings, dtype=poses.dtype, device=poses.device)
    turns[:, 4] *= 2 * math.pi / headings
    expanded = poses[..., None, :].expand(*poses.shape[:-1], headings, 7)
    return perturb(expanded, turns.expand(*poses.shape[:-1], headings, 6))


def latent_starts(
    scene_poses: Tensor,
    scene_latents: Tensor,
    store_latents: Tensor,
    store_poses: Tensor,
    store_scenes: Tensor,
    k: int = LATENT_STARTS,
    headings: int = HEADINGS,
) -> Tensor:
    """Starts [B, S, headings + k, 7] per query and scene: the teacher's pose for the scene
    (``scene_poses`` [B, S, 7]) at ``headings`` headings (:func:`heading_starts`, its own
    first), then the poses (``store_poses`` [M, 7]) of the ``k`` train images of that scene
    (``store_scenes`` [M]) whose latents (``store_latents`` [M, 2d], each for its own scene)
    are nearest (Euclidean) to the query's latent for the scene (``scene_latents`` [B, S,
    2d]), nearest first."""
    sizes = check_shape(scene_poses, "scene_poses", "B S 7")
    b, s = sizes["B"], sizes["S"]
    d = check_shape(scene_latents, "scene_latents", f"{b} {s} D")["D"]
    m = check_shape(store_latents, "store_latents", f"M {d}")["M"]
    check_shape(store_poses, "store_poses", f"{m} 7")
    check_shape(store_scenes, "store_scenes", f"{m}")
    counts = torch.bincount(store_scenes.long().cpu(), minlength=s)
    if k > int(counts.min()):
        raise ValueError(
            f"{k} latent starts per scene, but a scene has {int(counts.min())} train rows"
        )
    near = scene_poses.new_zeros(b, s, k, 7)
    for scene in range(s):  # a few scenes: one distance matrix each
        rows = (store_scenes == scene).nonzero().flatten()
        distance = torch.cdist(scene_latents[:, scene].float(), store_latents[rows].float())
        nearest = distance.topk(k, largest=False).indices  # [B, k], nearest first
        near[:, scene] = store_poses[rows][nearest].to(near)
    return torch.cat([heading_starts(scene_poses, headings), near], 2)
