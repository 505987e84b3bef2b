"""The polish of render-and-compare compiled (numba, CPU): one loop per query runs
:func:`pae.render_compare.kernels.reference.polish_tensor`'s Levenberg–Marquardt steps
(tested equal), with its work buffers allocated once per query, never per hypothesis, step
or point."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch
from torch import Tensor

from pae.core.compiled import jit
from pae.render_compare.kernels.numba_score import (
    add_moments,
    as_array,
    bilinear,
    project_and_sample,
    project_point,
    sampled_score,
)
from pae.render_compare.kernels.reference import (
    DAMPING_DOWN,
    DAMPING_RANGE,
    DAMPING_UP,
    N_PARAMS,
    NOT_SEEN_SCORE,
    PolishProblem,
    PolishSettings,
    image_gradients,
)


class _Query(NamedTuple):
    """One query's inputs to the polish: surface points [P, 3] (world), their rendered values
    and weights ``valid`` [P], intrinsics [4], the band-passed grey target [h, w] and its
    gradients along u and v [h, w] (px⁻¹)."""

    points: np.ndarray
    values: np.ndarray
    valid: np.ndarray
    intrinsics: np.ndarray
    target: np.ndarray
    grad_u: np.ndarray
    grad_v: np.ndarray


class _Workspace(NamedTuple):
    """A query's work space, reused by each of its hypotheses: ``work`` [P, 6] (per seen
    point its sample, the gradient along u and v, the camera-frame point), ``seen`` [P],
    ``system`` [8, 8], ``rhs`` and ``step`` [8], ``moved_rotation`` and ``turn`` [3, 3],
    ``moved_position`` [3]."""

    work: np.ndarray
    seen: np.ndarray
    system: np.ndarray
    rhs: np.ndarray
    step: np.ndarray
    moved_rotation: np.ndarray
    moved_position: np.ndarray
    turn: np.ndarray


@jit(nogil=True, fastmath=True)
def _cholesky_solve(matrix: np.ndarray, rhs: np.ndarray, out: np.ndarray) -> bool:
    """Solve matrix [n, n] (symmetric positive definite; overwritten by its factor) · out
    = rhs [n]; False where a pivot is not positive."""
    n = matrix.shape[0]
    for j in range(n):
        pivot = matrix[j, j]
        for k in range(j):
            pivot -= matrix[j, k] * matrix[j, k]
        if not pivot > 0:
            return False
        matrix[j, j] = math.sqrt(pivot)
        for i in range(j + 1, n):
            value = matrix[i, j]
            for k in range(j):
                value -= matrix[i, k] * matrix[j, k]
            matrix[i, j] = value / matrix[j, j]
    for i in range(n):
        value = rhs[i]
        for k in range(i):
            value -= matrix[i, k] * out[k]
        out[i] = value / matrix[i, i]
    for i in range(n - 1, -1, -1):
        value = out[i]
        for k in range(i + 1, n):
            value -= matrix[k, i] * out[k]
        out[i] = value / matrix[i, i]
    return True


@jit(nogil=True, fastmath=True)
def _rotate_by(rotation: np.ndarray, omega: np.ndarray, turn: np.ndarray, out: np.ndarray) -> None:
    """out [3, 3] = rotation [3, 3] · exp([ω]×) for ω = omega [3] (Rodrigues, as
    :func:`rotation_vector_to_matrix`); turn [3, 3]: work space."""
    x, y, z = omega[0], omega[1], omega[2]
    square = x * x + y * y + z * z
    angle = math.sqrt(square)
    if angle < 1e-9:
        first, second = 1.0, 0.5
    else:
        first, second = math.sin(angle) / angle, (1 - math.cos(angle)) / square
    turn[0, 0] = 1 + second * (x * x - square)
    turn[1, 1] = 1 + second * (y * y - square)
    turn[2, 2] = 1 + second * (z * z - square)
    turn[0, 1] = -first * z + second * x * y
    turn[1, 0] = first * z + second * x * y
    turn[0, 2] = first * y + second * x * z
    turn[2, 0] = -first * y + second * x * z
    turn[1, 2] = -first * x + second * y * z
    turn[2, 1] = first * x + second * y * z
    for i in range(3):
        for j in range(3):
            out[i, j] = (
                rotation[i, 0] * turn[0, j]
                + rotation[i, 1] * turn[1, j]
                + rotation[i, 2] * turn[2, j]
            )


@jit(nogil=True, fastmath=True)
def _polish_one(
    query: _Query,
    rotation: np.ndarray,
    position: np.ndarray,
    score: float,
    settings: PolishSettings,
    space: _Workspace,
) -> float:
    """The steps of :func:`polish_tensor` for one hypothesis of ``query``: rotation [3, 3]
    and position [3] updated in place; returns its score."""
    points, values, valid, intrinsics, target, grad_u, grad_v = query
    iterations, damping, min_overlap, trim_sigma, trim_passes = settings
    work, seen, system, rhs, step, moved_rotation, moved_position, turn = space
    n_points = points.shape[0]
    h, w = target.shape
    focal = (intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3])
    fx, fy = focal[0], focal[1]
    lam = damping
    sampled = work[:, 0]
    for _ in range(iterations):
        r = rotation
        origin = (position[0], position[1], position[2])
        moments = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        for p in range(n_points):
            seen[p] = False
            if valid[p] <= 0:
                continue
            inside, x, y, z, u, v = project_point(points, p, r, origin, focal, h, w)
            if not inside:
                continue
            seen[p] = True
            a = bilinear(target, u, v)
            work[p, 0] = a
            work[p, 1] = bilinear(grad_u, u, v)
            work[p, 2] = bilinear(grad_v, u, v)
            work[p, 3], work[p, 4], work[p, 5] = x, y, z
            moments = add_moments(moments, valid[p], a, values[p])
        total, sum_a, sum_c, sum_ac, sum_aa, _ = moments
        if total <= 0 or score <= NOT_SEEN_SCORE:
            break
        mean_a, mean_c = sum_a / total, sum_c / total
        cov = sum_ac - total * mean_a * mean_c
        var_a = sum_aa - total * mean_a * mean_a
        alpha = cov / max(var_a, 1e-12)
        beta = mean_c - alpha * mean_a
        system[:, :] = 0.0
        rhs[:] = 0.0
        for p in range(n_points):
            if not seen[p]:
                continue
            a, g_u, g_v = work[p, 0], work[p, 1], work[p, 2]
            x, y, z = work[p, 3], work[p, 4], work[p, 5]
            e0 = g_u * fx / z
            e1 = g_v * fy / z
            e2 = -(g_u * fx * x + g_v * fy * y) / (z * z)
            step[0] = -alpha * (r[0, 0] * e0 + r[0, 1] * e1 + r[0, 2] * e2)
            step[1] = -alpha * (r[1, 0] * e0 + r[1, 1] * e1 + r[1, 2] * e2)
            step[2] = -alpha * (r[2, 0] * e0 + r[2, 1] * e1 + r[2, 2] * e2)
            step[3] = alpha * (e1 * z - e2 * y)
            step[4] = alpha * (e2 * x - e0 * z)
            step[5] = alpha * (e0 * y - e1 * x)
            step[6] = a
            step[7] = 1.0
            weight = valid[p]
            residual = weight * (alpha * a + beta - values[p])
            for i in range(N_PARAMS):
                weighted = weight * step[i]
                rhs[i] += step[i] * residual
                for j in range(i + 1):
                    system[i, j] += weighted * step[j]
        for i in range(N_PARAMS):
            for j in range(i):
                system[j, i] = system[i, j]
        for i in range(N_PARAMS):
            system[i, i] += lam * system[i, i] + 1e-12
        for i in range(N_PARAMS):
            rhs[i] = -rhs[i]
        solved = _cholesky_solve(system, rhs, step)
        for i in range(6):
            solved = solved and math.isfinite(step[i])
        if solved:
            for i in range(3):
                moved_position[i] = position[i] + step[i]
            _rotate_by(rotation, step[3:6], turn, moved_rotation)
            reference = project_and_sample(
                points, valid, moved_rotation, moved_position, intrinsics, target, sampled, seen
            )
            moved = sampled_score(
                sampled, seen, values, valid, reference, min_overlap, trim_sigma, trim_passes
            )
            solved = moved > score
        if solved:
            rotation[:, :] = moved_rotation
            position[:] = moved_position
            score = moved
            lam = max(lam * DAMPING_DOWN, DAMPING_RANGE[0])
        else:
            lam = min(lam * DAMPING_UP, DAMPING_RANGE[1])
    return score


@jit(parallel=True, nogil=True, fastmath=True)
def _polish(
    points: np.ndarray,
    values: np.ndarray,
    valid: np.ndarray,
    rotations: np.ndarray,
    positions: np.ndarray,
    scores: np.ndarray,
    intrinsics: np.ndarray,
    target: np.ndarray,
    grad_u: np.ndarray,
    grad_v: np.ndarray,
    settings: PolishSettings,
) -> None:
    """:func:`_polish_one` on every hypothesis of every query, in place: rotations [B, K, 3,
    3], positions [B, K, 3], scores [B, K]; one query per task, its work space made once."""
    n_queries, n_hypotheses = scores.shape
    n_points = points.shape[1]
    for b in numba.prange(n_queries):
        query = _Query(
            points[b], values[b], valid[b], intrinsics[b], target[b], grad_u[b], grad_v[b]
        )
        space = _Workspace(
            np.empty((n_points, 6), np.float64),
            np.empty(n_points, np.bool_),
            np.empty((N_PARAMS, N_PARAMS), np.float64),
            np.empty(N_PARAMS, np.float64),
            np.empty(N_PARAMS, np.float64),
            np.empty((3, 3), np.float64),
            np.empty(3, np.float64),
            np.empty((3, 3), np.float64),
        )
        rotation = np.empty((3, 3), np.float64)
        position = np.empty(3, np.float64)
        for k in range(n_hypotheses):
            rotation[:, :] = rotations[b, k]
            position[:] = positions[b, k]
            scores[b, k] = _polish_one(query, rotation, position, scores[b, k], settings, space)
            rotations[b, k] = rotation
            positions[b, k] = position


def polish_compiled(
    problem: PolishProblem, settings: PolishSettings
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`pae.render_compare.kernels.reference.polish_tensor`'s steps compiled, on CPU
    (same arguments and results)."""
    grad_u, grad_v = image_gradients(problem.target)
    rotation = as_array(problem.rotations).copy()
    position = as_array(problem.positions).copy()
    score = as_array(problem.scores).copy()
    _polish(
        as_array(problem.points),
        as_array(problem.values),
        as_array(problem.valid),
        rotation,
        position,
        score,
        as_array(problem.intrinsics),
        as_array(problem.target),
        as_array(grad_u),
        as_array(grad_v),
        PolishSettings(
            int(settings.iterations),
            float(settings.damping),
            float(settings.min_overlap),
            float(settings.trim_sigma),
            int(settings.trim_passes),
        ),
    )
    device = problem.points.device
    return (
        torch.from_numpy(rotation).to(device),
        torch.from_numpy(position).to(device),
        torch.from_numpy(score).to(device),
    )
