"""Every config group option composes and instantiates; bad options fail with clear messages."""

import subprocess
import sys
from enum import Enum
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from pae import CONFIG_DIR

GROUPS = {
    name: sorted(p.stem for p in (Path(CONFIG_DIR) / name).glob("*.yaml"))
    for name in (
        "data",
        "backbone",
        "teacher",
        "pae",
        "student",
        "decoder",
        "rpr",
        "iapr",
        "scene_model",
        "refine",
        "trainer",
        "logger",
        "callbacks",
        "stage",
        "experiment",
    )
}


def _compose(config: str, overrides: list[str]):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config, overrides=overrides)


def _leaves(node: object, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], object]]:
    """(keys, value) of every leaf of a loaded config file (keys may hold dots: sweep params)."""
    if isinstance(node, dict):
        return [leaf for key, value in node.items() for leaf in _leaves(value, (*path, key))]
    return [(path, node)]


@pytest.mark.parametrize(
    ("group", "option"), [(g, o) for g, options in GROUPS.items() for o in options]
)
def test_every_group_option_composes(group: str, option: str) -> None:
    """The option is chosen, and every value its file writes (not one that interpolates or
    must be given) is in the composed config: it took effect, not something else's value."""
    from omegaconf import ListConfig, OmegaConf

    overrides = [f"{group}={option}"]
    if group == "data" and option != "synthetic":
        overrides.append("data.root=/data/somewhere")
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=overrides, return_hydra_config=True)
    assert cfg.hydra.runtime.choices[group] == option
    file = OmegaConf.to_container(OmegaConf.load(Path(CONFIG_DIR) / group / f"{option}.yaml"))
    written = {k: v for k, v in (file or {}).items() if k != "defaults"}
    leaves = _leaves(written, () if group == "experiment" else (group,))
    assert leaves or "defaults" in (file or {}) or option == "none"  # cpu: only its base
    for keys, value in leaves:
        if isinstance(value, str) and ("${" in value or value == "???"):
            continue
        composed = cfg
        for key in keys:
            composed = composed[key]
        if isinstance(composed, ListConfig):
            composed = OmegaConf.to_container(composed)
        if isinstance(composed, Enum):  # hydra.mode
            composed = composed.name
        assert composed == value, f"{group}={option}: {'.'.join(keys)}"


@pytest.mark.parametrize("option", GROUPS["pae"])
def test_pae_options_instantiate_with_teacher_latent_size(option: str) -> None:
    cfg = _compose("train", [f"pae={option}", "teacher.model.latent_dim=32"])
    pae = instantiate(cfg.pae)
    assert pae.latent_dim == 32


@pytest.mark.parametrize("option", GROUPS["backbone"])
def test_backbone_options_instantiate(option: str) -> None:
    cfg = _compose("train", [f"backbone={option}"])
    assert instantiate(cfg.backbone).out_dim > 0


def test_pae_bands_override_reaches_the_model() -> None:
    cfg = _compose("train", ["pae.L=3"])
    assert instantiate(cfg.pae).fourier.L == 3


def test_eval_config_composes() -> None:
    cfg = _compose("eval", ["student_ckpt=/x.ckpt", "refine=knn_closed_form"])
    assert cfg.refine.weight_model == "closed_form"


