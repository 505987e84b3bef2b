"""Shared fixtures: a tiny synthetic dataset and a composed training config over it."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, open_dict

from pae import CONFIG_DIR
from pae.config.schemas import register_schemas

register_schemas()  # every test composes pae's configs as pae-train does

REFERENCE_LABELS = Path(
    os.environ.get("PAE_REFERENCE_LABELS")
    or Path(__file__).resolve().parents[2] / "shared" / "reference" / "labels"
)
"""The real Cambridge Landmarks and 7-Scenes label files (``7Scenes/chess_train.csv``, ...):
the folder ``PAE_REFERENCE_LABELS`` names, else ``../shared/reference/labels`` beside the
repository. Tests marked ``reference_labels`` read them, and skip where the folder is absent."""


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``reference_labels`` skip where REFERENCE_LABELS is absent, naming it."""
    if REFERENCE_LABELS.is_dir():
        return
    skip = pytest.mark.skip(reason=f"no reference label files in {REFERENCE_LABELS}")
    for item in items:
        if "reference_labels" in item.keywords:
            item.add_marker(skip)


def pytest_report_collectionfinish(config: pytest.Config, items: list[pytest.Item]) -> str:
    """One line: whether the reference label files were found, and how many tests read them."""
    using = sum("reference_labels" in item.keywords for item in items)
    found = "found" if REFERENCE_LABELS.is_dir() else "absent (those tests skip)"
    return f"reference labels: {found} at {REFERENCE_LABELS}; {using} tests read them"


TINY = {"scenes": 2, "train_frames": 24, "test_frames": 12, "size": 32}


@pytest.fixture(scope="session")
def tiny_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2-scene synthetic dataset of 32 px frames, rendered once per test session."""
    from pae.synthetic import write_synthetic_dataset

    root = tmp_path_factory.mktemp("tiny_synthetic")
    write_synthetic_dataset(root, seed=0, **TINY)
    return root


def tiny_data_overrides(root: Path) -> list[str]:
    """Overrides that point the data config (train or eval) at the tiny dataset."""
    return [
        f"data.root={root}",
        f"data.scenes={TINY['scenes']}",
        f"data.train_frames={TINY['train_frames']}",
        f"data.test_frames={TINY['test_frames']}",
        f"data.size={TINY['size']}",
        "data.crop=28",
    ]


TINY_SCENE_MODEL = [
    "scene_model.max_epochs=1",
    "scene_model.batches_per_epoch=3",
    "scene_model.rays_per_batch=1024",
    "scene_model.model.num_voxels=8000",
    "render_compare.refiner.rounds=2",
    "render_compare.refiner.candidates=4",
]
"""A scene model and refiner small enough for the tiny dataset: seconds, not a result."""


def tiny_overrides(root: Path) -> list[str]:
    """Overrides that point the default config at the tiny dataset with 1-2 epoch runs."""
    return [
        *tiny_data_overrides(root),
        "data.batch_size=8",
        "teacher.max_epochs=2",
        "student.max_epochs=2",
        "decoder.max_epochs=1",
        "rpr.max_epochs=1",
        "trainer.check_val_every_n_epoch=1",
        "callbacks=minimal",
        "+trainer.enable_progress_bar=false",
        f"student.latent_cache_dir={root.parent / 'latent_cache'}",
    ]


@pytest.fixture
def compose_train(tiny_root: Path) -> Callable[..., DictConfig]:
    """compose_train(*overrides, run_dir=...) -> the train config over the tiny dataset."""

    def make(*overrides: str, run_dir: Path | None = None) -> DictConfig:
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            cfg = compose(
                "train",
                overrides=[*tiny_overrides(tiny_root), *overrides],
                return_hydra_config=True,
            )
        if run_dir is not None:
            with open_dict(cfg):
                cfg.hydra.runtime.output_dir = str(run_dir)
        return cfg

    return make


FOCAL_CAMERA = {"fx": 25.0, "fy": 25.0, "cx": 15.5, "cy": 15.5, "width": 32, "height": 32}
"""data.camera for the tiny dataset's label files with a focal column (``with_focal_column``)."""


def with_focal_column(tiny_root: Path, out: Path, train_focal: np.ndarray) -> tuple[Path, Path]:
    """The tiny dataset's train and test label files written to ``out`` with a focal column:
    ``train_focal`` (px, one per train row) and 25 px for every test row."""
    from pae.data.labels import read_labels, write_labels

    paths = []
    for split in ("train", "test"):
        table = read_labels(tiny_root / "labels" / f"all_{split}.csv")
        focal = train_focal if split == "train" else np.full(len(table), 25.0)
        paths.append(out / f"{split}.csv")
        write_labels(paths[-1], dataclasses.replace(table, focal=focal))
    return paths[0], paths[1]


POISON_M = 1000.0
"""How far (m) the poisoned validation and test rows are moved."""
MAGENTA = (255, 0, 255)
"""The colour of every poisoned validation and test image."""


@pytest.fixture(scope="session")
def poisoned_root(tiny_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny benchmark with its validation rows (the held-out train sequences) and test
    rows moved ``POISON_M`` away and their images magenta: what reads them shows it."""
    import dataclasses
    import shutil

    import numpy as np
    from PIL import Image

    from pae.data.holdout import held_out_rows
    from pae.data.labels import read_labels, write_labels

    root = tmp_path_factory.mktemp("poisoned") / "data"
    shutil.copytree(tiny_root, root)
    for split in ("train", "test"):
        path = root / "labels" / f"all_{split}.csv"
        table = read_labels(path)
        rows = np.ones(len(table), bool) if split == "test" else held_out_rows(table, 1, 0.1)[0]
        poses = table.poses.copy()
        poses[rows, :3] += POISON_M
        write_labels(path, dataclasses.replace(table, poses=poses))
        for i in np.flatnonzero(rows).tolist():
            image = Image.open(root / table.img_path[i])
            Image.new("RGB", image.size, MAGENTA).save(root / table.img_path[i])
    return root
