"""Compiled volume rendering of a voxel grid on the CPU (numba): forward and backward.

Both passes march ``BLOCK_RAYS`` rays side by side, one sample index at a time: the grid's
reads (:func:`_read_block`) and the backward's scatter stay scalar, the arithmetic between
them (softplus, opacities, sigmoids, compositing and its adjoint) runs in float32 SIMD lanes
with :func:`_exp_parts`'s polynomial exponential. A ray stops adding light once its
transmittance falls below ``STOP_TRANSMITTANCE``, a block once all its rays have. The
backward marches each ray again and scatters into per-thread gradient copies (summed after).
Both compute what :meth:`VoxelGrid.composite` computes with ``grid_sample`` (tested).

Grid layout: ``[nz, ny, nx, 4]`` float32 (raw density, raw RGB), channels last. Each ray's
samples (depths, world points, their contraction and grid coordinates) are computed inside
the kernels, as :meth:`VoxelGrid.sample_depths` and :meth:`VoxelGrid.normalised` define them.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
from torch import Tensor

from pae.core.compiled import jit


class RaySegments(NamedTuple):
    """Rays and where they are sampled: origins [R, 3], directions [R, 3] (world frame), and
    the depths (in units of the directions) where sampling starts (``near``: ``near_m`` or
    where the ray enters the bounds), where it leaves the bounds (``leave``) and where it
    ends (``far``: contracted grids sample beyond the bounds; else ``leave``), each [R].
    Tensors for the grid's tensor path, float64 arrays for the compiled one."""

    origins: Tensor | np.ndarray
    directions: Tensor | np.ndarray
    near: Tensor | np.ndarray
    leave: Tensor | np.ndarray
    far: Tensor | np.ndarray


class GridGeometry(NamedTuple):
    """Where a grid lies: its bounds ``lo`` and ``hi`` [3] (m), ``cells`` [3] (voxels per axis
    minus one, x y z), ``inverse_voxel_m`` (1 / voxel length, m) and ``contract``."""

    lo: np.ndarray
    hi: np.ndarray
    cells: np.ndarray
    inverse_voxel_m: float
    contract: bool


class March(NamedTuple):
    """What the forward and backward kernels march: the grid [nz, ny, nx, 4] in their layout
    (``channels_last``), the rays (``RaySegments`` of float64 arrays), their sample offsets
    [R, S] (or [1, S], the same for every ray), the grid's ``GridGeometry``, the shift added
    to the raw density, the background colour [3] (after its sigmoid) and the forward pass's
    ``surface_share`` (:func:`render_forward`)."""

    grid: np.ndarray
    rays: RaySegments
    offsets: np.ndarray
    geometry: GridGeometry
    density_shift: float
    background: np.ndarray
    surface_share: float = 0.0


STOP_TRANSMITTANCE = 1e-4
"""A ray's march stops once less than this share of its light remains."""
BLOCK_RAYS = 32
"""Rays a thread marches side by side in either pass (the SIMD loops' length)."""

_ONE, _TWO, _HALF = np.float32(1.0), np.float32(2.0), np.float32(0.5)
_ZERO = np.float32(0.0)
_LOG2E = np.float32(1.4426950408889634)
_EXP2_LIMIT = np.float32(126.0)
_EXP2_TAYLOR = tuple(
    np.float32(math.log(2) ** k / math.factorial(k)) for k in range(6, 0, -1)
)  # 2^f = sum (f ln 2)^k / k!, |f| <= 1/2: relative error below 2e-7 at degree 6
_ATANH_SERIES = tuple(np.float32(1 / k) for k in range(13, 2, -2))
# log1p(z) = 2 atanh(u), u = z / (2 + z) <= 1/3 for z in [0, 1]: 2u(1 + u²/3 + ... + u¹²/13)


