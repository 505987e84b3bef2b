"""A store of train poses answering k-nearest-neighbour queries in pose space, per scene."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from pae.geometry import canonicalize_quaternion

PoseDistance = Literal["normalized", "fixed"]


def _as_tensor(values: Tensor | np.ndarray, dtype: torch.dtype, name: str) -> Tensor:
    if isinstance(values, np.ndarray):
        values = torch.from_numpy(values)
    if not isinstance(values, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor or a numpy array, got {type(values)}")
    return values.detach().to(dtype)


def _unit_canonical_quaternions(q: Tensor, name: str) -> Tensor:
    """q [..., 4] -> unit quaternions with qw >= 0; raises on (near) zero norm."""
    if bool((q.norm(dim=-1) < 1e-8).any()):
        raise ValueError(f"{name} holds quaternions of (near) zero norm")
    return canonicalize_quaternion(q)


def _check_poses(poses: Tensor, name: str) -> None:
    if poses.ndim != 2 or poses.shape[1] != 7:
        raise ValueError(
            f"{name} must have shape [N, 7] (x, y, z, qw, qx, qy, qz), got {tuple(poses.shape)}"
        )
    if not bool(torch.isfinite(poses).all()):
        raise ValueError(f"{name} holds NaN or infinite values")


class PoseIndex:
    """k-nearest train poses of query poses, searched only within the query's scene.

    poses: [N, 7] = x, y, z (m), qw, qx, qy, qz, stored as float32 with unit, qw >= 0
    quaternions. scenes: [N] integer scene ids, or None for a single scene (id 0).

    Distances between a query pose and a stored pose combine the position distance
    ``‖Δx‖`` (m) and the orientation distance (rotation angle between the quaternions, deg):

    - ``"normalized"``: each of the two is divided by its maximum over the stored poses of
      the query's scene, then they are summed (dimensionless; the public PAE code's rule,
      which measures orientation by ‖q − q'‖ instead, a distance that depends on the signs);
    - ``"fixed"``: ``‖Δx‖ + rot_weight · angle`` with ``rot_weight`` in metres per degree.

    Distances are computed in float64 over ``chunk_size`` queries at a time, so memory
    stays bounded by ``chunk_size × (largest scene)``.
    """

    def __init__(
        self,
        poses: Tensor | np.ndarray,
        scenes: Tensor | np.ndarray | None = None,
        *,
        distance: PoseDistance = "normalized",
        rot_weight: float = 0.1,
        chunk_size: int = 256,
    ) -> None:
        if distance not in ("normalized", "fixed"):
            raise ValueError(f"distance must be 'normalized' or 'fixed', got {distance!r}")
        if not (math.isfinite(rot_weight) and rot_weight >= 0):
            raise ValueError(f"rot_weight must be a finite number >= 0, got {rot_weight}")
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        poses_t = _as_tensor(poses, torch.float32, "poses")
        _check_poses(poses_t, "poses")
        if poses_t.shape[0] == 0:
            raise ValueError("poses is empty: the index needs at least one pose")
        if scenes is None:
            scenes_t = torch.zeros(poses_t.shape[0], dtype=torch.long, device=poses_t.device)
        else:
            scenes_t = _as_tensor(scenes, torch.long, "scenes").to(poses_t.device)
            if scenes_t.shape != (poses_t.shape[0],):
                raise ValueError(
                    f"scenes must have shape [N] = [{poses_t.shape[0]}], "
                    f"got {tuple(scenes_t.shape)}"
                )
        quaternions = _unit_canonical_quaternions(poses_t[:, 3:], "poses")
        self._poses = torch.cat([poses_t[:, :3], quaternions], dim=1).contiguous()
        self._scenes = scenes_t.contiguous()
        self.distance: PoseDistance = distance
        self.rot_weight = float(rot_weight)
        self.chunk_size = int(chunk_size)
        # Entries grouped by scene: the stable sort keeps the original order within a scene.
        self._order = torch.sort(self._scenes, stable=True).indices
        scene_ids, counts = torch.unique_consecutive(self._scenes[self._order], return_counts=True)
        ends = torch.cumsum(counts, 0)
        self._scene_blocks: dict[int, tuple[int, int]] = {
            int(s): (int(e - c), int(e)) for s, c, e in zip(scene_ids, counts, ends, strict=True)
        }
        self._sorted_positions = self._poses[self._order, :3].double()
        # Renormalised in float64: a float32 norm error of 1e-7 would otherwise read as an
        # angle of ~0.03° through acos near 1.
        sorted_quaternions = self._poses[self._order, 3:].double()
        self._sorted_quaternions = sorted_quaternions / sorted_quaternions.norm(dim=1, keepdim=True)

    @property
    def poses(self) -> Tensor:
        """[N, 7] stored poses (float32, unit quaternions with qw >= 0)."""
        return self._poses

    @property
    def scenes(self) -> Tensor:
        """[N] long scene id of each stored pose."""
        return self._scenes

    @property
    def scene_ids(self) -> list[int]:
        """Sorted distinct scene ids in the store."""
        return sorted(self._scene_blocks)

    @property
    def device(self) -> torch.device:
        return self._poses.device

    def __len__(self) -> int:
        return self._poses.shape[0]

    def scene_size(self, scene: int) -> int:
        """Number of stored poses of one scene (0 when absent)."""
        start, end = self._scene_blocks.get(int(scene), (0, 0))
        return end - start

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the store's tensors (poses, scene ids and the search copies)."""
        tensors = (
            self._poses,
            self._scenes,
            self._order,
            self._sorted_positions,
            self._sorted_quaternions,
        )
        return sum(t.element_size() * t.nelement() for t in tensors)

    def to(self, device: torch.device | str) -> PoseIndex:
        """A copy of the index on ``device``."""
        return PoseIndex(
            self._poses.to(device),
            self._scenes.to(device),
            distance=self.distance,
            rot_weight=self.rot_weight,
            chunk_size=self.chunk_size,
        )

    def query(
        self, poses: Tensor, scenes: Tensor | None = None, k: int = 3
    ) -> tuple[Tensor, Tensor]:
        """k nearest stored poses of each query pose within its scene.

        poses: [B, 7] query poses (quaternions need not be normalised); scenes: [B] long, or
        None when the store holds a single scene. Returns (indices [B, k] long into
        ``self.poses``, distances [B, k] float32), nearest first, on the queries' device.
        """
        if not isinstance(poses, Tensor):
            raise TypeError(f"poses must be a torch.Tensor, got {type(poses)}")
        _check_poses(poses, "query poses")
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        out_device = poses.device
        batch = poses.shape[0]
        if scenes is None:
            if len(self._scene_blocks) != 1:
                raise ValueError(
                    f"the index holds {len(self._scene_blocks)} scenes: pass the queries' scenes"
                )
            scenes_t = torch.full((batch,), self.scene_ids[0], dtype=torch.long)
        else:
            if scenes.shape != (batch,):
                raise ValueError(
                    f"scenes must have shape [B] = [{batch}], got {tuple(scenes.shape)}"
                )
            scenes_t = scenes.detach().to("cpu", torch.long)
        query_poses = poses.detach().to(self.device, torch.float64)
        query_positions = query_poses[:, :3]
        query_quaternions = _unit_canonical_quaternions(query_poses[:, 3:], "query poses")

        indices = torch.empty(batch, k, dtype=torch.long, device=self.device)
        distances = torch.empty(batch, k, dtype=torch.float32, device=self.device)
        for scene in torch.unique(scenes_t).tolist():
            size = self.scene_size(scene)
            if size == 0:
                raise ValueError(f"scene {scene} has no stored poses (stored: {self.scene_ids})")
            if size < k:
                raise ValueError(f"scene {scene} holds {size} stored poses, fewer than k={k}")
            start, end = self._scene_blocks[scene]
            rows = torch.nonzero(scenes_t == scene).squeeze(1).to(self.device)
            for chunk in rows.split(self.chunk_size):
                dist = self._distances(query_positions[chunk], query_quaternions[chunk], start, end)
                best, local = torch.topk(dist, k, dim=1, largest=False, sorted=True)
                indices[chunk] = self._order[start + local]
                distances[chunk] = best.float()
        return indices.to(out_device), distances.to(out_device)

    def _distances(self, positions: Tensor, quaternions: Tensor, start: int, end: int) -> Tensor:
        """Distances [b, end - start] (float64) of queries to the stored block [start, end)."""
        stored_positions = self._sorted_positions[start:end]
        stored_quaternions = self._sorted_quaternions[start:end]
        position_dist = torch.cdist(
            positions, stored_positions, compute_mode="donot_use_mm_for_euclid_dist"
        )
        cos_half = (quaternions @ stored_quaternions.T).abs().clamp(max=1.0)
        angle_deg = torch.rad2deg(2.0 * torch.acos(cos_half))
        if self.distance == "fixed":
            return position_dist + self.rot_weight * angle_deg
        tiny = torch.finfo(torch.float64).tiny
        position_scale = position_dist.amax(dim=1, keepdim=True).clamp(min=tiny)
        angle_scale = angle_deg.amax(dim=1, keepdim=True).clamp(min=tiny)
        return position_dist / position_scale + angle_deg / angle_scale
