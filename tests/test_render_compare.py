"""Render-and-compare: camera intrinsics, the voxel grid scene model, the refiner, the step."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from torch import Tensor

from pae import CONFIG_DIR
from pae.core.camera import Intrinsics, camera_rays, project, resized_size
from pae.core.geometry import pose_errors
from pae.core.pose_sampling import perturb
from pae.render_compare.images import band_pass, clip_bright, trimmed_zncc, zncc
from pae.render_compare.refiner import RenderCompareRefiner, RenderCompareResult, gate
from pae.scene_model.oracle import OracleSceneModel
from pae.scene_model.voxel_grid import VoxelGrid, VoxelGridSceneModel
from pae.scene_model.voxel_layout import camera_bounds
from pae.synthetic import (
    Appearance,
    PinholeCamera,
    SyntheticScene,
    SyntheticSettings,
    furnish,
    make_scene,
    make_sequences,
    render_batch,
    room_textures,
    world_to_camera,
)
from pae.synthetic.datamodule import SyntheticDataModule
from tests.conftest import (
    FOCAL_CAMERA,
    MAGENTA,
    POISON_M,
    TINY,
    TINY_SCENE_MODEL,
    tiny_data_overrides,
    with_focal_column,
)


def _camera_pose(position: list[float], yaw: float = 0.3, pitch: float = -0.1) -> torch.Tensor:
    """A camera-to-world pose [7] looking roughly along +x (world z up)."""
    from pae.core.geometry import matrix_to_quaternion
    from pae.synthetic.camera import look_rotations

    rotation = look_rotations(np.array([yaw]), np.array([pitch]), np.array([0.05]))
    q = matrix_to_quaternion(torch.from_numpy(rotation))[0]
    return torch.cat([torch.tensor(position, dtype=torch.float64), q]).float()


def test_intrinsics_follow_resize_and_crop_when_projecting_known_points() -> None:
    """A world point's pixel, mapped through the loaders' resize and centre crop, is where
    the transformed intrinsics project it (7-Scenes' camera, 640x480 -> 256 -> 224)."""
    camera = Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
    pose = _camera_pose([0.1, -0.2, 1.3]).double().numpy()
    points = np.array([[2.0, 0.3, 1.1], [3.0, -0.8, 1.9], [1.5, 0.2, 0.6]])
    local = world_to_camera(points, pose)
    pixels = local @ camera.matrix().T
    pixels = pixels[:, :2] / pixels[:, 2:]
    width, height = resized_size(640, 480, 256)
    scale = np.array([width / 640, height / 480])
    left, top = (width - 224) // 2, (height - 224) // 2
    expected = (pixels + 0.5) * scale - 0.5 - np.array([left, top])
    after = camera.preprocessed(256, 224)
    got = project(torch.from_numpy(local), torch.tensor(after.vector(), dtype=torch.float64))
    np.testing.assert_allclose(got.numpy(), expected, atol=1e-9)
    assert (after.width, after.height) == (224, 224)


def test_synthetic_intrinsics_put_a_box_corner_on_its_rendered_pixel(tiny_root: Path) -> None:
    """The data module's intrinsics after its resize and crop project the synthetic camera's
    rays back onto the pixels they were cast through (the renderer's own geometry)."""
    data = SyntheticDataModule(
        root=str(tiny_root), **TINY, crop=28, shorter_edge=TINY["size"], cache_images=True
    )
    data.setup()
    k = data.intrinsics("test")[0].double()
    camera = PinholeCamera(TINY["size"])
    pose = data.datasets["test"].poses[0].double()
    point = torch.tensor([1.0, 0.5, 1.2], dtype=torch.float64)
    full = camera.project(point[None].numpy(), pose.numpy())[0]
    crop_offset = (TINY["size"] - 28) // 2
    local = torch.from_numpy(world_to_camera(point[None].numpy(), pose.numpy()))
    np.testing.assert_allclose(project(local, k)[0].numpy(), full - crop_offset, atol=1e-9)


@pytest.mark.parametrize("contract", [False, True])
def test_compiled_volume_rendering_equals_the_grid_sample_path(contract: bool) -> None:
    torch.manual_seed(0)
    grid = VoxelGrid([[-2, -2, -0.5], [2, 2, 2.5]], num_voxels=4000, contract=contract)
    with torch.no_grad():
        grid.grid.normal_(0, 2)
        grid.grid[:, 0] += torch.linspace(-3, 5, grid.grid.shape[2])[None, :, None, None]
    origins = torch.zeros(300, 3) + torch.tensor([0.0, 0.0, 1.0])
    directions = torch.randn(300, 3)
    weights = torch.rand(300, 3)
    outputs = []
    for engine in ("numba", "torch"):
        torch.manual_seed(1)
        rgb, _, opacity = grid.composite(origins, directions, 32, 0.05, True, engine)
        grads = torch.autograd.grad((rgb * weights).sum(), [grid.grid, grid.background])
        outputs.append((rgb, opacity, *grads))
    for compiled, reference in zip(*outputs, strict=True):
        scale = reference.abs().max().clamp_min(1.0)
        assert (compiled - reference).abs().max() / scale < 2e-3
    with torch.no_grad():
        surfaces = [
            grid.composite(origins, directions, 32, 0.05, False, engine, surface_share=0.7)[1]
            for engine in ("numba", "torch")
        ]
    torch.testing.assert_close(*surfaces, atol=1e-4, rtol=1e-5)


def test_a_scenes_rays_render_alike_in_one_run_and_interleaved_with_anothers() -> None:
    """A scene's rays (and cameras) on their own, in chunks smaller than the batch, render
    bit for bit as the same rays (cameras) interleaved with another scene's, and their depth
    errors match under the same draws; an unknown scene id is an error."""
    from pae.bench.render_compare import bench_queries, room_grid

    model = room_grid(2, num_voxels=4000)
    model.chunk_rays = 7
    torch.manual_seed(0)
    origins = torch.randn(40, 3) * 0.5 + torch.tensor([0.0, 0.0, 1.4])
    directions = torch.randn(40, 3)
    alone = model.render_rays(origins, directions, torch.zeros(40, dtype=torch.long))
    interleaved = torch.arange(80) % 2
    rays = origins.repeat_interleave(2, 0), directions.repeat_interleave(2, 0)
    both = model.render_rays(*rays, interleaved)
    for one, mixed in zip(alone, both, strict=True):
        assert torch.equal(one, mixed[interleaved == 0])
    assert not torch.equal(alone[0], both[0][interleaved == 1])
    with pytest.raises(ValueError, match="scene id 2 of 2 scenes"):
        model.render_rays(origins, directions, torch.full((40,), 2))
    with pytest.raises(ValueError, match="scene id -1 of 2 scenes"):
        model.render_rays(origins, directions, torch.arange(40) % 2 - 1)
    _, intrinsics, poses, _ = bench_queries(6, 2, 8, seed=0)
    cameras = torch.tensor([1, 0, 1, 1, 0, 0])
    mixed = model.render(poses, cameras, intrinsics, 8, 8)
    for scene in (0, 1):
        own = cameras == scene
        rendered = model.render(poses[own], cameras[own], intrinsics[own], 8, 8)
        for part, mixed_part in zip(rendered, mixed, strict=True):
            assert torch.equal(part, mixed_part[own])
    target = torch.rand(80) + 1.0
    torch.manual_seed(1)  # the jittered draws: scene 0's rays first, then scene 1's
    mixed_error = model.depth_error(*rays, interleaved, target)
    torch.manual_seed(1)
    for scene, grid in enumerate(model.grids):
        own = interleaved == scene
        error = grid.depth_error(
            rays[0][own], rays[1][own], target[own], model.samples_per_ray, model.near_m
        )
        assert torch.equal(error, mixed_error[own])


@pytest.mark.parametrize("engine", ["numba", "torch"])
def test_the_surface_share_puts_the_depth_on_a_wall_behind_faint_fog(engine: str) -> None:
    """A wall at x = 1.5 m behind faint fog: the light's mean depth is pulled 15 cm or more
    towards the camera, the depth by which the ray has gathered 70 % of its opacity lies on
    the wall's face (within a voxel, 10 cm)."""
    grid = VoxelGrid([[-2, -2, -2], [2, 2, 2]], num_voxels=64_000)
    nx = grid.grid.shape[-1]
    x = torch.linspace(-2, 2, nx)
    with torch.no_grad():
        grid.grid[:, 0] = torch.where(x.sub(1.5).abs() < 0.1, 12.0, 0.5)
    origins = torch.zeros(8, 3)
    directions = torch.tensor([[1.0, 0.0, 0.0]]).expand(8, 3) + torch.randn(8, 3) * 0.01
    with torch.no_grad():
        _, mean_depth, opacity = grid.composite(origins, directions, 256, 0.05, False, engine)
        _, share_depth, _ = grid.composite(
            origins, directions, 256, 0.05, False, engine, surface_share=0.7
        )
    assert bool((opacity > 0.99).all())
    assert bool((mean_depth < 1.35).all())
    assert bool((share_depth - 1.45).abs().max() < 0.1)
    with pytest.raises(ValueError, match="surface_share"):
        RenderCompareRefiner.configured(OracleSceneModel([]), surface_share=1.0)


def test_the_forward_kernels_polynomial_exp_and_log1p_match_the_library_ones() -> None:
    from pae.scene_model.voxel_render import _exp_parts, _log1p_unit

    for x in np.linspace(-20.0, 20.0, 401, dtype=np.float32):
        mantissa, bits = _exp_parts(x)
        value = float(mantissa) * float(np.array(bits, np.int32).view(np.float32))
        assert abs(value - math.exp(float(x))) <= 2e-6 * math.exp(float(x))
    for z in np.linspace(0.0, 1.0, 101, dtype=np.float32):
        assert abs(_log1p_unit(z) - math.log1p(float(z))) <= 1e-6 * max(math.log1p(float(z)), 1e-30)
    assert _exp_parts(np.float32(-200.0))[1] == 1 << 23  # clamped to 2^-126, not wrapped


def test_compiled_total_variation_equals_the_tensor_one_and_reads_the_grid_in_place() -> None:
    torch.manual_seed(0)
    grid = VoxelGrid([[-2, -2, -0.5], [2, 2, 2.5]], num_voxels=4000)
    with torch.no_grad():
        grid.grid.normal_(0, 1)
    assert grid.kernel_cells().ctypes.data == grid.grid.data_ptr()  # no copy per step
    values, grads = [], []
    for engine in ("numba", "torch"):
        value = grid.total_variation(engine)
        grads.append(torch.autograd.grad(value, grid.grid)[0])
        values.append(value.detach())
    assert abs(values[0] - values[1]) < 1e-6 * values[1]
    assert (grads[0] - grads[1]).abs().max() < 1e-5 * grads[1].abs().max()


def _one_box_scene() -> SyntheticScene:
    """A room holding one textured box."""
    rng = np.random.default_rng(3)
    size = np.array([5.0, 4.0, 2.6])
    from pae.synthetic import Box

    lo = np.array([-size[0] / 2, -size[1] / 2, 0.0])
    room = Box(lo, lo + size, room_textures(rng, size))
    boxes = furnish(rng, room, np.array([-0.5, -0.5, 1.2]), np.array([0.5, 0.5, 1.6]), 0.4)[:1]
    return SyntheticScene("box", room, boxes, np.array([0.5, 0.5, 2.1]), None)


def test_a_grid_fitted_to_a_one_box_scene_renders_an_unseen_view() -> None:
    """Trained on 48 views of a one-box room, the grid renders a view between them well
    above what the mean train image explains (PSNR after a per-image gain and bias fit)."""
    from pae.callbacks.scene_quality import fitted_psnr_db

    scene = _one_box_scene()
    size = 24
    camera = PinholeCamera(size)
    rng = np.random.default_rng(0)
    yaws = np.linspace(0, 2 * math.pi, 48, endpoint=False)
    train = torch.stack(
        [_camera_pose([*rng.uniform(-0.5, 0.5, 2), 1.4], yaw, -0.05) for yaw in yaws]
    )
    images = render_batch(scene, train.double().numpy(), camera, Appearance(), supersample=1)
    target = torch.from_numpy(images).float().div(255).permute(0, 3, 1, 2)
    k = torch.tensor([camera.focal_px, camera.focal_px, camera.principal_point] * 1)
    k = torch.tensor([camera.focal_px, camera.focal_px, k[2], k[2]]).expand(len(train), 4)
    model = VoxelGridSceneModel(
        [camera_bounds(train[:, :3], [2.2, 2.2, 1.3]).tolist()],
        n_appearances=1,
        num_voxels=30_000,
        samples_per_ray=48,
        contract=False,
        near_m=0.05,
    )
    origins, directions = camera_rays(train, k, size, size)
    colours = target.permute(0, 2, 3, 1).reshape(len(train), -1, 3)
    optimiser = torch.optim.Adam(model.parameters(), lr=0.1)
    torch.manual_seed(0)
    for _ in range(120):
        row, pixel = torch.randint(len(train), (2048,)), torch.randint(size * size, (2048,))
        rgb, _, _ = model.render_rays(
            origins[row, pixel], directions[row, pixel], torch.zeros(2048, dtype=torch.long), True
        )
        loss = (rgb - colours[row, pixel]).square().mean() + 1e-3 * model.total_variation()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    unseen = _camera_pose([0.2, -0.1, 1.45], yaws[5] + math.pi / 48, -0.05)[None]
    truth = render_batch(scene, unseen.double().numpy(), camera, Appearance(), supersample=1)
    truth = torch.from_numpy(truth).float().div(255).permute(0, 3, 1, 2)
    with torch.no_grad():
        rendered = model.render(unseen, torch.zeros(1, dtype=torch.long), k[:1], size, size).rgb
    psnr = fitted_psnr_db(rendered, truth)
    mean_image = fitted_psnr_db(target.mean(0, keepdim=True), truth)
    assert psnr.item() > 20.0
    assert psnr.item() > mean_image.item() + 5.0


def _oracle_queries(n: int = 6) -> tuple[OracleSceneModel, torch.Tensor, torch.Tensor, ...]:
    """Queries along benchmark scene 0's test walks (48 px), their intrinsics, true poses and
    the true poses moved by about 0.3 m and 5 degrees."""
    scene = make_scene(0)
    camera = PinholeCamera(48)
    walks = make_sequences(0, scene, SyntheticSettings(train_frames=6, test_frames=8 * n))
    poses = walks[-1].poses[::4]
    truth = torch.from_numpy(poses).float()
    images = render_batch(scene, poses, camera, Appearance(), supersample=1)
    images = torch.from_numpy(images).float().div(255).permute(0, 3, 1, 2)
    f, c = camera.focal_px, camera.principal_point
    intrinsics = torch.tensor([f, f, c, c]).expand(len(truth), 4)
    generator = torch.Generator().manual_seed(0)
    steps = torch.cat(
        [
            0.18 * torch.randn(len(truth), 3, generator=generator),
            0.05 * torch.randn(len(truth), 3, generator=generator),
        ],
        1,
    )
    return OracleSceneModel([scene]), images, intrinsics, truth, perturb(truth, steps)


def test_refinement_against_the_true_scene_moves_estimates_towards_the_truth() -> None:
    model, images, intrinsics, truth, start = _oracle_queries()
    refiner = RenderCompareRefiner.configured(
        model, rounds=8, candidates=16, resolution=24, reference_size=16
    )
    result = refiner(images, intrinsics, start, torch.zeros(len(truth), dtype=torch.long))
    before, _ = pose_errors(start, truth)
    after, _ = pose_errors(result.poses, truth)
    assert after.median() < 0.6 * before.median()


def test_batched_search_equals_a_per_query_search_for_a_fixed_seed() -> None:
    model, images, intrinsics, _, start = _oracle_queries(5)
    refiner = RenderCompareRefiner.configured(
        model, rounds=4, candidates=8, resolution=16, reference_size=12, chunk=3, seed=7
    )
    scenes = torch.zeros(len(start), dtype=torch.long)
    draws = refiner.draws(len(start))
    batched = refiner(images, intrinsics, start, scenes).poses
    for b in range(len(start)):
        alone = refiner(
            images[b : b + 1], intrinsics[b : b + 1], start[b : b + 1], scenes[:1], draws[b : b + 1]
        ).poses
        torch.testing.assert_close(alone[0], batched[b], atol=1e-5, rtol=0)


def test_compiled_and_tensor_scores_agree() -> None:
    model, images, intrinsics, _, start = _oracle_queries(4)
    scenes = torch.zeros(len(start), dtype=torch.long)
    results = [
        RenderCompareRefiner.configured(
            model, rounds=3, candidates=8, resolution=16, reference_size=12, engine=engine
        )(images, intrinsics, start, scenes)
        for engine in ("numba", "torch")
    ]
    torch.testing.assert_close(
        results[0].initial_score, results[1].initial_score, atol=1e-4, rtol=0
    )
    torch.testing.assert_close(results[0].poses, results[1].poses, atol=1e-4, rtol=0)


def test_compiled_and_tensor_trimmed_scores_agree() -> None:
    model, images, intrinsics, _, start = _oracle_queries(4)
    scenes = torch.zeros(len(start), dtype=torch.long)
    settings = {"rounds": 3, "candidates": 8, "resolution": 16, "reference_size": 12}
    results = [
        RenderCompareRefiner.configured(model, trim_sigma=2.0, engine=engine, **settings)(
            images, intrinsics, start, scenes
        )
        for engine in ("numba", "torch")
    ]
    torch.testing.assert_close(results[0].score, results[1].score, atol=2e-3, rtol=0)
    plain = RenderCompareRefiner.configured(model, engine="numba", **settings)(
        images, intrinsics, start, scenes
    )
    assert not torch.allclose(plain.initial_score, results[0].initial_score)


def test_the_trimmed_score_ignores_an_occluder_that_plain_zncc_does_not() -> None:
    generator = torch.Generator().manual_seed(0)
    rendered = torch.rand(4, 400, generator=generator)
    query = 0.7 * rendered + 0.1 + 0.01 * torch.randn(4, 400, generator=generator)
    query[:, :80] = 1.0  # a bright occluder over a fifth of the points
    weights = torch.ones_like(query)
    plain, trimmed = zncc(query, rendered, weights), trimmed_zncc(query, rendered, weights, 2.0)
    assert (plain < 0.8).all()
    assert (trimmed > 0.95).all()
    assert torch.equal(trimmed_zncc(query, rendered, weights, 0.0), plain)


def test_the_gate_keeps_the_start_unless_the_score_beats_it_by_the_margin() -> None:
    initial = torch.zeros(3, 7)
    initial[:, 3] = 1.0
    refined = initial.clone()
    refined[:, 0] = 1.0
    result = RenderCompareResult(refined, torch.tensor([0.5, 0.62, 0.9]), torch.full((3,), 0.5))
    gated = gate(result, initial, 0.1)
    assert gated.accepted.tolist() == [False, True, True]
    assert gated.poses[:, 0].tolist() == [0.0, 1.0, 1.0]


def test_the_gate_also_keeps_the_start_where_the_refined_score_is_below_the_floor() -> None:
    initial = torch.zeros(3, 7)
    initial[:, 3] = 1.0
    refined = initial.clone()
    refined[:, 0] = 1.0
    result = RenderCompareResult(refined, torch.tensor([0.3, 0.62, 0.9]), torch.zeros(3))
    assert gate(result, initial, 0.1, floor=0.5).accepted.tolist() == [False, True, True]
    assert gate(result, initial, 0.1).accepted.all()


def test_the_auto_margin_rejects_refinements_that_made_poses_worse() -> None:
    from pae.render_compare.calibration import ACCEPT_ALL, choose_gate

    gains = torch.linspace(0.01, 0.5, 100)
    scores = torch.full((100,), 0.8)
    start = torch.full((100,), 0.4)
    refined = torch.where(gains > 0.2, torch.full((100,), 0.1), torch.full((100,), 2.0))
    margin, floor = choose_gate(gains, scores, refined, start)
    assert 0.2 <= margin < 0.25 and floor == ACCEPT_ALL  # the grid point above the worse ones
    assert choose_gate(gains, scores, torch.full((100,), 0.1), start) == (ACCEPT_ALL, ACCEPT_ALL)


def test_the_auto_floor_rejects_refinements_the_scene_model_does_not_explain() -> None:
    """Gains do not tell the bad refinements apart, their low final scores do: the floor
    chosen is the grid point just above the bad ones, and a fixed margin is kept."""
    from pae.render_compare.calibration import ACCEPT_ALL, choose_gate

    gains = torch.rand(100, generator=torch.Generator().manual_seed(0))
    scores = torch.linspace(0.2, 0.9, 100)
    start = torch.full((100,), 0.4)
    refined = torch.where(scores > 0.45, torch.full((100,), 0.1), torch.full((100,), 2.0))
    margin, floor = choose_gate(gains, scores, refined, start, margin=ACCEPT_ALL)
    assert margin == ACCEPT_ALL and 0.45 <= floor < 0.5  # the grid point above the bad ones


def test_the_log_ratio_gate_keeps_good_starts_that_the_refiner_would_make_worse() -> None:
    """Half the starts are 1 cm off and refined to 3 cm, half 1 m off and refined to 3 cm,
    the gains alike: the mean error prefers accepting all (it is dominated by the far
    starts), the mean log ratio weighs both halves alike; where every refinement makes its
    start worse, the gate keeps every start."""
    from pae.render_compare.calibration import ACCEPT_ALL, KEEP_ALL, choose_gate

    gains = torch.rand(100, generator=torch.Generator().manual_seed(1))
    scores = torch.full((100,), 0.9)
    start = torch.cat([torch.full((50,), 0.01), torch.full((50,), 1.0)])
    refined = torch.full((100,), 0.03)
    assert choose_gate(gains, scores, refined, start)[0] == ACCEPT_ALL
    worse = torch.full((100,), 0.05)
    good = torch.full((100,), 0.01)
    margin, floor = choose_gate(gains, scores, worse, good, objective="log_ratio")
    assert not ((gains > margin) & (scores > floor)).any()
    gains = torch.linspace(0.1, 0.3, 100)  # above every margin quantile but KEEP_ALL's
    spread = torch.linspace(0.5, 0.95, 100).flip(0)
    margin, floor = choose_gate(gains, spread, worse, good, objective="log_ratio")
    assert not ((gains > margin) & (spread > floor)).any() and gains.max() < KEEP_ALL
    with pytest.raises(ValueError, match="unknown gate objective"):
        choose_gate(gains, scores, refined, start, objective="median")


def test_calibrating_for_any_start_improves_the_val_starts_on_average(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """calibrate_any_start on a tiny scene: starts at every scale of the ladder, the steps and
    gate chosen so that the mean log error ratio over those val starts falls well below 0
    (keeping every start, which the gate may always choose, gives 0), and refine() under the
    calibration gives the same val poses; every
    high-pass of ``highpass_px`` tried, at every level and at the finest only, each without
    and with each local contrast of ``contrast_px``, then each of ``surface_shares``."""
    from pae.render_compare import AnyStartOptions, Queries, api, calibrate_any_start, refine
    from pae.render_compare.calibration import HIGHPASS_PX
    from pae.render_compare.settings import RenderCompareSettings

    tried, shares = set(), set()
    build = api.build_refiner

    def spy(scene_model: Any, settings: Any, steps: Any = None) -> Any:
        if steps:
            tried.add(
                (steps["highpass_sigma_px"], steps["highpass_levels"], steps["contrast_sigma_px"])
            )
            shares.add(steps.get("surface_share"))
        return build(scene_model, settings, steps)

    monkeypatch.setattr(api, "build_refiner", spy)
    model, images, intrinsics, truth, _ = _oracle_queries(12)
    scenes = torch.zeros(len(truth), dtype=torch.long)
    settings = {"rounds": 3, "candidates": 8, "resolution": 16, "reference_size": 12}
    options = AnyStartOptions(
        highpass_px=(HIGHPASS_PX, 6.0), contrast_px=(3.0,), surface_shares=(0.6,)
    )
    calibration, refinement, starts = calibrate_any_start(
        model, Queries(images, intrinsics, scenes), truth, 2.0, settings, options
    )
    before = pose_errors(starts, truth)[0]
    after = pose_errors(refinement.poses, truth)[0]
    assert float(((after + 1e-3) / (before + 1e-3)).log().mean()) < -0.25  # -0.34 here
    again = refine(model, Queries(images, intrinsics, scenes), starts, calibration, None, settings)
    torch.testing.assert_close(again.poses, refinement.poses)
    chosen = {
        "position_sigma_m",
        "orientation_sigma_deg",
        "highpass_sigma_px",
        "highpass_levels",
        "contrast_sigma_px",
    }
    # the benchmark's renderer has exact depths: no surface share beats its own
    assert set(calibration.steps) == chosen and shares == {None, 0.6}
    assert calibration.steps["highpass_sigma_px"] in (0.0, HIGHPASS_PX, 6.0)
    assert calibration.steps["contrast_sigma_px"] in (0.0, 3.0)
    own = RenderCompareSettings(**settings)
    expected = {(own.highpass_sigma_px, own.highpass_levels, own.contrast_sigma_px)}
    assert tried == expected | {
        (px, levels, contrast)
        for px in (HIGHPASS_PX, 6.0)
        for levels in (0, 1)
        for contrast in (0.0, 3.0)
    }
    kept = ~refinement.accepted
    torch.testing.assert_close(refinement.poses[kept], starts[kept].to(refinement.poses))


def test_calibrating_for_any_start_tries_the_listed_filters_too(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """AnyStartOptions.filters (the run's filters_from_val): each tried with every first step
    over the refiner's own filter, beside the built-in grid; an unknown key is a one-line
    error naming it."""
    from pae.render_compare import AnyStartOptions, Queries, api, calibrate_any_start
    from pae.render_compare.calibration import STEP_SHARES

    tried = []
    build = api.build_refiner

    def spy(scene_model: Any, settings: Any, steps: Any = None) -> Any:
        if steps:
            tried.append(dict(steps))
        return build(scene_model, settings, steps)

    monkeypatch.setattr(api, "build_refiner", spy)
    model, images, intrinsics, truth, _ = _oracle_queries(4)
    scenes = torch.zeros(len(truth), dtype=torch.long)
    settings = {"rounds": 2, "candidates": 4, "resolution": 16, "reference_size": 12}
    clip = {"highlight_quantile": 0.8}
    options = AnyStartOptions(highpass_px=(), contrast_px=(), surface_shares=(), filters=[clip])
    calibrate_any_start(model, Queries(images, intrinsics, scenes), truth, 2.0, settings, options)
    clipped = [steps for steps in tried if steps.get("highlight_quantile") == 0.8]
    assert len(clipped) == len(tried) // 2 == len(STEP_SHARES)
    assert all(steps["highpass_sigma_px"] == 0.0 for steps in clipped)  # over the own filter
    with pytest.raises(ValueError, match="filters_from_val: glare is not a filter setting"):
        AnyStartOptions(filters=[{"glare": 1.0}])


def test_the_search_draws_the_same_numbers_chunk_by_chunk() -> None:
    refiner = RenderCompareRefiner.configured(OracleSceneModel([]), rounds=3, candidates=5, seed=3)
    stream = refiner.draw_stream()
    pieces = torch.cat([stream(n) for n in (1, 4, 2)])
    torch.testing.assert_close(pieces, refiner.draws(7), atol=0, rtol=0)


def test_fit_images_are_resized_with_their_intrinsics(tiny_root: Path) -> None:
    from pae.scene_model.rays import fit_images

    data = SyntheticDataModule(
        root=str(tiny_root), **TINY, crop=28, shorter_edge=TINY["size"], cache_images=True
    )
    data.setup()
    dataset = data.datasets["train"]
    intrinsics = data.intrinsics("train", crop=False)
    images, scaled = fit_images(dataset, intrinsics, TINY["size"] // 2)
    assert images.dtype == torch.uint8
    assert images.shape == (len(dataset), 3, TINY["size"] // 2, TINY["size"] // 2)
    torch.testing.assert_close(scaled[:, :2], intrinsics[:, :2] / 2)
    same, unscaled = fit_images(dataset, intrinsics, None)
    assert torch.equal(same, dataset.__getitems__(list(range(len(dataset))))["image"])
    assert torch.equal(unscaled, intrinsics)


def _poisoned_data(root: Path) -> SyntheticDataModule:
    data = SyntheticDataModule(
        root=str(root), **TINY, crop=28, shorter_edge=TINY["size"], cache_images=True
    )
    data.setup()
    return data


GRID = {"num_voxels": 512, "samples_per_ray": 8, "near_m": 0.05}


def test_bounds_come_from_the_train_cameras_only(poisoned_root: Path) -> None:
    """The grid's bounds are the clean train rows' positions plus the margin, read from the
    label file here; a validation or test row read would move them by POISON_M."""
    from pae.data.labels import read_labels
    from pae.scene_model.base import SceneModelInputs
    from pae.scene_model.voxel_layout import camera_extent_m

    data = _poisoned_data(poisoned_root)
    table = read_labels(poisoned_root / "labels" / "all_train.csv")
    clean = np.abs(table.poses[:, :3]).max(1) < POISON_M / 2
    inputs = SceneModelInputs(data, "sequence", lambda key: None)
    auto = {"margin_floor_m": 0.1, "margin_fraction": 0.5, "contract_above_m": 1e6}
    _, fixed = VoxelGridSceneModel.build(
        {"margin_m": [1.0, 2.0, 0.5], "contract": "auto", "auto_scale": auto, **GRID},
        inputs,
    )
    _, automatic = VoxelGridSceneModel.build(
        {"margin_m": "auto", "contract": False, "auto_scale": auto, **GRID}, inputs
    )
    assert fixed["contract"] is False and "margin_m" not in fixed and "auto_scale" not in fixed
    assert fixed["n_appearances"] == len(
        {(s, q) for s, q, c in zip(table.scene, table.seq, clean, strict=True) if c}
    )
    for s, name in enumerate(data.scene_names):
        rows = clean & (np.asarray(table.scene) == name)
        positions = torch.from_numpy(table.poses[rows, :3])
        extent = torch.tensor(max(0.1, 0.5 * camera_extent_m(positions))).double()
        for config, margin in (
            (fixed, torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)),
            (automatic, extent),
        ):
            bounds = torch.tensor(config["bounds"][s], dtype=torch.float64)
            torch.testing.assert_close(bounds[0], positions.min(0).values - margin)
            torch.testing.assert_close(bounds[1], positions.max(0).values + margin)
    street = {**auto, "contract_above_m": 0.0}
    _, contracted = VoxelGridSceneModel.build(
        {"margin_m": 1.0, "contract": "auto", "auto_scale": street, **GRID}, inputs
    )
    assert contracted["contract"] is True


def test_camera_extent_ignores_a_few_stray_frames() -> None:
    from pae.scene_model.voxel_layout import camera_extent_m

    positions = torch.zeros(200, 3)
    positions[:, 0] = torch.linspace(0, 4, 200)
    positions[0] = torch.tensor([500.0, 0.0, 0.0])  # one stray frame
    assert camera_extent_m(positions) == pytest.approx(4.0, abs=0.2)


def test_scene_model_rays_come_from_the_train_images_only(poisoned_root: Path) -> None:
    """Every ray starts at a clean train camera, runs through one of its pixels and carries
    that pixel's colour; a validation or test row read would start POISON_M away or be
    magenta."""
    from pae.core.camera import camera_rays
    from pae.scene_model.rays import RayLoader

    data = _poisoned_data(poisoned_root)
    data.train_batches = RayLoader(rays_per_batch=512, batches=2)
    batch = next(iter(data.train_dataloader()))
    train = data.datasets["train"]
    assert (train.poses[:, :3].abs().amax(1) < POISON_M / 2).all()
    images = train.__getitems__(list(range(len(train))))["image"]
    h, w = images.shape[-2:]
    _, directions = camera_rays(train.poses, data.intrinsics("train", crop=False), w, h)
    row = (batch["origins"][:, None] - train.poses[None, :, :3]).norm(dim=-1).argmin(1)
    assert torch.allclose(batch["origins"], train.poses[row, :3])
    unit = directions[row] / directions[row].norm(dim=-1, keepdim=True)
    ray = batch["directions"] / batch["directions"].norm(dim=-1, keepdim=True)
    pixel = (unit * ray[:, None]).sum(-1).argmax(1)  # the pixel whose ray it is
    torch.testing.assert_close(batch["directions"], directions[row, pixel], atol=1e-5, rtol=0)
    colours = images[row].flatten(2)[torch.arange(len(row)), :, pixel].float() / 255
    torch.testing.assert_close(batch["rgb"], colours)
    magenta = torch.tensor(MAGENTA) / 255
    assert not (batch["rgb"] == magenta).all(1).any()


def test_ray_batches_are_drawn_from_seed_epoch_and_batch_alone(tiny_root: Path) -> None:
    """A RayLoader's batch depends on (seed, the data module's trainer's epoch, batch) and
    nothing drawn before it: a resumed run's loader gives what an uninterrupted one's did."""
    from types import SimpleNamespace

    from pae.scene_model.rays import RayLoader

    data = _poisoned_data(tiny_root)

    def batch(seed: int, epoch: int, index: int) -> dict[str, torch.Tensor]:
        data.trainer = SimpleNamespace(current_epoch=epoch)
        torch.manual_seed(seed + 100 * epoch + index)  # the global generator plays no part
        return RayLoader(rays_per_batch=64, batches=3, seed=seed)(data).dataset[index]

    first = batch(0, 1, 2)
    assert all(torch.equal(first[k], batch(0, 1, 2)[k]) for k in ("origins", "rgb"))
    assert first["seed"] == batch(0, 1, 2)["seed"]
    for other in (batch(0, 2, 2), batch(0, 1, 1), batch(1, 1, 2)):
        assert not torch.equal(first["origins"], other["origins"])
        assert first["seed"] != other["seed"]
    at_start = batch(0, 0, 1)["origins"]
    data.trainer = None  # no trainer: epoch 0
    assert torch.equal(at_start, RayLoader(64, 3)(data).dataset[1]["origins"])


def test_render_compare_step_logs_its_rows_and_marks_the_oracle(
    tiny_root: Path, tmp_path: Path
) -> None:
    """stage=render_compare on the tiny benchmark: honest and oracle rows, the scene model's
    quality, a timing; on data without true scenes the oracle row is absent."""
    from pae.report.tables import format_results_table
    from pae.train import run

    overrides = [
        *tiny_data_overrides(tiny_root),
        "data.batch_size=8",
        "callbacks=minimal",
        "+trainer.enable_progress_bar=false",
        "teacher.max_epochs=1",
        *TINY_SCENE_MODEL,
        "scene_model.image_size=16",  # fit to smaller images than the data's
        "stage.steps=[teacher,scene_model]",
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    metrics = run(cfg, tmp_path)
    for method in ("render_compare", "render_compare_oracle"):
        # the figures are those of the per-query records: the gate's pose where accepted,
        # the start elsewhere
        (path,) = tmp_path.rglob(f"queries_test_{method}.csv")
        rows = np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")
        accepted = rows["accepted"] == 1
        pos = np.where(accepted, rows["refined_pos_m"], rows["start_pos_m"])
        rot = np.where(accepted, rows["refined_rot_deg"], rows["start_rot_deg"])
        for scene in ("scene00", "scene01"):  # figures per scene (the CSV rounds to 1e-5)
            rows_of = rows["scene"] == scene
            figure = metrics[f"test/{method}/{scene}/pos_median_m"]
            assert figure == pytest.approx(np.median(pos[rows_of]), abs=1e-5)
            within = np.mean((pos[rows_of] <= 0.1) & (rot[rows_of] <= 10.0))
            assert metrics[f"test/{method}/{scene}/within_10cm_10deg"] == pytest.approx(within)
        assert metrics[f"test/{method}/accepted_share"] == pytest.approx(accepted.mean())
        # the margin applied at test is the one chosen on the last validation run
        assert metrics[f"test/{method}/accept_margin"] == metrics[f"val/{method}/accept_margin"]
    assert "test/scene_model/psnr_db" in metrics
    assert metrics["bench/render_compare/ms_per_query"] > 0
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["test/render_compare/pos_median_m"] == metrics["test/render_compare/pos_median_m"]
    table = format_results_table(metrics)
    assert "render_compare_oracle †" in table and "render_compare †" not in table
    assert "bound" in table


def test_the_oracle_needs_synthetic_data(tiny_root: Path) -> None:
    from pae.data.datamodule import PoseDataModule
    from pae.lit.eval_outputs import oracle_scenes

    plain = PoseDataModule(
        str(tiny_root),
        str(tiny_root / "labels" / "all_train.csv"),
        str(tiny_root / "labels" / "all_test.csv"),
    )
    assert oracle_scenes(plain) is None
    synthetic = SyntheticDataModule(root=str(tiny_root), **TINY)
    synthetic.setup()
    assert len(oracle_scenes(synthetic)) == TINY["scenes"]


def test_a_focal_column_sets_each_rows_intrinsics(tiny_root: Path, tmp_path: Path) -> None:
    """Per-image focal lengths (px at data.camera's size) are read, written back and carried
    through the loaders' resize and crop."""
    from pae.data.datamodule import PoseDataModule
    from pae.data.labels import read_labels

    focal = np.linspace(20.0, 30.0, len(read_labels(tiny_root / "labels" / "all_train.csv")))
    labels, test_labels = with_focal_column(tiny_root, tmp_path, focal)
    np.testing.assert_array_equal(read_labels(labels).focal, focal)
    data = PoseDataModule(
        str(tiny_root),
        str(labels),
        str(test_labels),
        shorter_edge=64,
        crop=56,
        camera=FOCAL_CAMERA,
    )
    data.setup()
    train, test = data.intrinsics("train"), data.intrinsics("test")
    kept = data.tables["train"].focal  # the held-out validation sequences aside
    assert np.isin(kept, focal).all() and len(kept) >= len(focal) // 2
    np.testing.assert_allclose(train[:, 0].numpy(), 2 * kept, rtol=1e-6)
    centre = (15.5 + 0.5) * 2 - 0.5 - (64 - 56) // 2  # resized, then cropped
    np.testing.assert_allclose(test[0].numpy(), [50.0, 50.0, centre, centre], rtol=1e-6)


def test_a_focal_column_with_a_bad_value_names_its_line(tmp_path: Path) -> None:
    from pae.data.labels import LabelError, read_labels

    labels = tmp_path / "bad.csv"
    labels.write_text(
        "scene,split,seq,img_path,t1,t2,t3,q1,q2,q3,q4,focal\n"
        "a,train,s,a/1.png,0,0,0,1,0,0,0,500\n"
        "a,train,s,a/2.png,0,0,0,1,0,0,0,-3\n"
    )
    with pytest.raises(LabelError, match=r"bad.csv:3: .*focal"):
        read_labels(labels)


def _fake_run(
    model: Any, images: Tensor, intrinsics: Tensor, start: Tensor, truth: Tensor, log_dir: Any
) -> tuple[Any, Any]:
    """A trainer and a scene-model module with one scene's collected evaluation outputs,
    as the render-and-compare callback reads them."""
    from types import SimpleNamespace

    n = len(truth)
    scenes = torch.zeros(n, dtype=torch.long)
    trainer = SimpleNamespace(world_size=1, datamodule=SimpleNamespace(), log_dir=log_dir)
    outputs = {
        "image": images,
        "intrinsics": intrinsics,
        "estimate": start,
        "scene_estimate": scenes,
        "pose": truth,
        "scene": scenes,
        "index": torch.arange(n),
    }
    module = SimpleNamespace(
        scene_model=model,
        teacher=None,
        scene_names=["scene00"],
        log_dict=lambda figures: None,
        eval_outputs=[outputs],
    )
    return trainer, module


def test_the_callback_refines_without_reading_the_true_poses(tmp_path: Path) -> None:
    """The refined poses are the same whatever the evaluated split's true poses are: they
    only enter the error figures and the per-query file."""
    from pae.callbacks.render_compare import ORACLE, RenderCompareCallback

    model, images, intrinsics, truth, start = _oracle_queries(4)
    n = len(truth)
    callback = RenderCompareCallback(
        {"rounds": 3, "candidates": 8, "resolution": 16, "reference_size": 12}, oracle=False
    )
    refined = []
    for gt in (truth, torch.full_like(truth, float("nan"))):
        trainer, module = _fake_run(model, images, intrinsics, start, gt, str(tmp_path))
        callback.refine(trainer, module, "test")
        refined.append(callback.refined["test"][ORACLE])
        if torch.isfinite(gt).all():
            rows = (tmp_path / "queries_test_render_compare_oracle.csv").read_text().splitlines()
    header, *rows = [row.split(",") for row in rows]
    assert header[:3] == ["index", "scene", "start_pos_m"] and len(rows) == n
    assert [int(r[0]) for r in rows] == list(range(n)) and {r[1] for r in rows} == {"scene00"}
    start_pos, _ = pose_errors(start, truth)
    torch.testing.assert_close(
        torch.tensor([float(r[2]) for r in rows]), start_pos.float(), atol=1e-5, rtol=0
    )
    assert torch.isfinite(refined[1]).all()
    torch.testing.assert_close(refined[0], refined[1])


def test_the_polish_runs_inside_an_evaluation_loop_and_aligns_further() -> None:
    """Lightning evaluates in inference mode; the Levenberg–Marquardt polish runs there and
    takes the search's poses closer to the truth."""
    model, images, intrinsics, truth, start = _oracle_queries(4)
    scenes = torch.zeros(len(start), dtype=torch.long)
    settings = {"rounds": 3, "candidates": 8, "resolution": 24, "reference_size": 16}
    with torch.inference_mode():
        plain = RenderCompareRefiner.configured(model, polish_steps=0, **settings)(
            images, intrinsics, start, scenes
        )
        polished = RenderCompareRefiner.configured(model, polish_steps=8, **settings)(
            images, intrinsics, start, scenes
        )
    searched, _ = pose_errors(plain.poses, truth)
    aligned, _ = pose_errors(polished.poses, truth)
    assert torch.isfinite(polished.poses).all()
    assert aligned.median() < 0.5 * searched.median()


def test_the_paper_decoder_is_a_scene_model_without_depth() -> None:
    """The PAE decoder renders at a pose (no depth), resized to the size asked for; the
    refiner then renders every candidate instead of projecting a surface."""
    from pae.models.decoder import ImageDecoder
    from pae.models.pae import PoseAutoEncoder
    from pae.scene_model.base import PaeDecoderSceneModel

    model = PaeDecoderSceneModel(PoseAutoEncoder(latent_dim=16), ImageDecoder(latent_dim=16))
    poses = _camera_pose([0.0, 0.0, 1.4])[None].repeat(3, 1)
    intrinsics = torch.tensor([20.0, 20.0, 11.5, 11.5]).expand(3, 4)
    rendering = model.render(poses, torch.zeros(3, dtype=torch.long), intrinsics, 24, 24)
    assert rendering.rgb.shape == (3, 3, 24, 24) and rendering.depth is None
    rendered: list[int] = []
    render = model.render

    def counted(at: Tensor, *args: Any, **kwargs: Any) -> Any:
        rendered.append(len(at))
        return render(at, *args, **kwargs)

    model.render = counted  # type: ignore[method-assign]
    with torch.no_grad():
        images = rendering.rgb.detach()
        refiner = RenderCompareRefiner.configured(model, rounds=2, candidates=4, resolution=24)
        result = refiner(images, intrinsics, poses, torch.zeros(3, dtype=torch.long))
    # every round's 3 queries x 4 hypotheses x 4 candidates rendered at once (a surface
    # would be rendered only at the start and once more before the finest level: 3 poses)
    per_round = 3 * refiner.hypotheses * 4
    assert max(rendered) == per_round and rendered.count(per_round) >= 2
    assert torch.isfinite(result.poses).all() and torch.isfinite(result.score).all()


def test_the_search_steps_follow_the_teachers_val_error() -> None:
    from pae.callbacks.render_compare import HONEST, RenderCompareCallback
    from pae.render_compare import build_refiner
    from pae.render_compare.calibration import steps_from_errors

    truth = torch.zeros(4, 7)
    truth[:, 3] = 1.0
    estimate = truth.clone()
    estimate[:, 0] = torch.tensor([1.0, 2.0, 3.0, 4.0])  # median position error 2.5 m
    callback = RenderCompareCallback(
        {"rounds": 2}, oracle=False, step_from_val={"position": 0.4, "orientation": 0.5}
    )
    model = OracleSceneModel([])
    calibration = callback.calibration(HONEST)
    refiner = build_refiner(model, callback.settings, calibration.steps)
    assert refiner.sigma == pytest.approx((0.25, math.radians(4.0)))
    steps = steps_from_errors(estimate, truth, callback.options.step_from_val)
    assert steps["position_sigma_m"] == pytest.approx(1.0)
    refiner = build_refiner(model, callback.settings, steps)
    assert refiner.sigma[0] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="step_from_val"):
        RenderCompareCallback(step_from_val={"position": 0.4})


def test_per_image_appearance_gives_each_train_row_its_own_code(tiny_root: Path) -> None:
    data = SyntheticDataModule(root=str(tiny_root), **TINY, crop=28, shorter_edge=TINY["size"])
    data.setup()
    n = len(data.datasets["train"])
    ids, count = data.appearance_ids("train", "image")
    assert count == n and torch.equal(ids, torch.arange(n))
    sequence_ids, sequences = data.appearance_ids("train")
    assert sequences < n and sequence_ids.max() == sequences - 1
    with pytest.raises(ValueError, match=r"scene_model\.appearance"):
        data.appearance_ids("train", "frame")


def _fit_module(**kwargs: object) -> object:
    import functools

    from pae.lit.scene_model import SceneModelModule

    bounds = [[[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]]
    return SceneModelModule(
        VoxelGridSceneModel(
            bounds, 4, num_voxels=1000, samples_per_ray=8, contract=False, near_m=0.05
        ),
        torch.nn.Linear(1, 1),
        functools.partial(torch.optim.Adam, lr=0.1),
        scene_names=["scene00"],
        configs={},
        **kwargs,
    )


@pytest.mark.filterwarnings("ignore:You are trying to `self.log")
def test_the_trimmed_fit_leaves_the_worst_explained_rays_out() -> None:
    """With fit_trim 0.25 the loss is the mean error of the best-explained three quarters of
    the rays: rays whose colour no grid explains (an occluder's) do not pull the fit."""
    torch.manual_seed(0)
    rays = 64
    directions = torch.nn.functional.normalize(torch.randn(rays, 3), dim=1)
    colours = torch.full((rays, 3), 0.5)
    colours[:16] = torch.tensor([1.0, 0.0, 1.0])  # a quarter of the rays: an occluder
    batch = {
        "origins": torch.zeros(rays, 3),
        "directions": directions,
        "scene": torch.zeros(rays, dtype=torch.long),
        "appearance": torch.zeros(rays, dtype=torch.long),
        "rgb": colours,
        "seed": 1,  # the samples' jitter
    }
    losses = {}
    for trim in (0.0, 0.25):
        module = _fit_module(tv_weight=0.0, fit_trim=trim, fit_trim_from_epoch=0)
        losses[trim] = module.training_step(batch, 0).item()
        torch.manual_seed(1)
        rgb, _, _ = module.scene_model.render_rays(
            batch["origins"], batch["directions"], batch["scene"], jitter=True
        )
        errors = (rgb - colours).square().mean(1)
    assert losses[0.25] == pytest.approx(errors.sort().values[:48].mean().item(), rel=1e-5)
    assert losses[0.25] < 0.5 * losses[0.0]


def test_the_appearance_codes_get_their_own_learning_rate() -> None:
    module = _fit_module(appearance_lr=0.01)
    groups = module.trainable_parameters()
    assert [g.get("lr") for g in groups] == [None, 0.01]
    codes = {id(p) for p in module.scene_model.appearance.parameters()}
    assert {id(p) for p in groups[1]["params"]} == codes
    assert codes.isdisjoint(id(p) for p in groups[0]["params"])
    assert len(_fit_module().trainable_parameters()) == len(list(module.scene_model.parameters()))


def test_the_appearance_field_is_a_smooth_gain_over_the_image_fitted_with_the_codes() -> None:
    """appearance_field 3: a code's field starts at gain 1; raising the top-left node's
    log-gain brightens the top-left pixel by that factor, the image's centre by none and
    the ray halfway between by half of it (bilinear, in log-gain); without pixels or with
    no field the per-channel gain and bias alone apply. The field's log-gains are part of
    the appearance codes (their learning rate), and a field of 1 node is refused."""
    bounds = [[[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]]
    model = VoxelGridSceneModel(
        bounds, 2, num_voxels=1000, samples_per_ray=8, contract=False, near_m=0.05,
        appearance_field=3,
    )  # fmt: skip
    assert model.appearance.weight.shape == (2, 6 + 9)
    rgb = torch.full((3, 3), 0.5)
    codes = torch.tensor([1, 1, 1])
    pixels = torch.tensor([[0.0, 0.0], [0.5, 0.5], [0.25, 0.0]])
    torch.testing.assert_close(model.with_appearance(rgb, codes, pixels), rgb)
    with torch.no_grad():
        model.appearance.weight[1, 6] = math.log(2.0)  # code 1, node (row 0, column 0)
    seen = model.with_appearance(rgb, codes, pixels)[:, 0]
    torch.testing.assert_close(seen, torch.tensor([1.0, 0.5, 0.5 * math.sqrt(2.0)]))
    torch.testing.assert_close(model.with_appearance(rgb, codes), rgb)
    torch.testing.assert_close(model.with_appearance(rgb, codes * 0, pixels), rgb)
    with pytest.raises(ValueError, match="appearance_field"):
        VoxelGridSceneModel(
            bounds, 2, num_voxels=1000, samples_per_ray=8, contract=False, near_m=0.05,
            appearance_field=1,
        )  # fmt: skip


def test_the_band_pass_score_ignores_smooth_shading_that_plain_zncc_does_not() -> None:
    """A light fall-off across the image (a ramp ten times the texture's contrast) halves
    the plain ZNCC of an image with itself; after the band pass it stays above 0.8 (the
    replicated edges leave some of the ramp)."""
    torch.manual_seed(0)
    texture = torch.rand(1, 1, 32, 32)
    ramp = torch.linspace(0, 3, 32).view(1, 1, 1, 32).expand(1, 1, 32, 32)
    lit = texture + ramp

    def score(a: torch.Tensor, b: torch.Tensor, highpass: float) -> float:
        x, y = band_pass(a, 1.0, highpass).flatten(1), band_pass(b, 1.0, highpass).flatten(1)
        return zncc(x, y, torch.ones_like(x)).item()

    assert score(texture, lit, 0.0) < 0.5
    assert score(texture, lit, 4.0) > 0.8
    torch.testing.assert_close(band_pass(texture, 1.0, 0.0), band_pass(texture, 1.0, -1.0))
    with pytest.raises(ValueError, match="highpass_sigma_px"):
        RenderCompareRefiner.configured(OracleSceneModel([]), highpass_sigma_px=-1.0)


def test_the_local_contrast_evens_out_a_vignette_that_the_high_pass_leaves() -> None:
    """A gain that falls from 1 at the centre to 0.1 at the corners (vignetting, a highlight's
    edge) scales the texture's band pass there; divided by its local contrast the image
    correlates with the unvignetted one better than after the high pass alone."""
    torch.manual_seed(0)
    texture = torch.rand(1, 1, 48, 48)
    v, u = torch.meshgrid(torch.linspace(-1, 1, 48), torch.linspace(-1, 1, 48), indexing="ij")
    dimmed = texture * (1 - 0.45 * (u.square() + v.square()))

    def score(contrast: float) -> float:
        x = band_pass(texture, 0.5, 4.0, contrast).flatten(1)
        y = band_pass(dimmed, 0.5, 4.0, contrast).flatten(1)
        return zncc(x, y, torch.ones_like(x)).item()

    assert score(3.0) > score(0.0) + 0.02
    torch.testing.assert_close(band_pass(texture, 1.0, 4.0), band_pass(texture, 1.0, 4.0, 0.0))
    flat = band_pass(torch.full((1, 1, 16, 16), 0.5), 1.0, 4.0, 3.0)
    assert torch.isfinite(flat).all() and flat.abs().max() < 1e-3  # no texture: none made up
    with pytest.raises(ValueError, match="contrast_sigma_px"):
        RenderCompareRefiner.configured(OracleSceneModel([]), contrast_sigma_px=-1.0)


def test_clipping_the_brightest_values_keeps_a_highlight_from_steering_the_score() -> None:
    """A bright blob added to one image of a texture (a highlight the scene model does not
    have) lowers their correlation; clipped at the images' 70 % quantile first, the texture
    under it correlates again. Both engines clip the query and the renderings alike."""
    torch.manual_seed(0)
    texture = 0.3 + 0.2 * torch.rand(1, 1, 48, 48)
    v, u = torch.meshgrid(torch.linspace(-1, 1, 48), torch.linspace(-1, 1, 48), indexing="ij")
    lit = texture + 2.0 * torch.exp(-((u - 0.3).square() + v.square()) / 0.08)

    def score(quantile: float) -> float:
        x = band_pass(clip_bright(texture, quantile), 0.5, 4.0).flatten(1)
        y = band_pass(clip_bright(lit, quantile), 0.5, 4.0).flatten(1)
        return zncc(x, y, torch.ones_like(x)).item()

    assert score(0.7) > score(0.0) + 0.2
    assert torch.equal(clip_bright(lit, 0.0), lit)
    assert clip_bright(lit, 0.7).max() < lit.max() / 2
    with pytest.raises(ValueError, match="highlight_quantile"):
        RenderCompareRefiner.configured(OracleSceneModel([]), highlight_quantile=1.0)
    model, images, intrinsics, _, start = _oracle_queries(3)
    settings = {"rounds": 2, "candidates": 6, "resolution": 16, "highlight_quantile": 0.7}
    scenes = torch.zeros(3, dtype=torch.long)
    poses = [
        RenderCompareRefiner.configured(model, engine=engine, **settings)(
            images, intrinsics, start, scenes
        ).poses
        for engine in ("numba", "torch")
    ]
    torch.testing.assert_close(poses[0], poses[1], atol=1e-3, rtol=0)


def test_the_package_refines_without_lightning_as_the_callback_does(tmp_path: Path) -> None:
    """pae.render_compare's calibrate and refine run with lightning never imported, and give
    the callback's poses on the same val and test queries."""
    import subprocess
    import sys

    from pae.callbacks.render_compare import RenderCompareCallback

    settings = {"rounds": 3, "candidates": 8, "resolution": 16, "reference_size": 12}
    model, images, intrinsics, truth, start = _oracle_queries(6)
    callback = RenderCompareCallback(
        settings, oracle=False, step_from_val={"position": 0.3, "orientation": 0.4}
    )
    trainer, module = _fake_run(model, images, intrinsics, start, truth, None)
    for split in ("val", "test"):
        callback.refine(trainer, module, split)
    torch.save(
        {"images": images, "intrinsics": intrinsics, "truth": truth, "start": start},
        tmp_path / "queries.pt",
    )
    code = f"""
import sys, torch
from pae.render_compare import CalibrationOptions, Queries, Validation, calibrate, refine
from pae.scene_model.oracle import OracleSceneModel
q = torch.load({str(tmp_path / "queries.pt")!r})
from pae.synthetic import make_scene
model = OracleSceneModel([make_scene(0)])
queries = Queries(q["images"], q["intrinsics"], torch.zeros(6, dtype=torch.long))
settings = {settings!r}
options = CalibrationOptions(step_from_val={{"position": 0.3, "orientation": 0.4}})
val = Validation(queries, q["start"], q["truth"])
calibration, val = calibrate(model, val, options, settings=settings)
test = refine(model, queries, q["start"], calibration, settings=settings)
assert "lightning" not in sys.modules and "pytorch_lightning" not in sys.modules
torch.save({{"val": val.poses, "test": test.poses}}, {str(tmp_path / "out.pt")!r})
"""
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    out = torch.load(tmp_path / "out.pt")
    # the test split's refinement under the gate and steps chosen on val, as the callback's
    torch.testing.assert_close(out["test"], callback.refined["test"]["render_compare_oracle"])
    torch.testing.assert_close(out["val"], callback.refined["val"]["render_compare_oracle"])


def test_the_public_refine_names_a_wrong_shape() -> None:
    from pae.render_compare import Queries, refine

    model, images, intrinsics, _, start = _oracle_queries(3)
    with pytest.raises(ValueError, match=r"starts must be \[3, 7\], got \[3, 6\]"):
        refine(model, Queries(images, intrinsics, torch.zeros(3, dtype=torch.long)), start[:, :6])


def _designed_refiner(truth: Tensor, errors: dict[float | None, list[float]]) -> Any:
    """build_refiner's stand-in: a refiner that moves each query to its true pose shifted by
    ``errors[blur_sigma_px]`` m along x (the filter's ``blur_sigma_px``, None: the refiner's
    own), every score gain 0.4 (so that the gate can only accept all or keep all)."""

    def build(scene_model: Any, settings: Any, steps: Any = None) -> Any:
        shift = torch.tensor(errors[(steps or {}).get("blur_sigma_px")])

        def refiner(images: Tensor, intrinsics: Tensor, starts: Tensor, scenes: Tensor) -> Any:
            poses = truth.clone()
            poses[:, 0] += shift
            return RenderCompareResult(poses, torch.full((4,), 0.9), torch.full((4,), 0.5))

        return refiner

    return build


@pytest.mark.parametrize(("objective", "kept"), [("mean", 1.0), ("log_ratio", 2.0)])
def test_calibrate_keeps_the_filter_that_minimises_its_one_objective(
    monkeypatch: pytest.MonkeyPatch, objective: str, kept: float
) -> None:
    """``filters_from_val``: each tried on the val queries, the one whose gated refinement
    minimises the calibration's objective is kept in its steps. Starts 1 m off (two queries)
    and 1 cm off (two): filter 1.0 takes them to 10 cm and 2 cm (mean 0.06 m, mean log ratio
    -0.82), filter 2.0 leaves the far ones and takes the near ones to 0.1 mm (0.50 m, -1.15),
    the refiner's own leaves every start (0.505 m, 0): the mean picks 1.0, the log ratio
    2.0."""
    from pae.render_compare import CalibrationOptions, Queries, Validation, api, calibrate

    truth = torch.zeros(4, 7)
    truth[:, 1], truth[:, 3] = torch.arange(4.0), 1.0
    starts = truth.clone()
    starts[:, 0] += torch.tensor([1.0, 1.0, 0.01, 0.01])
    errors = {None: [1.0, 1.0, 0.01, 0.01], 1.0: [0.1, 0.1, 0.02, 0.02]}
    errors[2.0] = [1.0, 1.0, 1e-4, 1e-4]
    monkeypatch.setattr(api, "build_refiner", _designed_refiner(truth, errors))
    queries = Queries(torch.zeros(4, 3, 8, 8), torch.ones(4, 4), torch.zeros(4, dtype=torch.long))
    filters = [{}, {"blur_sigma_px": 1.0}, {"blur_sigma_px": 2.0}]
    options = CalibrationOptions(filters_from_val=filters, gate_objective=objective)
    calibration, best = calibrate(OracleSceneModel([]), Validation(queries, starts, truth), options)
    assert dict(calibration.steps) == {"blur_sigma_px": kept} and best.accepted.all()
    torch.testing.assert_close(pose_errors(best.poses, truth)[0], torch.tensor(errors[kept]))
    with pytest.raises(ValueError, match=r"render_compare\.filters_from_val: shrink is not"):
        CalibrationOptions(filters_from_val=[{"shrink": 0.5}])
    chosen = CalibrationOptions(filters_from_val=[{}, {"surface_share": 0.7}])
    assert chosen.filters_from_val[1] == {"surface_share": 0.7}  # a filter may place the surface
