"""The analytic polish of render-and-compare: Levenberg–Marquardt steps on the image residual.

For a hypothesis pose (camera to world: rotation R, position p) the reference surface points
X [P] (world) project to ``u(X_c)`` with ``X_c = Rᵀ(X − p)``; the band-passed query ``a`` is
sampled there and compared with the points' rendered values ``c`` through the residual
``r = α·a + β − c`` (α, β: the gain and offset fitted in closed form, so that minimising
``Σ r²`` maximises the ZNCC of a and c, the search's score). A step moves the pose as
:func:`pae.core.pose_sampling.perturb` does (a world-frame translation ``Δp``, a camera-frame
rotation vector ``ω``: ``R' = R·exp(ω)``), with the Jacobian

    ∂r/∂Δp = −α·R·e,   ∂r/∂ω = α·(e × X_c),   ∂r/∂α = a,   ∂r/∂β = 1,
    e = (g_u·fx/z, g_v·fy/z, −(g_u·fx·x + g_v·fy·y)/z²)

(g: the query's image gradient at u). Each iteration solves the damped 8×8 normal equations
``(H + λ·diag H)·δ = −g``; the step is kept where the score (the same ZNCC as the search's,
trimmed if configured) rises, and λ shrinks, else λ grows.

Two engines run the same steps on the same inputs (tested equal): :func:`polish_tensor`,
tensor operations on any torch device (the reference, and the GPU path), and
:func:`pae.render_compare.kernels.numba_polish.polish_compiled`, one compiled loop per query
(numba, CPU); likewise the score, :func:`score_tensor` beside
:func:`pae.render_compare.kernels.numba_score.compiled_zncc_scores`.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from pae.render_compare.images import trimmed_zncc

MIN_DEPTH_M = 0.05
"""Points nearer than this to a candidate camera (or behind it) are not seen."""
NOT_SEEN_SCORE = -2.0
"""The score of a candidate that sees too few of the reference points."""

FLOPS_PER_POINT_STEP = 264
"""Floating-point operations per reference point and polish iteration, counted from
``numba_polish._polish_one``: the projection 27, the three bilinear samples with their shared
weights 27, the moments 17, the Jacobian and residual 50, the normal equations' 44 dot
products 88 and the step's score 55 (``numba_score.FLOPS_PER_POINT_SCORE``): what
``bench/render_compare/mflop_per_query`` adds up."""
DAMPING_UP, DAMPING_DOWN = 5.0, 0.3
"""λ's factor after a rejected and after an accepted step."""
DAMPING_RANGE = (1e-7, 1e7)
N_PARAMS = 8
"""Δp (3), ω (3), α, β."""


