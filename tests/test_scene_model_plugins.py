"""Scene models as plugins: one module and one config under ``scene_model/``, built from the
config's ``_target_`` and checked before anything trains."""

from __future__ import annotations

import math
import re
import textwrap
from pathlib import Path

import pytest
import torch

from pae.core.errors import ConfigError
from pae.train import run

PLUGIN = '''
"""A scene model outside pae: one learned colour per scene."""

import torch
from torch import nn

from pae.scene_model.base import SceneModel, SceneRendering


class FlatSceneModel(SceneModel):
    has_depth = False
    trains = True
    from_run = ("n_scenes",)

    def __init__(self, n_scenes: int, brightness: float = 0.0) -> None:
        super().__init__()
        self.colour = nn.Parameter(torch.full((n_scenes, 3), brightness))

    @classmethod
    def build(cls, config, inputs):
        config = {**config, "n_scenes": inputs.data.n_scenes}
        return cls(**config), config

    def render_rays(self, origins, directions, scenes, jitter=False):
        ones = origins.new_ones(len(origins))
        return torch.sigmoid(self.colour[scenes]), ones, ones

    def render(self, poses, scenes, intrinsics, width, height):
        rgb = torch.sigmoid(self.colour[scenes])[:, :, None, None]
        return SceneRendering(rgb.expand(-1, 3, height, width))
'''

CONFIG = """
defaults:
  - base
  - _self_
model:
  _target_: flat_scene_plugin.FlatSceneModel
  brightness: 0.0
max_epochs: 1
batches_per_epoch: 3
rays_per_batch: 256
"""


@pytest.fixture
def plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """A module on sys.path and ``<dir>/scene_model/flat.yaml`` -> the searchpath override
    that adds the config folder."""
    modules = tmp_path / "modules"
    modules.mkdir()
    (modules / "flat_scene_plugin.py").write_text(textwrap.dedent(PLUGIN))
    monkeypatch.syspath_prepend(str(modules))
    configs = tmp_path / "configs" / "scene_model"
    configs.mkdir(parents=True)
    (configs / "flat.yaml").write_text(CONFIG)
    return f"hydra.searchpath=[file://{configs.parent}]"


SMALL_REFINER = ("render_compare.refiner.rounds=1", "render_compare.refiner.candidates=4")


def test_a_scene_model_in_its_own_module_and_config_trains_and_refines(
    compose_train, plugin: str, tmp_path: Path
) -> None:
    from pae.core.checkpoints import load_scene_model

    teacher_dir = tmp_path / "teacher"
    run(compose_train("stage=teacher", "teacher.max_epochs=0", run_dir=teacher_dir), teacher_dir)
    teacher_ckpt = teacher_dir / "checkpoints" / "last.ckpt"
    run_dir = tmp_path / "render_compare"
    cfg = compose_train(
        "stage=render_compare",
        "scene_model=flat",
        f"teacher_ckpt={teacher_ckpt}",
        plugin,
        *SMALL_REFINER,
        run_dir=run_dir,
    )
    metrics = run(cfg, run_dir)
    # the refiner moved the teacher's estimates against the plugin's renderings
    refined, start = (metrics[f"test/{m}/pos_median_m"] for m in ("render_compare", "teacher"))
    assert math.isfinite(refined) and refined != start
    assert metrics["test/render_compare/accepted_share"] > 0
    # a flat colour fitted with a gain and bias per image explains each image by its mean
    # colour: less than the mean train image does (which the same fit may also flatten)
    quality = (metrics[f"test/scene_model/{k}"] for k in ("psnr_db", "mean_image_psnr_db"))
    assert next(quality) < next(quality)
    loaded = load_scene_model(run_dir / "checkpoints" / "last.ckpt")
    assert type(loaded.model).__name__ == "FlatSceneModel"
    assert loaded.config == {
        "_target_": "flat_scene_plugin.FlatSceneModel",
        "brightness": 0.0,
        "n_scenes": 2,
    }
    assert not torch.equal(loaded.model.colour, torch.zeros(2, 3)), "the step trained it"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ("scene_model=flat", "+scene_model.model.brightnes=1"),
            "scene_model.model.brightnes: not an argument of flat_scene_plugin.FlatSceneModel",
        ),
        (
            ("scene_model=flat", "+scene_model.model.n_scenes=3"),
            "scene_model.model.n_scenes: filled in from the run for flat_scene_plugin.Flat",
        ),
        (("+scene_model.model.typo=1",), "scene_model.model.typo: not an argument of"),
        (
            ("scene_model.model.num_voxels=4",),
            "scene_model.model.num_voxels must be an integer >= 8",
        ),
        (("scene_model.model.margin_m=-1",), "scene_model.model.margin_m must be auto, one number"),
    ],
)
def test_a_bad_scene_model_config_stops_a_full_run_before_anything_trains(
    compose_train, plugin: str, tmp_path: Path, overrides: tuple[str, ...], message: str
) -> None:
    run_dir = tmp_path / "run"
    cfg = compose_train("stage=full", plugin, *overrides, run_dir=run_dir)
    with pytest.raises(ConfigError, match=re.escape(message)):
        run(cfg, run_dir)
    assert not run_dir.exists(), "nothing was trained or written"


def test_a_scene_model_that_needs_checkpoints_names_the_missing_one(
    compose_train, tmp_path: Path
) -> None:
    given = tmp_path / "teacher.ckpt"
    given.touch()
    cfg = compose_train("stage=render_compare", "scene_model=pae_decoder", f"teacher_ckpt={given}")
    with pytest.raises(ConfigError, match=r"stage=render_compare needs student_ckpt=PATH"):
        run(cfg, tmp_path / "run")
