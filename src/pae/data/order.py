"""The order of the train rows in each epoch, drawn from (seed, epoch) alone
(:mod:`pae.core.streams`): a resumed run visits the rows an uninterrupted one would."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import torch
from torch import Tensor
from torch.utils.data import Sampler

from pae.core import streams


def trainer_epoch(data: Any) -> int:
    """The training epoch under way in the trainer of ``data`` (a data module; 0 without one)."""
    trainer = data.trainer
    return trainer.current_epoch if trainer is not None else 0


class EpochOrder(Sampler[int]):
    """The rows 0..N-1 of an epoch (``epoch``: the one under way when the order is drawn):
    a permutation or, with ``weights`` [N], N rows drawn with replacement in proportion to
    them (scenes balanced), from a generator seeded with (``seed``, epoch) alone."""

    def __init__(
        self, n: int, seed: int, epoch: Callable[[], int], weights: Tensor | None = None
    ) -> None:
        self.n = n
        self.seed = seed
        self.epoch = epoch
        self.weights = weights

    def __len__(self) -> int:
        return self.n

    def __iter__(self) -> Iterator[int]:
        draws = streams.generator(self.seed, "order", self.epoch())
        if self.weights is None:
            order = torch.randperm(self.n, generator=draws)
        else:
            order = torch.multinomial(self.weights, self.n, replacement=True, generator=draws)
        return iter(order.tolist())
