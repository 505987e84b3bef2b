"""The weight regressor's fit compiled into one loop per query, for CPU tensors.

``pae.refine.regressor`` fits a batch of weight regressors with batched tensor operations;
each step then streams every query's later-layer weights and AdamW moments (≈ 23 k values
each for k = 3) through memory several times, which bounds it by memory traffic. Here one
compiled function (numba) runs a query's whole fit, forward, backward and the AdamW update
of each element fused, while its parameters stay in the core's cache, then moves to the next
query. The arithmetic is that of ``pae.refine.regressor``: the first layer by its closed
form (``FirstLayerGain``'s series, in float64) and the later layers' AdamW element by
element, in the inputs' dtype. Queries are split over ``torch.get_num_threads()`` threads
(the function releases the GIL). The kernels are ``pae.refine.fused_kernels``'; this module
declares what they implement (``FUSED_KERNEL``) and drives them (``fit_mlp_weights_fused``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from pae.core.compiled import run_in_parts
from pae.refine.fused_kernels import fit_rows
from pae.refine.regressor import (
    ADAM_BETAS,
    ADAM_EPS,
    SERIES_RATIO,
    SMALLEST_INPUTS,
    RegressorBatch,
)


@dataclass(frozen=True)
class CompiledKernel:
    """What a compiled fit implements of the weight regressor ``pae.refine.regressor``
    defines: ``engine="auto"`` runs it only for a configured model it implements (the others
    take the tensor path), and ``engine="numba"`` on any other is an error.

    activations: the hidden activations (keys of ``regressor.ACTIVATIONS``); objectives: the
    matching losses; min_hidden_layers: the fewest hidden layers it takes (any number above);
    skip_rule: the arithmetic it leaves out, and why that is exact for those activations.
    """

    activations: tuple[str, ...]
    objectives: tuple[str, ...]
    min_hidden_layers: int
    skip_rule: str

    def mismatch(self, activation: str, objective: str, hidden_layers: int) -> str | None:
        """Why this kernel cannot fit the configured model (None when it can)."""
        if activation not in self.activations:
            return f"it implements activation {' or '.join(self.activations)}, not {activation!r}"
        if objective not in self.objectives:
            return f"it implements objective {' or '.join(self.objectives)}, not {objective!r}"
        if hidden_layers < self.min_hidden_layers:
            return f"it needs at least {self.min_hidden_layers} hidden layer(s)"
        return None


FUSED_KERNEL = CompiledKernel(
    activations=("relu",),
    objectives=("l2", "mse"),
    min_hidden_layers=1,
    skip_rule=(
        "a hidden unit exactly 0 after the activation adds nothing forward and gets no "
        "gradient (ReLU's derivative is 0 there), so its weight row's AdamW step is the decay "
        "alone while its moments are 0: exact for ReLU only"
    ),
)
"""What ``fit_mlp_weights_fused`` implements (``fit_rows``)."""


def _numpy(tensor: Tensor) -> np.ndarray:
    return tensor.detach().contiguous().numpy()


def fit_mlp_weights_fused(
    regressors: RegressorBatch,
    iterations: int,
    lr: float,
    weight_decay: float,
    mse: bool,
    macs: np.ndarray | None = None,
) -> Tensor:
    """Final softmax weights [B, k] of the B weight regressors ``regressors``, fitted on the
    CPU by ``fit_rows``; float32 or float64, as their query. ``macs`` [B] (int64), when given,
    receives the multiply-adds each query's fit did (see ``fit_rows``)."""
    query, neighbours, layers = regressors.query, regressors.neighbours, regressors.layers
    dtype = query.dtype
    batch, k, dim = neighbours.shape
    shared = all(weight.shape[0] == 1 or weight.stride(0) == 0 for weight, _ in layers)
    rows = 1 if shared else batch
    start = torch.cat(
        [
            part[:rows].reshape(rows, -1).to(dtype)
            for weight, bias in layers
            for part in (weight, bias)
        ],
        dim=1,
    )
    sizes = np.array([layers[0][0].shape[1], *(weight.shape[2] for weight, _ in layers)])
    beta1, beta2 = ADAM_BETAS
    np_dtype = _numpy(query[:0]).dtype
    settings = np.array([beta1, beta2, ADAM_EPS, 1.0 - lr * weight_decay], dtype=np_dtype)
    steps = np.arange(1, iterations + 1)
    schedule = np.stack(
        [lr / (1.0 - beta1**steps), 1.0 / np.sqrt(1.0 - beta2**steps)], axis=1
    ).astype(np_dtype)
    arrays = [
        _numpy(query),
        _numpy(neighbours.reshape(batch, k * dim).to(dtype)),
        _numpy(regressors.first_preactivation.to(dtype)),
        _numpy(regressors.first_bias.to(dtype)),
    ]
    start_np = _numpy(start)
    out = np.empty((batch, k), dtype=arrays[0].dtype)
    counts = np.empty(batch, dtype=np.int64) if macs is None else macs
    smallest = min(k * dim, SMALLEST_INPUTS)
    ratio = SERIES_RATIO.get(dtype, 1e3)

    def run(part: slice) -> None:
        fit_rows(
            *(array[part] for array in arrays),
            start_np if shared else start_np[part],
            sizes,
            settings,
            schedule,
            mse,
            smallest,
            ratio,
            out[part],
            counts[part],
        )

    run_in_parts(run, batch, min_rows=32)
    return torch.from_numpy(out).to(query.device)
