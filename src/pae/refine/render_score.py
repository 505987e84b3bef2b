"""Compiled scoring of candidate poses for render-and-compare (numba, CPU).

For each query and candidate camera, the reference surface points are projected into the
candidate, the blurred grey query image is sampled bilinearly where they land, and the
weighted ZNCC of the sampled values with the points' rendered values is returned (optionally
trimmed of the points the rendering cannot explain): the score
:meth:`RenderCompareRefiner._score_projected` computes with tensor operations (tested equal),
in one pass per candidate instead of some twenty passes over every point.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from pae.compiled import jit

MIN_DEPTH_M = 0.05
"""Points nearer than this to a candidate camera (or behind it) are not seen."""
NOT_SEEN_SCORE = -2.0
"""The score of a candidate that sees too few of the reference points."""


@jit(nogil=True, fastmath=True)
def _fitted_moments(
    sampled: np.ndarray,
    seen: np.ndarray,
    values: np.ndarray,
    valid: np.ndarray,
    gain: float,
    offset: float,
    limit: float,
) -> tuple[float, float, float, float, float, float]:
    """Weighted sums (total, Σa, Σc, Σac, Σaa, Σcc) over the seen points [P] whose residual
    ``|a − gain·c − offset|`` is within ``limit`` (a: sampled query, c: rendered values)."""
    total = sum_a = sum_c = sum_ac = sum_aa = sum_cc = 0.0
    for p in range(sampled.shape[0]):
        if not seen[p]:
            continue
        a, c = sampled[p], values[p]
        if abs(a - gain * c - offset) > limit:
            continue
        weight = valid[p]
        total += weight
        sum_a += weight * a
        sum_c += weight * c
        sum_ac += weight * a * c
        sum_aa += weight * a * a
        sum_cc += weight * c * c
    return total, sum_a, sum_c, sum_ac, sum_aa, sum_cc


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
    world), positions [B, M, 3], intrinsics [B, 4], target [B, h, w] -> scores [B, M];
    trim_sigma > 0: ``trim_passes`` times, ZNCC again over the points whose residual after
    the previous pass's gain-and-bias fit is within trim_sigma residual standard deviations."""
    n_queries, n_candidates = rotations.shape[0], rotations.shape[1]
    n_points = points.shape[1]
    h, w = target.shape[1], target.shape[2]
    for job in numba.prange(n_queries * n_candidates):
        b = job // n_candidates
        m = job % n_candidates
        fx, fy, cx, cy = intrinsics[b, 0], intrinsics[b, 1], intrinsics[b, 2], intrinsics[b, 3]
        r = rotations[b, m]
        tx, ty, tz = positions[b, m, 0], positions[b, m, 1], positions[b, m, 2]
        reference = 0.0
        sampled = np.zeros(n_points, np.float32)
        seen = np.zeros(n_points, np.bool_)
        for p in range(n_points):
            if valid[b, p] <= 0:
                continue
            reference += valid[b, p]
            dx, dy, dz = points[b, p, 0] - tx, points[b, p, 1] - ty, points[b, p, 2] - tz
            z = r[0, 2] * dx + r[1, 2] * dy + r[2, 2] * dz
            if z <= MIN_DEPTH_M:
                continue
            u = fx * (r[0, 0] * dx + r[1, 0] * dy + r[2, 0] * dz) / z + cx
            v = fy * (r[0, 1] * dx + r[1, 1] * dy + r[2, 1] * dz) / z + cy
            if u < 0 or v < 0 or u > w - 1 or v > h - 1:
                continue
            u0 = min(int(u), w - 2)
            v0 = min(int(v), h - 2)
            fu, fv = u - u0, v - v0
            sampled[p] = (target[b, v0, u0] * (1 - fu) + target[b, v0, u0 + 1] * fu) * (1 - fv) + (
                target[b, v0 + 1, u0] * (1 - fu) + target[b, v0 + 1, u0 + 1] * fu
            ) * fv
            seen[p] = True
        total, sum_a, sum_b, sum_ab, sum_aa, sum_bb = _fitted_moments(
            sampled, seen, values[b], valid[b], 0.0, 0.0, np.inf
        )
        if reference <= 0 or total < min_overlap * reference:
            scores[b, m] = NOT_SEEN_SCORE
            continue
        for _ in range(trim_passes if trim_sigma > 0 else 0):
            cov = sum_ab - sum_a * sum_b / total
            var_a = sum_aa - sum_a * sum_a / total
            var_b = sum_bb - sum_b * sum_b / total
            gain = cov / max(var_b, 1e-12)
            offset = (sum_a - gain * sum_b) / total
            limit = trim_sigma * math.sqrt(max(var_a - gain * cov, 0.0) / total)
            total, sum_a, sum_b, sum_ab, sum_aa, sum_bb = _fitted_moments(
                sampled, seen, values[b], valid[b], gain, offset, limit
            )
            if total <= 0:
                break
        if total <= 0:
            scores[b, m] = 0.0
            continue
        cov = sum_ab - sum_a * sum_b / total
        var_a = sum_aa - sum_a * sum_a / total
        var_b = sum_bb - sum_b * sum_b / total
        scores[b, m] = cov / math.sqrt(max(var_a * var_b, 1e-12))


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
    the blurred grey queries ``target`` [B, h, w] (see the module docstring; ``trim_sigma``
    and ``trim_passes`` as :func:`pae.refine.render_compare.trimmed_zncc`)."""

    def array(t: Tensor) -> np.ndarray:
        return t.detach().to("cpu", torch.float32).contiguous().numpy()

    scores = np.empty(rotations.shape[:2], np.float32)
    _zncc_scores(
        array(points),
        array(values),
        array(valid),
        array(rotations),
        array(positions),
        array(intrinsics),
        array(target),
        float(min_overlap),
        float(trim_sigma),
        int(trim_passes),
        scores,
    )
    return torch.from_numpy(scores).to(points.device)
