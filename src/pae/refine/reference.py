"""Per-query references for the batched refinement: test oracles and benchmark baselines,
not part of the API (``pae.refine`` does not export them).

``refine_affine_per_query`` fits one query at a time with a fresh ``nn.Module`` and optimiser,
as the public code does (the closed form by another method than ``closed_form_weights``);
``first_layer_gain_direct`` is the plain chunked sum that ``FirstLayerGain``'s series
replaces.
"""

from __future__ import annotations

import inspect
import itertools
from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pae.refine.regressor import (
    ACTIVATIONS,
    ADAM_BETAS,
    ADAM_EPS,
    BAND_TERMS,
    LayerParams,
    check_mlp_init,
    init_weight_regressor,
    regressor_hidden_sizes,
)
from pae.refine.weights import (
    AffineFit,
    check_fit_inputs,
    check_logits_init,
    matching_loss,
    positions_of,
    refine_affine,
)


class WeightRegressor(nn.Module):
    """One query's weight regressor: k encodings [k, D] -> softmax weights [k]."""

    def __init__(
        self, k: int, latent_dim: int, hidden: Sequence[int], activation: str = "relu"
    ) -> None:
        super().__init__()
        sizes = [k * latent_dim, *hidden, k]
        layers: list[nn.Module] = []
        for fan_in, fan_out in itertools.pairwise(sizes):
            layers += [nn.Linear(fan_in, fan_out), ACTIVATIONS[activation]()]
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


def refine_affine_per_query(*args: Any, **kwargs: Any) -> AffineFit:
    """``refine_affine`` one query at a time, as the public code does: the test oracle.

    ``refine_affine``'s arguments (bound to its signature, defaults included, so the two
    cannot drift apart) and result. Each query gets a fresh ``nn.Module`` (MLP or logits) and
    its own AdamW, and is optimised with batch size 1. Without ``init`` or ``generator`` the
    MLP keeps ``nn.Linear``'s default initialisation (global RNG); with ``generator`` each
    query's parameters are drawn by ``init_weight_regressor``. ``closed_form`` is solved by
    another method than ``closed_form_weights`` (substitution and least squares, not the KKT
    system). ``chunk_size`` and ``engine`` do not apply.
    """
    bound = inspect.signature(refine_affine).bind(*args, **kwargs)
    bound.apply_defaults()
    options = bound.arguments
    query_latent, neighbour_latents, neighbour_poses = (
        options["query_latent"],
        options["neighbour_latents"],
        options["neighbour_poses"],
    )
    weight_model, objective, iterations = (
        options["weight_model"],
        options["objective"],
        options["iterations"],
    )
    lr, weight_decay, ridge = options["lr"], options["weight_decay"], options["ridge"]
    hidden, generator, init = options["hidden"], options["generator"], options["init"]
    activation = options["activation"]
    check_fit_inputs(
        query_latent, neighbour_latents, neighbour_poses, weight_model, objective, iterations
    )
    batch, k, dim = neighbour_latents.shape
    hidden_sizes = regressor_hidden_sizes(k) if hidden is None else tuple(hidden)
    if init is not None and weight_model == "mlp":
        hidden_sizes = tuple(
            weight.shape[2] for weight, _ in check_mlp_init(init, batch, k, dim)[:-1]
        )
    if len(hidden_sizes) == 0 or min(hidden_sizes) < 1:
        raise ValueError(f"hidden must list at least one positive width, got {hidden}")
    if init is not None and weight_model == "softmax_logits":
        check_logits_init(init, batch, k)
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
                regressor = WeightRegressor(k, dim, hidden_sizes, activation).to(query)
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
                loss = matching_loss(
                    query[row : row + 1], neighbours[row : row + 1], weights.unsqueeze(0), objective
                )
                loss.backward()
                optimiser.step()
            with torch.no_grad():
                rows.append(model(neighbours[row]))
        weights = torch.stack(rows).detach()
        return AffineFit(weights, positions_of(weights, neighbour_poses.detach()))


def first_layer_gain_direct(abs_inputs: Tensor, scale: Tensor, eps: float) -> Tensor:
    """S[b, j] = Σᵢ aᵢ² / (aᵢ·s[b, j] + eps) summed term by term in float64, at most
    ``BAND_TERMS`` terms at a time: what ``FirstLayerGain`` computes with its series.
    abs_inputs a [b, n] >= 0; scale s [b, h] >= 0 -> [b, h] (s = 0 gives 0)."""
    a, s = abs_inputs.to(torch.float64), scale.to(torch.float64)
    out = torch.empty_like(s)
    squares = a.square()
    rows = max(1, BAND_TERMS // (a.shape[1] * s.shape[1]))
    for start in range(0, len(a), rows):
        part = slice(start, start + rows)
        terms = squares[part, None, :] / (a[part, None, :] * s[part, :, None] + eps)
        out[part] = terms.sum(dim=-1)
    return torch.where(s > 0, out, 0.0)