@jit(nogil=True, inline="always", fastmath=True)
def _exp_parts(x: float) -> tuple[float, int]:
    """exp(x) of a float32 x as ``(p, bits)``: p in [0.7, 1.42] and 2^n as float32 exponent
    bits (``bits`` viewed as float32 is 2^n), exp(x) = p · 2^n, n clamped to ±126.
    Polynomial arithmetic only, so that a loop of them runs in SIMD lanes; relative error
    about 1e-6 for |x| < 20 (float32 rounding of x · log2 e), tested against ``math.exp``."""
    y = max(min(x * _LOG2E, _EXP2_LIMIT), -_EXP2_LIMIT)
    n = np.floor(y + _HALF)
    f = y - n
    c6, c5, c4, c3, c2, c1 = _EXP2_TAYLOR
    p = (((((c6 * f + c5) * f + c4) * f + c3) * f + c2) * f + c1) * f + _ONE
    return p, (np.int32(n) + np.int32(127)) << np.int32(23)


@jit(nogil=True, inline="always", fastmath=True)
def _log1p_unit(z: float) -> float:
    """log(1 + z) for float32 z in [0, 1], polynomial arithmetic only (relative error about
    1e-7)."""
    u = z / (_TWO + z)
    u2 = u * u
    a13, a11, a9, a7, a5, a3 = _ATANH_SERIES
    return (
        _TWO * u * (((((((a13 * u2 + a11) * u2 + a9) * u2 + a7) * u2 + a5) * u2 + a3) * u2) + _ONE)
    )


@jit(nogil=True, inline="always", fastmath=True)
def _depth(u: float, near: float, leave: float, far: float, contract: bool) -> float:
    """Depth at the fraction ``u`` in (0, 1) of a ray's samples (see VoxelGrid.sample_depths)."""
    if not contract:
        return near + (leave - near) * u
    if u < 0.5:
        return near + (leave - near) * min(2 * u, 1.0)
    s = max(2 * u - 1, 0.0)
    return 1.0 / ((1.0 - s) / leave + s / far)


@jit(nogil=True, inline="always")
def _offset_row(offsets: np.ndarray, r: int) -> int:
    """The row of ``offsets`` ([R, S], or [1, S] shared by every ray) that ray ``r`` reads."""
    return min(r, offsets.shape[0] - 1)


@jit(nogil=True, inline="always", fastmath=True)
def _point(rays: tuple, r: int, s: int, n: int, offsets: np.ndarray, geometry: tuple) -> tuple:
    """Grid coordinates, length (voxels) and depth of sample ``s`` of ray ``r`` (offsets
    [R, S] or [1, S] in [0, 1) within the samples' strata); ``rays`` and ``geometry``: the
    fields of ``RaySegments`` and ``GridGeometry``, unpacked once by the kernel."""
    origins, directions, nears, leaves, fars = rays
    lo, hi, cells, inverse_voxel_m, contract = geometry
    near, leave, far = nears[r], leaves[r], fars[r]
    row = _offset_row(offsets, r)
    t = _depth((s + offsets[row, s]) / n, near, leave, far, contract)
    norm = math.sqrt(directions[r, 0] ** 2 + directions[r, 1] ** 2 + directions[r, 2] ** 2)
    if contract:
        before = (
            near if s == 0 else _depth((s - 1 + offsets[row, s - 1]) / n, near, leave, far, True)
        )
        after = (
            far if s == n - 1 else _depth((s + 1 + offsets[row, s + 1]) / n, near, leave, far, True)
        )
        low = near if s == 0 else (before + t) / 2
        high = far if s == n - 1 else (t + after) / 2
        length = (high - low) * norm * inverse_voxel_m
    else:
        length = (leave - near) * norm / n * inverse_voxel_m
    ux = (origins[r, 0] + t * directions[r, 0] - lo[0]) / (hi[0] - lo[0]) * 2 - 1
    uy = (origins[r, 1] + t * directions[r, 1] - lo[1]) / (hi[1] - lo[1]) * 2 - 1
    uz = (origins[r, 2] + t * directions[r, 2] - lo[2]) / (hi[2] - lo[2]) * 2 - 1
    if contract:
        largest = max(abs(ux), abs(uy), abs(uz))
        scale = 0.5 if largest <= 1 else (2 - 1 / largest) / largest / 2
        ux, uy, uz = ux * scale, uy * scale, uz * scale
    return (
        (ux + 1) / 2 * cells[0],
        (uy + 1) / 2 * cells[1],
        (uz + 1) / 2 * cells[2],
        length,
        t,
    )


