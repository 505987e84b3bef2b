"""The polish of render-and-compare compiled (numba, CPU): one loop per query runs
:func:`pae.render_compare.kernels.reference.polish_tensor`'s Levenberg–Marquardt steps
(tested equal), with its work buffers allocated once per query, never per hypothesis, step
or point. Each step is a few branch-free loops over the points in float32 rows (structure of
arrays): the projection, the Jacobian and the normal equations' sums run in SIMD lanes, only
the bilinear reads of the images stay scalar."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch
from torch import Tensor

from pae.core.compiled import jit
from pae.render_compare.kernels.numba_score import (
    FRACTION_U,
    FRACTION_V,
    SAMPLE,
    VIEW_ROWS,
    WEIGHT,
    X,
    Y,
    Z,
    as_array,
    fitted_moments,
    project,
    sample_into,
    sampled_score,
)
from pae.render_compare.kernels.reference import (
    DAMPING_DOWN,
    DAMPING_RANGE,
    DAMPING_UP,
    MIN_DEPTH_M,
    N_PARAMS,
    NOT_SEEN_SCORE,
    PolishProblem,
    PolishSettings,
)


class _Query(NamedTuple):
    """One query's inputs to the polish: surface points [3, P] (world), their rendered values
    and weights ``valid`` [P], intrinsics [4], the band-passed grey target [h, w] and, per
    pixel, the target with its gradients along u and v (px⁻¹) ``with_gradients`` [h, w, 3]."""

    points: np.ndarray
    values: np.ndarray
    valid: np.ndarray
    intrinsics: np.ndarray
    target: np.ndarray
    with_gradients: np.ndarray


GRAD_U, GRAD_V = VIEW_ROWS, VIEW_ROWS + 1
"""Rows of the polish's view that hold the image's gradients at the points."""


class _Workspace(NamedTuple):
    """A query's work space, reused by each of its hypotheses: ``view`` [VIEW_ROWS + 2, P]
    (:data:`pae.render_compare.kernels.numba_score.VIEW_ROWS`, then the gradients along u and
    v), ``jacobian`` [8, P] and ``residual`` [P] (float32), ``system`` [8, 8], ``rhs`` and
    ``step`` [8], ``moved_rotation`` and ``turn`` [3, 3], ``moved_position`` [3]."""

    view: np.ndarray
    corner: np.ndarray
    jacobian: np.ndarray
    residual: np.ndarray
    system: np.ndarray
    rhs: np.ndarray
    step: np.ndarray
    moved_rotation: np.ndarray
    moved_position: np.ndarray
    turn: np.ndarray


@jit(nogil=True, fastmath=True)
def _with_gradients(target: np.ndarray, out: np.ndarray) -> None:
    """out [h, w, 3] = target [h, w] and its central differences along u and v (px⁻¹, edges
    replicated), as :func:`pae.render_compare.kernels.reference.image_gradients`."""
    h, w = target.shape
    for i in range(h):
        up, down = max(i - 1, 0), min(i + 1, h - 1)
        for j in range(w):
            left, right = max(j - 1, 0), min(j + 1, w - 1)
            out[i, j, 0] = target[i, j]
            out[i, j, 1] = (target[i, right] - target[i, left]) * np.float32(0.5)
            out[i, j, 2] = (target[down, j] - target[up, j]) * np.float32(0.5)


@jit(nogil=True, fastmath=True)
def _sample_with_gradients(images: np.ndarray, view: np.ndarray, corner: np.ndarray) -> None:
    """Rows SAMPLE, GRAD_U and GRAD_V of ``view`` = the three channels of images [h, w, 3]
    (:func:`_with_gradients`) at every point of ``view``, bilinearly, read together."""
    pixels = images.reshape(-1)
    right, down = np.uint32(3), np.uint32(3 * images.shape[1])
    one = np.float32(1.0)
    for p in range(view.shape[1]):
        top_left = corner[p] * np.uint32(3)
        below = top_left + down
        fu, fv = view[FRACTION_U, p], view[FRACTION_V, p]
        w00, w01 = (one - fu) * (one - fv), fu * (one - fv)
        w10, w11 = (one - fu) * fv, fu * fv
        for c, row in ((0, SAMPLE), (1, GRAD_U), (2, GRAD_V)):
            view[row, p] = (
                w00 * pixels[top_left + c]
                + w01 * pixels[top_left + right + c]
                + w10 * pixels[below + c]
                + w11 * pixels[below + right + c]
            )


@jit(nogil=True, fastmath=True)
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """Σ a · b over rows [P] (float32 lanes)."""
    total = np.float32(0.0)
    for p in range(a.shape[0]):
        total += a[p] * b[p]
    return total


@jit(nogil=True, fastmath=True)
def _jacobian(
    view: np.ndarray,
    values: np.ndarray,
    rotation: np.ndarray,
    focal: tuple[float, float],
    fit: tuple[float, float],
    jacobian: np.ndarray,
    residual: np.ndarray,
) -> None:
    """Per point of ``view`` the residual ``α·a + β − c`` and its derivatives w.r.t.
    (position, rotation vector, α, β), each times the square root of the point's weight ->
    residual [P] and jacobian [8, P], for the fit ``(α, β)``, the camera ``rotation`` [3, 3]
    and focal lengths (px): the normal equations' sums are then plain dot products."""
    r = rotation
    r00, r01, r02 = np.float32(r[0, 0]), np.float32(r[0, 1]), np.float32(r[0, 2])
    r10, r11, r12 = np.float32(r[1, 0]), np.float32(r[1, 1]), np.float32(r[1, 2])
    r20, r21, r22 = np.float32(r[2, 0]), np.float32(r[2, 1]), np.float32(r[2, 2])
    fx, fy = np.float32(focal[0]), np.float32(focal[1])
    alpha, beta = np.float32(fit[0]), np.float32(fit[1])
    one = np.float32(1.0)
    for p in range(view.shape[1]):
        a, g_u, g_v = view[SAMPLE, p], view[GRAD_U, p] * fx, view[GRAD_V, p] * fy
        x, y, z = view[X, p], view[Y, p], view[Z, p]
        root = math.sqrt(view[WEIGHT, p])
        inverse = one / max(z, np.float32(MIN_DEPTH_M))
        e0, e1 = g_u * inverse * root, g_v * inverse * root
        e2 = -(g_u * x + g_v * y) * inverse * inverse * root
        jacobian[0, p] = -alpha * (r00 * e0 + r01 * e1 + r02 * e2)
        jacobian[1, p] = -alpha * (r10 * e0 + r11 * e1 + r12 * e2)
        jacobian[2, p] = -alpha * (r20 * e0 + r21 * e1 + r22 * e2)
        jacobian[3, p] = alpha * (e1 * z - e2 * y)
        jacobian[4, p] = alpha * (e2 * x - e0 * z)
        jacobian[5, p] = alpha * (e0 * y - e1 * x)
        jacobian[6, p] = a * root
        jacobian[7, p] = root
        residual[p] = root * (alpha * a + beta - values[p])


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
    points, values, valid, intrinsics, target, with_gradients = query
    iterations, damping, min_overlap, trim_sigma, trim_passes = settings
    view, corner, jacobian, residual, system, rhs = space[:6]
    step, moved_rotation, moved_position, turn = space[6:]
    h, w = target.shape
    focal = (intrinsics[0], intrinsics[1])
    lam = damping
    for _ in range(iterations):
        project(points, valid, rotation, position, intrinsics, h, w, view, corner)
        _sample_with_gradients(with_gradients, view, corner)
        total, sum_a, sum_c, sum_ac, sum_aa, _ = fitted_moments(view, values, 0.0, 0.0, np.inf)
        if total <= 0 or score <= NOT_SEEN_SCORE:
            break
        mean_a, mean_c = sum_a / total, sum_c / total
        cov = sum_ac - total * mean_a * mean_c
        var_a = sum_aa - total * mean_a * mean_a
        alpha = cov / max(var_a, 1e-12)
        beta = mean_c - alpha * mean_a
        _jacobian(view, values, rotation, focal, (alpha, beta), jacobian, residual)
        for i in range(N_PARAMS):
            rhs[i] = -_dot(jacobian[i], residual)
            for j in range(i + 1):
                system[i, j] = _dot(jacobian[i], jacobian[j])
        for i in range(N_PARAMS):
            for j in range(i):
                system[j, i] = system[i, j]
        for i in range(N_PARAMS):
            system[i, i] += lam * system[i, i] + 1e-12
        solved = _cholesky_solve(system, rhs, step)
        for i in range(6):
            solved = solved and math.isfinite(step[i])
        if solved:
            for i in range(3):
                moved_position[i] = position[i] + step[i]
            _rotate_by(rotation, step[3:6], turn, moved_rotation)
            reference = project(
                points, valid, moved_rotation, moved_position, intrinsics, h, w, view, corner
            )
            sample_into(target, view, corner, SAMPLE)
            moved = sampled_score(view, values, reference, min_overlap, trim_sigma, trim_passes)
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
    settings: PolishSettings,
) -> None:
    """:func:`_polish_one` on every hypothesis of every query, in place: rotations [B, K, 3,
    3], positions [B, K, 3], scores [B, K]; one query per task, its work space made once."""
    n_queries, n_hypotheses = scores.shape
    n_points = points.shape[2]
    h, w = target.shape[1], target.shape[2]
    for b in numba.prange(n_queries):
        with_gradients = np.empty((h, w, 3), np.float32)
        _with_gradients(target[b], with_gradients)
        query = _Query(points[b], values[b], valid[b], intrinsics[b], target[b], with_gradients)
        space = _Workspace(
            np.empty((VIEW_ROWS + 2, n_points), np.float32),
            np.empty(n_points, np.uint32),
            np.empty((N_PARAMS, n_points), np.float32),
            np.empty(n_points, np.float32),
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
    rotation = as_array(problem.rotations).copy()
    position = as_array(problem.positions).copy()
    score = as_array(problem.scores).copy()
    _polish(
        as_array(problem.points.transpose(1, 2)),
        as_array(problem.values),
        as_array(problem.valid),
        rotation,
        position,
        score,
        as_array(problem.intrinsics),
        as_array(problem.target),
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
