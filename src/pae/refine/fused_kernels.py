"""The weight regressor's fit as compiled kernels (numba): ``fit_rows`` runs whole fits of a
part of the queries, forward, backward and the AdamW update of each element fused, built
from the first layer's closed-form gain (``_prepare_gain``, ``_band_gains``, in float64) and
the later layers' element-wise steps (``_adamw``, ``_decay``). ``pae.refine.fused`` prepares
their arrays and splits the queries over threads; the arithmetic is that of
``pae.refine.regressor``.
"""

from __future__ import annotations

import math

import numpy as np

from pae.core.compiled import FASTMATH, copy_into, insert_sorted, jit
from pae.refine.regressor import ADAM_EPS


@jit(nogil=True, fastmath=FASTMATH, error_model="numpy", inline="always")
def _sum_powers(a: np.ndarray, sums: np.ndarray) -> None:
    """sums [5] = Σ over the positive values of a [n] of (aᵢ, 1, aᵢ⁻¹, aᵢ⁻², aᵢ⁻³)."""
    total, count, first, second, third = 0.0, 0.0, 0.0, 0.0, 0.0
    for i in range(np.uint64(a.shape[0])):  # branch-free, so that it vectorises
        value = a[i]
        positive = value > 0.0
        inverse = 1.0 / value if positive else 0.0
        total += value
        count += 1.0 if positive else 0.0
        first += inverse
        second += inverse * inverse
        third += inverse * inverse * inverse
    sums[0], sums[1], sums[2], sums[3], sums[4] = total, count, first, second, third


@jit(nogil=True, fastmath=FASTMATH, error_model="numpy")
def _prepare_gain(a: np.ndarray, smallest: np.ndarray, sums: np.ndarray, where: np.ndarray) -> None:
    """Fill ``smallest`` [m] with the m smallest positive values of a [n] (ascending, inf
    where fewer; among equal values the first ones) and ``sums`` [m + 1, 5] with the power
    sums (aᵢ, 1, aᵢ⁻¹, aᵢ⁻², aᵢ⁻³) of the other positive values plus the c largest of
    ``smallest`` in row c. ``where`` [m] is scratch space; ``a`` is left as it was."""
    n = a.shape[0]
    m = smallest.shape[0]
    for slot in range(m):
        smallest[slot] = np.inf
        where[slot] = -1
    # the largest of m block minima bounds the m-th smallest value (the minima are m
    # distinct entries), so the search below skips most entries at one comparison each
    block = n // m
    bound = np.inf if block == 0 else 0.0
    for first in range(0, m * block, max(block, 1)):
        least = np.inf
        for i in range(first, first + block):
            value = a[i]
            least = value if value > 0.0 and value < least else least
        bound = max(bound, least)
    for i in range(n):
        value = a[i]
        if value <= bound and value > 0.0 and value < smallest[m - 1]:
            insert_sorted(smallest, where, value, i)
    for slot in range(m):  # leave the m smallest out of the sums, then put them back
        if where[slot] >= 0:
            a[where[slot]] = 0.0
    _sum_powers(a, sums[0])
    for slot in range(m):
        if where[slot] >= 0:
            a[where[slot]] = smallest[slot]
    for c in range(1, m + 1):
        for power in range(5):
            sums[c, power] = sums[c - 1, power]
        value = smallest[m - c]
        if value < np.inf:
            inverse = 1.0 / value
            sums[c, 0] += value
            sums[c, 1] += 1.0
            sums[c, 2] += inverse
            sums[c, 3] += inverse * inverse
            sums[c, 4] += inverse * inverse * inverse


@jit(nogil=True, fastmath=FASTMATH, error_model="numpy", inline="always")
def _power_sums(source: np.ndarray, a: np.ndarray, sums: np.ndarray) -> float:
    """a [n] = |source| in float64, ``sums`` [5] = its power sums (``_sum_powers``), as
    ``_prepare_gain``'s last row; returns the least positive value (inf if none)."""
    least = np.inf
    for i in range(np.uint64(a.shape[0])):
        value = abs(np.float64(source[i]))  # numba's float() would keep float32
        a[i] = value
        least = min(least, value if value > 0.0 else np.inf)
    _sum_powers(a, sums)
    return least


