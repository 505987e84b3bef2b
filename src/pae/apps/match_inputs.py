"""What a correspondence stage reads in `pae-localize` (:mod:`pae.render_compare.correspondences`):
the stages a run's config lists, its train views at a stage's match width and the queries'
files at that width."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from pae.apps.queries import Queries
from pae.core.errors import ConfigError, ImageError
from pae.data.datamodule import PoseDataModule
from pae.data.dataset import PoseDataset
from pae.lit.eval_outputs import teacher_descriptor, train_images
from pae.render_compare.correspondences import MatchQueries, MatchSettings, TrainImages


def configured_list(config: DictConfig, key: str) -> list[Any]:
    """What a run's ``config`` lists under ``render_compare.<key>`` (``[]``: none)."""
    stages = config.render_compare.get(key) or []
    listed = OmegaConf.to_container(stages) if OmegaConf.is_config(stages) else list(stages)
    assert isinstance(listed, list)
    return listed


def configured_matches(config: DictConfig) -> list[dict[str, Any]]:
    """The correspondence stages a run's ``config`` lists (``render_compare.matches_from_val``)."""
    return configured_list(config, "matches_from_val")


def run_train_images(
    run: tuple[Path, DictConfig],
    data: PoseDataModule,
    width: int,
    teacher: torch.nn.Module | None,
) -> TrainImages:
    """The train views at ``width`` px for a correspondence stage of the run (its folder and
    config) whose data is ``data`` (set up), retrieved by the descriptor its config names
    (``render_compare.match_descriptor``)."""
    folder, config = run
    if config.render_compare.get("match_descriptor", "teacher") != "teacher":
        return train_images(data, width, None)
    if teacher is None:
        raise ConfigError(
            f"{folder}: render_compare.match_descriptor=teacher needs the run's teacher; "
            "it has none (render_compare.match_descriptor=thumbnail)"
        )
    return train_images(data, width, teacher_descriptor(teacher, data.shorter_edge))


def match_queries(
    run: tuple[Path, DictConfig],
    queries: Queries,
    data: PoseDataModule,
    teacher: torch.nn.Module | None,
    intrinsics: Callable[[tuple[int, int], np.ndarray | None, int], Tensor],
    match: MatchSettings,
    train: TrainImages | None = None,
) -> MatchQueries | None:
    """What the correspondence stage ``match`` of the run (its folder and config) reads of
    the queries: their files at its
    match width, uncropped, with ``intrinsics`` ((h, w) on disk, the rows' focal lengths or
    None, the shorter edge in px -> [N, 4]), and the run's train views at that width
    (``train``, else read from its data, set up here); None where no stage runs."""
    if not match.active:
        return None
    table = queries.table
    size = PoseDataset(table, queries.root, table.scene_names, 1).image_size
    if size is None:
        raise ImageError("no images to localise")
    shorter = round(match.width * min(size) / size[1])
    dataset = PoseDataset(table, queries.root, table.scene_names, shorter, cache=True)
    assert dataset.images is not None
    if train is None:
        data.setup()
        train = run_train_images(run, data, match.width, teacher)
    vectors = intrinsics(size, table.focal, shorter).expand(len(table), 4)
    return MatchQueries(dataset.images, vectors, train)


MatchReader = Callable[[MatchSettings, TrainImages | None], MatchQueries | None]
"""The queries at a stage's match width (:func:`match_queries` with the run, queries, data
and intrinsics bound): the stage and the train views already read, if any."""
