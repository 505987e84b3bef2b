"""Compiled scoring of candidate poses for render-and-compare (numba, CPU).

For each query and candidate camera, the reference surface points are projected into the
candidate, the band-passed grey query image is sampled bilinearly where they land, and the
weighted ZNCC of the sampled values with the points' rendered values is returned (optionally
trimmed of the points the rendering cannot explain): the score
:meth:`RenderCompareRefiner._score_projected` and
:func:`pae.render_compare.kernels.reference.score_tensor` compute with tensor operations
(tested equal),
in one pass per candidate instead of some twenty passes over every point.

The per-point helpers (:func:`project_point`, :func:`project_and_sample`,
:func:`sampled_score`) are shared with the compiled polish
(:mod:`pae.render_compare.kernels.numba_polish`).
Work buffers are allocated once per query, never per candidate or per point.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from pae.core.compiled import jit
from pae.render_compare.kernels.reference import MIN_DEPTH_M, NOT_SEEN_SCORE

FLOPS_PER_POINT_SCORE = 40
"""Floating-point operations per reference point and candidate of the score (projection 21,
bilinear sample 11, moments 8), counted from :func:`project_and_sample` and
:func:`_fitted_moments`: what ``bench/render_compare/mflop_per_query`` adds up."""


@jit(nogil=True, fastmath=True, inline="always")
def bilinear(image: np.ndarray, u: float, v: float) -> float:
    """image [h, w] at (u, v) px inside [0, w-1] × [0, h-1], bilinearly."""
    h, w = image.shape
    u0 = min(int(u), w - 2)
    v0 = min(int(v), h - 2)
    fu, fv = u - u0, v - v0
    top = image[v0, u0] * (1 - fu) + image[v0, u0 + 1] * fu
    bottom = image[v0 + 1, u0] * (1 - fu) + image[v0 + 1, u0 + 1] * fu
    return top * (1 - fv) + bottom * fv


@jit(nogil=True, fastmath=True, inline="always")
def project_point(
    points: np.ndarray,
    p: int,
    rotation: np.ndarray,
    position: tuple[float, float, float],
    focal: tuple[float, float, float, float],
    h: int,
    w: int,
) -> tuple[bool, float, float, float, float, float]:
    """Point ``p`` of points [P, 3] (world) seen by the camera ``rotation`` [3, 3] (camera
    to world) at ``position`` (x, y, z) with intrinsics ``focal`` (fx, fy, cx, cy) -> (seen,
    x, y, z, u, v): its camera-frame coordinates (m), its pixel (u, v mean nothing unless
    deeper than ``MIN_DEPTH_M``) and whether it lies deeper than that and inside an image
    [h, w]. Scalars, not arrays, so that a loop over the points keeps them in registers."""
    r = rotation
    dx = points[p, 0] - position[0]
    dy = points[p, 1] - position[1]
    dz = points[p, 2] - position[2]
    x = r[0, 0] * dx + r[1, 0] * dy + r[2, 0] * dz
    y = r[0, 1] * dx + r[1, 1] * dy + r[2, 1] * dz
    z = r[0, 2] * dx + r[1, 2] * dy + r[2, 2] * dz
    u = v = z
    seen = z > MIN_DEPTH_M
    if seen:
        u = focal[0] * x / z + focal[2]
        v = focal[1] * y / z + focal[3]
        seen = 0 <= u <= w - 1 and 0 <= v <= h - 1
    return seen, x, y, z, u, v


@jit(nogil=True, fastmath=True)
def project_and_sample(
    points: np.ndarray,
    valid: np.ndarray,
    rotation: np.ndarray,
    position: np.ndarray,
    intrinsics: np.ndarray,
    target: np.ndarray,
    sampled: np.ndarray,
    seen: np.ndarray,
) -> float:
    """Project points [P, 3] (world) into the camera ``rotation`` [3, 3] (camera to world),
    ``position`` [3] with ``intrinsics`` [4]; where a valid point lands inside ``target``
    [h, w] (and deeper than ``MIN_DEPTH_M``) write its bilinear sample to ``sampled`` [P] and
    set ``seen`` [P]. Returns the valid points' total weight (the overlap's denominator)."""
    h, w = target.shape
    origin = (position[0], position[1], position[2])
    focal = (intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3])
    reference = 0.0
    for p in range(points.shape[0]):
        seen[p] = False
        if valid[p] <= 0:
            continue
        reference += valid[p]
        inside, _, _, _, u, v = project_point(points, p, rotation, origin, focal, h, w)
        if inside:
            sampled[p] = bilinear(target, u, v)
            seen[p] = True
    return reference


Moments = tuple[float, float, float, float, float, float]
"""Weighted sums (total, Σa, Σc, Σac, Σaa, Σcc) of samples a and values c."""


@jit(nogil=True, fastmath=True, inline="always")
def add_moments(moments: Moments, weight: float, a: float, c: float) -> Moments:
    """``moments`` with the sample ``a`` and value ``c`` of ``weight`` added."""
    total, sum_a, sum_c, sum_ac, sum_aa, sum_cc = moments
    return (
        total + weight,
        sum_a + weight * a,
        sum_c + weight * c,
        sum_ac + weight * a * c,
        sum_aa + weight * a * a,
        sum_cc + weight * c * c,
    )


@jit(nogil=True, fastmath=True)
def _fitted_moments(
    sampled: np.ndarray,
    seen: np.ndarray,
    values: np.ndarray,
    valid: np.ndarray,
    gain: float,
    offset: float,
    limit: float,
) -> Moments:
    """The moments over the seen points [P] whose residual ``|a − gain·c − offset|`` is
    within ``limit`` (a: sampled query, c: rendered values)."""
    moments = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for p in range(sampled.shape[0]):
        if not seen[p]:
            continue
        a, c = sampled[p], values[p]
        if abs(a - gain * c - offset) <= limit:
            moments = add_moments(moments, valid[p], a, c)
    return moments


@jit(nogil=True, fastmath=True)
def sampled_score(
    sampled: np.ndarray,
    seen: np.ndarray,
    values: np.ndarray,
    valid: np.ndarray,
    reference: float,
    min_overlap: float,
    trim_sigma: float,
    trim_passes: int,
) -> float:
    """The (trimmed) weighted ZNCC of the seen samples [P] with the rendered values [P];
    ``NOT_SEEN_SCORE`` where the seen weight is below ``min_overlap`` × ``reference``;
    trim_sigma > 0: ``trim_passes`` times, ZNCC again over the points whose residual after
    the previous pass's gain-and-bias fit is within trim_sigma residual standard deviations."""
    total, sum_a, sum_b, sum_ab, sum_aa, sum_bb = _fitted_moments(
        sampled, seen, values, valid, 0.0, 0.0, np.inf
    )
    if reference <= 0 or total < min_overlap * reference:
        return NOT_SEEN_SCORE
    for _ in range(trim_passes if trim_sigma > 0 else 0):
        cov = sum_ab - sum_a * sum_b / total
        var_a = sum_aa - sum_a * sum_a / total
        var_b = sum_bb - sum_b * sum_b / total
        gain = cov / max(var_b, 1e-12)
        offset = (sum_a - gain * sum_b) / total
        limit = trim_sigma * math.sqrt(max(var_a - gain * cov, 0.0) / total)
        total, sum_a, sum_b, sum_ab, sum_aa, sum_bb = _fitted_moments(
            sampled, seen, values, valid, gain, offset, limit
        )
        if total <= 0:
            return 0.0
    cov = sum_ab - sum_a * sum_b / total
    var_a = sum_aa - sum_a * sum_a / total
    var_b = sum_bb - sum_b * sum_b / total
    return cov / math.sqrt(max(var_a * var_b, 1e-12))