@jit(nogil=True, fastmath=FASTMATH, error_model="numpy", inline="always")
def _series(sums: np.ndarray, s: float, eps: float) -> float:
    """Σᵢ aᵢ² / (aᵢ·s + eps) by ``FirstLayerGain``'s series, (1/s)·Σₚ₌₀⁴ (−eps/s)ᵖ·Σᵢ
    aᵢ^(1−p), from the power sums ``sums`` [5] of ``_sum_powers`` (Horner in −eps/s)."""
    factor = -eps / s
    total = sums[4]
    for power in (3, 2, 1, 0):
        total = sums[power] + factor * total
    return total / s


@jit(nogil=True, fastmath=FASTMATH, error_model="numpy")
def _band_gains(
    a: np.ndarray,
    smallest: np.ndarray,
    sums: np.ndarray,
    spreads: np.ndarray,
    gains: np.ndarray,
    eps: float,
    ratio: float,
    scratch: np.ndarray,
) -> None:
    """gains[j] = Σᵢ aᵢ² / (aᵢ·s + eps) at s = spreads[j] > 0 for the units that
    ``_series_gains`` left NaN (some input below the series' range, aᵢ·s < ratio·eps), as
    ``FirstLayerGain`` evaluates it (float64): the series over the sums without the inputs
    below the unit's threshold (``_prepare_gain``'s sums row), plus those inputs' terms
    summed directly; when every one of the m smallest inputs is below it, all n terms
    directly. The units are taken together, so that the direct terms vectorise across them.
    ``scratch`` [5, h] is working space."""
    m = smallest.shape[0]
    units, scales, thresholds = scratch[0], scratch[1], scratch[2]
    counts, direct = scratch[3], scratch[4]
    pending = 0
    limit = 0.0
    for j in range(gains.shape[0]):
        if np.isnan(gains[j]):
            units[pending] = j
            scales[pending] = spreads[j]
            thresholds[pending] = ratio * eps / np.float64(spreads[j])
            counts[pending] = 0.0
            direct[pending] = 0.0
            if thresholds[pending] > limit:  # (a NaN threshold counts no input)
                limit = thresholds[pending]
            pending += 1
    for i in range(m):  # ascending: stop at the first input above every threshold
        value = smallest[i]
        if not value < limit:
            break
        for p in range(np.uint64(pending)):
            inside = value < thresholds[p]
            counts[p] += 1.0 if inside else 0.0
            direct[p] += value * value / (value * scales[p] + eps) if inside else 0.0
    for p in range(pending):
        s = scales[p]
        reach = m - int(counts[p])
        if reach == 0 and m < a.shape[0]:
            total = 0.0
            for i in range(a.shape[0]):
                total += a[i] * a[i] / (a[i] * s + eps)
        else:
            total = _series(sums[reach], s, eps) + direct[p]
        gains[int(units[p])] = total


@jit(nogil=True, fastmath=FASTMATH, error_model="numpy", inline="always")
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
    ``fit_rows``; ``fresh``: the moments are still zero (not read). Indices
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


@jit(nogil=True, fastmath=FASTMATH, error_model="numpy", inline="always")
def _decay(params: np.ndarray, base: int, count: int, keep: float) -> None:
    """AdamW's step of ``count`` parameters from ``base`` whose gradient and moments are all
    zero: the weight decay alone (the Adam term is 0 / (0 + eps) = 0)."""
    for j in range(np.uint64(count)):
        at = np.uint64(base) + j
        params[at] = keep * params[at]


