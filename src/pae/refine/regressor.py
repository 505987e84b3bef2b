"""The public code's weight regressor, fitted for every query of a batch at once: the single
definition of the MLP weight model (its layers, ``ACTIVATIONS``, initialisation and AdamW
fit). ``pae.refine.fused`` compiles a part of it and declares which (``FUSED_KERNEL``);
``pae.refine.reference`` fits it one query at a time, as a test oracle.

Per query an MLP over the k concatenated neighbour encodings (k·D → 64k → 32k → 16k → k,
ReLU by default) whose softmax gives the affine weights; freshly initialised for every query
(the later layers' starting values are one draw shared by the call's queries) and optimised
with AdamW.
Every query has its own parameter tensors; the large first layer (k·D × 64k per query) is
never stored: its AdamW update is computed in closed form from the fixed input
(``_fit_chunk``, ``FirstLayerGain``). ``pae.refine.weights.refine_affine`` is the entry point.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

LayerParams = tuple[Tensor, Tensor]
"""One batched linear layer: weight [B, in, out] (applied as ``h @ W``) and bias [B, out]."""
MatchingLoss = Callable[[Tensor, Tensor, Tensor], Tensor]
"""``(query [b, D], neighbours [b, k, D], weights [b, k]) -> scalar``, summed over queries."""

ACTIVATIONS: dict[str, type[torch.nn.Module]] = {
    "relu": torch.nn.ReLU,
    "tanh": torch.nn.Tanh,
    "gelu": torch.nn.GELU,
}
"""The hidden layers' activation by name (``relu``: the public code's). A new entry is all a
new activation needs; the compiled engine runs only the ones it declares."""
ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
"""AdamW's betas and eps for every iterative weight model (the public code's defaults)."""
SERIES_RATIO = {torch.float64: 1e3, torch.float32: 30.0}
"""Per working dtype, the aᵢ·s / eps above which ``FirstLayerGain`` uses its series: the
truncation error, below ratio⁻⁵, is under the dtype's rounding (1e-15; 4e-8)."""
BAND_TERMS = 1 << 20
"""The most terms ``FirstLayerGain`` (and its plain reference) sums in one tensor."""
SMALLEST_INPUTS = 32
"""How many of a row's smallest inputs ``FirstLayerGain`` keeps sorted for its direct sums."""


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


def check_mlp_init(init: object, batch: int, k: int, dim: int) -> Sequence[LayerParams]:
    """The MLP layers of ``init``, checked to chain from k·D inputs to k outputs for ``batch``
    queries."""
    if isinstance(init, Tensor) or not isinstance(init, Sequence) or len(init) < 2:
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


@dataclass(frozen=True, eq=False)
class RegressorBatch:
    """A batch of B weight regressors at the start of their fit: their inputs query [B, D]
    and neighbours [B, k, D]; first_preactivation [B, h], the first layer's x·W₁ (W₁ is never
    stored), and first_bias [B, h]; ``layers`` the later layers (weight [1 or B, in, out],
    bias [1 or B, out]; one row is shared by every query)."""

    query: Tensor
    neighbours: Tensor
    first_preactivation: Tensor
    first_bias: Tensor
    layers: Sequence[LayerParams]

    def rows(self, rows: slice) -> RegressorBatch:
        """The regressors of ``rows``, their biases and later layers in the query's dtype and
        on its device."""
        query = self.query
        return RegressorBatch(
            query[rows],
            self.neighbours[rows],
            self.first_preactivation[rows],
            self.first_bias[rows].to(query),
            [(weight[rows].to(query), bias[rows].to(query)) for weight, bias in self.layers],
        )


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


