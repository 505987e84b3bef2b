"""A user's own class in a group with a schema, through Hydra's idioms: ``group._target_=``
a class outside pae, ``~group.key`` for pae's keys it does not take and ``+group.key=`` for its
own, or a config file of the user's; the class is checked against its own constructor."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from pae.core.errors import ConfigError
from pae.train import run
from tests.conftest import tiny_overrides

USER_MODELS = '''
"""A user's models: constructors whose arguments differ from pae's classes'."""

import torch

from pae.models.backbones import Backbone
from pae.models.pae import PoseAutoEncoder
from pae.scene_model.base import SceneModel, SceneRendering


class NarrowPAE(PoseAutoEncoder):
    """One hidden layer of ``width`` units per branch on the raw pose."""

    def __init__(self, latent_dim: int, width: int, n_scenes: int = 1) -> None:
        super().__init__(latent_dim=latent_dim, hidden=[width], L=0, n_scenes=n_scenes)
        self.width = width


class SmallCNN(Backbone):
    """pae's small CNN, its map flattened at ``grid`` x ``grid``."""

    def __init__(self, grid: int, weights_path: str | None = None) -> None:
        super().__init__(name="small_cnn", weights_path=weights_path, pool="flatten", spatial=grid)


class GreySceneModel(SceneModel):
    """One grey level for every scene and pose, learned."""

    has_depth = False
    trains = True

    def __init__(self, grey: float) -> None:
        super().__init__()
        self.grey = torch.nn.Parameter(torch.tensor(grey))

    @classmethod
    def build(cls, config, inputs):
        return cls(**config), dict(config)

    def render_rays(self, origins, directions, scenes, jitter=False):
        ones = origins.new_ones(len(origins))
        return torch.sigmoid(self.grey).expand(len(origins), 3), ones, ones

    def render(self, poses, scenes, intrinsics, width, height):
        grey = torch.sigmoid(self.grey).expand(len(poses), 3, height, width)
        return SceneRendering(grey)
'''


@pytest.fixture
def user_modules(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The folder of the user's module ``user_models``, on sys.path."""
    modules = tmp_path / "modules"
    modules.mkdir()
    (modules / "user_models.py").write_text(textwrap.dedent(USER_MODELS))
    monkeypatch.syspath_prepend(str(modules))
    return modules


PYTHON_PATH = [path for path in os.environ.get("PYTHONPATH", "").split(os.pathsep) if path]
"""The test run's own PYTHONPATH (pae's source where tests run it so)."""

PAE_OVERRIDES = (
    "pae._target_=user_models.NarrowPAE",
    "~pae.hidden",
    "~pae.L",
    "~pae.scene_L",
    "+pae.width=8",
)
"""pae's PAE swapped for the user's: pae's keys it does not take deleted, its own added."""


def test_pae_train_trains_a_users_pae_given_on_the_command_line(
    tiny_root: Path, user_modules: Path, tmp_path: Path
) -> None:
    from pae.core.checkpoints import read_checkpoint

    run_dir = tmp_path / "run"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "pae.train",
            *tiny_overrides(tiny_root),
            "stage=pipeline",
            "teacher.max_epochs=1",
            "student.max_epochs=1",
            "refine=none",
            *PAE_OVERRIDES,
            f"hydra.run.dir={run_dir}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(user_modules), *PYTHON_PATH])},
    )
    assert result.returncode == 0, result.stderr[-2000:]
    checkpoint = read_checkpoint(run_dir / "student" / "checkpoints" / "last.ckpt")
    state = checkpoint["state_dict"]
    widths = {tuple(value.shape) for key, value in state.items() if "branch_x.0.weight" in key}
    assert widths == {(8, 3 + 13)}, "one hidden layer of 8 units on the position and scene code"


def test_a_users_backbone_and_scene_model_train(
    compose_train, user_modules: Path, tmp_path: Path
) -> None:
    run_dir = tmp_path / "run"
    cfg = compose_train(
        "stage=render_compare",
        "stage.steps=[teacher,scene_model]",
        "teacher.max_epochs=1",
        "backbone._target_=user_models.SmallCNN",
        *(f"~backbone.{key}" for key in ("name", "pretrained", "pool", "spatial")),
        "+backbone.grid=2",
        "scene_model.model._target_=user_models.GreySceneModel",
        *(f"~scene_model.model.{key}" for key in ("margin_m", "num_voxels", "samples_per_ray")),
        *(f"~scene_model.model.{key}" for key in ("appearance_field", "contract", "near_m")),
        *(f"~scene_model.model.{key}" for key in ("grow_from", "grow_at_epoch")),
        "~scene_model.model.auto_scale",
        "+scene_model.model.grey=0.0",
        "scene_model.max_epochs=1",
        "scene_model.batches_per_epoch=2",
        "scene_model.rays_per_batch=64",
        "render_compare.refiner.rounds=1",
        "render_compare.refiner.candidates=4",
        run_dir=run_dir,
    )
    metrics = run(cfg, run_dir)
    assert math.isfinite(metrics["test/teacher/pos_median_m"])
    assert "test/render_compare/pos_median_m" in metrics


def test_a_users_class_is_checked_against_its_own_constructor(
    compose_train, user_modules: Path, tmp_path: Path
) -> None:
    """pae's keys left in place, or a misspelt key of the user's, are named against the
    user's constructor before anything trains."""
    cases = (
        (("pae._target_=user_models.NarrowPAE", "+pae.width=8"), "pae.hidden: not an argument"),
        (
            (*PAE_OVERRIDES[:-1], "+pae.widht=8"),
            "pae.widht: not an argument of user_models.NarrowPAE; did you mean pae.width?",
        ),
        ((*PAE_OVERRIDES[:-1],), "pae.width: required by user_models.NarrowPAE, not set"),
    )
    for overrides, message in cases:
        cfg = compose_train("stage=pipeline", *overrides, run_dir=tmp_path / "run")
        with pytest.raises(ConfigError, match=re.escape(message)):
            run(cfg, tmp_path / "run")
        assert not (tmp_path / "run").exists()


def test_a_users_config_file_for_a_group_with_a_schema_composes(
    compose_train, user_modules: Path, tmp_path: Path
) -> None:
    """A config file of the user's own that starts from pae's option (and its schema) and
    changes the class."""
    from pae.config.validation import validate_models

    configs = tmp_path / "configs" / "pae"
    configs.mkdir(parents=True)
    (configs / "narrow.yaml").write_text(
        "defaults:\n  - mlp2\n  - _self_\n_target_: user_models.NarrowPAE\nwidth: 8\n"
    )
    cfg = compose_train(
        f"hydra.searchpath=[file://{configs.parent}]",
        "pae=narrow",
        "~pae.hidden",
        "~pae.L",
        "~pae.scene_L",
    )
    assert cfg.pae.width == 8
    validate_models(cfg)
