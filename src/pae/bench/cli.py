"""`make bench`: speed and size figures, each ratio measured side by side in one run.

Prints one JSON object of `bench/...` keys. Inputs are the synthetic benchmark and, where
present, the real label files in ../shared/reference/labels (poses only).

Benchmarks (``--only`` picks some): synthetic (rendering speed), student (cached teacher
latents), refine (the MLP weight refinement), pae (PAE latency, size, Adam step), index
(pose retrieval over the reference labels), sweep (a student sweep of fresh commands),
deploy (what each method keeps and its time per query), render_compare (the refiner's time
per query and its compiled paths), render_compare_real_starts (the refiner at the real-starts
experiment's scene model and 128-px comparison: its time per query, and the peak memory of a
process refining the largest 7-Scenes test split), render_compare_scale (the scene-model step run as
`pae-train stage=render_compare` on a dataset of 7-Scenes' size, 26,000 train and 17,000
test images of 640x480: its peak resident memory, fit and refinement seconds; minutes, so
only with --only; the --scale-* options shrink it), fingerprint (the train images'
fingerprint on the demo's train split and on 640x480 PNGs, per image times 7-Scenes' 43,000:
every byte against the older 4 KiB sample per file), contention (a teacher epoch and a
render-and-compare batch alone and beside one busy process, with pae's sleeping threads and
with OpenMP's spinning ones; minutes, so only with --only), export (a teacher exported by
pae-export: onnxruntime's milliseconds per image beside PyTorch's).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from pae.bench.contention import bench_contention
from pae.bench.export import bench_export
from pae.bench.fingerprint import (
    bench_fingerprint,
    bench_fingerprint_seven_scenes_size,
    demo_train_root,
)
from pae.bench.methods import bench_methods
from pae.bench.real_starts import bench_real_starts
from pae.bench.refinement import bench_first_layer_gain, bench_index, bench_refinement
from pae.bench.render_compare import bench_other_starts, bench_render_compare
from pae.bench.rendering import measure_render_speed
from pae.bench.scale import (
    SEVEN_SCENES,
    SEVEN_SCENES_TEST,
    SEVEN_SCENES_TRAIN,
    bench_render_compare_scale,
)
from pae.core.losses import LearnedPoseLoss
from pae.core.threads import configure_threads
from pae.data.datamodule import PoseDataModule
from pae.lit.student import StudentModule
from pae.models.backbones import Backbone
from pae.models.latents import TeacherLatentDataModule
from pae.models.pae import PoseAutoEncoder
from pae.models.posenet import PoseNet
from pae.synthetic import write_synthetic_dataset

REFERENCE_LABELS = Path(__file__).resolve().parents[4] / "shared" / "reference" / "labels"


def _student_epoch_seconds(module: StudentModule, loader: DataLoader, preprocess=None) -> float:
    """Seconds of one student epoch (forward, backward, Adam step) over `loader`, with the
    training configuration's Adam (``foreach``)."""
    optimizer = torch.optim.Adam(module.pae.parameters(), lr=1e-3, foreach=True)
    start = time.perf_counter()
    for batch in loader:
        if preprocess is not None:
            batch = {**batch, "image": preprocess(batch["image"], train=False)}
        loss = module.student_loss(batch)["loss"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return time.perf_counter() - start


def bench_student_cache(
    root: Path, backbone: str, image_size: int, crop: int, repeats: int = 3
) -> dict[str, float]:
    """One student epoch over the same train images: cached teacher latents vs the teacher
    running on every batch (images decoded in memory in both cases; best of `repeats`)."""
    data = PoseDataModule(
        root=str(root),
        train_labels=str(root / "labels" / "all_train.csv"),
        test_labels=str(root / "labels" / "all_test.csv"),
        shorter_edge=image_size,
        crop=crop,
        augment=False,
        batch_size=32,
        cache_images=True,
    )
    data.setup()
    spatial = {"pool": "flatten", "spatial": 2} if backbone == "small_cnn" else {}
    teacher = PoseNet(Backbone(backbone, **spatial), n_scenes=data.n_scenes)
    pae = PoseAutoEncoder(n_scenes=data.n_scenes)
    module = StudentModule(
        teacher, pae, LearnedPoseLoss(), torch.optim.Adam, data.scene_names, {}, {}
    )
    module.train()
    cached = TeacherLatentDataModule(data, teacher)
    cached.setup("fit")
    cached_s = min(
        _student_epoch_seconds(module, cached.train_dataloader()) for _ in range(repeats)
    )
    uncached_s = min(
        _student_epoch_seconds(module, data.train_dataloader(), data.preprocess)
        for _ in range(repeats)
    )
    key = f"bench/student/{backbone}_{crop}px"
    return {
        f"{key}/epoch_cached_s": cached_s,
        f"{key}/epoch_uncached_s": uncached_s,
        f"{key}/cache_speedup": uncached_s / cached_s,
    }


def bench_adam_step(module: torch.nn.Module, repeats: int = 200) -> dict[str, float]:
    """Milliseconds of one Adam step over ``module``'s parameters (random gradients): the
    default (one update per parameter tensor), ``foreach=True`` (the configuration's,
    ``conf/optim``: the same updates to the bit, batched over the tensors) and
    ``fused=True`` (one kernel; other rounding)."""
    for parameter in module.parameters():
        parameter.grad = torch.randn_like(parameter)
    seconds = {}
    for name, options in (
        ("default", {}),
        ("foreach", {"foreach": True}),
        ("fused", {"fused": True}),
    ):
        optimizer = torch.optim.Adam(module.parameters(), lr=1e-3, weight_decay=1e-4, **options)
        for _ in range(5):
            optimizer.step()
        start = time.perf_counter()
        for _ in range(repeats):
            optimizer.step()
        seconds[name] = (time.perf_counter() - start) / repeats
    return {
        "bench/pae/adam_step_ms": 1000 * seconds["default"],
        "bench/pae/foreach_adam_step_ms": 1000 * seconds["foreach"],
        "bench/pae/foreach_adam_speedup": seconds["default"] / seconds["foreach"],
        "bench/pae/fused_adam_step_ms": 1000 * seconds["fused"],
        "bench/pae/fused_adam_speedup": seconds["default"] / seconds["fused"],
    }


def bench_pae(n_scenes: int = 2, repeats: int = 200) -> dict[str, float]:
    """Paper Table 5: latency of one PAE forward pass (batch 1, CPU) and its weight size;
    and its Adam step (``bench_adam_step``)."""
    pae = PoseAutoEncoder(n_scenes=n_scenes).eval()
    pose = torch.tensor([[0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0]])
    scene = torch.tensor([1])
    with torch.no_grad():
        for _ in range(20):
            pae(pose, scene)
        start = time.perf_counter()
        for _ in range(repeats):
            pae(pose, scene)
    latency = (time.perf_counter() - start) / repeats
    size = sum(p.numel() * p.element_size() for p in pae.parameters())
    return {
        "bench/pae/latency_ms": 1000 * latency,
        "bench/pae/size_mb": size / 1e6,
        **bench_adam_step(pae),
    }


def _train(*overrides: str) -> float:
    """Seconds of one `pae-train` command (a fresh process, as a user runs it)."""
    command = [sys.executable, "-m", "pae.train", *overrides]
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"pae-train {' '.join(overrides)} failed: {result.stderr[-2000:]}")
    return time.perf_counter() - start


