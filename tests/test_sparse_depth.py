"""Depth from keypoints triangulated between train views (pae.scene_model.sparse_depth) and
the scene model's fit towards it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pae.core.geometry import matrix_to_quaternion
from pae.scene_model.oracle import OracleSceneModel
from pae.scene_model.sparse_depth import partner_views, sparse_depths, triangulate
from pae.scene_model.voxel_grid import VoxelGrid
from pae.synthetic import Appearance, PinholeCamera, SyntheticSettings, make_scene, render_batch
from pae.synthetic.trajectories import make_sequences

IDENTITY = [1.0, 0.0, 0.0, 0.0]
INTRINSICS = torch.tensor([100.0, 100.0, 64.0, 64.0])


def _project(points: torch.Tensor, position: torch.Tensor) -> torch.Tensor:
    """Points [K, 3] seen by a camera at ``position`` looking along +z -> px [K, 2]."""
    local = points - position
    fx, fy, cx, cy = INTRINSICS
    return torch.stack(
        [fx * local[:, 0] / local[:, 2] + cx, fy * local[:, 1] / local[:, 2] + cy], 1
    )


def test_triangulation_recovers_the_depth_and_refuses_what_does_not_meet() -> None:
    points = torch.tensor([[0.5, -0.3, 4.0], [-1.0, 0.2, 6.0], [0.0, 0.0, 400.0], [0.2, 0.1, 5.0]])
    a, b = torch.tensor([0.0, 0.0, 0.0]), torch.tensor([1.0, 0.0, 0.0])
    xy_a, xy_b = _project(points, a), _project(points, b)
    xy_b[3, 1] += 5.0  # a wrong match: off the epipolar line by 5 px
    poses_a = torch.tensor([[*a, *IDENTITY]])
    poses_b = torch.tensor([[*b, *IDENTITY]])
    depth, holds = triangulate(
        xy_a[None], xy_b[None], poses_a, poses_b, INTRINSICS[None], INTRINSICS[None]
    )
    torch.testing.assert_close(depth[0, :2], points[:2, 2], rtol=1e-4, atol=0)
    # the far point's rays meet at 0.14 degrees (below the parallax kept), the wrong match
    # reprojects 2.5 px off in each view
    assert holds[0].tolist() == [True, True, False, False]


def test_partners_lie_far_enough_away_in_the_same_scene_and_look_the_same_way() -> None:
    x = torch.arange(10.0)
    poses = torch.zeros(10, 7)
    poses[:, 0], poses[:, 3] = x, 1.0
    turned = matrix_to_quaternion(
        torch.tensor(
            [[math.cos(1.0), 0, math.sin(1.0)], [0, 1, 0], [-math.sin(1.0), 0, math.cos(1.0)]]
        )
    )
    poses[4, 3:] = turned  # 57 degrees off the others' axes
    scenes = torch.tensor([0] * 9 + [1])
    partners = partner_views(poses, scenes)
    # extent 8 m -> partners at 1.2 m or more
    assert partners[0].tolist() == [2, 3]
    assert sorted(partners[3].tolist()) == [1, 5]  # 2 and 4: too near, turned away
    assert 4 not in partners[:4].flatten().tolist() and partners[4].tolist() == [-1, -1]
    assert partners[9].tolist() == [-1, -1]  # alone in its scene


def test_keypoints_triangulated_on_the_benchmark_lie_on_its_surfaces() -> None:
    """The triangulated depths of the benchmark's rendered train views, against its own
    renderer's depth at the same pixels."""
    scene = make_scene(0)
    camera = PinholeCamera(128)
    settings = SyntheticSettings(train_frames=60, test_frames=4)
    train = np.concatenate([walk.poses for walk in make_sequences(0, scene, settings)[:-2]])
    poses = torch.from_numpy(train).float()
    images = torch.from_numpy(render_batch(scene, train, camera, Appearance(), supersample=1))
    images = images.permute(0, 3, 1, 2).contiguous()
    f, c = camera.focal_px, camera.principal_point
    intrinsics = torch.tensor([f, f, c, c]).expand(len(poses), 4)
    scenes = torch.zeros(len(poses), dtype=torch.long)
    depths = sparse_depths(images, poses, intrinsics, scenes)
    assert len(depths.row) >= 100 and len(depths.row.unique()) >= len(poses) // 2
    truth = OracleSceneModel([scene]).render(poses, scenes, intrinsics, 128, 128).depth
    at = truth[depths.row, depths.v.round().long(), depths.u.round().long()]
    error = (depths.depth / at).log().abs()
    assert error.median() < 0.03
    assert (error > 0.1).float().mean() < 0.1


