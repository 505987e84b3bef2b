"""What the train images' fingerprint costs (``pae.data.fingerprint``), side by side in one run:
every byte of each image hashed (BLAKE2b, what checkpoints record) against 4 KiB from the
middle of each file (SHA-256, what older checkpoints recorded), on the demo's train images."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from pae import CONFIG_DIR
from pae.data.fingerprint import images_blake2b, sampled_images_sha256
from pae.data.labels import LabelTable, read_labels
from pae.synthetic import write_synthetic_dataset

PREFIX = "bench/fingerprint"


def demo_train_root(spare: Path) -> Path:
    """The folder of the demo's dataset (``experiment=demo``): its folder under
    data/synthetic/ where its label files are, else the same settings rendered into ``spare``
    (an empty folder)."""
    with initialize_config_dir(str(CONFIG_DIR), version_base=None):
        cfg = compose("train", overrides=["experiment=demo"])
    data = instantiate(cfg.data)
    root = Path(data.root)
    if (root / "labels" / "all_train.csv").is_file():
        return root
    write_synthetic_dataset(spare, **data.render_args)
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
    ``sampled_ms`` (4 KiB per file, SHA-256), ``full_over_sampled`` (their ratio),
    ``full_mb_per_s`` (the files' bytes over ``full_ms``), ``images`` and ``mb`` (their number
    and total size, 10^6 bytes)."""
    table = read_labels(root / "labels" / "all_train.csv")
    total_bytes = sum((root / relative).stat().st_size for relative in table.img_path)
    full, sampled = [], []
    for _ in range(repeats):
        full.append(_milliseconds(images_blake2b, table, root))
        sampled.append(_milliseconds(sampled_images_sha256, table, root))
    return {
        f"{PREFIX}/images": float(len(table.img_path)),
        f"{PREFIX}/mb": total_bytes / 1e6,
        f"{PREFIX}/full_ms": min(full),
        f"{PREFIX}/sampled_ms": min(sampled),
        f"{PREFIX}/full_over_sampled": min(full) / min(sampled),
        f"{PREFIX}/full_mb_per_s": total_bytes / 1e6 / (min(full) / 1000),
    }
