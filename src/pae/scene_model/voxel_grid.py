"""A voxel radiance grid per scene (DVGO / Plenoxels style): density and colour on a dense
grid, sampled trilinearly and alpha-composited along stratified ray samples.

Bounds come from the train cameras (their positions plus a margin, computed by the caller),
never from the scene's geometry. With ``contract`` the grid covers unbounded scenes: points
outside the bounds are contracted as in mip-NeRF 360 (``x -> (2 - 1/‖x‖∞)·x/‖x‖∞`` in the
coordinates where the bounds are ``[-1, 1]³``), and half of each ray's samples are spaced
evenly in inverse depth out to 100 times the bounds' diagonal beyond them (``far_m``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, ListConfig
from torch import Tensor, nn

from pae.core.camera import camera_rays
from pae.core.checks import boolean, integer, is_int, number, present, setting
from pae.core.compiled import ENGINES, Engine
from pae.core.errors import ConfigError
from pae.scene_model.base import SceneModel, SceneModelInputs, SceneRendering
from pae.scene_model.voxel_composite import CompiledComposite, channels_last
from pae.scene_model.voxel_layout import (
    grid_shape,
    in_order_of,
    scene_order,
    train_scale,
    voxel_length_m,
)
from pae.scene_model.voxel_render import GridGeometry, RaySegments
from pae.scene_model.voxel_variation import CompiledTotalVariation

_EPS = 1e-9


class VoxelGrid(nn.Module):
    """One scene: a 4-channel grid [1, 4, nz, ny, nx] (raw density, raw RGB) over the box
    ``bounds`` [2, 3] (m), or over its contraction."""

    def __init__(
        self,
        bounds: Sequence[Sequence[float]],
        num_voxels: int,
        contract: bool = False,
        init_alpha: float = 1e-2,
    ) -> None:
        super().__init__()
        bounds_t = torch.as_tensor(bounds, dtype=torch.float32).reshape(2, 3)
        if not bool((bounds_t[1] > bounds_t[0]).all()):
            raise ValueError(f"scene bounds must have lo < hi on every axis, got {bounds}")
        self.register_buffer("lo", bounds_t[0].clone())
        self.register_buffer("hi", bounds_t[1].clone())
        self.contract = contract
        self.extent = (bounds_t[1] - bounds_t[0]).tolist()
        # softplus(shift) · (one voxel) = -log(1 - init_alpha): a faint initial fog
        self.density_shift = math.log(math.expm1(-math.log1p(-init_alpha)))
        self.background = nn.Parameter(torch.zeros(3))
        self._reshape(self._shape_for(num_voxels), keep=False)
        self.configured_voxel_m = self.voxel_m

    def resize(self, num_voxels: int, keep: bool = True) -> bool:
        """A grid of about ``num_voxels`` over the same bounds: ``keep``, the field as it is
        (raw values trilinear at the new nodes, the density rescaled so that each metre of a
        ray gathers the same light), else the initial fog. Whether the shape changed."""
        shape = self._shape_for(num_voxels)
        if shape == self.shape:
            return False
        self._reshape(shape, keep)
        return True

    def _shape_for(self, num_voxels: int) -> tuple[int, int, int]:
        """(nx, ny, nz) of about ``num_voxels`` over the bounds (or their contraction)."""
        extent = [2 * e for e in self.extent] if self.contract else self.extent
        return grid_shape(extent, num_voxels)

    def _reshape(self, shape: tuple[int, int, int], keep: bool) -> None:
        """:meth:`resize` to ``shape`` (nx, ny, nz)."""
        voxel_m = voxel_length_m(self.extent, shape, self.contract)
        size = (shape[2], shape[1], shape[0])  # (nz, ny, nx)
        cells = torch.zeros(1, 4, *size)
        if keep:
            with torch.no_grad():
                raw = F.interpolate(self.grid, size, mode="trilinear", align_corners=True)
                light = F.softplus(raw[:, :1] + self.density_shift) * voxel_m / self.voxel_m
                light = light.clamp_min(1e-12)  # softplus's inverse below stays finite
                density = light + torch.log(-torch.expm1(-light)) - self.density_shift
                cells = torch.cat([density, raw[:, 1:]], 1)
        self.shape, self.voxel_m = shape, voxel_m
        # stored channels last: the compiled kernels read and write it without a copy
        self.grid = nn.Parameter(cells.to(memory_format=torch.channels_last_3d))
        self._kernel_cells: tuple[tuple[int, int], np.ndarray] | None = None

    def _load_from_state_dict(self, state: Mapping[str, Any], prefix: str, *args: Any) -> None:
        """A stored grid of another shape (a fit saved before it grew) is loaded as it is."""
        stored = state.get(prefix + "grid")
        if stored is not None and stored.shape[:2] == (1, 4) and stored.shape != self.grid.shape:
            nz, ny, nx = stored.shape[2:]
            self._reshape((nx, ny, nz), keep=False)
        super()._load_from_state_dict(state, prefix, *args)

    def normalised(self, points: Tensor) -> Tensor:
        """World points [..., 3] -> grid coordinates in [-1, 1] (contracted when set)."""
        unit = (points - self.lo) / (self.hi - self.lo) * 2 - 1
        if not self.contract:
            return unit
        norm = unit.abs().amax(-1, keepdim=True).clamp_min(_EPS)
        contracted = torch.where(norm <= 1, unit, (2 - 1 / norm) * unit / norm)
        return contracted / 2

    def ray_bounds(self, origins: Tensor, directions: Tensor, near_m: float) -> RaySegments:
        """Rays [R, 3] -> their segments: the depths where sampling starts (``near_m`` or
        where the ray enters the bounds), where it leaves the bounds, and where it ends
        (contracted grids: ``far_m`` beyond the bounds; else where it leaves)."""
        safe = torch.where(directions.abs() < _EPS, torch.full_like(directions, _EPS), directions)
        t_lo, t_hi = (self.lo - origins) / safe, (self.hi - origins) / safe
        enter = torch.minimum(t_lo, t_hi).amax(-1)
        leave = torch.maximum(t_lo, t_hi).amin(-1)
        norm = directions.norm(dim=-1)
        near = torch.maximum(enter, near_m / norm)
        leave = torch.maximum(leave, near)
        far = leave + self.far_m / norm if self.contract else leave
        return RaySegments(origins, directions, near, leave, far)

    def sample_depths(self, rays: RaySegments, offsets: Tensor) -> tuple[Tensor, Tensor]:
        """Depths [R, S] of the samples along ``rays`` (see ``ray_bounds``) at ``offsets``
        [R, S] (or [1, S] for every ray) in [0, 1) within their strata, and their lengths
        [R, S] (m); rays that miss the bounds get zero-length samples."""
        near, leave, far = rays.near, rays.leave, rays.far
        samples = offsets.shape[1]
        norm = rays.directions.norm(dim=-1)
        steps = torch.arange(samples, device=offsets.device, dtype=offsets.dtype)
        unit = (steps + offsets) / samples  # [R, S] in (0, 1)
        if not self.contract:
            depth = near[:, None] + (leave - near)[:, None] * unit
            length = ((leave - near) * norm / samples)[:, None].expand_as(depth)
            return depth, length
        inner = unit < 0.5
        linear = near[:, None] + (leave - near)[:, None] * (2 * unit).clamp(max=1)
        s = (2 * unit - 1).clamp(min=0)
        inverse = 1 / (1 / leave[:, None] * (1 - s) + 1 / far[:, None] * s)
        depth = torch.where(inner, linear, inverse)
        edges = torch.cat([near[:, None], (depth[:, 1:] + depth[:, :-1]) / 2, far[:, None]], 1)
        return depth, (edges[:, 1:] - edges[:, :-1]) * norm[:, None]

    @property
    def far_m(self) -> float:
        """How far (m) beyond the bounds contracted rays sample: 100× their diagonal."""
        return 100 * float((self.hi - self.lo).norm())

    def composite(
        self,
        origins: Tensor,
        directions: Tensor,
        samples: int,
        near_m: float,
        jitter: bool,
        engine: Engine = "auto",
        surface_share: float = 0.0,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Volume rendering of rays [R, 3] -> rgb [R, 3] in [0, 1], depth [R] (along the
        directions, in their units), opacity [R]. The depth is the light's mean depth, or with
        ``surface_share`` in (0, 1) the depth of the first sample by which the ray has gathered
        that share of its opacity. ``engine``
        (:data:`pae.core.compiled.ENGINES`): ``numba`` the compiled renderer (CPU float32
        tensors), which stops each ray once its light is spent; ``torch`` ``grid_sample`` over
        every sample (any device); ``auto`` the first where it can run."""
        rays = self.ray_bounds(origins, directions, near_m)
        return self.composite_segments(rays, samples, jitter, engine, surface_share)

    def composite_segments(
        self,
        rays: RaySegments,
        samples: int,
        jitter: bool,
        engine: Engine = "auto",
        surface_share: float = 0.0,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """:meth:`composite` of rays whose segments (:meth:`ray_bounds`) are known."""
        origins = rays.origins
        if jitter:
            offsets = torch.rand((len(origins), samples), device=origins.device)
        else:
            offsets = origins.new_full((1, samples), 0.5)  # every ray's midpoints
        background = torch.sigmoid(self.background)
        if self.compiled(engine):
            geometry = GridGeometry(
                self.lo.double().numpy(),
                self.hi.double().numpy(),
                np.array([n - 1 for n in self.shape], np.float64),
                1 / self.voxel_m,
                bool(self.contract),
            )
            return CompiledComposite.apply(
                self.grid,
                self.kernel_cells(),
                background,
                rays,
                offsets,
                geometry,
                self.density_shift,
                surface_share,
            )
        weights, depth, raw = self._weights(rays, offsets)
        opacity = weights.sum(1)
        colour = torch.sigmoid(raw[1:]).permute(1, 2, 0)  # [R, S, 3]
        rgb = (weights[..., None] * colour).sum(1) + (1 - opacity)[:, None] * background
        if surface_share > 0:
            gathered = weights.detach().cumsum(1)
            first = (gathered < surface_share * gathered[:, -1:]).sum(1)
            surface = depth.gather(1, first.clamp(max=samples - 1)[:, None])[:, 0]
        else:
            surface = (weights * depth).sum(1) / opacity.clamp_min(1e-6)
        return rgb, surface, opacity

    def _weights(self, rays: RaySegments, offsets: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``grid_sample`` over every sample of ``rays`` at ``offsets`` [R, S] -> each sample's
        share of its ray's light [R, S], its depth [R, S] and the grid's raw values there
        [4, R, S] (differentiable w.r.t. the grid)."""
        depth, length = self.sample_depths(rays, offsets)
        points = rays.origins[:, None] + depth[..., None] * rays.directions[:, None]
        coords = self.normalised(points).view(1, -1, 1, 1, 3)
        raw = F.grid_sample(self.grid, coords, align_corners=True, padding_mode="border")
        raw = raw.view(4, *depth.shape)
        sigma = F.softplus(raw[0] + self.density_shift)  # per voxel length
        alpha = 1 - torch.exp(-sigma * length / self.voxel_m)
        transmit = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha], 1), 1)
        return alpha * transmit[:, :-1], depth, raw

    def depth_error(
        self, origins: Tensor, directions: Tensor, target: Tensor, samples: int, near_m: float
    ) -> Tensor:
        """How far from ``target`` [R] (depth along the directions, in their units) the light
        of rays [R, 3] ends: the light-weighted mean of ``|log(depth / target)|`` over the
        ray's samples (stratified, jittered), the light that passes every sample counted at
        the ray's farthest depth -> [R]. Differentiable w.r.t. the grid (``grid_sample``)."""
        rays = self.ray_bounds(origins, directions, near_m)
        offsets = torch.rand((len(origins), samples), device=origins.device)
        weights, depth, _ = self._weights(rays, offsets)
        log_target = target.clamp_min(_EPS).log()[:, None]
        error = (depth.clamp_min(_EPS).log() - log_target).abs()
        passed = 1 - weights.sum(1)
        beyond = (rays.far.clamp_min(_EPS).log() - log_target[:, 0]).abs()
        return (weights * error).sum(1) + passed * beyond

    def kernel_cells(self) -> np.ndarray:
        """The grid in the compiled kernels' layout [nz, ny, nx, 4]: copied once per change
        of the grid (an optimiser step, a loaded state), not once per call or chunk."""
        key = (self.grid._version, self.grid.data_ptr())
        if self._kernel_cells is None or self._kernel_cells[0] != key:
            self._kernel_cells = (key, channels_last(self.grid))
        return self._kernel_cells[1]

    def compiled(self, engine: Engine) -> bool:
        """Whether ``engine`` (:data:`pae.core.compiled.ENGINES`) runs the compiled kernels on
        this grid: ``numba`` (CPU float32 grids only), or ``auto`` where they can run."""
        if engine not in ENGINES:
            raise ValueError(f"unknown engine {engine!r}; choose one of {ENGINES}")
        runs = self.grid.device.type == "cpu" and self.grid.dtype == torch.float32
        if engine == "numba" and not runs:
            raise ValueError("engine 'numba' runs on CPU float32 grids only; use auto or torch")
        return engine != "torch" and runs

    def total_variation(self, engine: Engine = "auto") -> Tensor:
        """Mean squared difference of neighbouring voxels (density and colour channels) along
        each axis, summed over the axes; ``engine`` as in :meth:`composite` (the compiled one
        takes one pass forward and one backward)."""
        g = self.grid
        if self.compiled(engine):
            return CompiledTotalVariation.apply(g, self.kernel_cells())
        return (
            (g[..., 1:, :, :] - g[..., :-1, :, :]).square().mean()
            + (g[..., :, 1:, :] - g[..., :, :-1, :]).square().mean()
            + (g[..., :, :, 1:] - g[..., :, :, :-1]).square().mean()
        )


class VoxelGridSceneModel(SceneModel):
    """One :class:`VoxelGrid` per scene plus a per-image-sequence appearance: per-channel
    gain (``exp``) and bias and, with ``appearance_field`` = G >= 2, a gain that varies
    smoothly over the image (``exp`` of a bilinear G × G field), applied to training
    renderings only, so that a sequence's or an image's lighting (exposure, white balance,
    vignetting, a lamp's fall-off) does not bake into the grid.

    bounds: per scene [2, 3] (lo, hi) in metres; n_appearances: the train sequences over all
    scenes; num_voxels: per scene; samples_per_ray: stratified samples; near_m: the nearest
    depth rendered; appearance_field: G (0: none) (their defaults:
    conf/scene_model/voxel_grid.yaml). Built by the
    scene_model step from the train cameras (:func:`train_scale`: its config's ``margin_m``,
    ``auto_scale`` and ``contract: auto``) and the train images' appearance ids.
    """

    has_depth = True
    trains = True
    fits_depth = True
    from_run = ("bounds", "n_appearances")
    build_keys = ("margin_m", "auto_scale", "contract")

    def __init__(
        self,
        bounds: Sequence[Sequence[Sequence[float]]],
        n_appearances: int,
        num_voxels: int,
        samples_per_ray: int,
        contract: bool,
        near_m: float,
        appearance_field: int = 0,
        chunk_rays: int = 8192,
        grow_from: float = 1.0,
        grow_at_epoch: int = 0,
    ) -> None:
        super().__init__()
        if appearance_field == 1 or appearance_field < 0:
            raise ValueError(f"appearance_field must be 0 or >= 2, not {appearance_field}")
        self.grids = nn.ModuleList(VoxelGrid(b, num_voxels, contract) for b in bounds)
        self.num_voxels = num_voxels
        self.grow_from = grow_from
        self.grow_at_epoch = grow_at_epoch
        self.appearance_field = appearance_field
        # per code: log-gain [3], bias [3], then the field's G x G log-gains, row by row
        self.appearance = nn.Embedding(max(1, n_appearances), 6 + appearance_field**2)
        nn.init.zeros_(self.appearance.weight)
        self.samples_per_ray = samples_per_ray
        self.near_m = near_m
        self.chunk_rays = chunk_rays

    @classmethod
    def check_config(cls, cfg: DictConfig, key: str) -> None:
        """num_voxels >= 8, samples_per_ray >= 1, grow_from in (0, 1] and grow_at_epoch below
        the fit's epochs, appearance_field 0 or >= 2, contract true, false or auto, margin_m
        auto, one number >= 0 or three, auto_scale's numbers >= 0."""
        integer(cfg, f"{key}.num_voxels", 8)
        integer(cfg, f"{key}.samples_per_ray", 1)
        grow_from = setting(cfg, f"{key}.grow_from")
        if present(cfg, f"{key}.grow_from") and not (
            isinstance(grow_from, float | int) and 0 < grow_from <= 1
        ):
            raise ConfigError(f"{key}.grow_from must be a share in (0, 1], got {grow_from!r}")
        at = integer(cfg, f"{key}.grow_at_epoch", 0) if present(cfg, f"{key}.grow_at_epoch") else 0
        epochs = setting(cfg, "scene_model.max_epochs")
        if grow_from is not None and grow_from < 1 and is_int(epochs) and at >= epochs:
            raise ConfigError(f"{key}.grow_at_epoch={at} must be below {epochs} epochs")
        if (
            present(cfg, f"{key}.appearance_field")
            and integer(cfg, f"{key}.appearance_field", 0) == 1
        ):
            raise ConfigError(f"{key}.appearance_field must be 0 (none) or >= 2, got 1")
        number(cfg, f"{key}.near_m", 0, strict=False)
        if setting(cfg, f"{key}.contract") != "auto":
            boolean(cfg, f"{key}.contract")
        for name in ("margin_floor_m", "margin_fraction", "contract_above_m"):
            number(cfg, f"{key}.auto_scale.{name}", 0, strict=False)
        margin = setting(cfg, f"{key}.margin_m")
        values = list(margin) if isinstance(margin, ListConfig) else [margin]
        if margin != "auto" and (
            len(values) not in (1, 3)
            or not all((is_int(v) or isinstance(v, float)) and v >= 0 for v in values)
        ):
            raise ConfigError(
                f"{key}.margin_m must be auto, one number >= 0 or three, got {margin!r}"
            )

    @classmethod
    def build(
        cls, config: dict[str, Any], inputs: SceneModelInputs
    ) -> tuple[SceneModel, dict[str, Any] | None]:
        """Bounds from the train cameras, one appearance code per train sequence or image."""
        data = inputs.data
        poses, scenes = data.train_poses()
        config = train_scale(poses, scenes, data.n_scenes, config)
        _, config["n_appearances"] = data.appearance_ids("train", inputs.appearance)
        return cls(**config), config

    def render_rays(
        self,
        origins: Tensor,
        directions: Tensor,
        scenes: Tensor,
        jitter: bool = False,
        surface_share: float = 0.0,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Rays [R, 3] of scenes [R] -> rgb [R, 3], depth [R] (``surface_share``:
        :meth:`VoxelGrid.composite`), opacity [R]; one grid call per chunk of ``chunk_rays``
        of a scene's rays (rays not ordered by scene are ordered once, and back after)."""
        order, counts = scene_order(scenes, len(self.grids))
        if order is not None:
            origins, directions = origins[order], directions[order]
        parts = [(origins.new_zeros(0, 3), origins.new_zeros(0), origins.new_zeros(0))]
        first = 0
        for grid, count in zip(self.grids, counts, strict=True):
            run = slice(first, first + count)
            segments = grid.ray_bounds(origins[run], directions[run], self.near_m)
            for start in range(0, count, self.chunk_rays):
                chunk = RaySegments(*(part[start : start + self.chunk_rays] for part in segments))
                parts.append(
                    grid.composite_segments(
                        chunk, self.samples_per_ray, jitter, surface_share=surface_share
                    )
                )
            first += count
        rgb, depth, opacity = (torch.cat([part[i] for part in parts]) for i in range(3))
        return in_order_of(order, rgb), in_order_of(order, depth), in_order_of(order, opacity)

    def depth_error(
        self, origins: Tensor, directions: Tensor, scenes: Tensor, target: Tensor
    ) -> Tensor:
        """Rays [R, 3] of scenes [R] -> how far from ``target`` [R] (depth along the
        directions) their light ends [R] (:meth:`VoxelGrid.depth_error`)."""
        order, counts = scene_order(scenes, len(self.grids))
        if order is not None:
            origins, directions, target = origins[order], directions[order], target[order]
        parts, first, samples = [origins.new_zeros(0)], 0, self.samples_per_ray
        for grid, count in zip(self.grids, counts, strict=True):
            run = slice(first, first + count)
            if count:
                error = grid.depth_error(
                    origins[run], directions[run], target[run], samples, self.near_m
                )
                parts.append(error)
            first += count
        return in_order_of(order, torch.cat(parts))

    def with_appearance(
        self, rgb: Tensor, appearance: Tensor, pixels: Tensor | None = None
    ) -> Tensor:
        """Renderings [R, 3] as train sequence (or image) ``appearance`` [R] saw them, at
        ``pixels`` [R, 2] ((column, row) in [0, 1]; needed by the field, else ignored)."""
        code = self.appearance(appearance)
        rgb = rgb * code[:, :3].exp() + code[:, 3:6]
        if not self.appearance_field or pixels is None:
            return rgb
        g = self.appearance_field
        cell = pixels.clamp(0, 1) * (g - 1)
        corner = cell.floor().clamp(max=g - 2)
        t = cell - corner  # [R, 2] within the cell
        first = (corner[:, 1] * g + corner[:, 0]).long()  # the cell's top-left node
        nodes = torch.stack([first, first + 1, first + g, first + g + 1], 1)
        weights = torch.stack(
            [(1 - t[:, 0]) * (1 - t[:, 1]), t[:, 0] * (1 - t[:, 1]),
             (1 - t[:, 0]) * t[:, 1], t[:, 0] * t[:, 1]], 1,
        )  # fmt: skip
        field = code[:, 6:].gather(1, nodes)
        return rgb * (field * weights).sum(1, keepdim=True).exp()

    def total_variation(self) -> Tensor:
        """The grids' mean total variation, each weighed by its configured voxel's length
        over its own, squared: per unit of the field's gradient, the same at every size the
        fit grows through (1 at the configured size)."""
        return torch.stack(
            [g.total_variation() * (g.configured_voxel_m / g.voxel_m) ** 2 for g in self.grids]
        ).mean()

    def fit_stage(self, epoch: int, fresh: bool) -> bool:
        """Before epoch ``grow_at_epoch`` the grids hold ``grow_from`` × ``num_voxels``
        voxels, from it ``num_voxels``, grown with the field kept (a fresh fit starts from
        the initial fog): the coarse grid clears the empty space and places the surfaces,
        the fine one adds the detail."""
        coarse = epoch < self.grow_at_epoch and self.grow_from < 1
        voxels = max(8, round(self.grow_from * self.num_voxels)) if coarse else self.num_voxels
        return any([grid.resize(voxels, keep=not fresh) for grid in self.grids])

    def render(
        self,
        poses: Tensor,
        scenes: Tensor,
        intrinsics: Tensor,
        width: int,
        height: int,
        surface_share: float = 0.0,
    ) -> SceneRendering:
        """Images of poses [B, 7] in scenes [B] (see :meth:`SceneModel.render`); cameras not
        ordered by scene are rendered in scene order, so that each scene's rays are one run."""
        order, _ = scene_order(scenes, len(self.grids))
        if order is not None:
            ordered = self.render(
                poses[order], scenes[order], intrinsics[order], width, height, surface_share
            )
            return SceneRendering(*(in_order_of(order, part) for part in ordered))
        origins, directions = camera_rays(poses, intrinsics, width, height)
        pixels = origins.shape[1]
        rgb, depth, opacity = self.render_rays(
            origins.reshape(-1, 3),
            directions.reshape(-1, 3),
            scenes.repeat_interleave(pixels),
            surface_share=surface_share,
        )
        b = len(poses)
        return SceneRendering(
            rgb.view(b, height, width, 3).permute(0, 3, 1, 2),
            depth.view(b, height, width),
            opacity.view(b, height, width),
        )