def test_the_depth_error_pulls_the_light_to_the_target_depth() -> None:
    """Fitted on the depth error alone, an empty grid's rays end at their target's depth."""
    torch.manual_seed(0)
    grid = VoxelGrid([[-2, -2, -0.5], [2, 2, 3.5]], num_voxels=8000)
    origins = torch.zeros(256, 3)
    directions = torch.cat([0.4 * torch.rand(256, 2) - 0.2, torch.ones(256, 1)], 1)
    target = torch.full((256,), 2.0)
    before = grid.depth_error(origins, directions, target, 64, 0.05).mean()
    optimiser = torch.optim.Adam(grid.parameters(), lr=0.1)
    for _ in range(60):
        optimiser.zero_grad()
        grid.depth_error(origins, directions, target, 64, 0.05).mean().backward()
        optimiser.step()
    with torch.no_grad():
        after = grid.depth_error(origins, directions, target, 64, 0.05).mean()
        _, depth, opacity = grid.composite(origins, directions, 64, 0.05, jitter=False)
    assert after < 0.2 * before
    assert depth.median().item() == pytest.approx(2.0, rel=0.1)
    assert opacity.median() > 0.9


def test_ray_batches_add_rays_through_the_triangulated_keypoints_after_the_pixels() -> None:
    """Each batch's depth rays start at their image's camera and run through their keypoint,
    their targets the keypoints' depths; the pixel rays drawn before them are unchanged."""
    from pae.core.camera import directions_through
    from pae.scene_model.rays import RayBatches
    from pae.scene_model.sparse_depth import SparseDepths

    poses = torch.tensor([[0.0, 0, 0, *IDENTITY], [1.0, 2, 3, *IDENTITY]])
    images = torch.zeros(2, 3, 8, 8, dtype=torch.uint8)
    intrinsics = INTRINSICS[None].expand(2, 4)
    ids = torch.arange(2)
    depths = SparseDepths(torch.tensor([1, 0]), torch.tensor([3.5, 1.0]), torch.tensor([2.0, 6.0]),
                          torch.tensor([7.0, 9.0]))  # fmt: skip
    plain = RayBatches(images, poses, intrinsics, ids, ids, 16, 1)[0]
    batch = RayBatches(images, poses, intrinsics, ids, ids, 16, 1, depths=depths, depth_rays=32)[0]
    assert "depth" not in plain
    assert all(torch.equal(plain[k], batch[k]) for k in ("origins", "directions", "rgb"))
    rays = batch["depth"]
    which = (rays["target"] == 9.0).long()  # keypoint 1 (image 0) or 0 (image 1)
    assert 0 < which.sum() < 32
    torch.testing.assert_close(rays["origins"], poses[1 - which, :3])
    expected = directions_through(depths.u[which], depths.v[which], INTRINSICS)
    torch.testing.assert_close(rays["directions"], expected)
    assert torch.equal(rays["scene"], 1 - which)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (("scene_model=oracle",), "scene_model.depth_rays: scene_model.model._target_="),
        (("scene_model.depth_rays=-1",), "depth_rays"),
    ],
)
def test_depth_rays_need_a_model_that_fits_depth(
    compose_train, tmp_path, overrides, message
) -> None:
    from pae.core.errors import ConfigError
    from pae.train import run

    cfg = compose_train("stage=render_compare", "scene_model.depth_rays=64", *overrides)
    with pytest.raises((ConfigError, ValueError), match=message):
        run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()
