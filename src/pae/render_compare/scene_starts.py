"""Where render-and-compare starts in the scenes a multi-scene teacher did not predict: its
own pose for each scene, and the poses of the train images of that scene whose teacher
latents lie nearest to the query's latent for that scene. A teacher that took the query for
another room regresses a poor pose for the right one (a metre off where it erred on the
synthetic benchmark), from which the refinement does not reach the true pose; the nearest
train images by latent give starts the search can reach."""

from __future__ import annotations

import torch
from torch import Tensor

from pae.core.shapes import check_shape

LATENT_STARTS = 2
"""Train poses per scene added to the teacher's pose as starts."""


def latent_starts(
    scene_poses: Tensor,
    scene_latents: Tensor,
    store_latents: Tensor,
    store_poses: Tensor,
    store_scenes: Tensor,
    k: int = LATENT_STARTS,
) -> Tensor:
    """Starts [B, S, 1 + k, 7] per query and scene: the teacher's pose for the scene
    (``scene_poses`` [B, S, 7]), then the poses (``store_poses`` [M, 7]) of the ``k`` train
    images of that scene (``store_scenes`` [M]) whose latents (``store_latents`` [M, 2d], each
    for its own scene) are nearest (Euclidean) to the query's latent for the scene
    (``scene_latents`` [B, S, 2d]), nearest first."""
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
    return torch.cat([scene_poses[:, :, None], near], 2)