class FirstLayerGain:
    """S[b, j] = Σᵢ aᵢ² / (aᵢ·s[b, j] + eps) for fixed a = |x| [b, n] and any s [b, h] >= 0.

    Evaluated in float64. Terms with aᵢ·s >= ratio·eps are summed with the series
    (aᵢ/s)·Σₚ₌₀⁴ (−eps/(aᵢ s))ᵖ (relative error below ratio⁻⁵) from sums of aᵢ^(1−p),
    prepared once; the others (aᵢ near 0) are summed term by term. Only the ``SMALLEST_INPUTS``
    smallest positive inputs of a row can fall below the series' range in practice: they are kept
    sorted, with suffix sums, and the rest's sums are prepared once, so a step costs
    O(b·h·SMALLEST_INPUTS), with no full sort. Rows whose threshold exceeds even those are summed
    directly, at most ``BAND_TERMS`` terms at a time. Zero inputs add nothing; s = 0 gives 0.
    """

    def __init__(self, abs_inputs: Tensor, eps: float, ratio: float) -> None:
        a = abs_inputs.to(torch.float64)
        m = min(a.shape[1], SMALLEST_INPUTS)
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
            step = max(1, BAND_TERMS // self.inputs.shape[1])
            for part in range(0, len(rows), step):
                r, c = rows[part : part + step], cols[part : part + step]
                a, scale_rc = self.inputs[r], s[r, c].unsqueeze(-1)
                result[r, c] = (a.square() / (a * scale_rc + eps)).sum(dim=-1)
        return result


def _fit_chunk(
    regressors: RegressorBatch,
    iterations: int,
    lr: float,
    weight_decay: float,
    loss: MatchingLoss,
    activation: str = "relu",
) -> Tensor:
    """Optimise a batch of weight regressors; returns their final softmax weights [b, k].

    The first layer's weight W₁ [b, n, h] (n = k·D) is never stored. Its input x is the same
    at every step, so its gradient is x ⊗ δ (δ = ∂L/∂(xW₁), equal to the first bias'
    gradient) and AdamW's moments stay x ⊗ μ and x² ⊗ ν with μ, ν [b, h] updated by the
    same rules. One AdamW step therefore changes xW₁ to
    ``(1 − lr·wd)·xW₁ − lr/(1 − β₁ᵗ) · μ ⊙ S(√(ν/(1 − β₂ᵗ)))`` with ``S`` from
    ``FirstLayerGain``: the same arithmetic as a stored W₁, at O(b·h·n) per step instead
    of the many passes over 4 tensors of that size. ``regressors.first_preactivation`` is x·W₁
    at the start; the other parameters are ordinary tensors optimised by ``torch.optim.AdamW``.
    """
    beta1, beta2 = ADAM_BETAS
    query, neighbours = regressors.query, regressors.neighbours
    inputs = neighbours.reshape(neighbours.shape[0], -1)
    gain = FirstLayerGain(inputs.abs(), ADAM_EPS, SERIES_RATIO.get(query.dtype, 1e3))
    projected = regressors.first_preactivation.detach().clone()
    first_avg = torch.zeros_like(projected)
    first_avg_sq = torch.zeros_like(projected)
    bias = regressors.first_bias.detach().clone().requires_grad_(True)
    params = [
        tensor.detach().clone().requires_grad_(True)
        for layer in regressors.layers
        for tensor in layer
    ]
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

    act = ACTIVATIONS[activation]()

    def weights_now() -> Tensor:
        hidden = act(projected + bias)
        for position, (weight, layer_bias) in enumerate(rest):
            hidden = _BatchedLinear.apply(hidden, weight, layer_bias)
            if position < len(rest) - 1:
                hidden = act(hidden)
        return torch.softmax(hidden, dim=-1)

    for step in range(1, iterations + 1):
        optimiser.zero_grad(set_to_none=True)
        loss(query, neighbours, weights_now()).backward()
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


def _scaled_by_norms(noise: Tensor, inputs: Tensor, factor: float) -> Tensor:
    """noise [B, h] · ‖inputs[b]‖₂ · factor, inputs [B, n]. On the CPU with numpy, whose
    operations run on the calling thread: a multi-threaded torch operation here would leave
    its worker threads spinning on the cores the compiled fit is about to use."""
    if noise.device.type != "cpu" or noise.dtype not in (torch.float32, torch.float64):
        return noise * torch.linalg.vector_norm(inputs, dim=-1, keepdim=True) * factor
    values, draws = inputs.detach().numpy(), noise.numpy()
    norms = np.sqrt(np.einsum("bi,bi->b", values, values))[:, None]
    return torch.from_numpy(draws * norms * draws.dtype.type(factor))


def fit_mlp_weights(
    query: Tensor,
    neighbours: Tensor,
    iterations: int,
    lr: float,
    weight_decay: float,
    loss: MatchingLoss,
    hidden: Sequence[int] | None,
    generator: torch.Generator | None,
    init: Sequence[LayerParams] | None,
    chunk_size: int,
    fused: Callable[..., Tensor] | None = None,
    activation: str = "relu",
) -> Tensor:
    """Final softmax weights [B, k] of the batched weight regressors, one per query, each
    fitted with ``iterations`` AdamW steps on ``loss`` (see ``refine_affine``, which calls it).
    query [B, D]; neighbours [B, k, D]; ``chunk_size`` queries at a time, or all of them by
    ``fused(regressors, iterations, lr, weight_decay)`` (``regressors`` a ``RegressorBatch``)
    when given (``pae.refine.fused``, the same arithmetic compiled, for the models its
    ``FUSED_KERNEL`` implements). ``activation``: a key of ``ACTIVATIONS``."""
    if activation not in ACTIVATIONS:
        raise ValueError(f"unknown activation {activation!r}; choose one of {list(ACTIVATIONS)}")
    batch, k, dim = neighbours.shape
    fan_in = k * dim
    if hidden is not None and (len(hidden) == 0 or min(hidden) < 1):
        raise ValueError(f"hidden must list at least one positive width, got {hidden}")
    if init is None:
        sizes = [fan_in, *(regressor_hidden_sizes(k) if hidden is None else hidden), k]
        width = sizes[1]
        bound = 1.0 / math.sqrt(fan_in)
        noise = _empty_for_draw((batch, width), generator, query).normal_(generator=generator)
        first_preactivation = _scaled_by_norms(
            noise.to(query.device), neighbours.reshape(batch, -1), bound / math.sqrt(3.0)
        )
        first_bias = _uniform((batch, width), bound, generator, query)
        # one draw of the later layers' initial values serves every query (each still starts
        # from nn.Linear's distribution; each then trains its own copy)
        layers = [
            (weight.expand(batch, -1, -1), bias.expand(batch, -1))
            for weight, bias in _uniform_layers(1, sizes[1:], generator, query)
        ]
    else:
        (first_weight, first_bias), *layers = check_mlp_init(init, batch, k, dim)
        first_preactivation = torch.einsum(
            "bi,bio->bo", neighbours.reshape(batch, -1), first_weight.to(query)
        )
    regressors = RegressorBatch(query, neighbours, first_preactivation, first_bias, layers)
    if fused is not None:
        return fused(regressors, iterations, lr, weight_decay)
    chunks = [
        _fit_chunk(
            regressors.rows(slice(start, start + chunk_size)),
            iterations,
            lr,
            weight_decay,
            loss,
            activation,
        )
        for start in range(0, batch, chunk_size)
    ]
    return torch.cat(chunks, dim=0)