@jit(nogil=True, fastmath=FASTMATH, error_model="numpy", inline="always")
def _first_layer_step(
    grads: np.ndarray,
    first_avg: np.ndarray,
    first_avg_sq: np.ndarray,
    bias: np.ndarray,
    spreads: np.ndarray,
    settings: np.ndarray,
    step_size: float,
    root: float,
) -> None:
    """The first layer's AdamW step for the bias b₁ [h] (gradient ``grads`` [h], moments
    updated in place), and the spreads [h] = √ν̂ of the step's denominator."""
    beta1, beta2, eps, keep = settings[0], settings[1], settings[2], settings[3]
    one = beta1 / beta1
    for j in range(np.uint64(bias.shape[0])):
        grad = grads[j]
        first = beta1 * first_avg[j] + (one - beta1) * grad
        second = beta2 * first_avg_sq[j] + (one - beta2) * grad * grad
        first_avg[j] = first
        first_avg_sq[j] = second
        spread = np.sqrt(second) * root
        spreads[j] = spread
        bias[j] = keep * bias[j] - step_size * first / (spread + eps)


@jit(nogil=True, fastmath=FASTMATH, error_model="numpy", inline="always")
def _series_gains(
    spreads: np.ndarray, gains: np.ndarray, full: np.ndarray, least: float, eps: float, ratio: float
) -> bool:
    """gains[j] = Σᵢ aᵢ² / (aᵢ·s + eps) at s = spreads[j] (float64): 0 where s = 0, by the
    series over every input (``full``, the sums of ``_power_sums``) where the least positive
    input ``least`` is in its range, and NaN where it is not (``_band_gains`` sums those);
    returns whether any is NaN. Branch-free, so that it vectorises."""
    pending = False
    for j in range(np.uint64(spreads.shape[0])):
        scale = np.float64(spreads[j])
        factor = -eps / scale  # _series written out: a call here stops the loop vectorising
        gain = full[4]
        for power in (3, 2, 1, 0):
            gain = full[power] + factor * gain
        outside = not (scale <= 0.0) and not (least >= ratio * eps / scale)
        gains[j] = np.nan if outside else (gain / scale if scale > 0.0 else 0.0)
        pending |= outside
    return pending