@jit(nogil=True, inline="always", fastmath=True)
def _cell(point: np.ndarray, j: int, top: tuple, sx: int, sy: int, sz: int) -> int:
    """Column ``j`` of point [3, BLOCK_RAYS] (grid coordinates x, y, z) clamped inside a grid
    whose largest coordinates are ``top`` (x, y, z): returns its cell's flat index into the
    grid's values (strides ``sx``, ``sy``, ``sz``) and writes the fractions inside the cell
    back to the column."""
    x = min(max(point[0, j], _ZERO), top[0])
    y = min(max(point[1, j], _ZERO), top[1])
    z = min(max(point[2, j], _ZERO), top[2])
    k0 = min(np.int32(x), np.int32(top[0]) - 1)
    j0 = min(np.int32(y), np.int32(top[1]) - 1)
    i0 = min(np.int32(z), np.int32(top[2]) - 1)
    point[0, j] = x - np.float32(k0)
    point[1, j] = y - np.float32(j0)
    point[2, j] = z - np.float32(i0)
    return i0 * sz + j0 * sy + k0 * sx


@jit(nogil=True, inline="always", fastmath=True)
def _trilinear(
    cells: np.ndarray, corner: int, point: np.ndarray, j: int, sx: int, sy: int, sz: int
) -> tuple[float, float, float, float]:
    """The four channels of the flat grid ``cells`` interpolated in the cell ``corner`` at
    the fractions of column ``j`` of point [3, BLOCK_RAYS]."""
    fx, fy, fz = point[0, j], point[1, j], point[2, j]
    v0 = v1 = v2 = v3 = _ZERO
    for di in range(2):
        wz = fz if di else _ONE - fz
        for dj in range(2):
            wzy = wz * (fy if dj else _ONE - fy)
            w0, w1 = wzy * (_ONE - fx), wzy * fx
            o = corner + di * sz + dj * sy
            v0 += w0 * cells[o] + w1 * cells[o + sx]
            v1 += w0 * cells[o + 1] + w1 * cells[o + sx + 1]
            v2 += w0 * cells[o + 2] + w1 * cells[o + sx + 2]
            v3 += w0 * cells[o + 3] + w1 * cells[o + sx + 3]
    return v0, v1, v2, v3


@jit(nogil=True, inline="always", fastmath=True)
def _read_block(cells, samples: tuple, top: tuple, sx: int, sy: int, sz: int, shift: float):
    """A block's samples (point at grid coordinates, then the fractions in its cell; corner,
    density, colour, mantissa, exponent) read in place: raw density + ``shift``, colour, and
    exp(-|density|), exp(-colour) as mantissa × 2^exponent. Scalar reads, SIMD exponentials."""
    point, corner, density, colour, mantissa, exponent = samples
    for j in range(BLOCK_RAYS):
        corner[j] = _cell(point, j, top, sx, sy, sz)
    for j in range(BLOCK_RAYS):
        v0, v1, v2, v3 = _trilinear(cells, corner[j], point, j, sx, sy, sz)
        density[j] = v0 + shift
        colour[0, j], colour[1, j], colour[2, j] = v1, v2, v3
    for j in range(BLOCK_RAYS):
        mantissa[0, j], exponent[0, j] = _exp_parts(-abs(density[j]))
        for c in range(3):
            mantissa[c + 1, j], exponent[c + 1, j] = _exp_parts(-colour[c, j])


@jit(nogil=True, inline="always", fastmath=True)
def _scatter(
    grad: np.ndarray,
    corner: int,
    point: np.ndarray,
    j: int,
    out: np.ndarray,
    sx: int,
    sy: int,
    sz: int,
) -> None:
    """Add column ``j`` of out [4, BLOCK_RAYS] (one value per channel) times the trilinear
    weights of column ``j`` of point [3, BLOCK_RAYS] to the cell ``corner`` of the flat
    gradient ``grad``: the adjoint of :func:`_trilinear`."""
    fx, fy, fz = point[0, j], point[1, j], point[2, j]
    for di in range(2):
        wz = fz if di else _ONE - fz
        for dj in range(2):
            wzy = wz * (fy if dj else _ONE - fy)
            o = corner + di * sz + dj * sy
            for dk in range(2):
                w = wzy * (fx if dk else _ONE - fx)
                for c in range(4):
                    grad[o + dk * sx + c] += w * out[c, j]