def image_gradients(target: Tensor) -> tuple[Tensor, Tensor]:
    """Central differences (px⁻¹, edges replicated) of images [B, h, w] along u and v."""
    padded = torch.nn.functional.pad(target[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    grad_u = (padded[:, 1:-1, 2:] - padded[:, 1:-1, :-2]) / 2
    grad_v = (padded[:, 2:, 1:-1] - padded[:, :-2, 1:-1]) / 2
    return grad_u.contiguous(), grad_v.contiguous()


def rotation_vector_to_matrix(vector: Tensor) -> Tensor:
    """Rodrigues: rotation vectors [..., 3] (rad) -> matrices [..., 3, 3]."""
    angle = vector.norm(dim=-1, keepdim=True)[..., None]  # [..., 1, 1]
    x, y, z = vector.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).view(*vector.shape, 3)
    eye = torch.eye(3, dtype=vector.dtype, device=vector.device).expand_as(skew)
    small = angle < 1e-9
    safe = torch.where(small, torch.ones_like(angle), angle)
    first = torch.where(small, torch.ones_like(angle), torch.sin(safe) / safe)
    second = torch.where(small, torch.full_like(angle, 0.5), (1 - torch.cos(safe)) / safe**2)
    return eye + first * skew + second * (skew @ skew)


def _bilinear_tensor(images: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """images [N, h, w] at (u, v) [N, P] (clamped inside), as :func:`bilinear` samples."""
    n, h, w = images.shape
    u = u.clamp(0, w - 1)
    v = v.clamp(0, h - 1)
    u0 = u.long().clamp_max(w - 2)
    v0 = v.long().clamp_max(h - 2)
    fu, fv = u - u0, v - v0
    flat = images.reshape(n, h * w)

    def at(dv: int, du: int) -> Tensor:
        return flat.gather(1, (v0 + dv) * w + u0 + du)

    top = at(0, 0) * (1 - fu) + at(0, 1) * fu
    bottom = at(1, 0) * (1 - fu) + at(1, 1) * fu
    return top * (1 - fv) + bottom * fv


class _Projection:
    """Surface points [N, P, 3] (weights ``valid`` [N, P]) seen from cameras (rotations [N,
    3, 3], positions [N, 3], intrinsics [N, 4]): camera-frame points ``local`` [N, P, 3],
    pixels ``u``, ``v`` [N, P] and depths (1 where not ahead of the camera)."""

    def __init__(
        self, points: Tensor, valid: Tensor, rotation: Tensor, position: Tensor, intrinsics: Tensor
    ) -> None:
        self.rotation = rotation
        self.intrinsics = intrinsics
        self.local = torch.einsum("npj,nji->npi", points - position[:, None], rotation)
        x, y, z = self.local.unbind(-1)
        fx, fy, cx, cy = (k[:, None] for k in intrinsics.unbind(-1))
        depth = torch.where(z > MIN_DEPTH_M, z, torch.ones_like(z))
        self.u = fx * x / depth + cx
        self.v = fy * y / depth + cy
        self.depth = depth
        self.valid = valid
        self.ahead = z > MIN_DEPTH_M

    def seen(self, h: int, w: int) -> Tensor:
        inside = (self.u >= 0) & (self.v >= 0) & (self.u <= w - 1) & (self.v <= h - 1)
        return self.ahead & inside & (self.valid > 0)


def _moments(a: Tensor, c: Tensor, weights: Tensor) -> tuple[Tensor, ...]:
    """total, means of a and c, cov(a, c) and var(a), var(c) sums [N] (weights [N, P])."""
    total = weights.sum(-1)
    safe = total.clamp_min(1e-12)
    mean_a = (weights * a).sum(-1) / safe
    mean_c = (weights * c).sum(-1) / safe
    da, dc = a - mean_a[:, None], c - mean_c[:, None]
    return (
        total,
        mean_a,
        mean_c,
        (weights * da * dc).sum(-1),
        (weights * da * da).sum(-1),
        (weights * dc * dc).sum(-1),
    )


def score_tensor(
    points: Tensor,
    values: Tensor,
    valid: Tensor,
    rotation: Tensor,
    position: Tensor,
    intrinsics: Tensor,
    target: Tensor,
    min_overlap: float,
    trim_sigma: float,
    trim_passes: int,
) -> Tensor:
    """The score [N] of :func:`pae.render_compare.kernels.numba_score.sampled_score` for one
    camera per row:
    points [N, P, 3], values, valid [N, P], rotation [N, 3, 3], position [N, 3], intrinsics
    [N, 4], target [N, h, w]."""
    h, w = target.shape[-2:]
    view = _Projection(points, valid, rotation, position, intrinsics)
    seen = view.seen(h, w)
    a = _bilinear_tensor(target, view.u, view.v)
    weights = valid * seen
    reference = valid.clamp_min(0).sum(-1)
    total = weights.sum(-1)
    score = trimmed_zncc(a, values, weights, trim_sigma, trim_passes)
    unseen = (reference <= 0) | (total < min_overlap * reference)
    return torch.where(unseen, torch.full_like(score, NOT_SEEN_SCORE), score)


def _normal_equations(
    view: _Projection, values: Tensor, target: Tensor, grad_u: Tensor, grad_v: Tensor
) -> tuple[Tensor, Tensor]:
    """H [N, 8, 8] and g [N, 8] (float64) of the residual ``α·a + β − c`` at the cameras of
    ``view``: values c [N, P], target a and its gradients [N, h, w]."""
    h, w = target.shape[-2:]
    weights = (view.valid * view.seen(h, w)).double()
    a = _bilinear_tensor(target, view.u, view.v).double()
    g_u = _bilinear_tensor(grad_u, view.u, view.v).double()
    g_v = _bilinear_tensor(grad_v, view.u, view.v).double()
    c = values.double()
    _, mean_a, mean_c, cov, var_a, _ = _moments(a, c, weights)
    alpha = cov / var_a.clamp_min(1e-12)
    beta = mean_c - alpha * mean_a
    residual = alpha[:, None] * a + beta[:, None] - c
    local = view.local.double()
    x, y, _ = local.unbind(-1)
    z = view.depth.double()
    fx, fy = (k[:, None].double() for k in view.intrinsics.unbind(-1)[:2])
    e = torch.stack([g_u * fx / z, g_v * fy / z, -(g_u * fx * x + g_v * fy * y) / z**2], -1)
    d_position = -torch.einsum("nij,npj->npi", view.rotation.double(), e)
    d_rotation = torch.linalg.cross(e, local)
    jacobian = torch.cat(
        [
            alpha[:, None, None] * d_position,
            alpha[:, None, None] * d_rotation,
            a[..., None],
            torch.ones_like(a)[..., None],
        ],
        -1,
    )  # [N, P, 8]
    weighted = weights[..., None] * jacobian
    return (
        torch.einsum("npi,npj->nij", weighted, jacobian),
        torch.einsum("npi,np->ni", weighted, residual),
    )


class PolishProblem(NamedTuple):
    """What the polish aligns: surface points [B, P, 3] (world), their rendered values and
    weights ``valid`` [B, P]; K hypotheses per query, rotations [B, K, 3, 3] (camera to
    world), positions [B, K, 3] and their scores [B, K]; intrinsics [B, 4] and the
    band-passed grey targets [B, h, w]."""

    points: Tensor
    values: Tensor
    valid: Tensor
    rotations: Tensor
    positions: Tensor
    scores: Tensor
    intrinsics: Tensor
    target: Tensor


class PolishSettings(NamedTuple):
    """The polish's ``iterations``, first λ (``damping``), the least share of the surface a
    pose must see (``min_overlap``) and the score's trimming (``trim_sigma``,
    ``trim_passes``: :func:`pae.render_compare.images.trimmed_zncc`)."""

    iterations: int
    damping: float
    min_overlap: float
    trim_sigma: float = 0.0
    trim_passes: int = 2


def polish_tensor(
    problem: PolishProblem, settings: PolishSettings
) -> tuple[Tensor, Tensor, Tensor]:
    """``iterations`` Levenberg–Marquardt steps (see the module docstring) on each hypothesis
    of ``problem``, with tensor operations on its device -> (rotations, positions, scores)
    after the steps, shaped as the problem's."""
    points, values, valid, rotations, positions, scores, intrinsics, target = problem
    iterations, damping, min_overlap, trim_sigma, trim_passes = settings
    b, k = scores.shape
    rows = torch.arange(b, device=points.device).repeat_interleave(k)
    grad_u, grad_v = image_gradients(target)
    points, values, valid = points[rows], values[rows], valid[rows]
    intrinsics, target = intrinsics[rows], target[rows]
    grad_u, grad_v = grad_u[rows], grad_v[rows]
    trim = (min_overlap, trim_sigma, trim_passes)
    rotation = rotations.reshape(b * k, 3, 3).clone()
    position = positions.reshape(b * k, 3).clone()
    score = scores.reshape(b * k).clone()
    lam = torch.full_like(score, damping, dtype=torch.float64)
    eye = torch.eye(N_PARAMS, dtype=torch.float64, device=points.device)
    for _ in range(iterations):
        view = _Projection(points, valid, rotation, position, intrinsics)
        hessian, gradient = _normal_equations(view, values, target, grad_u, grad_v)
        diagonal = torch.diagonal(hessian, dim1=-2, dim2=-1)
        damped = hessian + (lam[:, None] * diagonal)[..., None] * eye + 1e-12 * eye
        factor, info = torch.linalg.cholesky_ex(damped)
        step = -torch.cholesky_solve(gradient[..., None], factor)[..., 0]
        solved = (info == 0) & torch.isfinite(step[:, :6]).all(-1) & (score > NOT_SEEN_SCORE)
        step = torch.where(solved[:, None], step, torch.zeros_like(step)).to(position.dtype)
        moved_position = position + step[:, :3]
        moved_rotation = rotation @ rotation_vector_to_matrix(step[:, 3:6])
        moved = score_tensor(
            points, values, valid, moved_rotation, moved_position, intrinsics, target, *trim
        )
        better = solved & (moved > score)
        rotation = torch.where(better[:, None, None], moved_rotation, rotation)
        position = torch.where(better[:, None], moved_position, position)
        score = torch.where(better, moved, score)
        lam = torch.where(better, lam * DAMPING_DOWN, lam * DAMPING_UP).clamp(*DAMPING_RANGE)
    return rotation.view(b, k, 3, 3), position.view(b, k, 3), score.view(b, k)
