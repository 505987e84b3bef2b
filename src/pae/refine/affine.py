"""Test-time position refinement: the query's latent as an affine combination of the latents
of its nearest train poses (paper §3.3).

Given the query latent ``z`` [D] (D = 2d, ``Latents.joint()``) and the PAE encodings ``ẑᵢ`` of
its k nearest train poses, weights ``a`` with ``Σ aᵢ = 1`` are fitted so that ``Σ aᵢ ẑᵢ ≈ z``,
and the refined position is ``Σ aᵢ xᵢ``. Three weight models:

- ``"mlp"``: the public code's weight regressor, an MLP over the k concatenated encodings
  (k·D → 64k → 32k → 16k → k, ReLU) whose softmax gives ``a``; freshly initialised for every
  query (in ``refine_affine`` the later layers' starting values are one draw shared by the
  call's queries) and optimised with AdamW for ``iterations`` steps;
- ``"softmax_logits"``: free logits per query (softmax gives ``a``), optimised the same way;
- ``"closed_form"``: the exact equality-constrained least-squares solution (weights may be
  negative, so the position may leave the neighbours' convex hull).

``refine_affine`` optimises every query of a batch at once with per-query parameter tensors
(the MLP's large first layer, k·D × 64k per query, is never stored: see ``_fit_regressor``);
``refine_affine_per_query`` is the reference that follows the public code (one query at a time,
a fresh ``nn.Module`` and optimiser per query). For the same initial parameters both give the
same result, since the batch objective is the sum of the per-query objectives and AdamW updates
each element independently.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from typing import Literal, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pae.geometry import average_quaternions, canonicalize_quaternion, normalize_quaternion
from pae.models.base import Latents
from pae.refine.index import PoseIndex

WeightModel = Literal["softmax_logits", "mlp", "closed_form"]
OrientationMode = Literal["teacher", "affine", "markley"]
Objective = Literal["l2", "mse"]
LayerParams = tuple[Tensor, Tensor]
"""One batched linear layer: weight [B, in, out] (applied as ``h @ W``) and bias [B, out]."""
InitParams = Tensor | Sequence[LayerParams]
"""Initial parameters: logits [B, k] for ``softmax_logits``, the MLP layers for ``mlp``."""
PoseEncoder = Callable[[Tensor, Tensor | None], Latents]

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
SERIES_RATIO = {torch.float64: 1e3, torch.float32: 30.0}
"""Per working dtype, the aᵢ·s / eps above which ``_FirstLayerGain`` uses its series: the
truncation error, below ratio⁻⁵, is under the dtype's rounding (1e-15; 4e-8)."""
_BAND_TERMS = 1 << 20
_SMALLEST = 32
WEIGHT_MODELS: tuple[str, ...] = ("softmax_logits", "mlp", "closed_form")
ORIENTATION_MODES: tuple[str, ...] = ("teacher", "affine", "markley")


class AffineFit(NamedTuple):
    """weights [B, k] (Σ = 1) and the refined positions [B, 3] = Σ aᵢ xᵢ (m)."""

    weights: Tensor
    positions: Tensor


class RefinementResult(NamedTuple):
    """poses [B, 7] refined; weights [B, k]; neighbour_indices [B, k] into the pose index."""

    poses: Tensor
    weights: Tensor
    neighbour_indices: Tensor


def regressor_hidden_sizes(k: int) -> tuple[int, ...]:
    """Hidden widths of the public code's weight regressor for k neighbours."""
    return (64 * k, 32 * k, 16 * k)


def _empty_for_draw(
    shape: tuple[int, ...], generator: torch.Generator | None, like: Tensor
) -> Tensor:
    """An empty tensor of ``like``'s dtype on ``generator``'s device (``like``'s without one)."""
    device = generator.device if generator is not None else like.device
    return torch.empty(shape, dtype=like.dtype, device=device)


def _uniform(
    shape: tuple[int, ...], bound: float, generator: torch.Generator | None, like: Tensor
) -> Tensor:
    """U(−bound, bound) samples from ``generator``, with ``like``'s dtype and device."""
    values = _empty_for_draw(shape, generator, like).uniform_(-bound, bound, generator=generator)
    return values.to(like.device)


