"""Timings of test-time refinement: batched vs per-query weight fitting, the first layer's
series against the plain sum it replaces, and the pose index."""

from __future__ import annotations

import functools
import itertools
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from pae.data.labels import LabelTable, read_labels
from pae.refine.fused import fit_mlp_weights_fused
from pae.refine.index import PoseIndex
from pae.refine.reference import WeightRegressor, first_layer_gain_direct, refine_affine_per_query
from pae.refine.regressor import (
    ADAM_BETAS,
    ADAM_EPS,
    SERIES_RATIO,
    FirstLayerGain,
    fit_mlp_weights,
    regressor_hidden_sizes,
)
from pae.refine.weights import matching_loss, refine_affine


def _seconds(run: Callable[[], object], repeats: int = 1) -> float:
    """Wall-clock seconds of ``run()``, the least of ``repeats`` runs."""
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - start)
    return best


def refine_public_loop(
    query_latent: Tensor,
    neighbour_latents: Tensor,
    neighbour_poses: Tensor,
    iterations: int = 3,
    lr: float = 1e-3,
    weight_decay: float = 0.01,
) -> Tensor:
    """The public script's refinement loop, ported as it is, as the speed baseline: one weight
    regressor and one AdamW made once and reused across queries; per query ``iterations``
    steps at batch size 1 on the mean squared latent error, the weights of the last forward
    pass give the position, then the weight matrices (not the biases) are re-initialised
    (Xavier uniform). query_latent [B, D], neighbour_latents [B, k, D], neighbour_poses
    [B, k, 7] -> positions [B, 3] (m). The AdamW moments and the biases carry over from query
    to query, as in the script, so it is a timing reference only; ``refine_affine_per_query``
    is the correctness reference."""
    batch, k, dim = neighbour_latents.shape
    model = WeightRegressor(k, dim, regressor_hidden_sizes(k))
    optimiser = torch.optim.AdamW(
        model.parameters(), lr=lr, betas=ADAM_BETAS, eps=ADAM_EPS, weight_decay=weight_decay
    )
    mse = torch.nn.MSELoss()
    positions = []
    for row in range(batch):
        for _ in range(iterations):
            optimiser.zero_grad()
            weights = model(neighbour_latents[row])
            combined = (weights.unsqueeze(-1) * neighbour_latents[row]).sum(dim=0)
            mse(query_latent[row], combined).backward()
            optimiser.step()
        with torch.no_grad():
            positions.append(weights @ neighbour_poses[row, :, :3])
        for parameter in model.parameters():
            if parameter.dim() > 1:
                torch.nn.init.xavier_uniform_(parameter)
    return torch.stack(positions)


def mlp_flops_per_query(k: int, latent_dim: int, iterations: int) -> float:
    """FLOPs of the MLP weight model for one query with every weight stored, 2 per
    multiply-add: per step a forward and a backward (the inputs' and the weights' gradients,
    twice the forward), then one last forward; the optimiser's element-wise update is not
    counted. latent_dim is D, the size of one neighbour encoding."""
    sizes = [k * latent_dim, *regressor_hidden_sizes(k), k]
    macs = sum(a * b for a, b in itertools.pairwise(sizes))
    return 2 * macs * (3 * iterations + 1)


def fused_flops_per_query(
    query: Tensor, neighbours: Tensor, iterations: int, generator: torch.Generator
) -> float:
    """FLOPs (2 per multiply-add) the fused loop actually does per query, counted by the
    loop itself (``pae.refine.fused_kernels.fit_rows``' ``macs``), with ``refine_affine``'s defaults
    (lr 1e-3, weight decay 0.01, the L2 objective) on these inputs."""
    macs = np.zeros(len(query), dtype=np.int64)
    fit_mlp_weights(
        query,
        neighbours,
        iterations,
        1e-3,
        0.01,
        functools.partial(matching_loss, objective="l2"),
        None,
        generator,
        None,
        64,
        functools.partial(fit_mlp_weights_fused, mse=False, macs=macs),
    )
    return 2.0 * float(macs.mean())


