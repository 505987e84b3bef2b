"""Learning-rate schedules built from the steps they span (the ``scheduler`` factories of
pae's modules are called with ``optimizer`` and ``total_steps``)."""

from __future__ import annotations

import torch


def exponential_decay(
    optimizer: torch.optim.Optimizer, total_steps: int, final_ratio: float = 0.1
) -> torch.optim.lr_scheduler.ExponentialLR:
    """Every group's learning rate times ``final_ratio`` after ``total_steps`` steps, by the
    same factor each step (DVGO's and Plenoxels' decay of a grid's rate)."""
    if not 0.0 < final_ratio <= 1.0:
        raise ValueError(f"exponential_decay: final_ratio must lie in (0, 1], not {final_ratio}")
    if total_steps < 1:
        raise ValueError(f"exponential_decay: total_steps must be >= 1, not {total_steps}")
    return torch.optim.lr_scheduler.ExponentialLR(optimizer, final_ratio ** (1.0 / total_steps))