def _uniform_layers(
    batch: int, sizes: Sequence[int], generator: torch.Generator | None, like: Tensor
) -> list[LayerParams]:
    """Batched linear layers ``sizes[0] -> sizes[1] -> …`` drawn as ``nn.Linear`` does."""
    layers: list[LayerParams] = []
    for fan_in, fan_out in itertools.pairwise(sizes):
        bound = 1.0 / math.sqrt(fan_in)
        weight = _uniform((batch, fan_in, fan_out), bound, generator, like)
        layers.append((weight, _uniform((batch, fan_out), bound, generator, like)))
    return layers


class _BatchedLinear(torch.autograd.Function):
    """[b, i] inputs through per-row weights [b, i, o] and biases [b, o] -> [b, o].

    The weight gradient (a batch of outer products) is formed by broadcasting, several times
    faster on CPU than the batched matrix product autograd would use.
    """

    @staticmethod
    def forward(inputs: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
        return torch.baddbmm(bias.unsqueeze(1), inputs.unsqueeze(1), weight).squeeze(1)

    @staticmethod
    def setup_context(
        ctx: torch.autograd.function.FunctionCtx, inputs: tuple, output: Tensor
    ) -> None:
        layer_inputs, weight, _ = inputs
        ctx.save_for_backward(layer_inputs, weight)

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: Tensor) -> tuple[Tensor, ...]:
        layer_inputs, weight = ctx.saved_tensors
        grad_inputs = torch.bmm(grad.unsqueeze(1), weight.transpose(1, 2)).squeeze(1)
        grad_weight = layer_inputs.unsqueeze(2) * grad.unsqueeze(1)
        return grad_inputs, grad_weight, grad