@jit(nogil=True, inline="always", fastmath=True)
def _marching(march: March) -> tuple:
    """What both passes read from ``march`` before their loops: the grid's values flattened,
    their strides along x, y and z, the rays' and the grid's fields as plain tuples (which the
    parallel loops read), the largest grid coordinates (x, y, z) and the density shift, both
    float32."""
    grid, rays, _, geometry, density_shift, _, _ = march
    nz, ny, nx = grid.shape[0], grid.shape[1], grid.shape[2]
    origins, directions, nears, leaves, fars = rays
    lo, hi, per_axis, inverse_voxel_m, contract = geometry
    return (
        grid.reshape(-1),
        (4, nx * 4, ny * nx * 4),
        (origins, directions, nears, leaves, fars),
        (lo, hi, per_axis, inverse_voxel_m, contract),
        (np.float32(nx - 1), np.float32(ny - 1), np.float32(nz - 1)),
        np.float32(density_shift),
    )


@jit(nogil=True, inline="always", fastmath=True)
def _ray_steps(
    r: int, j: int, n: int, segments: tuple, where: tuple, start: np.ndarray, step: np.ndarray
) -> float:
    """Column ``j`` of start and step [3, BLOCK_RAYS]: ray ``r``'s grid coordinates at its near
    depth and per stratum of its ``n`` samples (uncontracted grids) -> their length (voxels)."""
    origins, directions, nears, leaves, _ = segments
    lo, hi, per_axis, inverse_voxel_m, _ = where
    span = leaves[r] - nears[r]
    for axis in range(3):
        to_grid = per_axis[axis] / (hi[axis] - lo[axis])
        at_near = origins[r, axis] + nears[r] * directions[r, axis]
        start[axis, j] = (at_near - lo[axis]) * to_grid
        step[axis, j] = span / n * directions[r, axis] * to_grid
    norm = math.sqrt(directions[r, 0] ** 2 + directions[r, 1] ** 2 + directions[r, 2] ** 2)
    return span * norm / n * inverse_voxel_m


