"""Compiled scoring of candidate poses for render-and-compare (numba, CPU).

For each query and candidate camera, the reference surface points are projected into the
candidate, the blurred grey query image is sampled bilinearly where they land, and the
weighted ZNCC of the sampled values with the points' rendered values is returned: the score
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
    scores: np.ndarray,
) -> None:
    """points [B, P, 3], values [B, P], valid [B, P], rotations [B, M, 3, 3] (camera to
    world), positions [B, M, 3], intrinsics [B, 4], target [B, h, w] -> scores [B, M]."""
    n_queries, n_candidates = rotations.shape[0], rotations.shape[1]
    h, w = target.shape[1], target.shape[2]
    for job in numba.prange(n_queries * n_candidates):
        b = job // n_candidates
        m = job % n_candidates
        fx, fy, cx, cy = intrinsics[b, 0], intrinsics[b, 1], intrinsics[b, 2], intrinsics[b, 3]
        r = rotations[b, m]
        tx, ty, tz = positions[b, m, 0], positions[b, m, 1], positions[b, m, 2]
        total = sum_a = sum_b = sum_ab = sum_aa = sum_bb = 0.0
        reference = 0.0
        for p in range(points.shape[1]):
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
            sampled = (target[b, v0, u0] * (1 - fu) + target[b, v0, u0 + 1] * fu) * (1 - fv) + (
                target[b, v0 + 1, u0] * (1 - fu) + target[b, v0 + 1, u0 + 1] * fu
            ) * fv
            weight = valid[b, p]
            a = sampled
            c = values[b, p]
            total += weight
            sum_a += weight * a
            sum_b += weight * c
            sum_ab += weight * a * c
            sum_aa += weight * a * a
            sum_bb += weight * c * c
        if reference <= 0 or total < min_overlap * reference:
            scores[b, m] = NOT_SEEN_SCORE
            continue
        cov = sum_ab - sum_a * sum_b / total
        var = (sum_aa - sum_a * sum_a / total) * (sum_bb - sum_b * sum_b / total)
        scores[b, m] = cov / math.sqrt(max(var, 1e-12))


def compiled_zncc_scores(
    points: Tensor,
    values: Tensor,
    valid: Tensor,
    rotations: Tensor,
    positions: Tensor,
    intrinsics: Tensor,
    target: Tensor,
    min_overlap: float,
) -> Tensor:
    """Scores [B, M] of candidates (rotations [B, M, 3, 3], positions [B, M, 3]) against
    the blurred grey queries ``target`` [B, h, w] (see the module docstring)."""

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
        scores,
    )
    return torch.from_numpy(scores).to(points.device)
