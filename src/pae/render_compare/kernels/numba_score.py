"""Compiled scoring of candidate poses for render-and-compare (numba, CPU).

For each query and candidate camera, the reference surface points are projected into the
candidate, the band-passed grey query image is sampled bilinearly where they land, and the
weighted ZNCC of the sampled values with the points' rendered values is returned (optionally
trimmed of the points the rendering cannot explain): the score
:meth:`RenderCompareRefiner._score_projected` and
:func:`pae.render_compare.kernels.reference.score_tensor` compute with tensor operations
(tested equal),
in one pass per candidate instead of some twenty passes over every point.

The per-point helpers (:func:`project`, :func:`sample_into`, :func:`sampled_score`) are
shared with the compiled polish (:mod:`pae.render_compare.kernels.numba_polish`). They keep
a candidate's points in a ``view`` [VIEW_ROWS, P] of float32 rows (structure of arrays) and
run each step as its own branch-free loop over the points: the projection and the moments run
in SIMD lanes, only the bilinear reads of the image stay scalar. Work buffers are allocated
once per query, never per candidate or per point.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from pae.core.compiled import jit
from pae.render_compare.kernels.reference import MIN_DEPTH_M, NOT_SEEN_SCORE

FLOPS_PROJECT = 27
"""Floating-point operations per point of :func:`project`: the offset 3, the rotation 15,
the inverse depth 1, the pixel 6, its fractions in the bilinear cell 2."""
FLOPS_SAMPLE = 11
"""Per point of :func:`sample_into`: the two weights' complements 2, the bilinear blend 9."""
FLOPS_MOMENTS = 17
"""Per point of :func:`fitted_moments`: the residual tested against the limit 3, the six
weighted sums 14."""
FLOPS_PER_POINT_SCORE = FLOPS_PROJECT + FLOPS_SAMPLE + FLOPS_MOMENTS
"""Per reference point and candidate of the score (55): what
``bench/render_compare/mflop_per_query`` adds up."""


VIEW_ROWS = 7
"""Rows of a candidate's ``view`` of the points: camera-frame x, y, z (m), the weight (the
point's ``valid`` where it is seen, deeper than ``MIN_DEPTH_M`` and inside the image, else
0), the fractions along u and v of its pixel inside the bilinear cell (clamped inside the
image, so that every point can be sampled) and the image's sample there. Beside it,
``corner`` [P] (uint32): the flat index of each cell's top-left pixel."""
X, Y, Z, WEIGHT, FRACTION_U, FRACTION_V, SAMPLE = range(VIEW_ROWS)

_ZERO = np.float32(0.0)
_ONE = np.float32(1.0)
_MIN_DEPTH = np.float32(MIN_DEPTH_M)


@jit(nogil=True, fastmath=True)
def project(
    points: np.ndarray,
    valid: np.ndarray,
    rotation: np.ndarray,
    position: np.ndarray,
    intrinsics: np.ndarray,
    h: int,
    w: int,
    view: np.ndarray,
    corner: np.ndarray,
) -> float:
    """Project points [3, P] (world, one row per axis) into the camera ``rotation`` [3, 3]
    (camera to world), ``position`` [3] with ``intrinsics`` [4] (fx, fy, cx, cy) for an image
    [h, w]: rows X to FRACTION_V of ``view`` [VIEW_ROWS, P] and ``corner`` [P]. Returns the
    valid points' total weight (the overlap's denominator)."""
    r = rotation
    r00, r01, r02 = np.float32(r[0, 0]), np.float32(r[0, 1]), np.float32(r[0, 2])
    r10, r11, r12 = np.float32(r[1, 0]), np.float32(r[1, 1]), np.float32(r[1, 2])
    r20, r21, r22 = np.float32(r[2, 0]), np.float32(r[2, 1]), np.float32(r[2, 2])
    px, py, pz = np.float32(position[0]), np.float32(position[1]), np.float32(position[2])
    fx, fy = np.float32(intrinsics[0]), np.float32(intrinsics[1])
    cx, cy = np.float32(intrinsics[2]), np.float32(intrinsics[3])
    u_max, v_max = np.float32(w - 1), np.float32(h - 1)
    last_u, last_v, width = np.int32(w - 2), np.int32(h - 2), np.int32(w)
    reference = 0.0
    for p in range(points.shape[1]):
        dx, dy, dz = points[0, p] - px, points[1, p] - py, points[2, p] - pz
        x = r00 * dx + r10 * dy + r20 * dz
        y = r01 * dx + r11 * dy + r21 * dz
        z = r02 * dx + r12 * dy + r22 * dz
        inverse = _ONE / max(z, _MIN_DEPTH)
        u = fx * x * inverse + cx
        v = fy * y * inverse + cy
        seen = (z > _MIN_DEPTH) & (u >= _ZERO) & (u <= u_max) & (v >= _ZERO) & (v <= v_max)
        weight = max(valid[p], _ZERO)
        view[X, p], view[Y, p], view[Z, p] = x, y, z
        view[WEIGHT, p] = weight if seen else _ZERO
        u, v = min(max(u, _ZERO), u_max), min(max(v, _ZERO), v_max)
        u0, v0 = min(np.int32(u), last_u), min(np.int32(v), last_v)
        view[FRACTION_U, p] = u - np.float32(u0)
        view[FRACTION_V, p] = v - np.float32(v0)
        corner[p] = np.uint32(v0 * width + u0)
        reference += weight
    return reference


