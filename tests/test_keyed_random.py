"""Keyed random numbers: a row's numbers follow from the seed and its key alone."""

from __future__ import annotations

import torch

from pae.core.keyed_random import keyed_normals


def test_a_rows_normals_depend_on_its_key_and_the_seed_alone() -> None:
    keys = torch.arange(4000) * 7 + 3
    normals = keyed_normals(5, keys, 101)
    assert normals.shape == (4000, 101) and normals.dtype == torch.float32
    picked = torch.tensor([17, 2, 3999, 2])
    assert torch.equal(keyed_normals(5, keys[picked], 101), normals[picked]), "batch-free"
    assert not torch.equal(keyed_normals(6, keys[:3], 101), normals[:3]), "the seed counts"
    assert not torch.equal(normals[0], normals[1]), "keys differ"
    values = normals.double().flatten()
    assert abs(float(values.mean())) < 0.01 and abs(float(values.std()) - 1) < 0.01
    tail = float((values.abs() > 3).double().mean())
    assert 0.0020 < tail < 0.0034, "a normal's tail: 0.27 % beyond 3 sd"
    columns = torch.corrcoef(normals[:, :20].T.double()) - torch.eye(20, dtype=torch.float64)
    assert columns.abs().max() < 0.06, "positions within a row uncorrelated"