@jit(nogil=True, fastmath=FASTMATH, error_model="numpy")
def fit_rows(
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
    macs: np.ndarray,
) -> None:
    """Fit the weight regressors of rows ``query`` [b, D] / ``inputs`` [b, k·D] and write their
    final softmax weights to ``out`` [b, k].

    first_preactivation, first_bias [b, h]: x·W₁ and b₁ at the start; ``start`` [1 or b, P]:
    the later layers' starting values, layer by layer W [in, out] (row-major, applied as
    h @ W) then b [out], for ``sizes`` = (h, …, k). In the inputs' dtype: ``settings`` = (β₁,
    β₂, eps, 1 − lr·weight decay) and ``schedule`` [iterations, 2] = (lr / (1 − β₁ᵗ),
    1 / √(1 − β₂ᵗ)) for steps t = 1, 2, …. The loss is ‖z − Σ aᵢ ẑᵢ‖₂, or its mean square
    when ``mse``.

    A weight row whose input unit is exactly zero (a ReLU that is off) has a zero gradient;
    while it has had no other, its moments are zero too and its AdamW step is the weight
    decay alone (``_decay``), which skips the square root and division of about half the
    rows. Its input gradient is zero, so its backward dot product is skipped as well.

    ``macs`` [b] (int64) receives the multiply-adds each row's fit did: the later layers'
    forward products, input-gradient dot products and weight gradients (one per weight row
    updated, as ``value · grad``), the loss and its gradient (2·k·D per step), the first
    layer's power sums (5 per input, once) and series (5 per unit and step). Not counted: the
    element-wise AdamW arithmetic, the softmax, and the band gains' rare direct sums.
    """
    rows, dim = query.shape
    width = inputs.shape[1]
    k = width // dim
    h = sizes[0]
    layers = sizes.shape[0] - 1
    count = start.shape[1]
    beta1, keep = settings[0], settings[3]
    one = beta1 / beta1
    zero = beta1 - beta1
    iterations = schedule.shape[0]
    eps64 = np.float64(ADAM_EPS)  # the first layer's gain, in float64 as in FirstLayerGain
    params = np.empty(count, dtype=start.dtype)
    avg = np.empty(count, dtype=start.dtype)
    avg_sq = np.empty(count, dtype=start.dtype)
    total_units = 0
    for layer in range(layers + 1):
        total_units += sizes[layer]
    units = np.empty(total_units, dtype=start.dtype)  # every layer's output, after ReLU
    grads = np.empty(total_units, dtype=start.dtype)
    moving = np.empty(total_units, dtype=np.bool_)  # a weight row whose moments are not zero
    projected = np.empty(h, dtype=start.dtype)
    bias = np.empty(h, dtype=start.dtype)
    first_avg = np.empty(h, dtype=start.dtype)
    first_avg_sq = np.empty(h, dtype=start.dtype)
    spreads = np.empty(h, dtype=start.dtype)
    gains = np.empty(h, dtype=np.float64)
    scratch = np.empty((5, h), dtype=np.float64)
    combined = np.empty(dim, dtype=start.dtype)
    weight_grad = np.empty(k, dtype=start.dtype)
    a = np.empty(width, dtype=np.float64)
    smallest = np.empty(smallest_count, dtype=np.float64)
    sums = np.empty((smallest_count + 1, 5), dtype=np.float64)
    where = np.empty(smallest_count, dtype=np.int64)
    full = np.empty(5, dtype=np.float64)
    for row in range(rows):
        done = 5 * width
        least = _power_sums(inputs[row], a, full)
        prepared = False  # ``smallest`` and ``sums``, for _band_gains, made when first needed
        copy_into(start[row if start.shape[0] > 1 else 0], params)
        copy_into(first_preactivation[row], projected)
        copy_into(first_bias[row], bias)
        for j in range(h):
            first_avg[j] = zero
            first_avg_sq[j] = zero
        for j in range(total_units):
            moving[j] = False
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
                        done += fan_out
                        base = np.uint64(offset + i * fan_out)
                        for j in range(np.uint64(fan_out)):
                            units[out_at + j] += value * params[base + j]
                if layer < layers - 1:
                    for j in range(np.uint64(fan_out)):
                        units[out_at + j] = max(units[out_at + j], zero)
                offset = bias_at + fan_out
                unit_in = unit_out
            largest = units[unit_in]
            for j in range(1, k):
                largest = max(largest, units[unit_in + j])
            norm = 0.0
            for j in range(k):
                out[row, j] = math.exp(units[unit_in + j] - largest)
                norm += out[row, j]
            for j in range(k):
                out[row, j] /= norm
            if step == iterations:
                break
            done += 2 * width + 5 * h
            # loss gradient with respect to the softmax weights, then the logits
            copy_into(query[row], combined)
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
                    if value == 0:
                        grads[unit_in + i] = zero
                        if not moving[unit_in + i]:
                            _decay(params, base, fan_out, keep)
                            continue
                    else:
                        done += fan_out
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
                        not moving[unit_in + i],
                    )
                    done += fan_out
                    moving[unit_in + i] = True
            # the first layer: bias by AdamW, x·W₁ by its closed form (its moments are x ⊗ μ
            # and x² ⊗ ν, with μ, ν those of the bias)
            _first_layer_step(
                grads[:h], first_avg, first_avg_sq, bias, spreads, settings, step_size, root
            )
            if _series_gains(spreads, gains, full, least, eps64, ratio):
                if not prepared:
                    _prepare_gain(a, smallest, sums, where)
                    prepared = True
                _band_gains(a, smallest, sums, spreads, gains, eps64, ratio, scratch)
            for j in range(h):
                projected[j] = keep * projected[j] - step_size * first_avg[j] * gains[j]
        macs[row] = done
