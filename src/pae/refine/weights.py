"""Affine weights for test-time refinement (paper §3.3), fitted for every query at once.

Given the query latent ``z`` [D] (D = 2d, ``Latents.joint()``) and the PAE encodings ``ẑᵢ`` of
its k nearest train poses, weights ``a`` with ``Σ aᵢ = 1`` are fitted so that ``Σ aᵢ ẑᵢ ≈ z``,
and the refined position is ``Σ aᵢ xᵢ``. Three weight models:

- ``"mlp"``: the public code's weight regressor (``pae.refine.regressor``), an MLP over the k
  concatenated encodings whose softmax gives ``a``, freshly initialised for every query and
  optimised with AdamW for ``iterations`` steps;
- ``"softmax_logits"``: free logits per query (softmax gives ``a``), optimised the same way;
- ``"closed_form"``: the exact equality-constrained least-squares solution (weights may be
  negative, so the position may leave the neighbours' convex hull).

``refine_affine`` optimises every query of a batch at once with per-query parameter tensors.
It gives what fitting one query at a time, as the public code does, gives
(``pae.refine.reference``, the test oracle): the batch objective is the sum of the per-query
objectives and AdamW updates each element independently.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from pae.core.compiled import ENGINES, Engine
from pae.refine.fused import FUSED_KERNEL, fit_mlp_weights_fused
from pae.refine.regressor import (
    ADAM_BETAS,
    ADAM_EPS,
    LayerParams,
    fit_mlp_weights,
    regressor_hidden_sizes,
)

WeightModel = Literal["softmax_logits", "mlp", "closed_form"]
Objective = Literal["l2", "mse"]
InitParams = Tensor | Sequence[LayerParams]
"""Initial parameters: logits [B, k] for ``softmax_logits``, the MLP layers for ``mlp``."""
WEIGHT_MODELS: tuple[str, ...] = ("softmax_logits", "mlp", "closed_form")


class AffineFit(NamedTuple):
    """weights [B, k] (Σ = 1) and the refined positions [B, 3] = Σ aᵢ xᵢ (m)."""

    weights: Tensor
    positions: Tensor


def closed_form_weights(
    query_latent: Tensor, neighbour_latents: Tensor, ridge: float = 1e-6
) -> Tensor:
    """Affine weights [B, k] minimising ‖z − Σ aᵢ ẑᵢ‖₂ subject to Σ aᵢ = 1, exactly.

    Solves the KKT system of the equality-constrained least squares, batched, on latents
    centred at the neighbours' mean (which leaves the objective unchanged when Σ a = 1 and
    improves conditioning). A ridge of ``ridge`` × (mean squared centred norm) on ``a`` keeps
    the system solvable when neighbours coincide; it favours equal weights. Weights may be
    negative.
    """
    centre = neighbour_latents.mean(dim=1, keepdim=True)
    centred = neighbour_latents - centre  # [B, k, D]
    target = (query_latent.unsqueeze(1) - centre).transpose(1, 2)  # [B, D, 1]
    gram = centred @ centred.transpose(1, 2)  # [B, k, k]
    rhs = (centred @ target).squeeze(-1)  # [B, k]
    batch, k, _ = gram.shape
    scale = gram.diagonal(dim1=1, dim2=2).mean(dim=1)
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    eye = torch.eye(k, dtype=gram.dtype, device=gram.device)
    ones = torch.ones(batch, k, 1, dtype=gram.dtype, device=gram.device)
    top = torch.cat([gram + ridge * scale[:, None, None] * eye, ones], dim=2)
    bottom = torch.cat([ones.transpose(1, 2), torch.zeros_like(ones[:, :1])], dim=2)
    kkt = torch.cat([top, bottom], dim=1)  # [B, k+1, k+1]
    solution = torch.linalg.solve(kkt, torch.cat([rhs, ones[:, :1, 0]], dim=1))
    return solution[:, :k]


def combine(weights: Tensor, vectors: Tensor) -> Tensor:
    """Σᵢ weights[b, i] · vectors[b, i] -> [B, D]; weights [B, k], vectors [B, k, D]."""
    return (weights.unsqueeze(-1) * vectors).sum(dim=1)


def matching_loss(
    query_latent: Tensor, neighbour_latents: Tensor, weights: Tensor, objective: Objective = "l2"
) -> Tensor:
    """Sum over queries of the per-query matching loss (so each query's gradient is its own)."""
    residual = query_latent - combine(weights, neighbour_latents)
    if objective == "l2":
        return torch.linalg.vector_norm(residual, dim=-1).sum()
    return residual.pow(2).mean(dim=-1).sum()


def positions_of(weights: Tensor, neighbour_poses: Tensor) -> Tensor:
    """Σ aᵢ xᵢ [B, 3] (m): weights [B, k], neighbour_poses [B, k, 7] (or [B, k, 3])."""
    return combine(weights, neighbour_poses[..., :3].to(weights.dtype))


def check_fit_inputs(
    query_latent: Tensor,
    neighbour_latents: Tensor,
    neighbour_poses: Tensor,
    weight_model: str,
    objective: str,
    iterations: int,
) -> None:
    if weight_model not in WEIGHT_MODELS:
        raise ValueError(f"weight_model must be one of {WEIGHT_MODELS}, got {weight_model!r}")
    if objective not in ("l2", "mse"):
        raise ValueError(f"objective must be 'l2' or 'mse', got {objective!r}")
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    if query_latent.ndim != 2:
        raise ValueError(f"query_latent must be [B, D], got {tuple(query_latent.shape)}")
    batch, dim = query_latent.shape
    if (
        neighbour_latents.ndim != 3
        or neighbour_latents.shape[0] != batch
        or neighbour_latents.shape[2] != dim
    ):
        raise ValueError(
            f"neighbour_latents must be [B, k, D] = [{batch}, k, {dim}], "
            f"got {tuple(neighbour_latents.shape)}"
        )
    k = neighbour_latents.shape[1]
    if neighbour_poses.shape[:2] != (batch, k) or neighbour_poses.shape[2] not in (3, 7):
        raise ValueError(
            f"neighbour_poses must be [B, k, 7] = [{batch}, {k}, 7], "
            f"got {tuple(neighbour_poses.shape)}"
        )


def check_logits_init(init: InitParams, batch: int, k: int) -> Tensor:
    if not isinstance(init, Tensor) or init.shape != (batch, k):
        shape = tuple(init.shape) if isinstance(init, Tensor) else type(init).__name__
        raise ValueError(f"softmax_logits init must be logits [B, k] = [{batch}, {k}], got {shape}")
    return init


def refine_affine(
    query_latent: Tensor,
    neighbour_latents: Tensor,
    neighbour_poses: Tensor,
    *,
    weight_model: WeightModel = "mlp",
    iterations: int = 3,
    lr: float = 1e-3,
    weight_decay: float = 0.01,
    objective: Objective = "l2",
    hidden: Sequence[int] | None = None,
    generator: torch.Generator | None = None,
    init: InitParams | None = None,
    chunk_size: int = 64,
    ridge: float = 1e-6,
    engine: Engine = "auto",
    activation: str = "relu",
) -> AffineFit:
    """Affine weights for every query at once.

    query_latent [B, D]; neighbour_latents [B, k, D]; neighbour_poses [B, k, 7] (or [B, k, 3]),
    positions in metres. The iterative models take ``iterations`` AdamW steps (``lr``,
    ``weight_decay``, betas (0.9, 0.999), eps 1e-8) on the summed per-query loss
    ‖z − Σ aᵢ ẑᵢ‖₂ (``objective="l2"``, the paper) or its mean square (``"mse"``, the public
    code); the returned weights are those of the parameters after the last step.

    ``init`` gives the initial parameters (see ``InitParams``; for the MLP it also fixes the
    hidden widths, ``hidden`` being for drawn ones). Without it logits start at
    zero (uniform weights), and each query's MLP is drawn from ``generator``: the first
    layer's bias per query and the later layers once per call, shared as starting values,
    as ``nn.Linear`` does (U(±1/√fan_in)); the first layer's weights per query as
    N(0, 1/(3·fan_in)), the same variance, which lets x·W₁ be drawn directly (see
    ``pae.refine.regressor``). ``engine`` picks how the MLP is fitted: ``"numba"``, one
    compiled loop per query (``pae.refine.fused``, float32 or float64 CPU tensors), or
    ``"torch"``, tensor operations over ``chunk_size`` queries at a time (their optimiser
    state then stays in cache: 64 is fastest on CPU); ``"auto"`` takes the fused loop where
    it can run and the batched path elsewhere. ``activation`` is the MLP's hidden activation
    (a key of ``pae.refine.regressor.ACTIVATIONS``); the fused loop implements only what
    ``pae.refine.fused.FUSED_KERNEL`` declares, so ``"auto"`` takes the batched path for any
    other model and ``"numba"`` refuses it. The engines give the same result up to rounding.
    Works under ``torch.no_grad`` and ``torch.inference_mode``; the outputs carry no autograd
    graph.
    """
    check_fit_inputs(
        query_latent, neighbour_latents, neighbour_poses, weight_model, objective, iterations
    )
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    on_cpu = query_latent.device.type == "cpu"
    compilable = on_cpu and query_latent.dtype in (torch.float32, torch.float64)
    if engine == "numba" and not compilable:
        raise ValueError(
            "engine 'numba' runs on float32 or float64 CPU tensors, got "
            f"{query_latent.dtype} on {query_latent.device}"
        )
    batch, k, _ = neighbour_latents.shape
    mismatch = None
    if weight_model == "mlp":
        layers = len(init) - 1 if init is not None else len(hidden or regressor_hidden_sizes(k))
        mismatch = FUSED_KERNEL.mismatch(activation, objective, layers)
        if engine == "numba" and mismatch:
            raise ValueError(f"engine 'numba' cannot fit this weight regressor: {mismatch}")
    loss = functools.partial(matching_loss, objective=objective)
    fused = weight_model == "mlp" and compilable and engine != "torch" and mismatch is None
    with torch.inference_mode(False), torch.enable_grad():
        query = query_latent.detach()
        neighbours = neighbour_latents.detach().to(query.dtype)
        if not fused:  # tensors made under inference mode cannot enter autograd: copy them
            query, neighbours = query.clone(), neighbours.clone()
        if weight_model == "closed_form":
            with torch.no_grad():
                weights = closed_form_weights(query, neighbours, ridge)
        elif weight_model == "softmax_logits":
            start = (
                torch.zeros(batch, k, dtype=query.dtype, device=query.device)
                if init is None
                else check_logits_init(init, batch, k).to(query)
            )
            logits = start.detach().clone().requires_grad_(True)
            optimiser = torch.optim.AdamW(
                [logits], lr=lr, betas=ADAM_BETAS, eps=ADAM_EPS, weight_decay=weight_decay
            )
            for _ in range(iterations):
                optimiser.zero_grad(set_to_none=True)
                loss(query, neighbours, torch.softmax(logits, dim=-1)).backward()
                optimiser.step()
            with torch.no_grad():
                weights = torch.softmax(logits, dim=-1)
        else:
            weights = fit_mlp_weights(
                query,
                neighbours,
                iterations,
                lr,
                weight_decay,
                loss,
                hidden,
                generator,
                init,
                chunk_size,
                functools.partial(fit_mlp_weights_fused, mse=objective == "mse") if fused else None,
                activation,
            )
        weights = weights.detach()
        return AffineFit(weights, positions_of(weights, neighbour_poses.detach()))
