"""A voxel grid that grows during its fit: resized with its field kept, staged by epoch,
its total variation weighed per unit of gradient, and loaded at whatever size it was saved."""

from __future__ import annotations

import functools
import math
from types import SimpleNamespace

import pytest
import torch
from omegaconf import OmegaConf

from pae.core.errors import ConfigError
from pae.core.schedules import exponential_decay
from pae.lit.scene_model import SceneModelModule
from pae.runs.trainer import optimisation
from pae.scene_model.voxel_grid import VoxelGrid, VoxelGridSceneModel

BOUNDS = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]


def _smooth_grid(num_voxels: int) -> VoxelGrid:
    """A grid holding a smooth field: a fog whose density and colour vary slowly."""
    grid = VoxelGrid(BOUNDS, num_voxels)
    nz, ny, nx = grid.grid.shape[2:]
    z, y, x = torch.meshgrid(
        torch.linspace(-1, 1, nz), torch.linspace(-1, 1, ny), torch.linspace(-1, 1, nx),
        indexing="ij",
    )  # fmt: skip
    with torch.no_grad():
        grid.grid[0, 0] = 2 * torch.cos(1.5 * x) * torch.cos(y) + 1
        grid.grid[0, 1] = torch.sin(2 * x)
        grid.grid[0, 2] = torch.cos(2 * y)
        grid.grid[0, 3] = x * z
    return grid


def _rays(n: int = 400) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    origins = torch.zeros(n, 3) + torch.tensor([0.0, 0.0, -3.0])
    directions = torch.randn(n, 3, generator=generator) * 0.12 + torch.tensor([0.0, 0.0, 1.0])
    return origins, directions


@pytest.mark.parametrize("engine", ["torch", "numba"])
def test_a_grown_grid_renders_the_field_it_held(engine: str) -> None:
    grid = _smooth_grid(4_000)
    origins, directions = _rays()
    with torch.no_grad():
        before = grid.composite(origins, directions, 256, 0.05, False, engine)
        assert grid.resize(32_000)
        assert math.prod(grid.shape) > 6 * 4_000 and grid.voxel_m < 0.6 * grid.configured_voxel_m
        after = grid.composite(origins, directions, 256, 0.05, False, engine)
    assert 0.3 < float(before[2].mean()) < 0.95  # neither empty nor opaque
    assert (after[2] - before[2]).abs().max() < 0.02  # the same light per metre
    assert (after[0] - before[0]).abs().max() < 0.02
    assert not grid.resize(32_000)  # the same size: nothing to do


def test_a_grid_grown_without_rescaling_its_density_would_be_denser() -> None:
    """What the rescaling does: the raw density copied to half-length voxels doubles the
    light each metre gathers, and the grid grown by resize does not."""
    grid = _smooth_grid(4_000)
    origins, directions = _rays()
    with torch.no_grad():
        coarse = grid.composite(origins, directions, 256, 0.05, False, "torch")[2]
        naive = _smooth_grid(32_000)  # the same field's raw values at the finer nodes
        copied = naive.composite(origins, directions, 256, 0.05, False, "torch")[2]
        grid.resize(32_000)
        grown = grid.composite(origins, directions, 256, 0.05, False, "torch")[2]
    assert float((copied - coarse).mean()) > 0.05
    assert float((grown - coarse).abs().mean()) < 0.2 * float((copied - coarse).mean())


def _model(grow_from: float = 0.125, grow_at_epoch: int = 2) -> VoxelGridSceneModel:
    return VoxelGridSceneModel(
        [BOUNDS, [[0.0, 0.0, 0.0], [3.0, 2.0, 1.0]]], n_appearances=1, num_voxels=8_000,
        samples_per_ray=16, contract=False, near_m=0.05, grow_from=grow_from,
        grow_at_epoch=grow_at_epoch,
    )  # fmt: skip


def test_the_fit_starts_coarse_and_grows_at_its_epoch() -> None:
    model = _model()
    full = [grid.shape for grid in model.grids]
    assert model.fit_stage(0, fresh=True)
    for grid, shape in zip(model.grids, full, strict=True):
        assert math.prod(grid.shape) < math.prod(shape) / 6
        assert float(grid.grid.detach().abs().max()) == 0.0  # the initial fog
        with torch.no_grad():
            grid.grid[0, 1:] = 0.7  # what the coarse fit learned
    assert not model.fit_stage(1, fresh=False)
    # weighed by (configured voxel / this voxel)^2: the coarse grid's gradient counts alike
    with torch.no_grad():
        tv = torch.stack(
            [g.total_variation() * (g.configured_voxel_m / g.voxel_m) ** 2 for g in model.grids]
        ).mean()
        assert float(model.total_variation()) == pytest.approx(float(tv))
    assert all(g.configured_voxel_m / g.voxel_m < 0.6 for g in model.grids)
    assert model.fit_stage(2, fresh=False)
    assert [grid.shape for grid in model.grids] == full
    assert all(torch.allclose(g.grid.detach()[0, 1:], torch.tensor(0.7)) for g in model.grids)
    assert not model.fit_stage(3, fresh=False)


def test_one_size_from_the_start_changes_nothing() -> None:
    model = _model(grow_from=1.0, grow_at_epoch=0)
    before = {key: value.clone() for key, value in model.state_dict().items()}
    assert not model.fit_stage(0, fresh=True)
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    with torch.no_grad():
        plain = torch.stack([g.total_variation() for g in model.grids]).mean()
        assert float(model.total_variation()) == float(plain)


