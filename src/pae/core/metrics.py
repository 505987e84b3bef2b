"""Pose-error metric: gathers per-sample errors (DDP-safe: every sample counted once) and
reports medians per scene."""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from pae.core.geometry import average_quaternions, pose_errors


class PoseErrorMetric(Metric):
    """Position (m) and orientation (deg) errors of a split.

    `compute()` returns `{"pos_median_m", "rot_median_deg", "pos_mean_m", "rot_mean_deg"}`
    overall — the average of the per-scene figures, as the paper's multi-scene tables do — and
    `{"<scene>/pos_median_m", ...}` per scene when there is more than one scene.

    Updates that pass the samples' dataset indices are counted once per index: the padding
    repeats a distributed sampler adds to even out the processes' shares are dropped.
    """

    full_state_update = False

    def __init__(self, scene_names: list[str] | None = None) -> None:
        super().__init__()
        self.scene_names = list(scene_names or ["scene"])
        self.add_state("pos", default=[], dist_reduce_fx="cat")
        self.add_state("rot", default=[], dist_reduce_fx="cat")
        self.add_state("scene", default=[], dist_reduce_fx="cat")
        self.add_state("index", default=[], dist_reduce_fx="cat")

    def update(
        self,
        pred: Tensor,
        target: Tensor,
        scene: Tensor | None = None,
        index: Tensor | None = None,
    ) -> None:
        """pred, target [B, 7]; scene [B] long indices into scene_names; index [B] long
        dataset indices of the samples (None: every update holds distinct samples)."""
        pos, rot = pose_errors(pred.detach().float(), target.float())
        self.pos.append(pos)
        self.rot.append(rot)
        if scene is None:
            scene = torch.zeros(len(pos), dtype=torch.long, device=pos.device)
        self.scene.append(scene.long())
        if index is not None:
            self.index.append(index.long())

    def compute(self) -> dict[str, Tensor]:
        pos, rot, scene = (dim_zero_cat(s) for s in (self.pos, self.rot, self.scene))
        if isinstance(self.index, Tensor) or self.index:
            index = dim_zero_cat(self.index)
            if len(index) != len(pos):
                raise ValueError("PoseErrorMetric: pass index with every update or with none")
            keep = first_occurrences(index)
            pos, rot, scene = pos[keep], rot[keep], scene[keep]
        return summarise_errors(pos, rot, scene, self.scene_names)


def first_occurrences(index: Tensor) -> Tensor:
    """Positions [M] of the first occurrence of each distinct value of index [N], in
    increasing order of the value: gathered outputs with repeated samples -> each sample once."""
    order = torch.sort(index, stable=True).indices
    ordered = index[order]
    keep = torch.ones_like(ordered, dtype=torch.bool)
    keep[1:] = ordered[1:] != ordered[:-1]
    return order[keep]


WITHIN = {"5cm_5deg": (0.05, 5.0), "10cm_10deg": (0.10, 10.0)}
"""The shares of queries within (position m, orientation deg) that localisation papers report
beside medians: ``within_5cm_5deg``, ``within_10cm_10deg``."""


def summarise_errors(
    pos: Tensor, rot: Tensor, scene: Tensor, scene_names: list[str]
) -> dict[str, Tensor]:
    """Errors [N] with scene ids [N] -> medians, means and the ``WITHIN`` shares (in [0, 1]),
    per scene and averaged over scenes.

    Medians are numpy's: the mean of the two middle values for an even count."""
    per_scene: dict[str, list[Tensor]] = {}
    out: dict[str, Tensor] = {}
    for index, name in enumerate(scene_names):
        mask = scene == index
        if not mask.any():
            continue
        figures = {
            "pos_median_m": pos[mask].quantile(0.5),
            "rot_median_deg": rot[mask].quantile(0.5),
            "pos_mean_m": pos[mask].mean(),
            "rot_mean_deg": rot[mask].mean(),
            **{
                f"within_{name}": ((pos[mask] <= metres) & (rot[mask] <= degrees)).float().mean()
                for name, (metres, degrees) in WITHIN.items()
            },
        }
        for key, value in figures.items():
            per_scene.setdefault(key, []).append(value)
            if len(scene_names) > 1:
                out[f"{name}/{key}"] = value
    for key, values in per_scene.items():
        out[key] = torch.stack(values).mean()
    return out


def mean_pose_per_scene(poses: Tensor, scenes: Tensor, n_scenes: int) -> Tensor:
    """The trivial baseline: per scene, the mean train position and the Markley average
    train orientation. poses [N, 7], scenes [N] -> [n_scenes, 7]."""
    out = poses.new_zeros(n_scenes, 7)
    for index in range(n_scenes):
        mask = scenes == index
        if mask.any():
            out[index, :3] = poses[mask, :3].mean(0)
            out[index, 3:] = average_quaternions(poses[mask, 3:].unsqueeze(0)).squeeze(0)
    return out
