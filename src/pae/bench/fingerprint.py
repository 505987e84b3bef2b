"""What the train images' fingerprint costs (``pae.data.fingerprint``), side by side in one run:
every byte of each image hashed (BLAKE2b, what checkpoints record) against 4 KiB from the
middle of each file (SHA-256, what older checkpoints recorded), and a run's first fingerprint
with the digest cache (every file hashed, the cache written) against a re-run's (each file's
digest read back from the cache), on the demo's train images and on images of 7-Scenes' size
(640x480 PNG), whose per-image cost gives 7-Scenes' 43,000."""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from hydra.utils import instantiate

from pae.config.schemas import compose_config
from pae.data.fingerprint import CACHE_NAME, DigestCache, images_blake2b, sampled_images_sha256
from pae.data.labels import LabelTable, read_labels, write_labels
from pae.synthetic import write_synthetic_dataset

PREFIX = "bench/fingerprint"
SEVEN_SCENES_IMAGES = 43_000
"""7-Scenes' train and test images (26,000 + 17,000 colour frames of 640x480)."""


def demo_train_root(spare: Path) -> Path:
    """The folder of the demo's dataset (``experiment=demo``): its folder under
    data/synthetic/ where its label files are, else the same settings rendered into ``spare``
    (an empty folder)."""
    cfg = compose_config("train", ["experiment=demo"])
    data = instantiate(cfg.data)
    root = Path(data.root)
    if (root / "labels" / "all_train.csv").is_file():
        return root
    write_synthetic_dataset(spare, data.render_settings)
    return spare


def _milliseconds(
    hash_images: Callable[[LabelTable, Path], str], table: LabelTable, root: Path
) -> float:
    """Milliseconds of one ``hash_images`` over ``table``'s images."""
    start = time.perf_counter()
    hash_images(table, root)
    return 1000 * (time.perf_counter() - start)


def bench_fingerprint(root: Path, repeats: int = 5) -> dict[str, float]:
    """The fingerprint of the train images of the dataset at ``root`` (labels/all_train.csv),
    best of ``repeats`` alternating runs on a warm disk: ``full_ms`` (every byte, BLAKE2b),
    ``sampled_ms`` (4 KiB per file, SHA-256), ``cached_first_ms`` (every byte with an empty
    digest cache: each file hashed and the cache written, a run's first fingerprint) and
    ``cached_rerun_ms`` (the cache read back and each file's size and modification time
    checked, every later step and run), ``full_over_sampled`` and ``full_over_rerun`` (their
    ratios), ``full_mb_per_s`` (the files' bytes over ``full_ms``), ``images`` and ``mb``
    (their number and total size, 10^6 bytes). The cache is kept in a temporary folder, not
    beside the data."""
    table = read_labels(root / "labels" / "all_train.csv")
    total_bytes = sum((root / relative).stat().st_size for relative in table.img_path)
    full, sampled, first, rerun = [], [], [], []
    with tempfile.TemporaryDirectory() as folder:
        cache = Path(folder) / CACHE_NAME

        def first_run(table: LabelTable, root: Path) -> str:
            cache.unlink(missing_ok=True)
            return images_blake2b(table, root, DigestCache(cache, root))

        def later_run(table: LabelTable, root: Path) -> str:
            return images_blake2b(table, root, DigestCache(cache, root))

        for _ in range(repeats):
            full.append(_milliseconds(images_blake2b, table, root))
            sampled.append(_milliseconds(sampled_images_sha256, table, root))
            first.append(_milliseconds(first_run, table, root))
            rerun.append(_milliseconds(later_run, table, root))
    return {
        f"{PREFIX}/images": float(len(table.img_path)),
        f"{PREFIX}/mb": total_bytes / 1e6,
        f"{PREFIX}/full_ms": min(full),
        f"{PREFIX}/sampled_ms": min(sampled),
        f"{PREFIX}/cached_first_ms": min(first),
        f"{PREFIX}/cached_rerun_ms": min(rerun),
        f"{PREFIX}/full_over_sampled": min(full) / min(sampled),
        f"{PREFIX}/full_over_rerun": min(full) / min(rerun),
        f"{PREFIX}/full_mb_per_s": total_bytes / 1e6 / (min(full) / 1000),
    }


def seven_scenes_sized_root(folder: Path, count: int, seed: int = 0) -> Path:
    """``count`` 640x480 PNG images with a photograph's entropy (smooth shading, texture and
    sensor noise; about 7-Scenes' frame size on disk) and their labels/all_train.csv, written
    into ``folder``."""
    generator = np.random.default_rng(seed)
    v, u = np.mgrid[0:480, 0:640].astype(np.float32)
    paths = []
    for index in range(count):
        phase = generator.uniform(0, 2 * np.pi, 3).astype(np.float32)
        shading = 110 + 60 * np.sin(u / 97 + phase[:, None, None]) * np.cos(v / 71 + phase[0])
        texture = generator.normal(0, 18, (3, 480, 640)).astype(np.float32)
        image = np.clip(shading + texture, 0, 255).astype(np.uint8).transpose(1, 2, 0)
        relative = f"seq-01/frame-{index:06d}.color.png"
        (folder / "seq-01").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(folder / relative), image)
        paths.append(relative)
    poses = np.zeros((count, 7))
    poses[:, 3] = 1.0
    table = LabelTable(["sized"] * count, ["train"] * count, ["seq-01"] * count, paths, poses)
    write_labels(folder / "labels" / "all_train.csv", table)
    return folder


def bench_fingerprint_seven_scenes_size(folder: Path, count: int = 200) -> dict[str, float]:
    """:func:`bench_fingerprint` on ``count`` images of 7-Scenes' size written into
    ``folder`` (:func:`seven_scenes_sized_root`), under ``bench/fingerprint_7scenes_size``,
    with ``full_s_for_7scenes``, ``sampled_s_for_7scenes``, ``cached_first_s_for_7scenes``
    and ``cached_rerun_s_for_7scenes``: the per-image cost times 7-Scenes'
    ``SEVEN_SCENES_IMAGES`` (s)."""
    figures = bench_fingerprint(seven_scenes_sized_root(folder, count), repeats=3)
    prefix = f"{PREFIX}_7scenes_size"
    sized = {key.replace(PREFIX, prefix): value for key, value in figures.items()}
    per_image = SEVEN_SCENES_IMAGES / count / 1000
    for name in ("full", "sampled", "cached_first", "cached_rerun"):
        sized[f"{prefix}/{name}_s_for_7scenes"] = figures[f"{PREFIX}/{name}_ms"] * per_image
    return sized
