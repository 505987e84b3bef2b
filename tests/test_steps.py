"""The step registry (pae.steps) and the checks of model configs against their constructors."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
import yaml
from omegaconf import open_dict

from pae import CONFIG_DIR
from pae.config.validation import validate_train_config
from pae.core.errors import ConfigError
from pae.steps import RESUMABLE_CHANGES, STEPS, missing_checkpoints, steps_of
from pae.train import run

SRC = Path(__file__).resolve().parents[1] / "src" / "pae"


def test_every_stage_lists_registered_steps_and_every_step_is_in_a_stage() -> None:
    listed = set()
    for path in sorted((Path(CONFIG_DIR) / "stage").glob("*.yaml")):
        steps = yaml.safe_load(path.read_text())["steps"]
        assert steps_of(steps), path
        listed |= set(steps)
    assert listed == set(STEPS)


def test_every_fit_function_resolves_and_takes_its_checkpoints_by_name() -> None:
    import inspect

    for step in STEPS.values():
        parameters = inspect.signature(step.fit_function()).parameters
        assert list(parameters)[2:] == [*step.needs, *step.optional], step.name


def test_unknown_step_is_an_error(compose_train) -> None:
    cfg = compose_train("stage=teacher")
    with open_dict(cfg):
        cfg.stage.steps = ["teacher", "scene_modle"]
    with pytest.raises(ConfigError, match=r"unknown stage.steps \['scene_modle'\]; choose from"):
        validate_train_config(cfg)


def test_checkpoints_come_from_the_command_line_or_an_earlier_step() -> None:
    none = dict.fromkeys(("teacher_ckpt", "student_ckpt", "decoder_ckpt"))
    assert missing_checkpoints(["teacher", "student"], none) == []
    assert missing_checkpoints(["student"], none) == [("student", "teacher_ckpt")]
    assert missing_checkpoints(["decoder", "rpr"], none | {"student_ckpt": "s.ckpt"}) == []
    assert missing_checkpoints(["rpr", "decoder"], none | {"student_ckpt": "s"}) == [
        ("rpr", "decoder_ckpt")
    ]


def test_every_step_may_change_its_epochs_on_resume() -> None:
    for step in STEPS.values():
        assert f"{step.group}.max_epochs" in RESUMABLE_CHANGES


def test_no_private_name_is_imported_across_modules() -> None:
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("pae"):
                private = [a.name for a in node.names if a.name.startswith("_")]
                assert not private, f"{path}: imports {private} from {node.module}"


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (
            "+pae.LL=3",
            "pae.LL: not an argument of pae.models.pae.PoseAutoEncoder; did you mean pae.L?",
        ),
        ("+teacher.model.width=3", "teacher.model.width: not an argument of"),
        ("+backbone.depth=3", "teacher.model.backbone.depth: not an argument of"),
        ("+iapr.model.layers=2", "iapr.model.layers: not an argument of"),
        ("iapr.model.backbone=???", "iapr.model.backbone is required and not set"),
        ("pae._target_=pae.models.pae.Nothing", "pae._target_=pae.models.pae.Nothing: cannot"),
        (
            "+data.cam=1",
            "data.cam: not an argument of pae.synthetic.datamodule.SyntheticDataModule; "
            "did you mean data.camera?",
        ),
        ("+trainer.typo=1", "trainer.typo: not an argument of lightning.Trainer"),
        ("+refine.k_=1", "refine.k_: not an argument of pae.callbacks.refinement"),
        ("+render_compare.oracles=1", "did you mean render_compare.oracle?"),
        ("+render_compare.refiner.round=3", "did you mean render_compare.refiner.rounds?"),
        ("render_compare.refiner.rounds=-1", "render_compare: render_compare needs rounds"),
        (
            "+callbacks.model_checkpoint.typo=1",
            "callbacks.model_checkpoint.typo: not an argument of lightning.pytorch.callbacks",
        ),
    ],
)
def test_model_keys_are_checked_against_the_constructor_before_anything_trains(
    compose_train, tmp_path: Path, override: str, message: str
) -> None:
    cfg = compose_train("stage=pipeline", override, run_dir=tmp_path)
    with pytest.raises(ConfigError, match=re.escape(message)):
        run(cfg, tmp_path)
    assert list(tmp_path.iterdir()) == [], "nothing was trained or written"


def test_a_pae_class_with_other_arguments_passes(compose_train, tmp_path: Path) -> None:
    """A PAE without L or hidden: its own arguments are checked, not the default PAE's."""
    cfg = compose_train("stage=pipeline")
    with open_dict(cfg):
        cfg.pae = {
            "_target_": "tests.test_steps.WidePAE",
            "latent_dim": "${teacher.model.latent_dim}",
            "width": 32,
        }
    validate_train_config(cfg)
    with open_dict(cfg):
        cfg.pae.width = "wide"
    with pytest.raises(ConfigError, match=r"pae\.width must be an integer, got 'wide'"):
        validate_train_config(cfg)


