"""experiments/benchmark_hard/start_audit.py: the nearest train camera and the variants."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from types import ModuleType

import pytest
import torch
from torch import Tensor

SCRIPT = Path(__file__).resolve().parents[1] / "experiments/benchmark_hard/start_audit.py"


def _audit() -> ModuleType:
    spec = importlib.util.spec_from_file_location("start_audit", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _pose(x: float, yaw_deg: float) -> list[float]:
    half = math.radians(yaw_deg) / 2
    return [x, 0.0, 0.0, math.cos(half), 0.0, math.sin(half), 0.0]


def test_the_nearest_train_pose_is_of_the_querys_scene_and_weighs_degrees_against_metres() -> None:
    """A query at x = 0: the train pose 0.1 m and 30 deg away loses to the one 0.4 m and
    0 deg away (0.1 + 3 > 0.4 + 0), and a pose of another scene at the query's own place is
    never the nearest."""
    audit = _audit()
    train = torch.tensor([_pose(0.1, 30.0), _pose(0.4, 0.0), _pose(0.0, 0.0)])
    train_scenes = torch.tensor([0, 0, 1])
    query = torch.tensor([_pose(0.0, 0.0)])
    position, orientation = audit.nearest_train(query, torch.tensor([0]), train, train_scenes)
    assert abs(position.item() - 0.4) < 1e-6 and orientation.item() < 1e-3
    position, orientation = audit.nearest_train(query, torch.tensor([1]), train, train_scenes)
    assert position.item() < 1e-6


def test_a_variant_reads_whole_numbers_as_counts_and_the_rest_as_floats() -> None:
    audit = _audit()
    assert audit.parse_variant("candidates=48,highlight_quantile=0.7,rounds=12") == {
        "candidates": 48,
        "highlight_quantile": 0.7,
        "rounds": 12,
    }
    assert audit.parse_variant("") == {}
    variant = audit.parse_variant("highpass_sigma_px=4.0")
    assert isinstance(variant["highpass_sigma_px"], float)
    with pytest.raises(ValueError, match="'candidate' is not a refiner setting"):
        audit.parse_variant("candidate=48")
    with pytest.raises(ValueError, match="'rounds' is not key=number"):
        audit.parse_variant("rounds")


def test_the_renderings_stack_the_queries_above_each_models_rendering() -> None:
    """Two models that render flat grey 0.25 and 0.75: three columns of queries (white) above
    one row per model, each in its own shade."""
    from pae.scene_model.base import SceneRendering

    audit = _audit()

    class Flat:
        def __init__(self, level: float) -> None:
            self.level = level

        def render(
            self, poses: Tensor, scenes: Tensor, intrinsics: Tensor, width: int, height: int
        ) -> SceneRendering:
            return SceneRendering(torch.full((len(poses), 3, height, width), self.level))

    val = {
        "image": torch.ones(5, 3, 6, 8),
        "pose": torch.zeros(5, 7),
        "scene": torch.zeros(5, dtype=torch.long),
        "intrinsics": torch.ones(5, 4),
    }
    picture = audit.renderings({"a": Flat(0.25), "b": Flat(0.75)}, val, 3)
    assert picture.shape == (18, 24, 3) and picture.dtype.name == "uint8"
    assert (picture[:6] == 255).all()
    assert (picture[6:12] == 64).all() and (picture[12:] == 191).all()
