"""The voxel grid's total variation compiled on the CPU (numba): the mean squared difference
of neighbouring cells along each axis in one pass forward and one backward, reading the grid
in the kernels' layout ``[nz, ny, nx, C]`` (:func:`pae.scene_model.voxel_composite.channels_last`)
instead of a dozen tensor passes (:meth:`VoxelGrid.total_variation`'s tensor engine, tested
equal)."""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from pae.core.compiled import jit


@jit(parallel=True, nogil=True, fastmath=True)
def variation_sums(cells: np.ndarray) -> tuple[float, float, float]:
    """Sums of the squared differences of neighbouring cells [nz, ny, nx, C] along x, y, z."""
    nz, ny, nx, nc = cells.shape
    sx = sy = sz = 0.0
    for i in numba.prange(nz):
        for j in range(ny):
            for k in range(nx):
                for c in range(nc):
                    v = cells[i, j, k, c]
                    if k + 1 < nx:
                        sx += (cells[i, j, k + 1, c] - v) ** 2
                    if j + 1 < ny:
                        sy += (cells[i, j + 1, k, c] - v) ** 2
                    if i + 1 < nz:
                        sz += (cells[i + 1, j, k, c] - v) ** 2
    return sx, sy, sz


@jit(parallel=True, nogil=True, fastmath=True)
def variation_gradient(
    cells: np.ndarray, wx: float, wy: float, wz: float, grad: np.ndarray
) -> None:
    """grad [nz, ny, nx, C] = the gradient of ``wx·sx + wy·sy + wz·sz`` (the sums of
    :func:`variation_sums`) w.r.t. cells [nz, ny, nx, C]."""
    nz, ny, nx, nc = cells.shape
    for i in numba.prange(nz):
        for j in range(ny):
            for k in range(nx):
                for c in range(nc):
                    v = cells[i, j, k, c]
                    g = 0.0
                    if k > 0:
                        g += wx * (v - cells[i, j, k - 1, c])
                    if k + 1 < nx:
                        g += wx * (v - cells[i, j, k + 1, c])
                    if j > 0:
                        g += wy * (v - cells[i, j - 1, k, c])
                    if j + 1 < ny:
                        g += wy * (v - cells[i, j + 1, k, c])
                    if i > 0:
                        g += wz * (v - cells[i - 1, j, k, c])
                    if i + 1 < nz:
                        g += wz * (v - cells[i + 1, j, k, c])
                    grad[i, j, k, c] = 2.0 * g


class CompiledTotalVariation(torch.autograd.Function):
    """(grid [1, C, nz, ny, nx], the same grid in the kernels' layout [nz, ny, nx, C]) -> the
    mean squared difference of neighbouring cells along each axis, summed over the axes
    (:meth:`VoxelGrid.total_variation`), in one pass forward and one backward instead of
    a dozen tensor passes."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx, grid: Tensor, cells: np.ndarray
    ) -> Tensor:
        nz, ny, nx, nc = cells.shape
        counts = (nz * ny * (nx - 1) * nc, nz * (ny - 1) * nx * nc, (nz - 1) * ny * nx * nc)
        sums = variation_sums(cells)
        ctx.cells, ctx.counts = cells, counts
        ctx.dtype = grid.dtype
        value = sum(s / n for s, n in zip(sums, counts, strict=True))
        return torch.tensor(value, dtype=grid.dtype)

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx, grad_value: Tensor
    ) -> tuple[Tensor, None]:
        scale = float(grad_value)
        weights = [scale / n for n in ctx.counts]
        grad = np.empty_like(ctx.cells)
        variation_gradient(ctx.cells, *weights, grad)
        return torch.from_numpy(grad).permute(3, 0, 1, 2)[None].to(ctx.dtype), None
