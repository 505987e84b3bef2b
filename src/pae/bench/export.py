"""`pae-bench --only export`: milliseconds per image of a teacher exported by `pae-export`
(``pae.apps.export``), run by onnxruntime on this machine's cores, beside the same teacher in
PyTorch, measured side by side in one run (alternating, best of ``repeats``) at a batch of 1
(a query as it comes) and of ``batch`` images.

The teachers are PoseNet on the demo's small CNN at its 56 px crop and on EfficientNet-B0 at
the paper's 224 px, 2 scenes, untrained: speed does not depend on the weights."""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial

import torch

from pae.apps.export import TeacherGraph, onnx_bytes
from pae.models.backbones import Backbone
from pae.models.posenet import PoseNet

TEACHERS = {
    "posenet_small_cnn_56px": (lambda: Backbone("small_cnn", pool="flatten", spatial=2), 56),
    "posenet_efficientnet_b0_224px": (lambda: Backbone("efficientnet_b0"), 224),
}
"""Name -> (its backbone, the crop in px) of each teacher timed."""


def ms_per_image(run: Callable[[], object], images: int, seconds: float) -> float:
    """Mean milliseconds per image of ``run()`` (a batch of ``images``) over as many calls as
    fill ``seconds`` (at least 3, after 2 unmeasured)."""
    for _ in range(2):
        run()
    calls = 0
    start = time.perf_counter()
    while calls < 3 or time.perf_counter() - start < seconds:
        run()
        calls += 1
    return 1000 * (time.perf_counter() - start) / (calls * images)


def bench_export(
    teachers: tuple[str, ...] = tuple(TEACHERS),
    batch: int = 16,
    repeats: int = 3,
    seconds: float = 1.0,
) -> dict[str, float]:
    """Per teacher and batch size (1 and ``batch``): ``torch_ms_per_image``,
    ``onnxruntime_ms_per_image`` (the exported graph, as many threads as torch has) and
    ``torch_over_onnxruntime`` (> 1: onnxruntime is faster), each the best of ``repeats``
    alternating measurements of about ``seconds`` each."""
    import onnxruntime

    threads = torch.get_num_threads()
    figures: dict[str, float] = {"bench/export/threads": float(threads)}
    for name in teachers:
        backbone, crop = TEACHERS[name]
        graph = TeacherGraph(PoseNet(backbone(), n_scenes=2)).eval()
        outputs = ["pose", "latent", "scene_logits"]
        model = onnx_bytes(graph, (torch.zeros(2, 3, crop, crop),), ["image"], outputs, name)
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        session = onnxruntime.InferenceSession(model, options, providers=["CPUExecutionProvider"])
        for size in (1, batch):
            images = torch.randn(size, 3, crop, crop)
            engines = {
                "torch": partial(graph, images),
                "onnxruntime": partial(session.run, None, {"image": images.numpy()}),
            }
            timed: dict[str, list[float]] = {engine: [] for engine in engines}
            with torch.no_grad():
                for _ in range(repeats):
                    for engine, run in engines.items():
                        timed[engine].append(ms_per_image(run, size, seconds))
            key = f"bench/export/{name}/batch_{size}"
            best = {engine: min(values) for engine, values in timed.items()}
            figures[f"{key}/torch_ms_per_image"] = best["torch"]
            figures[f"{key}/onnxruntime_ms_per_image"] = best["onnxruntime"]
            figures[f"{key}/torch_over_onnxruntime"] = best["torch"] / best["onnxruntime"]
    return figures