def bench_sweep(
    root: Path, scenes: int, train_frames: int, test_frames: int, size: int, epochs: int = 2
) -> dict[str, float]:
    """A 3-job student sweep (pae.L=0,3,6) of one teacher, each a fresh `pae-train -m`
    command, in wall-clock seconds: one job after another with every job computing its own
    latents (`sequential_uncached_s`), one after another on one shared teacher-latent cache
    (`sequential_cached_s`), and 2 jobs at a time (joblib) on one shared cache
    (`parallel_cached_s`); each cached sweep starts with an empty cache. `speedup` =
    sequential_uncached / parallel_cached is the product of the cache's share
    (`cache_speedup` = sequential_uncached / sequential_cached) and the parallelism's
    (`parallel_speedup` = sequential_cached / parallel_cached)."""
    data = [
        f"data.root={root}",
        f"data.scenes={scenes}",
        f"data.train_frames={train_frames}",
        f"data.test_frames={test_frames}",
        f"data.size={size}",
        "callbacks=minimal",
        "+trainer.enable_progress_bar=false",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        _train("stage=teacher", "teacher.max_epochs=1", f"hydra.run.dir={out / 'teacher'}", *data)
        sweep = [
            "-m",
            "stage=student",
            f"teacher_ckpt={out / 'teacher' / 'checkpoints' / 'last.ckpt'}",
            "pae.L=0,3,6",
            f"student.max_epochs={epochs}",
            "refine=none",
            *data,
        ]
        uncached = _train(
            *sweep, "student.latent_cache_dir=null", f"hydra.sweep.dir={out / 'sequential'}"
        )
        cached = _train(
            *sweep,
            f"student.latent_cache_dir={out / 'cache_sequential'}",
            f"hydra.sweep.dir={out / 'sequential_cached'}",
        )
        parallel = _train(
            *sweep,
            "hydra/launcher=joblib",
            "hydra.launcher.n_jobs=2",
            f"student.latent_cache_dir={out / 'cache_parallel'}",
            f"hydra.sweep.dir={out / 'parallel'}",
        )
    return {
        "bench/sweep/sequential_uncached_s": uncached,
        "bench/sweep/sequential_cached_s": cached,
        "bench/sweep/parallel_cached_s": parallel,
        "bench/sweep/cache_speedup": uncached / cached,
        "bench/sweep/parallel_speedup": cached / parallel,
        "bench/sweep/speedup": uncached / parallel,
    }


BENCHMARKS = (
    "synthetic",
    "student",
    "refine",
    "pae",
    "index",
    "sweep",
    "deploy",
    "render_compare",
    "render_compare_per_image",
    "render_compare_real_starts",
    "render_compare_scale",
    "fingerprint",
    "contention",
    "export",
)
"""The benchmarks pae-bench runs (``--only`` picks some)."""
DEFAULT_BENCHMARKS = tuple(
    name for name in BENCHMARKS if name not in ("render_compare_scale", "contention")
)
"""What a plain `pae-bench` (`make bench`) runs: all but the minutes-long
render_compare_scale and contention."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pae-bench", description=__doc__)
    parser.add_argument("--train-frames", type=int, default=800, help="per scene, student bench")
    parser.add_argument("--queries", type=int, default=500, help="refinement bench queries")
    parser.add_argument("--labels", type=Path, default=REFERENCE_LABELS)
    parser.add_argument(
        "--device",
        default="cpu",
        help="torch device of the render_compare benchmark (e.g. cuda: the tensor engine)",
    )
    scale = parser.add_argument_group(
        "render_compare_scale", "the scene-model step's dataset (default: 7-Scenes' size)"
    )
    scale.add_argument("--scale-train", type=int, default=SEVEN_SCENES_TRAIN, metavar="N")
    scale.add_argument("--scale-test", type=int, default=SEVEN_SCENES_TEST, metavar="N")
    scale.add_argument(
        "--scale-scenes",
        type=int,
        default=len(SEVEN_SCENES),
        choices=range(1, len(SEVEN_SCENES) + 1),
        metavar="N",
    )
    scale.add_argument(
        "--scale-size",
        type=int,
        nargs=2,
        default=(640, 480),
        metavar=("WIDTH", "HEIGHT"),
        help="px of the image files",
    )
    scale.add_argument(
        "--scale-root",
        type=Path,
        default=None,
        help="folder for the dataset and runs (a temporary folder inside it, removed after; "
        "default: the system's temporary folder)",
    )
    parser.add_argument(
        "--only",
        nargs="+",
        choices=BENCHMARKS,
        help="run only these benchmarks (default: all but render_compare_scale and contention)",
    )
    args = parser.parse_args(argv)
    print(configure_threads().summary(), file=sys.stderr)
    torch.manual_seed(0)
    chosen = set(args.only or DEFAULT_BENCHMARKS)
    figures: dict[str, float] = {}
    if "synthetic" in chosen:
        figures["bench/synthetic/frames_per_s"] = measure_render_speed()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        if chosen & {"student", "sweep"}:
            write_synthetic_dataset(root, scenes=2, train_frames=args.train_frames, test_frames=20)
        if "student" in chosen:
            demo_teacher = bench_student_cache(root, "small_cnn", 64, 56)
            figures |= demo_teacher
            figures["bench/student/cache_speedup"] = demo_teacher[
                "bench/student/small_cnn_56px/cache_speedup"
            ]
            small = Path(tmp) / "paper_size"
            write_synthetic_dataset(small, scenes=1, train_frames=64, test_frames=4, size=256)
            figures |= bench_student_cache(small, "efficientnet_b0", 256, 224, repeats=1)
        if "sweep" in chosen:
            figures |= bench_sweep(root, 2, args.train_frames, 20, 64)
        if "fingerprint" in chosen:
            demo = root / "demo"
            demo.mkdir()
            figures |= bench_fingerprint(demo_train_root(demo))
            figures |= bench_fingerprint_seven_scenes_size(root / "seven_scenes_size")
    if "refine" in chosen:
        figures |= bench_refinement(n_queries=args.queries)
        figures |= bench_first_layer_gain()
    if "pae" in chosen:
        figures |= bench_pae()
    if "deploy" in chosen:
        figures |= bench_methods()
    if "render_compare" in chosen:
        figures |= bench_render_compare(device=args.device)
    if "render_compare_per_image" in chosen:
        figures |= bench_other_starts()
    if "render_compare_real_starts" in chosen:
        figures |= bench_real_starts()
    if "contention" in chosen:
        figures |= bench_contention()
    if "export" in chosen:
        figures |= bench_export()
    if "render_compare_scale" in chosen:
        figures |= bench_render_compare_scale(
            args.scale_train,
            args.scale_test,
            args.scale_scenes,
            *args.scale_size,
            root=args.scale_root,
        )
    train_files = sorted(args.labels.glob("*/*_train.csv")) if args.labels.is_dir() else []
    if train_files and "index" in chosen:
        figures |= bench_index(train_files)
    print(json.dumps({k: round(v, 4) for k, v in figures.items()}, indent=2, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