def matmul_gflops(size: int = 1024, repeats: int = 5) -> float:
    """Measured float32 matrix-product speed of this machine (GFLOP/s, best of ``repeats``)."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    a @ b
    best = _seconds(lambda: a @ b, repeats)
    return 2 * size**3 / best / 1e9


def bench_refinement(
    n_queries: int = 500,
    k: int = 3,
    latent_dim: int = 256,
    iterations: int = 3,
    seed: int = 0,
    public_queries: int = 100,
    repeats: int = 3,
) -> dict[str, float]:
    """Milliseconds per query of the MLP weight model: batched, the cleaned per-query
    reference, and the public script's loop (``refine_public_loop``, on the first
    ``public_queries`` queries), all on the same random inputs: query latents
    [n, 2·latent_dim], neighbour latents near them [n, k, 2·latent_dim], poses [n, k, 7].
    Each is warmed up on a few queries first (which also compiles the fused loop); the
    batched path, its tensor-operation path and the public loop each take the least time of
    ``repeats`` runs, so that a busy moment on a shared machine does not decide the ratio.
    "batched" is ``refine_affine``'s default on the CPU (``engine="auto"``: the fused
    compiled loop); ``tensor_ops`` is its ``engine="torch"`` path. ``speedup`` is public
    loop / batched. Two figures against the measured matrix-product speed: ``roofline_fraction``
    is the time the arithmetic the fused loop actually does (``fused_flops_per_query``,
    ``mflop_done_per_query``) needs at that speed, over the batched time (a fraction of the
    limit: at most 1 unless the loop outran the matrix product); ``stored_weight_ratio`` is
    the same for the arithmetic of the model with every weight stored
    (``mlp_flops_per_query``, ``mflop_per_query``), which the closed-form first layer and the
    skipped zero units avoid, so it may exceed 1: how much faster than that arithmetic at
    matrix-product speed the batched path runs. Also times the batched ``softmax_logits``
    and ``closed_form`` models on the same inputs.
    """
    generator = torch.Generator().manual_seed(seed)
    dim = 2 * latent_dim
    query = torch.randn(n_queries, dim, generator=generator)
    neighbours = query.unsqueeze(1) + 0.3 * torch.randn(n_queries, k, dim, generator=generator)
    poses = torch.randn(n_queries, k, 7, generator=generator)
    warm = slice(0, min(4, n_queries))
    public = slice(0, min(public_queries, n_queries))
    options = {"iterations": iterations, "generator": generator}

    refine_affine(query[warm], neighbours[warm], poses[warm], **options)
    refine_affine(query[warm], neighbours[warm], poses[warm], engine="torch", **options)
    refine_affine_per_query(query[warm], neighbours[warm], poses[warm], **options)
    refine_public_loop(query[warm], neighbours[warm], poses[warm], iterations)
    batched = _seconds(lambda: refine_affine(query, neighbours, poses, **options), repeats)
    tensor_ops = _seconds(
        lambda: refine_affine(query, neighbours, poses, engine="torch", **options), repeats
    )
    per_query = _seconds(lambda: refine_affine_per_query(query, neighbours, poses, **options))
    loop = _seconds(
        lambda: refine_public_loop(query[public], neighbours[public], poses[public], iterations),
        repeats,
    )
    logits = _seconds(
        lambda: refine_affine(query, neighbours, poses, weight_model="softmax_logits", **options)
    )
    closed = _seconds(lambda: refine_affine(query, neighbours, poses, weight_model="closed_form"))
    gflops = matmul_gflops()
    per_query_ms = 1e3 / n_queries
    batched_ms = batched * per_query_ms
    loop_ms = loop * 1e3 / (public.stop - public.start)
    flops = mlp_flops_per_query(k, dim, iterations)
    done = fused_flops_per_query(query, neighbours, iterations, generator)
    seconds_per_flop_ms = 1e3 / (gflops * 1e9)
    return {
        "bench/refine/batched_ms_per_query": batched_ms,
        "bench/refine/tensor_ops_ms_per_query": tensor_ops * per_query_ms,
        "bench/refine/per_query_ms_per_query": per_query * per_query_ms,
        "bench/refine/public_loop_ms_per_query": loop_ms,
        "bench/refine/speedup": loop_ms / batched_ms,
        "bench/refine/speedup_vs_per_query": per_query * per_query_ms / batched_ms,
        "bench/refine/mflop_per_query": flops / 1e6,
        "bench/refine/matmul_gflops": gflops,
        "bench/refine/mflop_done_per_query": done / 1e6,
        "bench/refine/roofline_fraction": done * seconds_per_flop_ms / batched_ms,
        "bench/refine/stored_weight_ratio": flops * seconds_per_flop_ms / batched_ms,
        "bench/refine/softmax_logits_ms_per_query": logits * per_query_ms,
        "bench/refine/closed_form_ms_per_query": closed * per_query_ms,
    }


def bench_first_layer_gain(
    batch: int = 64, k: int = 3, latent_dim: int = 256, repeats: int = 20, seed: int = 0
) -> dict[str, float]:
    """Milliseconds of one ``FirstLayerGain`` step (the MLP weight model's closed-form first
    layer) on one ``refine_affine`` chunk's sizes (``batch`` queries, n = k·2·latent_dim
    inputs, h = 64k hidden units, float32 working dtype), against the plain chunked sum it
    replaces (``first_layer_gain_direct``); each includes one third of its preparation (a
    fit prepares once and takes 3 steps). Best of ``repeats``; ``series_speedup`` is their
    ratio."""
    generator = torch.Generator().manual_seed(seed)
    inputs = torch.randn(batch, 2 * k * latent_dim, generator=generator, dtype=torch.float64)
    inputs = inputs.abs()
    scale = 1e-3 * torch.rand(batch, regressor_hidden_sizes(k)[0], generator=generator)
    scale = scale.double()
    ratio = SERIES_RATIO[torch.float32]

    def series() -> None:
        gain = FirstLayerGain(inputs, ADAM_EPS, ratio)
        for _ in range(3):
            gain(scale)

    def direct() -> None:
        for _ in range(3):
            first_layer_gain_direct(inputs, scale, ADAM_EPS)

    series(), direct()
    series_ms = min(_seconds(series) for _ in range(repeats)) * 1e3 / 3
    direct_ms = min(_seconds(direct) for _ in range(repeats)) * 1e3 / 3
    return {
        "bench/refine/first_layer_series_ms": series_ms,
        "bench/refine/first_layer_direct_ms": direct_ms,
        "bench/refine/first_layer_series_speedup": direct_ms / series_ms,
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
    Times the default (compiled) search and the tensor search (``engine="torch"``) and
    reports whether they return the same neighbours (1.0).
    """
    if not label_files:
        raise ValueError("bench_index needs at least one train label file")
    train = LabelTable.concat(read_labels(path) for path in label_files)
    test = LabelTable.concat(read_labels(_test_file(Path(path))) for path in label_files)
    names = train.scene_names
    index = PoseIndex(train.poses, train.scene_ids(names))
    tensor_index = PoseIndex(train.poses, train.scene_ids(names), engine="torch")
    rows = np.random.default_rng(0).choice(len(test), size=min(n_queries, len(test)), replace=False)
    queries = torch.from_numpy(test.poses[rows]).float()
    scenes = torch.from_numpy(test.scene_ids(names)[rows])
    index.query(queries[:8], scenes[:8], k)
    tensor_index.query(queries[:8], scenes[:8], k)
    seconds = _seconds(lambda: index.query(queries, scenes, k))
    tensor_seconds = _seconds(lambda: tensor_index.query(queries, scenes, k))
    found, tensor_found = index.query(queries, scenes, k), tensor_index.query(queries, scenes, k)
    return {
        "bench/index/memory_mb": index.memory_bytes / 1e6,
        "bench/index/ms_per_query": seconds * 1e3 / len(rows),
        "bench/index/tensor_ops_ms_per_query": tensor_seconds * 1e3 / len(rows),
        "bench/index/same_as_tensor_search": float(torch.equal(found[0], tensor_found[0])),
        "bench/index/n_poses": float(len(index)),
    }
