"""Where each scene's voxel grid lies and how fine it is (bounds and contraction from the
train cameras alone, never the scene's geometry; the grid's shape and voxel length for a
number of voxels), and the order the rays of several scenes are marched in."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor


def grid_shape(extent: Sequence[float], num_voxels: int) -> tuple[int, int, int]:
    """(nx, ny, nz) of cubic voxels filling ``extent`` [3] (m) with about ``num_voxels``."""
    volume = math.prod(extent)
    voxel = (volume / num_voxels) ** (1 / 3)
    return tuple(max(2, round(e / voxel)) for e in extent)  # type: ignore[return-value]


def camera_bounds(positions: Tensor, margin_m: float | Sequence[float]) -> Tensor:
    """Axis-aligned bounds [2, 3] (lo, hi) of camera positions [N, 3] plus a margin (m),
    one value or one per axis."""
    margin = torch.as_tensor(margin_m, dtype=torch.float64).expand(3)
    positions = positions.double()
    return torch.stack([positions.min(0).values - margin, positions.max(0).values + margin])


def camera_extent_m(positions: Tensor) -> float:
    """The largest side (m) of the box holding the middle 96 % of camera positions [N, 3]
    along each axis: the camera region's size, robust to a few stray frames."""
    if len(positions) < 2:
        return 0.0
    q = torch.tensor([0.02, 0.98], dtype=torch.float64)
    spread = positions.double().quantile(q, dim=0)
    return float((spread[1] - spread[0]).max())


def train_scale(
    poses: Tensor, scenes: Tensor, n_scenes: int, config: Mapping[str, Any]
) -> dict[str, Any]:
    """The grid's bounds and contraction from the train cameras alone (poses [N, 7] of scene
    ids [N]; never the scene's geometry): per scene the camera positions' bounds plus
    ``margin_m``, and ``contract``. ``margin_m: auto`` is ``max(auto_scale.margin_floor_m,
    auto_scale.margin_fraction × extent)`` per scene (extent: :func:`camera_extent_m`);
    ``contract: auto`` contracts space when some scene's extent exceeds
    ``auto_scale.contract_above_m`` (a street, not a room). Returns ``config`` with ``bounds``
    and ``contract`` set, and ``margin_m`` and ``auto_scale`` gone."""
    positions = [poses[scenes == s, :3] for s in range(n_scenes)]
    extents = [camera_extent_m(p) for p in positions]
    config = dict(config)
    margin, auto = config.pop("margin_m"), config.pop("auto_scale")
    if margin == "auto":
        margins = [max(auto["margin_floor_m"], auto["margin_fraction"] * e) for e in extents]
    else:
        margins = [margin] * len(positions)
    if config.get("contract") == "auto":
        config["contract"] = max(extents, default=0.0) > auto["contract_above_m"]
    pairs = zip(positions, margins, strict=True)
    config["bounds"] = [camera_bounds(p, m).tolist() for p, m in pairs]
    return config


def voxel_length_m(extent: Sequence[float], shape: Sequence[int], contract: bool) -> float:
    """The voxel's length (m) inside bounds of ``extent`` [3] (m) of a grid of ``shape``
    (nx, ny, nz) (contracted grids spend half of each axis on the space beyond the bounds)."""
    voxel_m = float(min(e / (n - 1) for e, n in zip(extent, shape, strict=True)))
    return 2 * voxel_m if contract else voxel_m


def scene_order(scenes: Tensor, n_scenes: int) -> tuple[Tensor | None, list[int]]:
    """How the rays (or cameras) of scenes [R] are put in scene order: the stable sorting
    order (None where they are in order already) and each scene's count [n_scenes]; a scene
    id outside [0, n_scenes) is a ValueError naming it."""
    order = None
    if bool((scenes[1:] < scenes[:-1]).any()):
        order = torch.argsort(scenes, stable=True)
        scenes = scenes[order]
    if len(scenes) and (int(scenes[0]) < 0 or int(scenes[-1]) >= n_scenes):
        wrong = int(scenes[0]) if int(scenes[0]) < 0 else int(scenes[-1])
        raise ValueError(f"scene id {wrong} of {n_scenes} scenes")
    return order, torch.bincount(scenes, minlength=n_scenes).tolist()


def in_order_of(order: Tensor | None, values: Tensor) -> Tensor:
    """``values`` [R, ...] in scene order (:func:`scene_order`) back in the rays' order."""
    return values if order is None else torch.empty_like(values).index_copy(0, order, values)