def test_unknown_group_option_lists_valid_choices(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "pae.train", "pae=transformer", f"hydra.run.dir={tmp_path}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode != 0
    assert "fourier_mlp4" in result.stderr and "mlp2" in result.stderr


@pytest.mark.parametrize("option", GROUPS["experiment"])
def test_experiments_with_sweep_parameters_sweep_by_themselves(option: str) -> None:
    from hydra.types import RunMode

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", [f"experiment={option}"], return_hydra_config=True)
    if cfg.hydra.sweeper.get("params"):
        assert cfg.hydra.mode == RunMode.MULTIRUN, f"experiment={option} needs hydra.mode"


def test_config_files_with_a_schema_set_only_what_differs_from_it() -> None:
    """Defaults live in code (settings records and constructors, behind
    ``pae.config.schemas``): a config file that starts from a schema sets no key of it to the
    schema's own default."""
    from omegaconf import OmegaConf

    from pae.config.schemas import SCHEMAS

    checked = set()
    for path in sorted(Path(CONFIG_DIR).rglob("*.yaml")):
        values = OmegaConf.to_container(OmegaConf.load(path)) or {}
        for entry in values.get("defaults", []) if isinstance(values, dict) else []:
            if not isinstance(entry, dict) or not next(iter(entry)).startswith("/schema/"):
                continue
            ((choice, name),) = entry.items()
            group, package = choice.removeprefix("/schema/").split("@")
            defaults = OmegaConf.to_container(OmegaConf.structured(SCHEMAS[group, name]))
            node = values if package == "_here_" else values.get(package, {})
            checked.add((group, name))
            for key, value in node.items():
                if key != "defaults":
                    assert value != defaults[key], f"{path.name}: {key} is the schema's default"
    assert checked == set(SCHEMAS), set(SCHEMAS) - checked


def test_a_key_no_schema_has_or_a_value_of_another_type_is_refused_when_composing() -> None:
    from hydra.errors import ConfigCompositionException

    for key in (
        "data.val_walk=2",
        "refine.kk=3",
        "pae.l=4",
        "pae.L=abc",
        "data.val_walks=1.5",
        "render_compare.refiner.rounds=1.5",
        "teacher.model.dropout=abc",
    ):
        with pytest.raises(ConfigCompositionException, match=key.replace(".", r"\.")):
            _compose("train.yaml", [key])


def test_the_refinement_and_its_index_share_their_defaults() -> None:
    """The paper's refinement's defaults have one home, read by the callback, the method and
    the retrieval store alike."""
    import inspect

    from pae.callbacks.refinement import TestTimeRefinement
    from pae.refine import PoseIndex
    from pae.refine.settings import RefinementSettings

    protocols = TestTimeRefinement().protocols
    assert (protocols.k, protocols.rot_weight) == (RefinementSettings.k, 0.01)
    assert inspect.signature(PoseIndex).parameters["rot_weight"].default == protocols.rot_weight


def test_old_key_pae_ckpt_is_read_as_student_ckpt_with_one_warning(capsys) -> None:
    from pae.config.validation import apply_renamed_keys
    from pae.core.errors import ConfigError
    from pae.core.run_context import start_run

    start_run()
    for config in ("train", "eval"):
        cfg = _compose(config, ["pae_ckpt=/x.ckpt"])
        apply_renamed_keys(cfg, "pae-train")
        assert cfg.student_ckpt == "/x.ckpt" and cfg.pae_ckpt is None
    assert capsys.readouterr().err == (
        "pae-train: warning: pae_ckpt is deprecated, use student_ckpt (the old name is read for "
        "one more release)\n"
    )
    with pytest.raises(ConfigError, match="pae_ckpt is the old name of student_ckpt"):
        apply_renamed_keys(_compose("eval", ["pae_ckpt=/x.ckpt", "student_ckpt=/y.ckpt"]))


def test_entry_points_load_no_torch_before_a_run() -> None:
    """A sweep's launching process (joblib, submitit) starts its jobs without importing torch:
    it is imported by the jobs, which train."""
    code = (
        "import sys, pae.train, pae.evaluate, pae.config.preflight; "
        "print(sorted({'torch', 'lightning'} & set(sys.modules)))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_configured_adam_updates_as_the_default_loop_does() -> None:
    """``conf/optim`` batches Adam's updates over the parameter tensors (``foreach``) for
    speed: the parameters it reaches, under the one-cycle schedule, are those of the default
    per-tensor loop to the bit, so figures recorded with either reproduce."""
    import torch

    config = _compose("train.yaml", ["stage=student"])
    assert config.student.optimizer.foreach is True
    results = []
    for foreach in (True, False):
        torch.manual_seed(0)
        network = torch.nn.Sequential(
            torch.nn.Linear(7, 32), torch.nn.ReLU(), torch.nn.Linear(32, 5)
        )
        optimizer = instantiate(config.student.optimizer, foreach=foreach)(
            params=list(network.parameters())
        )
        scheduler = instantiate(config.student.scheduler)(optimizer=optimizer, total_steps=30)
        generator = torch.Generator().manual_seed(1)
        for _ in range(30):
            inputs = torch.randn(16, 7, generator=generator)
            optimizer.zero_grad()
            network(inputs).square().mean().backward()
            optimizer.step()
            scheduler.step()
        results.append(torch.cat([p.detach().flatten() for p in network.parameters()]))
    assert torch.equal(results[0], results[1])


def test_a_schema_read_from_a_signature_has_its_defaults_and_leaves_out_what_runs_fill_in() -> None:
    """The schema of a class comes from its source: literal and named-constant defaults,
    mandatory arguments as ``???``, and neither ``n_scenes`` nor ``from_run`` arguments."""
    import inspect

    from omegaconf import MISSING

    from pae.callbacks.render_compare import RenderCompareCallback
    from pae.config.signatures import source_fields
    from pae.models.posenet import PoseNet
    from pae.scene_model.voxel_grid import VoxelGridSceneModel

    for target, cls in (
        ("pae.callbacks.render_compare.RenderCompareCallback", RenderCompareCallback),
        ("pae.models.posenet.PoseNet", PoseNet),
    ):
        fields = {name: spec for name, _, spec in source_fields(target)}
        signature = inspect.signature(cls).parameters
        assert set(fields) == set(signature) - {"n_scenes"}
        for name, spec in fields.items():
            default = signature[name].default
            expected = MISSING if default is inspect.Parameter.empty else default
            assert spec.default == expected, (target, name)
    voxels = {
        name for name, _, _ in source_fields("pae.scene_model.voxel_grid.VoxelGridSceneModel")
    }
    assert "bounds" in VoxelGridSceneModel.from_run and "bounds" not in voxels
    assert "num_voxels" in voxels


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("teacher.scene_loss_weight=-1", "teacher.scene_loss_weight must be a number >= 0"),
        ("student.input=noise", "unknown student.input 'noise'; choose one of ['gt', 'teacher']"),
        ("decoder.max_epochs=-2", "decoder.max_epochs must be an integer >= 0, got -2"),
        ("rpr.pair_k=0", "rpr.pair_k must be an integer >= 1, got 0"),
        ("iapr.start.position_m=-1", "iapr.start.position_m must be a number >= 0, got -1"),
        ("scene_model.image_size=2", "scene_model.image_size must be null or an integer >= 4"),
        ("student.optimizer.weight_decay=-1", "student.optimizer.weight_decay must be a number"),
        ("pae.hidden=[64,0]", "pae.hidden must be a list of layer widths >= 1, got [64, 0]"),
    ],
)
def test_each_step_groups_record_names_a_bad_value_by_its_key(override: str, message: str) -> None:
    """The steps' own settings are checked by their records (``pae.steps.settings``), one for
    every group a step reads, each error naming the key."""
    import re

    from pae.config.validation import validate_train_config
    from pae.core.errors import ConfigError
    from pae.steps import GROUPS
    from pae.steps.settings import STEP_SETTINGS

    assert set(STEP_SETTINGS) == set(GROUPS)
    with pytest.raises(ConfigError, match=re.escape(message)):
        validate_train_config(_compose("train.yaml", [override]))
