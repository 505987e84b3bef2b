"""A store of train poses answering k-nearest-neighbour queries in pose space, per scene."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from pae.core.compiled import ENGINES, Engine, insert_sorted, jit, run_in_parts
from pae.core.geometry import canonicalize_quaternion
from pae.refine.settings import RefinementSettings

PoseDistance = Literal["normalized", "fixed"]
_DEGREES_PER_HALF_TURN = 360.0 / math.pi
"""Rotation angle in degrees per radian of acos(|q·q'|) (the angle is twice that)."""


@jit(nogil=True, error_model="numpy")
def _unit_rows64(store: np.ndarray, positions: np.ndarray, quaternions: np.ndarray) -> None:
    """Stored rows [N, 7] (float32) into float64 positions [N, 3] and quaternions [N, 4]
    renormalised in float64, as ``PoseIndex._block64`` gives them, on the calling thread
    (multi-threaded tensor operations here would leave their threads spinning beside the
    search's)."""
    for row in range(store.shape[0]):
        for axis in range(3):
            positions[row, axis] = store[row, axis]
        norm = 0.0
        for axis in range(4):
            value = np.float64(store[row, 3 + axis])  # numba's float() keeps float32
            quaternions[row, axis] = value
            norm += value * value
        norm = math.sqrt(norm)
        for axis in range(4):
            quaternions[row, axis] /= norm


@jit(nogil=True, error_model="numpy")
def _nearest(
    query_positions: np.ndarray,
    query_quaternions: np.ndarray,
    starts: np.ndarray,
    ends: np.ndarray,
    positions: np.ndarray,
    quaternions: np.ndarray,
    normalized: bool,
    rot_weight: float,
    indices: np.ndarray,
    distances: np.ndarray,
) -> None:
    """k nearest stored poses of each query, by ``PoseIndex``'s distance, in float64.

    query_positions [b, 3], query_quaternions [b, 4] (unit), positions [N, 3], quaternions
    [N, 4] (unit); query i is searched among rows starts[i] to ends[i] (its scene's block);
    writes indices [b, k] (rows of the N) and distances [b, k], nearest first.
    One pass gathers the distances' maxima; the second skips a stored pose without its arc
    cosine when a lower bound of its distance (acos(c) ≥ √(2(1 − c))) already exceeds the
    k-th best so far.
    """
    k = indices.shape[1]
    tiny = 2.2250738585072014e-308
    position = np.empty(positions.shape[0])
    cosine = np.empty(positions.shape[0])
    for row in range(query_positions.shape[0]):
        first, count = starts[row], ends[row] - starts[row]
        qx, qy, qz = query_positions[row, 0], query_positions[row, 1], query_positions[row, 2]
        qw, qa, qb, qc = (
            query_quaternions[row, 0],
            query_quaternions[row, 1],
            query_quaternions[row, 2],
            query_quaternions[row, 3],
        )
        farthest = 0.0
        least_cosine = 1.0
        for j in range(count):
            at = first + j
            dx, dy, dz = qx - positions[at, 0], qy - positions[at, 1], qz - positions[at, 2]
            position[j] = math.sqrt(dx * dx + dy * dy + dz * dz)
            dot = (
                qw * quaternions[at, 0]
                + qa * quaternions[at, 1]
                + qb * quaternions[at, 2]
                + qc * quaternions[at, 3]
            )
            cosine[j] = min(abs(dot), 1.0)
            farthest = max(farthest, position[j])
            least_cosine = min(least_cosine, cosine[j])
        position_scale, angle_scale, angle_factor = 1.0, 1.0, rot_weight
        if normalized:
            position_scale = max(farthest, tiny)
            angle_scale = max(math.acos(least_cosine) * _DEGREES_PER_HALF_TURN, tiny)
            angle_factor = 1.0
        best = np.full(k, np.inf)
        found = np.full(k, -1)
        for j in range(count):
            distance = position[j] / position_scale
            if distance >= best[k - 1]:
                continue
            bound = math.sqrt(2.0 * (1.0 - cosine[j])) * _DEGREES_PER_HALF_TURN
            if distance + angle_factor * (1.0 - 1e-9) * bound / angle_scale >= best[k - 1]:
                continue
            angle = math.acos(cosine[j]) * _DEGREES_PER_HALF_TURN
            distance += angle_factor * (angle / angle_scale)
            if distance < best[k - 1]:
                insert_sorted(best, found, distance, first + j)
        indices[row] = found
        distances[row] = best


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

    Distances are computed in float64. ``engine``: ``"numba"`` searches with a compiled loop
    per query that skips most arc cosines (``_nearest``; CPU only), ``"torch"`` with tensor
    operations over ``chunk_size`` queries at a time (memory bounded by ``chunk_size ×
    (largest scene)``); ``"auto"`` takes the first on the CPU and the second elsewhere.
    """

    def __init__(
        self,
        poses: Tensor | np.ndarray,
        scenes: Tensor | np.ndarray | None = None,
        *,
        distance: PoseDistance = "normalized",
        rot_weight: float = RefinementSettings.rot_weight,
        chunk_size: int = 256,
        engine: Engine = "auto",
    ) -> None:
        if distance not in ("normalized", "fixed"):
            raise ValueError(f"distance must be 'normalized' or 'fixed', got {distance!r}")
        if engine not in ENGINES:
            raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
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
        poses_t = torch.cat([poses_t[:, :3], quaternions], dim=1)
        self.distance: PoseDistance = distance
        self.rot_weight = float(rot_weight)
        self.chunk_size = int(chunk_size)
        self.engine: Engine = engine
        if engine == "numba" and poses_t.device.type != "cpu":
            raise ValueError(f"engine 'numba' searches on the CPU only, got {poses_t.device} poses")
        # One float32 copy, each scene's poses contiguous (kept in the given order when they
        # are already; else stably sorted by scene, keeping that permutation as int32).
        run_ids, run_counts = torch.unique_consecutive(scenes_t, return_counts=True)
        grouped = len(run_ids) == len(torch.unique(scenes_t))
        order = None if grouped else torch.sort(scenes_t, stable=True).indices
        self._order = None if order is None else order.to(torch.int32)
        self._store = (poses_t if order is None else poses_t[order]).contiguous()
        if order is not None:
            run_ids, run_counts = torch.unique_consecutive(scenes_t[order], return_counts=True)
        ends = torch.cumsum(run_counts, 0)
        self._scene_blocks: dict[int, tuple[int, int]] = {
            int(s): (int(e - c), int(e)) for s, c, e in zip(run_ids, run_counts, ends, strict=True)
        }

    def _original_order(self, stored: Tensor) -> Tensor:
        """Rows [N, ...] in the store's (scene-grouped) order -> the caller's order."""
        if self._order is None:
            return stored
        return torch.empty_like(stored).index_copy_(0, self._order.long(), stored)

    @property
    def poses(self) -> Tensor:
        """[N, 7] stored poses (float32, unit quaternions with qw >= 0), in the given order."""
        return self._original_order(self._store)

    @property
    def scenes(self) -> Tensor:
        """[N] long scene id of each stored pose, in the given order."""
        ids = torch.tensor(list(self._scene_blocks), dtype=torch.long, device=self.device)
        sizes = torch.tensor([e - s for s, e in self._scene_blocks.values()], device=self.device)
        return self._original_order(torch.repeat_interleave(ids, sizes))

    @property
    def scene_ids(self) -> list[int]:
        """Sorted distinct scene ids in the store."""
        return sorted(self._scene_blocks)

    @property
    def device(self) -> torch.device:
        return self._store.device

    def __len__(self) -> int:
        return self._store.shape[0]

    def scene_size(self, scene: int) -> int:
        """Number of stored poses of one scene (0 when absent)."""
        start, end = self._scene_blocks.get(int(scene), (0, 0))
        return end - start

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the store's tensors: 28 per pose (float32), 4 more when the poses
        were not given grouped by scene. Searches work on float64 copies of one scene's
        block, made per ``chunk_size`` queries."""
        tensors = [self._store] if self._order is None else [self._store, self._order]
        return sum(t.element_size() * t.nelement() for t in tensors)

    def to(self, device: torch.device | str) -> PoseIndex:
        """A copy of the index on ``device``."""
        return PoseIndex(
            self.poses.to(device),
            self.scenes.to(device),
            distance=self.distance,
            rot_weight=self.rot_weight,
            chunk_size=self.chunk_size,
            engine=self.engine if torch.device(device).type == "cpu" else "torch",
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

        present = torch.unique(scenes_t).tolist()
        for scene in present:
            size = self.scene_size(scene)
            if size == 0:
                raise ValueError(f"scene {scene} has no stored poses (stored: {self.scene_ids})")
            if size < k:
                raise ValueError(f"scene {scene} holds {size} stored poses, fewer than k={k}")
        if self.device.type == "cpu" and self.engine != "torch":
            found, best = self._search_fused(query_positions, query_quaternions, scenes_t, k)
            found = found if self._order is None else self._order[found].long()
            return found.to(out_device), best.float().to(out_device)
        indices = torch.empty(batch, k, dtype=torch.long, device=self.device)
        distances = torch.empty(batch, k, dtype=torch.float32, device=self.device)
        for scene in present:
            start, end = self._scene_blocks[scene]
            positions, quaternions = self._block64(start, end)
            rows = torch.nonzero(scenes_t == scene).squeeze(1).to(self.device)
            for chunk in rows.split(self.chunk_size):
                dist = self._distances(
                    query_positions[chunk], query_quaternions[chunk], positions, quaternions
                )
                best, local = torch.topk(dist, k, dim=1, largest=False, sorted=True)
                found = start + local
                indices[chunk] = found if self._order is None else self._order[found].long()
                distances[chunk] = best.float()
        return indices.to(out_device), distances.to(out_device)

    def _block64(self, start: int, end: int) -> tuple[Tensor, Tensor]:
        """Stored rows start..end in float64: positions [M, 3], quaternions [M, 4],
        renormalised in float64 (a float32 norm error of 1e-7 would otherwise read as an
        angle of ~0.03° through acos near 1)."""
        block = self._store[start:end].double()
        quaternions = block[:, 3:]
        return block[:, :3], quaternions / quaternions.norm(dim=1, keepdim=True)

    def _search_fused(
        self, positions: Tensor, quaternions: Tensor, scenes: Tensor, k: int
    ) -> tuple[Tensor, Tensor]:
        """``_nearest`` over B queries (float64 positions [B, 3], unit quaternions [B, 4],
        scene ids [B]), each within its scene's block: store rows [B, k] and distances
        [B, k] (float64), nearest first. Queries run in scene order, so each thread's rows
        read few blocks."""
        order = torch.argsort(scenes, stable=True)
        in_order = scenes[order]
        bounds = torch.empty(len(order), 2, dtype=torch.long)
        for scene in torch.unique(in_order).tolist():
            bounds[in_order == scene] = torch.tensor(self._scene_blocks[scene])
        stored = [np.empty((len(self), 3)), np.empty((len(self), 4))]
        _unit_rows64(self._store.numpy(), *stored)
        arrays = [positions[order].contiguous().numpy(), quaternions[order].contiguous().numpy()]
        arrays += [bounds[:, 0].contiguous().numpy(), bounds[:, 1].contiguous().numpy()]
        indices = np.empty((len(order), k), dtype=np.int64)
        distances = np.empty((len(order), k))
        normalized, weight = self.distance == "normalized", self.rot_weight

        def run(part: slice) -> None:
            _nearest(
                *(a[part] for a in arrays),
                *stored,
                normalized,
                weight,
                indices[part],
                distances[part],
            )

        run_in_parts(run, len(order), min_rows=32)
        found = torch.empty_like(torch.from_numpy(indices))
        best = torch.empty_like(torch.from_numpy(distances))
        found[order], best[order] = torch.from_numpy(indices), torch.from_numpy(distances)
        return found, best

    def _distances(
        self,
        positions: Tensor,
        quaternions: Tensor,
        stored_positions: Tensor,
        stored_quaternions: Tensor,
    ) -> Tensor:
        """Distances [b, M] (float64) of b queries to M stored poses of one scene."""
        position_dist = torch.cdist(
            positions, stored_positions, compute_mode="donot_use_mm_for_euclid_dist"
        )
        angle_deg = (quaternions @ stored_quaternions.T).abs_().clamp_(max=1.0)
        angle_deg.acos_().mul_(360.0 / math.pi)
        if self.distance == "fixed":
            return position_dist.add_(angle_deg, alpha=self.rot_weight)
        tiny = torch.finfo(torch.float64).tiny
        position_scale = position_dist.amax(dim=1, keepdim=True).clamp_(min=tiny)
        angle_scale = angle_deg.amax(dim=1, keepdim=True).clamp_(min=tiny)
        return position_dist.div_(position_scale).add_(angle_deg.div_(angle_scale))