def test_a_coarse_state_loads_into_a_model_built_at_the_configured_size() -> None:
    """A fit saved before it grew (a resumable checkpoint) loads as it was saved."""
    saved = _model()
    saved.fit_stage(0, fresh=True)
    with torch.no_grad():
        for grid in saved.grids:
            grid.grid.normal_()
    state = saved.state_dict()
    loaded = _model()
    assert loaded.grids[0].grid.shape != state["grids.0.grid"].shape
    loaded.load_state_dict(state)
    for ours, theirs in zip(loaded.grids, saved.grids, strict=True):
        assert torch.equal(ours.grid, theirs.grid)
        assert ours.shape == theirs.shape and ours.voxel_m == theirs.voxel_m
    origins, directions = _rays(50)
    with torch.no_grad():
        a = loaded.grids[0].composite(origins, directions, 32, 0.05, False, "numba")
        b = saved.grids[0].composite(origins, directions, 32, 0.05, False, "numba")
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"grow_from": 0.0}, "grow_from must be a share in"),
        ({"grow_from": 1.5}, "grow_from must be a share in"),
        ({"grow_from": 0.125, "grow_at_epoch": 20}, "grow_at_epoch=20 must be below 20"),
        ({"grow_from": 0.125, "grow_at_epoch": -1}, "grow_at_epoch"),
    ],
)
def test_growth_settings_out_of_range_name_their_key(settings: dict, message: str) -> None:
    model = {"num_voxels": 8000, "samples_per_ray": 16, "near_m": 0.05, "contract": "auto",
             "margin_m": "auto", "appearance_field": 0,
             "auto_scale": {"margin_floor_m": 2.0, "margin_fraction": 0.25,
                            "contract_above_m": 10.0}} | settings  # fmt: skip
    cfg = OmegaConf.create({"scene_model": {"max_epochs": 20, "model": model}})
    with pytest.raises(ConfigError, match=message) as error:
        VoxelGridSceneModel.check_config(cfg, "scene_model.model")
    assert "scene_model.model.grow" in str(error.value)


def test_exponential_decay_ends_every_rate_at_its_ratio() -> None:
    grids = [torch.nn.Parameter(torch.zeros(3)), torch.nn.Parameter(torch.zeros(2))]
    optimizer = torch.optim.Adam([{"params": grids[:1]}, {"params": grids[1:], "lr": 0.01}], lr=0.1)
    scheduler = exponential_decay(optimizer, total_steps=50, final_ratio=0.1)
    rates = [[group["lr"] for group in optimizer.param_groups]]
    for _ in range(50):
        optimizer.step()
        scheduler.step()
        rates.append([group["lr"] for group in optimizer.param_groups])
    assert rates[-1] == pytest.approx([0.01, 0.001])
    # the same factor each step: half way, the square root of the ratio
    assert rates[25] == pytest.approx([0.1 * 0.1**0.5, 0.01 * 0.1**0.5])
    for bad in ({"final_ratio": 0.0}, {"final_ratio": 1.5}, {"total_steps": 0}):
        with pytest.raises(ValueError, match="exponential_decay"):
            exponential_decay(optimizer, **({"total_steps": 10} | bad))


def test_an_optimiser_built_when_the_grid_grows_schedules_the_steps_left() -> None:
    """The scene fit's optimiser is built again when the grid grows: its schedule spans the
    rest of the fit, so the grown grid's rate decays to its end rather than from mid-way."""
    module = SceneModelModule(
        _model(), None, optimizer=functools.partial(torch.optim.Adam, lr=0.1),
        scene_names=["a", "b"], configs={},
        scheduler=functools.partial(exponential_decay, final_ratio=0.1),
    )  # fmt: skip
    for done, left in ((0, 100), (40, 60)):
        module._trainer = SimpleNamespace(estimated_stepping_batches=100, global_step=done)
        scheduler = module.configure_optimizers()["lr_scheduler"]["scheduler"]
        assert scheduler.gamma == pytest.approx(0.1 ** (1 / left))


@pytest.mark.parametrize(
    ("scheduler", "message"),
    [
        ({"final_ratio": 0.0}, "final_ratio must lie in"),
        ({"final_ratio": 0.1, "typo": 1}, "typo"),
    ],
)
def test_a_bad_schedule_is_a_config_error_naming_its_key(scheduler: dict, message: str) -> None:
    """Built once on a stand-in optimiser when the step's factories are made, before any data."""
    group = OmegaConf.create(
        {"scene_model": {
            "optimizer": {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 0.1},
            "scheduler": {
                "_target_": "pae.core.schedules.exponential_decay", "_partial_": True, **scheduler
            },
        }}
    )  # fmt: skip
    with pytest.raises(ConfigError, match=f"scene_model.scheduler: .*{message}"):
        optimisation(group.scene_model)
    group.scene_model.scheduler = {"_target_": "pae.core.schedules.exponential_decay",
                                   "_partial_": True}  # fmt: skip
    assert optimisation(group.scene_model)["scheduler"] is not None


def test_a_bad_optimiser_setting_is_a_config_error_naming_the_optimiser() -> None:
    """A typo in the optimiser's settings names the optimiser, not the scheduler after it."""
    group = OmegaConf.create(
        {"scene_model": {
            "optimizer": {"_target_": "torch.optim.Adam", "_partial_": True, "lrr": 0.1},
            "scheduler": {"_target_": "pae.core.schedules.exponential_decay", "_partial_": True},
        }}
    )  # fmt: skip
    with pytest.raises(ConfigError, match=r"scene_model\.optimizer: .*lrr"):
        optimisation(group.scene_model)
