"""The weight regressor's fit compiled into one loop per query, for CPU tensors.

``pae.refine.regressor`` fits a batch of weight regressors with batched tensor operations;
each step then streams every query's later-layer weights and AdamW moments (≈ 23 k values
each for k = 3) through memory several times, which bounds it by memory traffic. Here one
compiled function (numba) runs a query's whole fit, forward, backward and the AdamW update
of each element fused, while its parameters stay in the core's cache, then moves to the next
query. The arithmetic is that of ``pae.refine.regressor``: the first layer by its closed
form (``_FirstLayerGain``'s series, in float64) and the later layers' AdamW element by
element, in the inputs' dtype. Queries are split over ``torch.get_num_threads()`` threads
(the function releases the GIL).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
import torch
from torch import Tensor

from pae.refine.regressor import _SMALLEST, ADAM_BETAS, ADAM_EPS, SERIES_RATIO, LayerParams

_FASTMATH = {"reassoc", "contract"}
"""Reassociated sums (vectorised reductions) and fused multiply-adds; no other liberties, so
NaN and infinity keep their meaning. ``error_model="numpy"``: a division by zero gives inf or
NaN as in numpy and torch instead of raising, which also lets divisions vectorise."""


@numba.njit(cache=True, nogil=True)
def insert_sorted(values: np.ndarray, labels: np.ndarray, value: float, label: int) -> None:
    """Insert ``value`` (with ``label``) into the ascending ``values`` [m] (and ``labels``
    [m]), dropping the last entry; the caller has checked that value < values[-1]."""
    slot = values.shape[0] - 1
    while slot > 0 and values[slot - 1] > value:
        values[slot] = values[slot - 1]
        labels[slot] = labels[slot - 1]
        slot -= 1
    values[slot] = value
    labels[slot] = label


@numba.njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _prepare_gain(
    a: np.ndarray, smallest: np.ndarray, sums: np.ndarray, where: np.ndarray, rest: np.ndarray
) -> None:
    """Fill ``smallest`` [m] with the m smallest positive values of a [n] (ascending, inf
    where fewer) and ``sums`` [m + 1, 5] with the power sums (aᵢ, 1, aᵢ⁻¹, aᵢ⁻², aᵢ⁻³) of the
    other positive values plus the c largest of ``smallest`` in row c. ``where`` [m] and
    ``rest`` [n] are scratch space."""
    n = a.shape[0]
    m = smallest.shape[0]
    smallest[:] = np.inf
    where[:] = -1
    for i in range(n):
        if a[i] > 0.0 and a[i] < smallest[m - 1]:
            insert_sorted(smallest, where, a[i], i)
    rest[:] = a
    for slot in range(m):
        if where[slot] >= 0:
            rest[where[slot]] = 0.0
    total, count, first, second, third = 0.0, 0.0, 0.0, 0.0, 0.0
    for i in range(n):  # branch-free, so that it vectorises: zeros add nothing
        value = rest[i]
        positive = value > 0.0
        inverse = 1.0 / value if positive else 0.0
        total += value
        count += 1.0 if positive else 0.0
        first += inverse
        second += inverse * inverse
        third += inverse * inverse * inverse
    sums[0, 0], sums[0, 1], sums[0, 2], sums[0, 3], sums[0, 4] = (
        total,
        count,
        first,
        second,
        third,
    )
    for c in range(1, m + 1):
        sums[c, :] = sums[c - 1, :]
        value = smallest[m - c]
        if value < np.inf:
            inverse = 1.0 / value
            sums[c, 0] += value
            sums[c, 1] += 1.0
            sums[c, 2] += inverse
            sums[c, 3] += inverse * inverse
            sums[c, 4] += inverse * inverse * inverse


@numba.njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _gain(
    a: np.ndarray,
    smallest: np.ndarray,
    sums: np.ndarray,
    s: float,
    eps: float,
    ratio: float,
) -> float:
    """Σᵢ aᵢ² / (aᵢ·s + eps) as ``_FirstLayerGain`` evaluates it (float64; s = 0 gives 0)."""
    if s <= 0.0:
        return 0.0
    m = smallest.shape[0]
    threshold = ratio * eps / s
    below = 0
    while below < m and smallest[below] < threshold:
        below += 1
    reach = m - below
    if reach == 0 and m < a.shape[0]:
        total = 0.0
        for i in range(a.shape[0]):
            total += a[i] * a[i] / (a[i] * s + eps)
        return total
    factor = -eps / s
    series = sums[reach, 4]
    for power in (3, 2, 1, 0):
        series = sums[reach, power] + factor * series
    total = series / s
    for i in range(below):
        total += smallest[i] * smallest[i] / (smallest[i] * s + eps)
    return total


@numba.njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _adamw(
    params: np.ndarray,
    avg: np.ndarray,
    avg_sq: np.ndarray,
    base: int,
    grads: np.ndarray,
    grad_base: int,
    count: int,
    value: float,
    settings: np.ndarray,
    step_size: float,
    root: float,
    fresh: bool,
) -> None:
    """One AdamW step of ``count`` parameters from ``base`` (one row of a weight, or a bias
    with ``value`` 1) whose gradient is ``value`` · grads[grad_base + j], moments ``avg``,
    ``avg_sq`` updated in place; ``settings`` and the step's ``step_size``, ``root`` as in
    ``_fit_rows``; ``fresh``: the first step, whose moments start at zero (not read). Indices
    are unsigned: numba then checks no negative index, and the loop
    vectorises."""
    beta1, beta2, eps, keep = settings[0], settings[1], settings[2], settings[3]
    one = beta1 / beta1
    for j in range(np.uint64(count)):
        at = np.uint64(base) + j
        grad = value * grads[np.uint64(grad_base) + j]
        if fresh:  # zero moments: nothing to read
            first = (one - beta1) * grad
            second = (one - beta2) * grad * grad
        else:
            first = beta1 * avg[at] + (one - beta1) * grad
            second = beta2 * avg_sq[at] + (one - beta2) * grad * grad
        avg[at] = first
        avg_sq[at] = second
        params[at] = keep * params[at] - step_size * first / (np.sqrt(second) * root + eps)


@numba.njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _fit_rows(
    query: np.ndarray,
    inputs: np.ndarray,
    first_preactivation: np.ndarray,
    first_bias: np.ndarray,
    start: np.ndarray,
    sizes: np.ndarray,
    settings: np.ndarray,
    schedule: np.ndarray,
    mse: bool,
    smallest_count: int,
    ratio: float,
    out: np.ndarray,
) -> None:
    """Fit the weight regressors of rows ``query`` [b, D] / ``inputs`` [b, k·D] and write their
    final softmax weights to ``out`` [b, k].

    first_preactivation, first_bias [b, h]: x·W₁ and b₁ at the start; ``start`` [1 or b, P]:
    the later layers' starting values, layer by layer W [in, out] (row-major, applied as
    h @ W) then b [out], for ``sizes`` = (h, …, k). In the inputs' dtype: ``settings`` = (β₁,
    β₂, eps, 1 − lr·weight decay) and ``schedule`` [iterations, 2] = (lr / (1 − β₁ᵗ),
    1 / √(1 − β₂ᵗ)) for steps t = 1, 2, …. The loss is ‖z − Σ aᵢ ẑᵢ‖₂, or its mean square
    when ``mse``.
    """
    rows, dim = query.shape
    width = inputs.shape[1]
    k = width // dim
    h = sizes[0]
    layers = sizes.shape[0] - 1
    count = start.shape[1]
    beta1, beta2, eps, keep = settings[0], settings[1], settings[2], settings[3]
    one = beta1 / beta1
    zero = beta1 - beta1
    iterations = schedule.shape[0]
    eps64 = float(eps)
    params = np.empty(count, dtype=start.dtype)
    avg = np.empty(count, dtype=start.dtype)
    avg_sq = np.empty(count, dtype=start.dtype)
    total_units = 0
    for layer in range(layers + 1):
        total_units += sizes[layer]
    units = np.empty(total_units, dtype=start.dtype)  # every layer's output, after ReLU
    grads = np.empty(total_units, dtype=start.dtype)
    projected = np.empty(h, dtype=start.dtype)
    bias = np.empty(h, dtype=start.dtype)
    first_avg = np.empty(h, dtype=start.dtype)
    first_avg_sq = np.empty(h, dtype=start.dtype)
    combined = np.empty(dim, dtype=start.dtype)
    weight_grad = np.empty(k, dtype=start.dtype)
    a = np.empty(width, dtype=np.float64)
    smallest = np.empty(smallest_count, dtype=np.float64)
    sums = np.empty((smallest_count + 1, 5), dtype=np.float64)
    count_sums = smallest_count  # the row of sums over every positive input
    where = np.empty(smallest_count, dtype=np.int64)
    rest = np.empty(width, dtype=np.float64)
    for row in range(rows):
        for i in range(width):
            a[i] = abs(float(inputs[row, i]))
        _prepare_gain(a, smallest, sums, where, rest)
        params[:] = start[row if start.shape[0] > 1 else 0]
        projected[:] = first_preactivation[row]
        bias[:] = first_bias[row]
        first_avg[:] = 0
        first_avg_sq[:] = 0
        for step in range(iterations + 1):
            # forward: every layer's output into ``units``, logits last
            for j in range(h):
                value = projected[j] + bias[j]
                units[j] = value if value > 0 else zero
            offset = 0
            unit_in = 0
            for layer in range(layers):
                fan_in, fan_out = sizes[layer], sizes[layer + 1]
                unit_out = unit_in + fan_in
                bias_at = offset + fan_in * fan_out
                out_at = np.uint64(unit_out)
                for j in range(np.uint64(fan_out)):
                    units[out_at + j] = params[np.uint64(bias_at) + j]
                for i in range(fan_in):
                    value = units[unit_in + i]
                    if value != 0:
                        base = np.uint64(offset + i * fan_out)
                        for j in range(np.uint64(fan_out)):
                            units[out_at + j] += value * params[base + j]
                if layer < layers - 1:
                    for j in range(np.uint64(fan_out)):
                        units[out_at + j] = max(units[out_at + j], zero)
                offset = bias_at + fan_out
                unit_in = unit_out
            logits = units[unit_in : unit_in + k]
            largest = logits.max()
            norm = 0.0
            for j in range(k):
                out[row, j] = math.exp(logits[j] - largest)
                norm += out[row, j]
            for j in range(k):
                out[row, j] /= norm
            if step == iterations:
                break
            # loss gradient with respect to the softmax weights, then the logits
            combined[:] = query[row]
            for j in range(k):
                neighbour = inputs[row, j * dim : (j + 1) * dim]
                share = out[row, j]
                for d in range(dim):
                    combined[d] -= share * neighbour[d]
            scale = 0.0
            if mse:
                scale = -2.0 / dim
            else:
                length = 0.0
                for d in range(dim):
                    length += combined[d] * combined[d]
                length = math.sqrt(length)
                if length > 0:
                    scale = -1.0 / length
            mean_grad = 0.0
            for j in range(k):
                neighbour = inputs[row, j * dim : (j + 1) * dim]
                dot = 0.0
                for d in range(dim):
                    dot += combined[d] * neighbour[d]
                weight_grad[j] = scale * dot
                mean_grad += out[row, j] * weight_grad[j]
            for j in range(k):
                grads[unit_in + j] = out[row, j] * (weight_grad[j] - mean_grad)
            # backward and AdamW, layer by layer from the last; each weight's input gradient
            # uses its value before the step, as backward-then-step does
            step_size, root = schedule[step, 0], schedule[step, 1]
            for layer in range(layers - 1, -1, -1):
                fan_in, fan_out = sizes[layer], sizes[layer + 1]
                unit_out = unit_in
                unit_in = unit_out - fan_in
                offset -= fan_in * fan_out + fan_out
                _adamw(
                    params,
                    avg,
                    avg_sq,
                    offset + fan_in * fan_out,
                    grads,
                    unit_out,
                    fan_out,
                    one,
                    settings,
                    step_size,
                    root,
                    step == 0,
                )
                for i in range(fan_in):
                    value = units[unit_in + i]
                    base = offset + i * fan_out
                    back = zero
                    for j in range(np.uint64(fan_out)):
                        back += params[np.uint64(base) + j] * grads[np.uint64(unit_out) + j]
                    grads[unit_in + i] = back if value > 0 else zero
                    _adamw(
                        params,
                        avg,
                        avg_sq,
                        base,
                        grads,
                        unit_out,
                        fan_out,
                        value,
                        settings,
                        step_size,
                        root,
                        step == 0,
                    )
            # the first layer: bias by AdamW, x·W₁ by its closed form (its moments are x ⊗ μ
            # and x² ⊗ ν, with μ, ν those of the bias)
            for j in range(h):
                grad = grads[j]
                first_avg[j] = beta1 * first_avg[j] + (one - beta1) * grad
                first_avg_sq[j] = beta2 * first_avg_sq[j] + (one - beta2) * grad * grad
                spread = np.sqrt(first_avg_sq[j]) * root
                bias[j] = keep * bias[j] - step_size * first_avg[j] / (spread + eps)
                scale = float(spread)
                if scale > 0.0 and smallest[0] >= ratio * eps64 / scale:
                    # every input in the series' range (the usual case): _gain's series
                    # with all the sums, inline
                    factor = -eps64 / scale
                    gain = sums[count_sums, 4]
                    for power in (3, 2, 1, 0):
                        gain = sums[count_sums, power] + factor * gain
                    gain /= scale
                else:
                    gain = _gain(a, smallest, sums, scale, eps64, ratio)
                projected[j] = keep * projected[j] - step_size * first_avg[j] * gain


def _numpy(tensor: Tensor) -> np.ndarray:
    return tensor.detach().contiguous().numpy()


def fit_mlp_weights_fused(
    query: Tensor,
    neighbours: Tensor,
    first_preactivation: Tensor,
    first_bias: Tensor,
    layers: Sequence[LayerParams],
    iterations: int,
    lr: float,
    weight_decay: float,
    mse: bool,
) -> Tensor:
    """Final softmax weights [B, k] of the weight regressors, fitted on the CPU by
    ``_fit_rows``. query [B, D]; neighbours [B, k, D]; first_preactivation, first_bias
    [B, h]; ``layers`` the later layers (weight [1 or B, in, out], bias [1 or B, out]; one
    row is shared by every query). float32 or float64, as ``query``."""
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
        _numpy(first_preactivation.to(dtype)),
        _numpy(first_bias.to(dtype)),
    ]
    start_np = _numpy(start)
    out = np.empty((batch, k), dtype=arrays[0].dtype)
    smallest = min(k * dim, _SMALLEST)
    ratio = SERIES_RATIO.get(dtype, 1e3)

    def run(part: slice) -> None:
        _fit_rows(
            *(array[part] for array in arrays),
            start_np if shared else start_np[part],
            sizes,
            settings,
            schedule,
            mse,
            smallest,
            ratio,
            out[part],
        )

    run_in_parts(run, batch, min_rows=32)
    return torch.from_numpy(out).to(query.device)


def run_in_parts(run: Callable[[slice], None], rows: int, min_rows: int) -> None:
    """Call ``run`` on consecutive row ranges of ``min_rows`` rows covering ``rows`` rows,
    on ``torch.get_num_threads()`` threads at once, each taking the next range when it is
    done (queries differ in cost): for compiled functions that release the GIL."""
    parts = [slice(lo, min(lo + min_rows, rows)) for lo in range(0, rows, min_rows)]
    threads = max(1, min(torch.get_num_threads(), len(parts)))
    if threads == 1:
        run(slice(0, rows))
        return
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(run, parts))
