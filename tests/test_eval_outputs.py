"""Joining an evaluation epoch's kept batches: each query once, in split order."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from pae.lit.eval_outputs import EVAL, collect_outputs


def _batch(index: list[int]) -> dict[str, torch.Tensor]:
    return {EVAL.index: torch.tensor(index), EVAL.pose: torch.tensor(index).float()[:, None]}


def test_collect_outputs_keeps_each_query_once_in_split_order() -> None:
    trainer = SimpleNamespace(world_size=1)
    repeated = SimpleNamespace(eval_outputs=[_batch([2, 0]), _batch([1, 2])])
    joined = collect_outputs(trainer, repeated)
    assert joined[EVAL.index].tolist() == [0, 1, 2]
    assert joined[EVAL.pose].flatten().tolist() == [0.0, 1.0, 2.0]
    in_order = SimpleNamespace(eval_outputs=[_batch([0, 1]), _batch([2, 3])])
    joined = collect_outputs(trainer, in_order)
    assert joined[EVAL.index].tolist() == [0, 1, 2, 3]
    assert joined[EVAL.pose].flatten().tolist() == [0.0, 1.0, 2.0, 3.0]
    assert len(in_order.eval_outputs) == 1  # the batches replaced by the joined one
    again = collect_outputs(trainer, in_order)
    assert again[EVAL.index].tolist() == [0, 1, 2, 3]
    assert again[EVAL.pose].data_ptr() == joined[EVAL.pose].data_ptr()  # no copy
    assert collect_outputs(trainer, SimpleNamespace(eval_outputs=[])) is None