@jit(parallel=True, nogil=True, fastmath=True)
def render_forward(
    march: March, rgb: np.ndarray, surface: np.ndarray, opacity: np.ndarray, used: np.ndarray
) -> None:
    """Composite the rays of ``march`` -> rgb [R, 3], surface [R], opacity [R], used [R]
    (samples marched). The surface is the light's mean depth, or with ``march.surface_share``
    > 0 the depth of the first sample by which the ray has gathered that share of its
    opacity (a quantile of the light: faint fog in front of a surface moves it little)."""
    offsets, background, share = march.offsets, march.background, march.surface_share
    cells, (sx, sy, sz), segments, where, top, shift = _marching(march)
    nears, leaves, contract = segments[2], segments[3], where[4]
    n_rays, n = march.rays.near.shape[0], offsets.shape[1]
    for block in numba.prange(-(-n_rays // BLOCK_RAYS)):
        rows = np.minimum(np.arange(BLOCK_RAYS) + block * BLOCK_RAYS, n_rays - 1)
        start = np.empty((3, BLOCK_RAYS), np.float32)
        step = np.empty((3, BLOCK_RAYS), np.float32)
        length = np.empty(BLOCK_RAYS, np.float32)
        depth0 = np.empty(BLOCK_RAYS, np.float32)
        depth_step = np.empty(BLOCK_RAYS, np.float32)
        if not contract:
            for j in range(BLOCK_RAYS):
                r = rows[j]
                length[j] = _ray_steps(r, j, n, segments, where, start, step)
                depth0[j] = nears[r]
                depth_step[j] = (leaves[r] - nears[r]) / n
        point = np.empty((3, BLOCK_RAYS), np.float32)  # grid coordinates, then fractions
        corner = np.empty(BLOCK_RAYS, np.int64)
        depth = np.empty(BLOCK_RAYS, np.float32)
        density = np.empty(BLOCK_RAYS, np.float32)
        colour = np.empty((3, BLOCK_RAYS), np.float32)
        mantissa = np.empty((4, BLOCK_RAYS), np.float32)
        exponent = np.empty((4, BLOCK_RAYS), np.int32)
        power = exponent.view(np.float32)
        samples = (point, corner, density, colour, mantissa, exponent)
        transmit = np.ones(BLOCK_RAYS, np.float32)
        light = np.zeros((4, BLOCK_RAYS), np.float32)  # red, green, blue, depth
        marched = np.zeros(BLOCK_RAYS, np.int64)
        gathered = np.zeros((n, BLOCK_RAYS), np.float32)  # opacity after each sample
        sampled_depth = np.zeros((n, BLOCK_RAYS), np.float32)
        last = n
        for s in range(n):
            if contract:
                for j in range(BLOCK_RAYS):
                    x, y, z, sample_length, t = _point(segments, rows[j], s, n, offsets, where)
                    point[0, j], point[1, j], point[2, j] = x, y, z
                    length[j], depth[j] = sample_length, t
            else:
                for j in range(BLOCK_RAYS):
                    u = np.float32(s) + offsets[_offset_row(offsets, rows[j]), s]
                    for axis in range(3):
                        point[axis, j] = start[axis, j] + u * step[axis, j]
                    depth[j] = depth0[j] + u * depth_step[j]
            _read_block(cells, samples, top, sx, sy, sz, shift)  # SIMD after
            for j in range(BLOCK_RAYS):
                sigma = max(density[j], _ZERO) + _log1p_unit(mantissa[0, j] * power[0, j])
                mantissa[0, j], exponent[0, j] = _exp_parts(-sigma * length[j])
            for j in range(BLOCK_RAYS):
                alpha = _ONE - mantissa[0, j] * power[0, j]
                live = transmit[j] >= STOP_TRANSMITTANCE
                weight = transmit[j] * alpha if live else _ZERO
                for c in range(3):
                    light[c, j] += weight / (_ONE + mantissa[c + 1, j] * power[c + 1, j])
                light[3, j] += weight * depth[j]
                transmit[j] = transmit[j] - weight
                marched[j] += 1 if live else 0
                gathered[s, j] = _ONE - transmit[j]
                sampled_depth[s, j] = depth[j]
            if transmit.max() < STOP_TRANSMITTANCE:
                last = s + 1
                break
        for j in range(min(BLOCK_RAYS, n_rays - block * BLOCK_RAYS)):
            r = rows[j]
            for c in range(3):
                rgb[r, c] = light[c, j] + transmit[j] * background[c]
            opacity[r] = 1.0 - transmit[j]
            surface[r] = light[3, j] / max(1.0 - transmit[j], 1e-6)
            if share > 0:
                threshold = share * (1.0 - transmit[j])
                k = 0
                while k < last - 1 and gathered[k, j] < threshold:
                    k += 1
                surface[r] = sampled_depth[k, j]
            used[r] = marched[j]


@jit(parallel=True, nogil=True, fastmath=True)
def render_backward(
    march: March,
    rgb: np.ndarray,
    used: np.ndarray,
    grad_rgb: np.ndarray,
    grad_grid: np.ndarray,
    grad_background: np.ndarray,
) -> None:
    """Gradient of a loss with d loss / d rgb = grad_rgb [R, 3] (of :func:`render_forward`'s
    rgb and used) w.r.t. the grid of ``march`` (added to grad_grid [T, nz, ny, nx, 4], one
    copy per chunk of rays) and the background colour (grad_background [T, 3]). Each chunk
    marches its rays ``BLOCK_RAYS`` at a time as the forward pass does; the reads of the grid
    and the scatter into its gradient stay scalar."""
    offsets = march.offsets
    cells, (sx, sy, sz), segments, where, top, shift = _marching(march)
    contract = where[4]
    chunks = grad_grid.shape[0]
    n_rays, n = march.rays.near.shape[0], offsets.shape[1]
    for t in numba.prange(chunks):
        grad = grad_grid[t].reshape(-1)
        first, last = t * n_rays // chunks, (t + 1) * n_rays // chunks
        rows = np.empty(BLOCK_RAYS, np.int64)
        start = np.empty((3, BLOCK_RAYS), np.float32)
        step = np.empty((3, BLOCK_RAYS), np.float32)
        length = np.empty(BLOCK_RAYS, np.float32)
        point = np.empty((3, BLOCK_RAYS), np.float32)  # grid coordinates, then fractions
        corner = np.empty(BLOCK_RAYS, np.int64)
        density = np.empty(BLOCK_RAYS, np.float32)
        colour = np.empty((3, BLOCK_RAYS), np.float32)
        mantissa = np.empty((4, BLOCK_RAYS), np.float32)
        exponent = np.empty((4, BLOCK_RAYS), np.int32)
        power = exponent.view(np.float32)
        samples = (point, corner, density, colour, mantissa, exponent)
        upstream = np.empty((3, BLOCK_RAYS), np.float32)  # d loss / d rgb
        total = np.empty(BLOCK_RAYS, np.float32)  # rgb · upstream
        done = np.empty(BLOCK_RAYS, np.float32)  # the samples' light so far · upstream
        transmit = np.empty(BLOCK_RAYS, np.float32)
        steps = np.empty(BLOCK_RAYS, np.int64)
        out = np.empty((4, BLOCK_RAYS), np.float32)  # d loss / d the sample's raw values
        for block in range(first, last, BLOCK_RAYS):
            for j in range(BLOCK_RAYS):
                r = min(block + j, last - 1)
                rows[j] = r
                inside = block + j < last
                for c in range(3):
                    upstream[c, j] = grad_rgb[r, c] if inside else _ZERO
                total[j] = rgb[r, 0] * upstream[0, j] + rgb[r, 1] * upstream[1, j]
                total[j] += rgb[r, 2] * upstream[2, j]
                done[j], transmit[j] = _ZERO, _ONE
                steps[j] = used[r] if inside else 0
                if not contract:
                    length[j] = _ray_steps(r, j, n, segments, where, start, step)
            for s in range(steps.max()):
                if contract:
                    for j in range(BLOCK_RAYS):
                        x, y, z, sample_length, _ = _point(segments, rows[j], s, n, offsets, where)
                        point[0, j], point[1, j], point[2, j] = x, y, z
                        length[j] = sample_length
                else:
                    for j in range(BLOCK_RAYS):
                        u = np.float32(s) + offsets[_offset_row(offsets, rows[j]), s]
                        for axis in range(3):
                            point[axis, j] = start[axis, j] + u * step[axis, j]
                _read_block(cells, samples, top, sx, sy, sz, shift)
                for j in range(BLOCK_RAYS):
                    x = density[j]
                    e = mantissa[0, j] * power[0, j]  # exp(-|x|)
                    out[0, j] = (_ONE if x >= _ZERO else e) / (_ONE + e)  # softplus' slope
                    sigma = max(x, _ZERO) + _log1p_unit(e)
                    mantissa[0, j], exponent[0, j] = _exp_parts(-sigma * length[j])
                for j in range(BLOCK_RAYS):
                    active = s < steps[j]
                    keep = mantissa[0, j] * power[0, j]
                    weight = transmit[j] * (_ONE - keep) if active else _ZERO
                    along = _ZERO
                    for c in range(3):
                        colour[c, j] = _ONE / (_ONE + mantissa[c + 1, j] * power[c + 1, j])
                        along += colour[c, j] * upstream[c, j]
                    done[j] += weight * along
                    d_sigma = length[j] * (transmit[j] * keep * along - (total[j] - done[j]))
                    out[0, j] = d_sigma * out[0, j] if active else _ZERO
                    for c in range(3):
                        out[c + 1, j] = (
                            weight * upstream[c, j] * colour[c, j] * (_ONE - colour[c, j])
                        )
                    transmit[j] = transmit[j] * keep if active else transmit[j]
                for j in range(BLOCK_RAYS):  # the scatter: scalar
                    if s < steps[j]:
                        _scatter(grad, corner[j], point, j, out, sx, sy, sz)
            for j in range(min(BLOCK_RAYS, last - block)):
                for c in range(3):
                    grad_background[t, c] += transmit[j] * upstream[c, j]
