"""Timings of test-time refinement: batched vs per-query weight fitting, and the pose index."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from pae.data.labels import LabelTable, read_labels
from pae.refine.affine import refine_affine, refine_affine_per_query
from pae.refine.index import PoseIndex


def _seconds(run: Callable[[], object]) -> float:
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def bench_refinement(
    n_queries: int = 500,
    k: int = 3,
    latent_dim: int = 256,
    iterations: int = 3,
    seed: int = 0,
) -> dict[str, float]:
    """Milliseconds per query of the MLP weight model, batched and one query at a time.

    Both run on the same random inputs: query latents [n, 2·latent_dim], neighbour latents
    near them [n, k, 2·latent_dim], neighbour poses [n, k, 7]; the per-query loop is the
    public code's procedure (batch size 1, fresh regressor and AdamW per query). Each is
    warmed up on a few queries first. Also times the batched ``softmax_logits`` and
    ``closed_form`` models on the same inputs.
    """
    generator = torch.Generator().manual_seed(seed)
    dim = 2 * latent_dim
    query = torch.randn(n_queries, dim, generator=generator)
    neighbours = query.unsqueeze(1) + 0.3 * torch.randn(n_queries, k, dim, generator=generator)
    poses = torch.randn(n_queries, k, 7, generator=generator)
    warm = slice(0, min(4, n_queries))
    options = {"iterations": iterations, "generator": generator}

    refine_affine(query[warm], neighbours[warm], poses[warm], **options)
    refine_affine_per_query(query[warm], neighbours[warm], poses[warm], **options)
    batched = _seconds(lambda: refine_affine(query, neighbours, poses, **options))
    per_query = _seconds(lambda: refine_affine_per_query(query, neighbours, poses, **options))
    logits = _seconds(
        lambda: refine_affine(query, neighbours, poses, weight_model="softmax_logits", **options)
    )
    closed = _seconds(lambda: refine_affine(query, neighbours, poses, weight_model="closed_form"))
    per_query_ms = 1e3 / n_queries
    return {
        "bench/refine/batched_ms_per_query": batched * per_query_ms,
        "bench/refine/per_query_ms_per_query": per_query * per_query_ms,
        "bench/refine/speedup": per_query / batched,
        "bench/refine/softmax_logits_ms_per_query": logits * per_query_ms,
        "bench/refine/closed_form_ms_per_query": closed * per_query_ms,
    }


def _test_file(train_file: Path) -> Path:
    name = train_file.name
    if not name.endswith("_train.csv"):
        raise ValueError(f"{train_file} does not end in _train.csv: cannot find its test file")
    return train_file.with_name(name[: -len("_train.csv")] + "_test.csv")


def bench_index(label_files: Sequence[Path], n_queries: int = 1000, k: int = 3) -> dict[str, float]:
    """Memory and query time of a ``PoseIndex`` over all train poses of ``label_files``.

    label_files are ``*_train.csv`` label files; the queries are ``n_queries`` poses drawn
    (fixed seed) from the matching ``*_test.csv`` files, each searched within its scene.
    """
    if not label_files:
        raise ValueError("bench_index needs at least one train label file")
    train = LabelTable.concat(read_labels(path) for path in label_files)
    test = LabelTable.concat(read_labels(_test_file(Path(path))) for path in label_files)
    names = train.scene_names
    index = PoseIndex(train.poses, train.scene_ids(names))
    rows = np.random.default_rng(0).choice(len(test), size=min(n_queries, len(test)), replace=False)
    queries = torch.from_numpy(test.poses[rows]).float()
    scenes = torch.from_numpy(test.scene_ids(names)[rows])
    index.query(queries[:8], scenes[:8], k)
    seconds = _seconds(lambda: index.query(queries, scenes, k))
    return {
        "bench/index/memory_mb": index.memory_bytes / 1e6,
        "bench/index/ms_per_query": seconds * 1e3 / len(rows),
        "bench/index/n_poses": float(len(index)),
    }
