"""Random numbers that are a function of a seed and a key alone (a counter-based generator):
each row of a batch draws from its own key, so a row's numbers do not depend on which other
rows share its batch or where it sits in it."""

from __future__ import annotations

import math

import torch
from torch import Tensor

_SPLITMIX_MULTIPLIERS = (0xBF58476D1CE4E5B9 - (1 << 64), 0x94D049BB133111EB - (1 << 64))
"""SplitMix64's finaliser constants as int64 (two's complement)."""
_GOLDEN_GAMMA = 0x9E3779B97F4A7C15 - (1 << 64)
"""SplitMix64's increment as int64: consecutive counters land far apart before mixing."""
_MANTISSA = 53


def _logical_shift(values: Tensor, bits: int) -> Tensor:
    """``values`` (int64) shifted right by ``bits`` as unsigned 64-bit integers."""
    return (values >> bits) & ((1 << (64 - bits)) - 1)


def _mix(values: Tensor) -> Tensor:
    """SplitMix64's finaliser on int64 ``values`` (wrapping arithmetic): a bijection that
    spreads every input bit over every output bit."""
    first, second = _SPLITMIX_MULTIPLIERS
    values = (values ^ _logical_shift(values, 30)) * first
    values = (values ^ _logical_shift(values, 27)) * second
    return values ^ _logical_shift(values, 31)


def keyed_normals(seed: int, keys: Tensor, count: int) -> Tensor:
    """Standard normals [N, count] (float32, on ``keys``' device), row i a function of
    ``seed`` and ``keys[i]`` (int64 [N]) alone: SplitMix64 of (seed, key, position) gives
    53-bit uniforms, the Box-Muller transform normals."""
    half = -(-count // 2)
    stream = _mix(torch.tensor(seed, dtype=torch.int64, device=keys.device) * _GOLDEN_GAMMA)
    row = _mix(keys.to(torch.int64)[:, None] ^ stream)
    position = torch.arange(1, 2 * half + 1, dtype=torch.int64, device=keys.device)
    bits = _mix(row + position * _GOLDEN_GAMMA)
    uniform = (_logical_shift(bits, 64 - _MANTISSA).double() + 0.5) / 2.0**_MANTISSA
    radius = torch.sqrt(-2.0 * torch.log(uniform[:, :half]))
    angle = (2.0 * math.pi) * uniform[:, half:]
    normals = torch.cat([radius * torch.cos(angle), radius * torch.sin(angle)], 1)
    return normals[:, :count].float()
