"""The acceptance gate of render-and-compare: a refined pose replaces the start only where
the scene model explains it better."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class RenderCompareResult(NamedTuple):
    """poses [B, 7] refined; score [B] of the refined pose; initial_score [B] of the start
    (both at the finest level, against the same rendering)."""

    poses: Tensor
    score: Tensor
    initial_score: Tensor


class GatedPoses(NamedTuple):
    """poses [B, 7]: the refined pose where accepted, else the start; accepted [B] bool."""

    poses: Tensor
    accepted: Tensor


ACCEPT_ALL = -4.0
"""A margin (floor) below every possible score gain (score; scores lie in [-2, 1]): every
refinement kept."""


def gate(
    result: RenderCompareResult, initial: Tensor, margin: float, floor: float = ACCEPT_ALL
) -> GatedPoses:
    """Keep a refined pose only where its score beats the start's by more than ``margin``
    (a ZNCC difference; below -3 accepts every refinement) and itself exceeds ``floor`` (a
    ZNCC; below -2 accepts any) -> :class:`GatedPoses`."""
    accepted = (result.score - result.initial_score > margin) & (result.score > floor)
    start = initial.to(result.poses)
    return GatedPoses(torch.where(accepted[:, None], result.poses, start), accepted)