@jit(nogil=True, fastmath=True)
def sample_into(image: np.ndarray, view: np.ndarray, corner: np.ndarray, row: int) -> None:
    """``view[row]`` = image [h, w] (C-contiguous) at every point of ``view`` (its cells
    ``corner`` and fractions), bilinearly; unsigned indices, so no wrap-around test."""
    pixels = image.reshape(-1)
    right, down = np.uint32(1), np.uint32(image.shape[1])
    for p in range(view.shape[1]):
        top_left = corner[p]
        below = top_left + down
        fu, fv = view[FRACTION_U, p], view[FRACTION_V, p]
        top = pixels[top_left] * (_ONE - fu) + pixels[top_left + right] * fu
        bottom = pixels[below] * (_ONE - fu) + pixels[below + right] * fu
        view[row, p] = top * (_ONE - fv) + bottom * fv


Moments = tuple[float, float, float, float, float, float]
"""Weighted sums (total, Σa, Σc, Σac, Σaa, Σcc) of samples a and values c."""


@jit(nogil=True, fastmath=True)
def fitted_moments(
    view: np.ndarray, values: np.ndarray, gain: float, offset: float, limit: float
) -> Moments:
    """The moments over the seen points of ``view`` (weights and samples a) with rendered
    values [P] c, over the points whose residual ``|a − gain·c − offset|`` is within
    ``limit``."""
    gain32, offset32, limit32 = np.float32(gain), np.float32(offset), np.float32(limit)
    total = sum_a = sum_c = sum_ac = sum_aa = sum_cc = 0.0
    for p in range(view.shape[1]):
        a, c = view[SAMPLE, p], values[p]
        kept = abs(a - gain32 * c - offset32) <= limit32
        weight = view[WEIGHT, p] if kept else _ZERO
        total += weight
        sum_a += weight * a
        sum_c += weight * c
        sum_ac += weight * a * c
        sum_aa += weight * a * a
        sum_cc += weight * c * c
    return total, sum_a, sum_c, sum_ac, sum_aa, sum_cc


@jit(nogil=True, fastmath=True)
def sampled_score(
    view: np.ndarray,
    values: np.ndarray,
    reference: float,
    min_overlap: float,
    trim_sigma: float,
    trim_passes: int,
) -> float:
    """The (trimmed) weighted ZNCC of the seen samples of ``view`` with the rendered values
    [P]; ``NOT_SEEN_SCORE`` where the seen weight is below ``min_overlap`` × ``reference``;
    trim_sigma > 0: ``trim_passes`` times, ZNCC again over the points whose residual after
    the previous pass's gain-and-bias fit is within trim_sigma residual standard deviations."""
    total, sum_a, sum_b, sum_ab, sum_aa, sum_bb = fitted_moments(view, values, 0.0, 0.0, np.inf)
    if reference <= 0 or total < min_overlap * reference:
        return NOT_SEEN_SCORE
    for _ in range(trim_passes if trim_sigma > 0 else 0):
        cov = sum_ab - sum_a * sum_b / total
        var_a = sum_aa - sum_a * sum_a / total
        var_b = sum_bb - sum_b * sum_b / total
        gain = cov / max(var_b, 1e-12)
        offset = (sum_a - gain * sum_b) / total
        limit = trim_sigma * math.sqrt(max(var_a - gain * cov, 0.0) / total)
        total, sum_a, sum_b, sum_ab, sum_aa, sum_bb = fitted_moments(
            view, values, gain, offset, limit
        )
        if total <= 0:
            return 0.0
    cov = sum_ab - sum_a * sum_b / total
    var_a = sum_aa - sum_a * sum_a / total
    var_b = sum_bb - sum_b * sum_b / total
    return cov / math.sqrt(max(var_a * var_b, 1e-12))


