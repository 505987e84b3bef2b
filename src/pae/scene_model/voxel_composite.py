"""The compiled volume renderer (:mod:`pae.scene_model.voxel_render`) as a torch autograd
function: :class:`CompiledComposite`, which :meth:`pae.scene_model.voxel_grid.VoxelGrid.composite`
calls on CPU tensors, and the grid's layout for its kernels (:func:`channels_last`)."""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from pae.scene_model.voxel_render import (
    GridGeometry,
    March,
    RaySegments,
    render_backward,
    render_forward,
)


def channels_last(grid: Tensor) -> np.ndarray:
    """A grid [1, 4, nz, ny, nx] in the kernels' layout [nz, ny, nx, 4]: a view where the grid
    is stored channels last (``torch.channels_last_3d``, as :class:`VoxelGrid` stores it), else
    a copy."""
    return grid.detach()[0].permute(1, 2, 3, 0).contiguous().numpy()


class CompiledComposite(torch.autograd.Function):
    """(grid [1, 4, nz, ny, nx], the same grid in the kernels' layout (``channels_last``,
    made once per change of the grid by the caller), background [3] after its sigmoid, rays
    (``RaySegments`` of tensors), offsets [R, S] (or [1, S] for every ray), geometry
    (``GridGeometry``), density_shift) -> rgb [R, 3], surface [R], opacity [R];
    differentiable in rgb w.r.t. the grid and the background."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx,
        grid: Tensor,
        cells: np.ndarray,
        background: Tensor,
        rays: RaySegments,
        offsets: Tensor,
        geometry: GridGeometry,
        density_shift: float,
        surface_share: float = 0.0,
    ) -> tuple[Tensor, Tensor, Tensor]:
        bg = background.detach().double().numpy()
        ray_array = RaySegments(*(part.detach().double().contiguous().numpy() for part in rays))
        offset_array = offsets.detach().float().contiguous().numpy()
        march = March(cells, ray_array, offset_array, geometry, density_shift, bg, surface_share)
        r = len(ray_array.near)
        rgb = np.empty((r, 3), np.float32)
        surface, opacity = np.empty(r, np.float32), np.empty(r, np.float32)
        used = np.empty(r, np.int64)
        render_forward(march, rgb, surface, opacity, used)
        ctx.save_for_backward(grid)
        ctx.arrays = (march, rgb, used)
        outputs = torch.from_numpy(rgb), torch.from_numpy(surface), torch.from_numpy(opacity)
        ctx.mark_non_differentiable(outputs[1], outputs[2])
        return outputs

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx,
        grad_rgb: Tensor,
        grad_surface: Tensor,
        grad_opacity: Tensor,
    ) -> tuple[Tensor | None, ...]:
        (grid,) = ctx.saved_tensors
        march, rgb, used = ctx.arrays
        chunks = max(1, numba.get_num_threads())
        grad_cells = np.zeros((chunks, *march.grid.shape), np.float32)
        grad_bg = np.zeros((chunks, 3), np.float64)
        g = grad_rgb.detach().float().contiguous().numpy()
        render_backward(march, rgb, used, g, grad_cells, grad_bg)
        grad_grid = torch.from_numpy(grad_cells.sum(0)).permute(3, 0, 1, 2)[None]
        grad_background = torch.from_numpy(grad_bg.sum(0)).to(grid.dtype)
        return grad_grid.to(grid.dtype), None, grad_background, None, None, None, None, None