def init_weight_regressor(
    batch: int,
    k: int,
    latent_dim: int,
    *,
    hidden: Sequence[int] | None = None,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> list[LayerParams]:
    """Independent weight-regressor parameters for ``batch`` queries, stored in full.

    latent_dim is D, the size of one neighbour encoding (the input has k·D features).
    Every weight and bias is drawn from U(−1/√fan_in, 1/√fan_in), the bounds of
    ``nn.Linear``'s default initialisation, from ``generator`` (on its device).
    """
    sizes = [k * latent_dim, *(regressor_hidden_sizes(k) if hidden is None else hidden), k]
    like = torch.empty(0, dtype=dtype, device=device)
    return _uniform_layers(batch, sizes, generator, like)


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


def _combine(weights: Tensor, vectors: Tensor) -> Tensor:
    """Σᵢ weights[b, i] · vectors[b, i] -> [B, D]; weights [B, k], vectors [B, k, D]."""
    return (weights.unsqueeze(-1) * vectors).sum(dim=1)


def _objective(
    query_latent: Tensor, neighbour_latents: Tensor, weights: Tensor, objective: Objective
) -> Tensor:
    """Sum over queries of the per-query matching loss (so each query's gradient is its own)."""
    residual = query_latent - _combine(weights, neighbour_latents)
    if objective == "l2":
        return torch.linalg.vector_norm(residual, dim=-1).sum()
    return residual.pow(2).mean(dim=-1).sum()


def _check_inputs(
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


def _check_logits_init(init: InitParams, batch: int, k: int) -> Tensor:
    if not isinstance(init, Tensor) or init.shape != (batch, k):
        shape = tuple(init.shape) if isinstance(init, Tensor) else type(init).__name__
        raise ValueError(f"softmax_logits init must be logits [B, k] = [{batch}, {k}], got {shape}")
    return init


def _check_mlp_init(init: InitParams, batch: int, k: int, dim: int) -> Sequence[LayerParams]:
    if isinstance(init, Tensor) or len(init) < 2:
        raise ValueError(
            "mlp init must be a sequence of at least two (weight [B, in, out], bias [B, out]) pairs"
        )
    fan_in = k * dim
    for weight, bias in init:
        if (
            weight.ndim != 3
            or weight.shape[:2] != (batch, fan_in)
            or bias.shape != (batch, weight.shape[2])
        ):
            raise ValueError(
                f"mlp init layer shapes {tuple(weight.shape)}, {tuple(bias.shape)} do not chain "
                f"from input [{batch}, {fan_in}]"
            )
        fan_in = weight.shape[2]
    if fan_in != k:
        raise ValueError(f"mlp init must end with k={k} outputs, got {fan_in}")
    return init


class _FirstLayerGain:
    """S[b, j] = Σᵢ aᵢ² / (aᵢ·s[b, j] + eps) for fixed a = |x| [b, n] and any s [b, h] >= 0.

    Evaluated in float64. Terms with aᵢ·s >= ratio·eps are summed with the series
    (aᵢ/s)·Σₚ₌₀⁴ (−eps/(aᵢ s))ᵖ (relative error below ratio⁻⁵) from sums of aᵢ^(1−p),
    prepared once; the others (aᵢ near 0) are summed term by term. Only the ``_SMALLEST``
    smallest positive inputs of a row can fall below the series' range in practice: they are kept
    sorted, with suffix sums, and the rest's sums are prepared once, so a step costs
    O(b·h·_SMALLEST), with no full sort. Rows whose threshold exceeds even those are summed
    directly, at most ``_BAND_TERMS`` terms at a time. Zero inputs add nothing; s = 0 gives 0.
    """

    def __init__(self, abs_inputs: Tensor, eps: float, ratio: float) -> None:
        a = abs_inputs.to(torch.float64)
        m = min(a.shape[1], _SMALLEST)
        # the m smallest positive inputs, ascending; inf where a row has fewer
        positive = torch.where(a > 0, a, math.inf)
        smallest, where_small = torch.topk(positive, m, dim=1, largest=False, sorted=True)
        rest = a.scatter(1, where_small, 0.0)
        finite = torch.where(torch.isinf(smallest), 0.0, smallest)
        self.sums = torch.cat(  # [b, m + 1, 5]: rest + the c largest of the m smallest
            [
                self._power_sums(rest).unsqueeze(1),
                self._power_sums(finite.flip(1), cumulative=True),
            ],
            dim=1,
        )
        self.sums[:, 1:] += self.sums[:, :1]
        self.smallest = smallest
        self.inputs = a
        self.eps = eps
        self.ratio = ratio

    @staticmethod
    def _power_sums(a: Tensor, cumulative: bool = False) -> Tensor:
        """Σ over positive aᵢ of aᵢ, 1, aᵢ⁻¹, aᵢ⁻², aᵢ⁻³ -> [b, 5] (running sums [b, n, 5])."""
        positive = a > 0
        inverse = torch.where(positive, 1.0 / torch.where(positive, a, 1.0), 0.0)
        powers = torch.stack([a, positive.to(a.dtype), inverse, inverse**2, inverse**3], dim=-1)
        return powers.cumsum(dim=1) if cumulative else powers.sum(dim=1)

    def __call__(self, scale: Tensor) -> Tensor:
        eps = self.eps
        s = scale.to(torch.float64)
        active = s > 0
        safe_scale = torch.where(active, s, 1.0)
        threshold = torch.where(active, self.ratio * eps / safe_scale, math.inf)  # [b, h]
        m = self.smallest.shape[1]
        # of the m smallest inputs, how many reach the threshold: the series covers them
        reach = m - torch.searchsorted(self.smallest, threshold, right=False)
        sums = torch.gather(self.sums, 1, reach.unsqueeze(-1).expand(-1, -1, 5))
        ratio = -eps / safe_scale  # Horner in (−eps/s) over the sums of aᵢ^(1−p), p = 4..0
        series = sums[..., 4]
        for power in (3, 2, 1, 0):
            series = sums[..., power] + ratio * series
        result = torch.where(active, series / safe_scale, 0.0)
        band = active & (reach < m)
        if bool(band.any()):  # the smallest inputs below the threshold, term by term
            rows, cols = band.nonzero(as_tuple=True)
            small, scale_rc = self.smallest[rows], s[rows, cols].unsqueeze(-1)
            terms = small.square() / (small * scale_rc + eps)
            below = small < threshold[rows, cols].unsqueeze(-1)
            result[rows, cols] += torch.where(below, terms, 0.0).sum(dim=-1)
        beyond = active & (reach == 0) & (m < self.inputs.shape[1])
        if bool(beyond.any()):  # rest values may lie below the threshold too: sum directly
            rows, cols = beyond.nonzero(as_tuple=True)
            step = max(1, _BAND_TERMS // self.inputs.shape[1])
            for part in range(0, len(rows), step):
                r, c = rows[part : part + step], cols[part : part + step]
                a, scale_rc = self.inputs[r], s[r, c].unsqueeze(-1)
                result[r, c] = (a.square() / (a * scale_rc + eps)).sum(dim=-1)
        return result


def _fit_regressor(
    query: Tensor,
    neighbours: Tensor,
    first_preactivation: Tensor,
    first_bias: Tensor,
    layers: Sequence[LayerParams],
    iterations: int,
    lr: float,
    weight_decay: float,
    objective: Objective,
) -> Tensor:
    """Optimise a batch of weight regressors; returns their final softmax weights [b, k].

    The first layer's weight W₁ [b, n, h] (n = k·D) is never stored. Its input x is the same
    at every step, so its gradient is x ⊗ δ (δ = ∂L/∂(xW₁), equal to the first bias'
    gradient) and AdamW's moments stay x ⊗ μ and x² ⊗ ν with μ, ν [b, h] updated by the
    same rules. One AdamW step therefore changes xW₁ to
    ``(1 − lr·wd)·xW₁ − lr/(1 − β₁ᵗ) · μ ⊙ S(√(ν/(1 − β₂ᵗ)))`` with ``S`` from
    ``_FirstLayerGain``: the same arithmetic as a stored W₁, at O(b·h·n) per step instead
    of the many passes over 4 tensors of that size. first_preactivation [b, h] is x·W₁ at
    the start; the other parameters are ordinary tensors optimised by ``torch.optim.AdamW``.
    """
    beta1, beta2 = ADAM_BETAS
    inputs = neighbours.reshape(neighbours.shape[0], -1)
    gain = _FirstLayerGain(inputs.abs(), ADAM_EPS, SERIES_RATIO.get(query.dtype, 1e3))
    projected = first_preactivation.detach().clone()
    first_avg = torch.zeros_like(projected)
    first_avg_sq = torch.zeros_like(projected)
    bias = first_bias.detach().clone().requires_grad_(True)
    params = [tensor.detach().clone().requires_grad_(True) for layer in layers for tensor in layer]
    rest = list(zip(params[0::2], params[1::2], strict=True))
    fused = True if query.device.type in ("cpu", "cuda") else None
    optimiser = torch.optim.AdamW(
        [bias, *params],
        lr=lr,
        betas=ADAM_BETAS,
        eps=ADAM_EPS,
        weight_decay=weight_decay,
        fused=fused,
    )

    def weights_now() -> Tensor:
        hidden = torch.relu(projected + bias)
        for position, (weight, layer_bias) in enumerate(rest):
            hidden = _BatchedLinear.apply(hidden, weight, layer_bias)
            if position < len(rest) - 1:
                hidden = torch.relu(hidden)
        return torch.softmax(hidden, dim=-1)

    for step in range(1, iterations + 1):
        optimiser.zero_grad(set_to_none=True)
        _objective(query, neighbours, weights_now(), objective).backward()
        optimiser.step()
        with torch.no_grad():
            delta = bias.grad
            first_avg.lerp_(delta, 1.0 - beta1)
            first_avg_sq.mul_(beta2).addcmul_(delta, delta, value=1.0 - beta2)
            scale = first_avg_sq.sqrt() / math.sqrt(1.0 - beta2**step)
            projected.mul_(1.0 - lr * weight_decay)
            projected.sub_(lr / (1.0 - beta1**step) * first_avg * gain(scale).to(projected))
    with torch.no_grad():
        return weights_now()


def _positions(weights: Tensor, neighbour_poses: Tensor) -> Tensor:
    return _combine(weights, neighbour_poses[..., :3].to(weights.dtype))


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
    ``_fit_regressor``). The MLP path runs ``chunk_size`` queries at a time (their optimiser
    state then stays in cache: 64 is fastest on CPU), which does not change the result.
    Works under ``torch.no_grad`` and ``torch.inference_mode``; the outputs carry no autograd
    graph.
    """
    _check_inputs(
        query_latent, neighbour_latents, neighbour_poses, weight_model, objective, iterations
    )
    batch, k, _ = neighbour_latents.shape
    with torch.inference_mode(False), torch.enable_grad():
        query = query_latent.detach().clone()
        neighbours = neighbour_latents.detach().to(query.dtype).clone()
        if weight_model == "closed_form":
            with torch.no_grad():
                weights = closed_form_weights(query, neighbours, ridge)
        elif weight_model == "softmax_logits":
            start = (
                torch.zeros(batch, k, dtype=query.dtype, device=query.device)
                if init is None
                else _check_logits_init(init, batch, k).to(query)
            )
            logits = start.detach().clone().requires_grad_(True)
            optimiser = torch.optim.AdamW(
                [logits], lr=lr, betas=ADAM_BETAS, eps=ADAM_EPS, weight_decay=weight_decay
            )
            for _ in range(iterations):
                optimiser.zero_grad(set_to_none=True)
                _objective(query, neighbours, torch.softmax(logits, dim=-1), objective).backward()
                optimiser.step()
            with torch.no_grad():
                weights = torch.softmax(logits, dim=-1)
        else:
            weights = _refine_mlp(
                query,
                neighbours,
                iterations,
                lr,
                weight_decay,
                objective,
                hidden,
                generator,
                init,
                chunk_size,
            )
        weights = weights.detach()
        return AffineFit(weights, _positions(weights, neighbour_poses.detach()))


def _refine_mlp(
    query: Tensor,
    neighbours: Tensor,
    iterations: int,
    lr: float,
    weight_decay: float,
    objective: Objective,
    hidden: Sequence[int] | None,
    generator: torch.Generator | None,
    init: InitParams | None,
    chunk_size: int,
) -> Tensor:
    """Final softmax weights [B, k] of the batched weight regressors (``refine_affine``)."""
    batch, k, dim = neighbours.shape
    fan_in = k * dim
    if hidden is not None and (len(hidden) == 0 or min(hidden) < 1):
        raise ValueError(f"hidden must list at least one positive width, got {hidden}")
    if init is None:
        sizes = [fan_in, *(regressor_hidden_sizes(k) if hidden is None else hidden), k]
        width = sizes[1]
        bound = 1.0 / math.sqrt(fan_in)
        norms = torch.linalg.vector_norm(neighbours.reshape(batch, -1), dim=-1, keepdim=True)
        first_preactivation = (
            _empty_for_draw((batch, width), generator, query)
            .normal_(generator=generator)
            .to(query.device)
            * norms
            * (bound / math.sqrt(3.0))
        )
        first_bias = _uniform((batch, width), bound, generator, query)
        # one draw of the later layers' initial values serves every query (each still starts
        # from nn.Linear's distribution; each then trains its own copy)
        layers = [
            (weight.expand(batch, -1, -1), bias.expand(batch, -1))
            for weight, bias in _uniform_layers(1, sizes[1:], generator, query)
        ]
    else:
        (first_weight, first_bias), *layers = _check_mlp_init(init, batch, k, dim)
        first_preactivation = torch.einsum(
            "bi,bio->bo", neighbours.reshape(batch, -1), first_weight.to(query)
        )
    chunks = []
    for start in range(0, batch, chunk_size):
        rows = slice(start, start + chunk_size)
        chunks.append(
            _fit_regressor(
                query[rows],
                neighbours[rows],
                first_preactivation[rows],
                first_bias[rows].to(query),
                [(weight[rows].to(query), bias[rows].to(query)) for weight, bias in layers],
                iterations,
                lr,
                weight_decay,
                objective,
            )
        )
    return torch.cat(chunks, dim=0)


class _WeightRegressor(nn.Module):
    """One query's weight regressor: k encodings [k, D] -> softmax weights [k]."""

    def __init__(self, k: int, latent_dim: int, hidden: Sequence[int]) -> None:
        super().__init__()
        sizes = [k * latent_dim, *hidden, k]
        layers: list[nn.Module] = []
        for fan_in, fan_out in itertools.pairwise(sizes):
            layers += [nn.Linear(fan_in, fan_out), nn.ReLU()]
        self.net = nn.Sequential(*layers[:-1])

    def load_batched(self, layers: Sequence[LayerParams], row: int) -> None:
        """Copy the parameters of query ``row`` from batched layers (weights are transposed)."""
        linears = [m for m in self.net if isinstance(m, nn.Linear)]
        with torch.no_grad():
            for linear, (weight, bias) in zip(linears, layers, strict=True):
                linear.weight.copy_(weight[row].T)
                linear.bias.copy_(bias[row])

    def forward(self, neighbour_latents: Tensor) -> Tensor:
        return F.softmax(self.net(neighbour_latents.reshape(1, -1)), dim=1).squeeze(0)


class _FreeLogits(nn.Module):
    """One query's free logits [k] -> softmax weights [k]."""

    def __init__(self, logits: Tensor) -> None:
        super().__init__()
        self.logits = nn.Parameter(logits.detach().clone())

    def forward(self, neighbour_latents: Tensor) -> Tensor:
        return F.softmax(self.logits, dim=0)


def _closed_form_by_substitution(query: Tensor, neighbours: Tensor, ridge: float) -> Tensor:
    """One query's ``closed_form_weights`` [k] computed another way: the constraint is
    substituted (a_k = 1 − Σ_{i<k} aᵢ) and the unconstrained, ridge-augmented least squares
    in the other k − 1 weights is solved by ``torch.linalg.lstsq``. query [D]; neighbours
    [k, D]."""
    k = neighbours.shape[0]
    if k == 1:
        return torch.ones(1, dtype=neighbours.dtype, device=neighbours.device)
    spread = (neighbours - neighbours.mean(dim=0)).pow(2).sum(dim=1).mean()
    penalty = ridge * (spread if spread > 0 else torch.ones_like(spread))
    last = neighbours[-1]
    columns = (neighbours[:-1] - last).T  # [D, k − 1]
    root = penalty.sqrt()
    eye = torch.eye(k - 1, dtype=neighbours.dtype, device=neighbours.device)
    system = torch.cat([columns, root * eye, -root * torch.ones_like(eye[:1])], dim=0)
    target = torch.cat([query - last, torch.zeros(k - 1).to(query), -root.reshape(1)], dim=0)
    free = torch.linalg.lstsq(system, target.unsqueeze(1)).solution.squeeze(1)
    return torch.cat([free, (1.0 - free.sum()).reshape(1)])


def refine_affine_per_query(
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
) -> AffineFit:
    """Reference for ``refine_affine`` that processes one query at a time, as the public code.

    Same arguments and result. Each query gets a fresh ``nn.Module`` (MLP or logits) and its
    own AdamW, and is optimised with batch size 1. Without ``init`` or ``generator`` the MLP
    keeps ``nn.Linear``'s default initialisation (global RNG); with ``generator`` each query's
    parameters are drawn by ``init_weight_regressor``. ``closed_form`` is solved by another
    method than ``closed_form_weights`` (substitution and least squares, not the KKT system).
    ``chunk_size`` is accepted for a common signature and unused.
    """
    _check_inputs(
        query_latent, neighbour_latents, neighbour_poses, weight_model, objective, iterations
    )
    batch, k, dim = neighbour_latents.shape
    hidden_sizes = regressor_hidden_sizes(k) if hidden is None else tuple(hidden)
    if init is not None and weight_model == "mlp":
        hidden_sizes = tuple(
            weight.shape[2] for weight, _ in _check_mlp_init(init, batch, k, dim)[:-1]
        )
    if len(hidden_sizes) == 0 or min(hidden_sizes) < 1:
        raise ValueError(f"hidden must list at least one positive width, got {hidden}")
    if init is not None and weight_model == "softmax_logits":
        _check_logits_init(init, batch, k)
    with torch.inference_mode(False), torch.enable_grad():
        query = query_latent.detach().clone()
        neighbours = neighbour_latents.detach().to(query.dtype).clone()
        rows = []
        for row in range(batch):
            if weight_model == "closed_form":
                rows.append(_closed_form_by_substitution(query[row], neighbours[row], ridge))
                continue
            model: nn.Module
            if weight_model == "softmax_logits":
                logits = (
                    torch.zeros(k, dtype=query.dtype, device=query.device)
                    if init is None
                    else init[row]
                )
                model = _FreeLogits(logits.to(query))
            else:
                regressor = _WeightRegressor(k, dim, hidden_sizes).to(query)
                if init is not None:
                    regressor.load_batched(init, row)
                elif generator is not None:
                    drawn = init_weight_regressor(
                        1,
                        k,
                        dim,
                        hidden=hidden_sizes,
                        generator=generator,
                        dtype=query.dtype,
                        device=query.device,
                    )
                    regressor.load_batched(drawn, 0)
                model = regressor
            optimiser = torch.optim.AdamW(
                model.parameters(), lr=lr, betas=ADAM_BETAS, eps=ADAM_EPS, weight_decay=weight_decay
            )
            for _ in range(iterations):
                optimiser.zero_grad(set_to_none=True)
                weights = model(neighbours[row])
                loss = _objective(
                    query[row : row + 1], neighbours[row : row + 1], weights.unsqueeze(0), objective
                )
                loss.backward()
                optimiser.step()
            with torch.no_grad():
                rows.append(model(neighbours[row]))
        weights = torch.stack(rows).detach()
        return AffineFit(weights, _positions(weights, neighbour_poses.detach()))


def combine_orientations(
    neighbour_q: Tensor, weights: Tensor, initial_q: Tensor, mode: OrientationMode = "teacher"
) -> Tensor:
    """Orientation [B, 4] (unit, qw >= 0) of the refined pose.

    neighbour_q [B, k, 4]; weights [B, k]; initial_q [B, 4] (the teacher's estimate).
    ``"teacher"``: the initial estimate (the paper). ``"affine"``: normalised Σ aᵢ qᵢ after
    flipping each neighbour onto the hemisphere of the first (the weighted average the
    supplementary evaluates). ``"markley"``: the weighted quaternion average of Markley et al.;
    negative weights (possible with ``closed_form``) are clamped to 0 since the average needs
    non-negative weights — Σ a = 1 guarantees at least one positive weight.
    """
    if mode not in ORIENTATION_MODES:
        raise ValueError(f"orientation mode must be one of {ORIENTATION_MODES}, got {mode!r}")
    if mode == "teacher":
        return canonicalize_quaternion(initial_q)
    neighbour_q = normalize_quaternion(neighbour_q)
    weights = weights.to(neighbour_q.dtype)
    if mode == "affine":
        alignment = (neighbour_q * neighbour_q[:, :1]).sum(dim=-1, keepdim=True)
        aligned = torch.where(alignment < 0, -neighbour_q, neighbour_q)
        return canonicalize_quaternion((weights.unsqueeze(-1) * aligned).sum(dim=1))
    return average_quaternions(neighbour_q, weights.clamp(min=0.0))


def perturb_positions(
    poses: Tensor, sigma_m: float, generator: torch.Generator | None = None
) -> Tensor:
    """poses [B, 7] with N(0, sigma_m²) noise (m) added to each position coordinate.

    The orientation is kept: the random-guess check of the paper's supplementary (§1.4).
    """
    draw_device = generator.device if generator is not None else poses.device
    noise = torch.randn(
        poses.shape[0], 3, generator=generator, device=draw_device, dtype=poses.dtype
    )
    perturbed = poses.clone()
    perturbed[:, :3] += sigma_m * noise.to(poses.device)
    return perturbed


class PositionRefiner:
    """Test-time position refinement of APR estimates with a PAE and a store of train poses.

    For each query: retrieve the k nearest train poses of the initial estimate in its scene,
    encode them with the PAE (one batched call, no gradients), fit affine weights so that the
    combined encodings match the query's latent, and return Σ aᵢ xᵢ with the orientation
    chosen by ``orientation``. Defaults follow the paper and its public code: k=3, 3 AdamW
    iterations, the MLP weight regressor, the teacher's orientation; the paper's L2 objective
    and lr 1e-3 (the public script uses the mean squared error and lr 1e-2:
    ``objective="mse", lr=1e-2``). ``seed`` seeds the generator that draws the regressors.

    A plain class (not an ``nn.Module``) so the PAE it uses is not registered twice in a
    LightningModule that owns both.
    """

    def __init__(
        self,
        index: PoseIndex,
        pae: PoseEncoder,
        *,
        k: int = 3,
        iterations: int = 3,
        lr: float = 1e-3,
        weight_decay: float = 0.01,
        weight_model: WeightModel = "mlp",
        orientation: OrientationMode = "teacher",
        objective: Objective = "l2",
        hidden: Sequence[int] | None = None,
        chunk_size: int = 64,
        seed: int = 0,
    ) -> None:
        if weight_model not in WEIGHT_MODELS:
            raise ValueError(f"weight_model must be one of {WEIGHT_MODELS}, got {weight_model!r}")
        if orientation not in ORIENTATION_MODES:
            raise ValueError(f"orientation must be one of {ORIENTATION_MODES}, got {orientation!r}")
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        self.index = index
        self.pae = pae
        self.k = k
        self.iterations = iterations
        self.lr = lr
        self.weight_decay = weight_decay
        self.weight_model: WeightModel = weight_model
        self.orientation: OrientationMode = orientation
        self.objective: Objective = objective
        self.hidden = hidden
        self.chunk_size = chunk_size
        self.generator = torch.Generator().manual_seed(seed)

    def neighbour_mean(self, neighbour_indices: Tensor, initial_poses: Tensor) -> Tensor:
        """[B, 7]: the plain mean position of the retrieved neighbours ``[B, k]`` (indices into
        the index), with the orientation of ``self.orientation`` under equal weights. The
        PAE-free baseline of the same retrieval: what the affine weights add is the
        difference to it."""
        neighbours = self.index.poses[neighbour_indices.to(self.index.device)].to(initial_poses)
        weights = torch.full(neighbours.shape[:2], 1.0 / neighbours.shape[1]).to(neighbours)
        orientation = combine_orientations(
            neighbours[..., 3:], weights, initial_poses[:, 3:], self.orientation
        )
        return torch.cat([neighbours[..., :3].mean(dim=1), orientation], dim=1)

    def __call__(
        self, query_latents: Latents, initial_poses: Tensor, scenes: Tensor | None = None
    ) -> RefinementResult:
        """query_latents: the APR's latents (x, q of [B, d]); initial_poses [B, 7]: its
        estimates; scenes [B] long: the scene of each query (``PoseRegressor.estimate``
        assigns them), None only for a single-scene index.
        """
        with torch.inference_mode(False):
            device = initial_poses.device
            initial = initial_poses.detach().clone()
            indices, _ = self.index.query(initial, scenes, self.k)
            batch = initial.shape[0]
            stored = self.index.poses[indices.to(self.index.device)]
            neighbour_poses = stored.to(device)  # [B, k, 7]
            neighbour_scenes = (
                None if scenes is None else scenes.detach().clone().repeat_interleave(self.k)
            )
            with torch.no_grad():
                encoded = self.pae(neighbour_poses.reshape(batch * self.k, 7), neighbour_scenes)
            query = query_latents.joint().detach().clone()
            neighbour_latents = encoded.joint().detach().clone().reshape(batch, self.k, -1)
            fit = refine_affine(
                query,
                neighbour_latents,
                neighbour_poses,
                weight_model=self.weight_model,
                iterations=self.iterations,
                lr=self.lr,
                weight_decay=self.weight_decay,
                objective=self.objective,
                hidden=self.hidden,
                generator=self.generator,
                chunk_size=self.chunk_size,
            )
            orientation = combine_orientations(
                neighbour_poses[..., 3:], fit.weights, initial[:, 3:], self.orientation
            )
            poses = torch.cat(
                [fit.positions.to(initial.dtype), orientation.to(initial.dtype)], dim=1
            )
        return RefinementResult(poses, fit.weights, indices)