@jit(nogil=True, fastmath=True)
def rotation_into(quaternion: np.ndarray, rotation: np.ndarray) -> None:
    """rotation [3, 3] = the matrix of ``quaternion`` [4] (w first; normalised first), as
    :func:`pae.core.geometry.quaternion_to_matrix`."""
    norm = math.sqrt(
        quaternion[0] ** 2 + quaternion[1] ** 2 + quaternion[2] ** 2 + quaternion[3] ** 2
    )
    scale = 1.0 / max(norm, 1e-12)
    w, x, y, z = (
        quaternion[0] * scale,
        quaternion[1] * scale,
        quaternion[2] * scale,
        quaternion[3] * scale,
    )
    rotation[0, 0] = 1 - 2 * (y * y + z * z)
    rotation[0, 1] = 2 * (x * y - w * z)
    rotation[0, 2] = 2 * (x * z + w * y)
    rotation[1, 0] = 2 * (x * y + w * z)
    rotation[1, 1] = 1 - 2 * (x * x + z * z)
    rotation[1, 2] = 2 * (y * z - w * x)
    rotation[2, 0] = 2 * (x * z - w * y)
    rotation[2, 1] = 2 * (y * z + w * x)
    rotation[2, 2] = 1 - 2 * (x * x + y * y)


@jit(parallel=True, nogil=True, fastmath=True)
def _zncc_scores(
    points: np.ndarray,
    values: np.ndarray,
    valid: np.ndarray,
    poses: np.ndarray,
    intrinsics: np.ndarray,
    target: np.ndarray,
    min_overlap: float,
    trim_sigma: float,
    trim_passes: int,
    scores: np.ndarray,
) -> None:
    """points [B, P, 3], values [B, P], valid [B, P], poses [B, M, 7] (camera to world:
    position, quaternion), intrinsics [B, 4], target [B, h, w] -> scores [B, M]. Each
    query's points are laid out one row per axis once, for all its candidates."""
    n_queries, n_candidates = poses.shape[0], poses.shape[1]
    n_points, h, w = points.shape[1], target.shape[1], target.shape[2]
    for b in numba.prange(n_queries):
        rows = np.ascontiguousarray(points[b].T)
        view = np.empty((VIEW_ROWS, n_points), np.float32)
        corner = np.empty(n_points, np.uint32)
        rotation = np.empty((3, 3), np.float32)
        for m in range(n_candidates):
            rotation_into(poses[b, m, 3:], rotation)
            reference = project(
                rows, valid[b], rotation, poses[b, m, :3], intrinsics[b], h, w, view, corner
            )
            sample_into(target[b], view, corner, SAMPLE)
            scores[b, m] = sampled_score(
                view, values[b], reference, min_overlap, trim_sigma, trim_passes
            )


def as_array(t: Tensor) -> np.ndarray:
    """A contiguous float32 CPU copy (or view) of ``t`` as a numpy array."""
    return t.detach().to("cpu", torch.float32).contiguous().numpy()


def compiled_zncc_scores(
    points: Tensor,
    values: Tensor,
    valid: Tensor,
    poses: Tensor,
    intrinsics: Tensor,
    target: Tensor,
    min_overlap: float,
    trim_sigma: float = 0.0,
    trim_passes: int = 2,
) -> Tensor:
    """Scores [B, M] of candidate poses [B, M, 7] (position, quaternion; camera to world)
    against the band-passed grey queries ``target`` [B, h, w] (see the module docstring;
    ``trim_sigma`` and ``trim_passes`` as :func:`pae.render_compare.images.trimmed_zncc`)."""
    scores = np.empty(poses.shape[:2], np.float32)
    _zncc_scores(
        as_array(points),
        as_array(values),
        as_array(valid),
        as_array(poses),
        as_array(intrinsics),
        as_array(target),
        float(min_overlap),
        float(trim_sigma),
        int(trim_passes),
        scores,
    )
    return torch.from_numpy(scores).to(points.device)
