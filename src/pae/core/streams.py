"""Random streams derived from (seed, stream name, number): a draw that depends on nothing that
ran before it, so a resumed run draws what an uninterrupted one would."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from contextlib import contextmanager

import torch


def derived_seed(seed: int, stream: str, number: int) -> int:
    """A 63-bit seed for draw ``number`` of ``stream`` under the run's ``seed``: the first 8
    bytes of SHA-256 over all three, so nearby numbers give unrelated seeds."""
    digest = hashlib.sha256(f"{seed}/{stream}/{number}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def generator(seed: int, stream: str, number: int) -> torch.Generator:
    """A CPU generator seeded with :func:`derived_seed`."""
    return torch.Generator().manual_seed(derived_seed(seed, stream, number))


@contextmanager
def seeded_global(seed: int, device: torch.device) -> Iterator[None]:
    """Inside the block, torch's global generators (the CPU's and ``device``'s, if a GPU) start
    from ``seed``; after it they continue as if the block had drawn nothing. For code that
    draws from the global generators without taking one."""
    devices = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        yield


def seed_global_for_batch(seed: int, step: str, epoch: int, batch: int, rank: int = 0) -> None:
    """Seed torch's global generators (the CPU's and every GPU's) for batch ``batch`` of
    training epoch ``epoch`` of ``step`` on process ``rank`` (``batch`` -1: the epoch's start,
    when its data order is drawn): what the batch then draws from them (augmentation,
    dropout) depends on (``seed``, step, rank, epoch, batch) alone. The CPU's generator and,
    once CUDA is in use, CUDA's: ``torch.manual_seed`` also seeds every other backend's and
    asks the driver whether CUDA is there, at about 1 ms a call."""
    value = derived_seed(seed, f"{step}/rank{rank}/epoch{epoch}", batch)
    torch.default_generator.manual_seed(value)
    if torch.cuda.is_initialized():
        torch.cuda.manual_seed_all(value)