@jit(parallel=True, nogil=True, fastmath=True)
def _zncc_scores(
    points: np.ndarray,
    values: np.ndarray,
    valid: np.ndarray,
    rotations: np.ndarray,
    positions: np.ndarray,
    intrinsics: np.ndarray,
    target: np.ndarray,
    min_overlap: float,
    trim_sigma: float,
    trim_passes: int,
    scores: np.ndarray,
) -> None:
    """points [B, P, 3], values [B, P], valid [B, P], rotations [B, M, 3, 3] (camera to
    world), positions [B, M, 3], intrinsics [B, 4], target [B, h, w] -> scores [B, M]."""
    n_queries, n_candidates = rotations.shape[0], rotations.shape[1]
    for b in numba.prange(n_queries):
        sampled = np.empty(points.shape[1], np.float64)
        seen = np.empty(points.shape[1], np.bool_)
        for m in range(n_candidates):
            reference = project_and_sample(
                points[b],
                valid[b],
                rotations[b, m],
                positions[b, m],
                intrinsics[b],
                target[b],
                sampled,
                seen,
            )
            scores[b, m] = sampled_score(
                sampled,
                seen,
                values[b],
                valid[b],
                reference,
                min_overlap,
                trim_sigma,
                trim_passes,
            )


def as_array(t: Tensor) -> np.ndarray:
    """A contiguous float32 CPU copy (or view) of ``t`` as a numpy array."""
    return t.detach().to("cpu", torch.float32).contiguous().numpy()


def compiled_zncc_scores(
    points: Tensor,
    values: Tensor,
    valid: Tensor,
    rotations: Tensor,
    positions: Tensor,
    intrinsics: Tensor,
    target: Tensor,
    min_overlap: float,
    trim_sigma: float = 0.0,
    trim_passes: int = 2,
) -> Tensor:
    """Scores [B, M] of candidates (rotations [B, M, 3, 3], positions [B, M, 3]) against
    the band-passed grey queries ``target`` [B, h, w] (see the module docstring;
    ``trim_sigma`` and ``trim_passes`` as :func:`pae.render_compare.images.trimmed_zncc`)."""
    scores = np.empty(rotations.shape[:2], np.float32)
    _zncc_scores(
        as_array(points),
        as_array(values),
        as_array(valid),
        as_array(rotations),
        as_array(positions),
        as_array(intrinsics),
        as_array(target),
        float(min_overlap),
        float(trim_sigma),
        int(trim_passes),
        scores,
    )
    return torch.from_numpy(scores).to(points.device)