class WidePAE:
    """A stand-in for another PAE architecture (only its signature is read)."""

    def __init__(self, latent_dim: int, width: int = 64, n_scenes: int = 1) -> None:
        self.latent_dim, self.width, self.n_scenes = latent_dim, width, n_scenes


def test_a_key_added_to_a_steps_settings_is_refused_with_its_nearest_name(
    compose_train, tmp_path: Path
) -> None:
    """`+teacher.max_epoch=3` (for max_epochs) would be read by nothing and train the default
    epochs: refused before any work; keys added inside a model config or to the trainer are
    left to their own checks."""
    from pae.config.validation import check_added_keys

    cfg = compose_train("stage=pipeline", "+teacher.max_epoch=3", run_dir=tmp_path)
    message = r"teacher\.max_epoch: not a setting of teacher .*did you mean teacher\.max_epochs\?"
    with pytest.raises(ConfigError, match=message):
        check_added_keys(cfg, ["+teacher.max_epoch=3"])
    with pytest.raises(ConfigError, match=r"student\.latent_los: .*student\.latent_loss\?"):
        check_added_keys(cfg, ["+student.latent_los=l2"])
    check_added_keys(cfg, ["+trainer.enable_progress_bar=false", "teacher.max_epochs=3"])
    check_added_keys(cfg, ["+teacher.model.width=3"])  # the constructor check's business


def test_a_misspelt_refiner_key_stops_the_run_before_any_work(
    compose_train, tmp_path: Path
) -> None:
    """`+render_compare.refiner.polish_step=1` (for polish_steps) is refused by the train
    config's checks, naming the nearest setting, before any step trains."""
    from pae.config.validation import validate_train_config

    override = "+render_compare.refiner.polish_step=1"
    cfg = compose_train("stage=full", override, run_dir=tmp_path)
    message = r"render_compare\.refiner\.polish_step: .*did you mean .*polish_steps\?"
    with pytest.raises(ConfigError, match=message):
        validate_train_config(cfg, [override])


def test_a_mandatory_value_left_unset_is_named_in_one_line(compose_train) -> None:
    """A ``???`` the user must give (a dataset's root) is named before any work; the ones pae
    fills in for each step (a logger's save_dir) are not the user's to give."""
    from pae.core.checks import check_missing

    cfg = compose_train("stage=pipeline")
    check_missing(cfg)
    with open_dict(cfg):
        cfg.data.root = "???"
    with pytest.raises(ConfigError, match=re.escape("data.root is required and not set: add")):
        check_missing(cfg)


def test_a_raw_download_without_label_files_points_at_pae_data_convert(tmp_path: Path) -> None:
    from hydra import compose, initialize_config_dir

    for scene_file, name, argument in (
        ("chess/TrainSplit.txt", "7-Scenes", "7scenes"),
        ("KingsCollege/dataset_train.txt", "Cambridge Landmarks", "cambridge"),
    ):
        root = tmp_path / argument
        (root / scene_file).parent.mkdir(parents=True)
        (root / scene_file).write_text("sequence1\n")
        data = "seven_scenes" if argument == "7scenes" else "cambridge"
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            cfg = compose("train", [f"data={data}", f"data.root={root}"])
        message = (
            f"data.train_labels={root}/labels/all_train.csv: no such file; {root} holds a raw "
            f"{name} download: `pae-data convert {argument} {root} {root}/labels` writes"
        )
        with pytest.raises(ConfigError, match=re.escape(message)):
            validate_train_config(cfg)
