"""experiments/render_compare_real_starts/floor.py's bounds: the benchmark's own renderer,
blurred, and how well a scene model explains queries at their true poses."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from types import ModuleType

import pytest
import torch

from pae.synthetic import PinholeCamera, SyntheticSettings, make_scene, make_sequences

FOLDER = Path(__file__).resolve().parents[1] / "experiments/render_compare_real_starts"
SETTINGS = {"blur_sigma_px": 0.3, "highpass_sigma_px": 4.0}


def _floor(monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    monkeypatch.syspath_prepend(str(FOLDER))  # floor.py imports run.py from beside it
    spec = importlib.util.spec_from_file_location("floor", FOLDER / "floor.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _queries(floor: ModuleType) -> dict[str, torch.Tensor]:
    """Four 48-px views of benchmark scene 0, rendered by its own renderer."""
    scene = make_scene(0)
    camera = PinholeCamera(48)
    walks = make_sequences(0, scene, SyntheticSettings(train_frames=6, test_frames=16))
    pose = torch.from_numpy(walks[-1].poses[::4]).float()
    f, c = camera.focal_px, camera.principal_point
    intrinsics = torch.tensor([f, f, c, c]).expand(len(pose), 4)
    scenes = torch.zeros(len(pose), dtype=torch.long)
    image = floor.BlurredOracle([scene], 0.0).render(pose, scenes, intrinsics, 48, 48).rgb
    return {"image": image, "pose": pose, "intrinsics": intrinsics, "scene": scenes}


def test_explained_ranks_a_blurred_renderer_below_the_sharp_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    floor = _floor(monkeypatch)
    queries = _queries(floor)
    scene = floor.BlurredOracle([make_scene(0)], 0.0)
    same = floor.explained(scene, scene, queries, SETTINGS)
    assert same["zncc_model"] == pytest.approx(1.0, abs=1e-4)
    assert same["zncc_model"] == pytest.approx(same["zncc_oracle"])
    assert same["depth_minus_oracle_median_m"] == 0.0
    assert same["opacity_model"] == 1.0
    assert same["surface_log_ratio_median"] == 0.0 and same["surface_within_10pc"] == 1.0
    blurred = floor.BlurredOracle([make_scene(0)], 2.0 / 48)
    worse = floor.explained(blurred, scene, queries, SETTINGS)
    assert worse["zncc_model"] < same["zncc_model"] - 0.05
    assert worse["depth_minus_oracle_median_m"] == 0.0


def test_picture_puts_query_renderer_and_model_side_by_side(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    cv2 = pytest.importorskip("cv2")
    floor = _floor(monkeypatch)
    queries = _queries(floor)
    sharp = floor.BlurredOracle([make_scene(0)], 0.0)
    blurred = floor.BlurredOracle([make_scene(0)], 2.0 / 48)
    path = tmp_path / "picture.png"
    floor.picture(blurred, sharp, queries, SETTINGS, path)
    pixels = cv2.imread(str(path)).astype(float)
    rows = len(queries["pose"])
    assert pixels.shape == (48 * rows, 48 * 6, 3)
    tiles = pixels.reshape(rows, 48, 6, 48, 3)
    # the queries are the renderer's own images: columns 0 and 1 (and 3 and 4) agree
    assert abs(tiles[:, :, 0] - tiles[:, :, 1]).max() <= 1
    assert abs(tiles[:, :, 3] - tiles[:, :, 4]).max() <= 1
    assert abs(tiles[:, :, 1] - tiles[:, :, 2]).mean() > 2  # the blurred model differs
    assert abs(tiles[:, :, 4] - tiles[:, :, 5]).mean() > 10
    for wrong in (tmp_path / "picture.jpg", tmp_path / "missing" / "picture.png"):
        with pytest.raises(SystemExit):
            floor.main(["unused", "--explain", "2", "--picture", str(wrong)])


def test_blurred_oracle_needs_the_true_scenes(monkeypatch: pytest.MonkeyPatch) -> None:
    floor = _floor(monkeypatch)
    with pytest.raises(SystemExit, match="true scenes"):
        floor.BlurredOracle(None, 0.0)


def test_oracle_depth_keeps_the_model_s_colours_on_the_benchmark_s_geometry(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """--oracle-depth: the model's colours, the true renderer's depth and opacity (here the
    model: a blurred renderer whose surfaces lie at half their depth, half transparent)."""
    floor = _floor(monkeypatch)
    queries = _queries(floor)
    sharp = floor.BlurredOracle([make_scene(0)], 0.0)

    class Foggy(floor.BlurredOracle):
        def render(self, *args: object, surface_share: float = 0.0) -> object:
            rendering = super().render(*args)
            return rendering._replace(depth=rendering.depth / 2, opacity=rendering.opacity / 2)

    foggy = Foggy([make_scene(0)], 2.0 / 48)
    args = (queries["pose"], queries["scene"], queries["intrinsics"], 48, 48)
    hybrid = floor.WithOracleDepth(foggy, sharp).render(*args, surface_share=0.7)
    truth = sharp.render(*args)
    torch.testing.assert_close(hybrid.rgb, foggy.render(*args).rgb)
    assert not torch.allclose(hybrid.rgb, truth.rgb)
    torch.testing.assert_close(hybrid.depth, truth.depth)
    torch.testing.assert_close(hybrid.opacity, truth.opacity)
    explained = floor.explained(foggy, sharp, queries, SETTINGS)
    assert explained["surface_log_ratio_median"] == pytest.approx(math.log(2), abs=1e-4)
    assert explained["surface_within_10pc"] == 0.0
    with pytest.raises(SystemExit):
        floor.main(["unused", "--oracle", "--oracle-depth"])


def test_windowed_scores_each_fit_on_each_scene_s_walk_alone(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A val walk that zigzags sharply (every third frame back, 0.1 m): the median window moves
    most of its frames, the Hampel window none. Two walks 100 m apart with their rows
    interleaved: each window reads its own walk only."""
    floor = _floor(monkeypatch)
    walk = torch.zeros(9, 7)
    walk[:, 0] = 0.1 * torch.arange(9)
    walk[:, 1] = 0.1 * torch.sin(2 * math.pi * torch.arange(9) / 3)
    walk[:, 3] = 1.0
    rows = floor.windowed(walk, walk, torch.zeros(9, dtype=torch.long), 5)
    assert set(rows) == {"median", "hampel"}
    assert rows["median"]["pos_median_m"] == pytest.approx(0.0866, abs=1e-3)
    assert rows["hampel"]["pos_median_m"] == pytest.approx(0.0, abs=1e-6)
    straight = walk.clone()
    straight[:, 1] = 0.0
    far = straight.clone()
    far[:, 0] += 100.0
    both = torch.stack([straight, far], 1).flatten(0, 1)  # rows interleaved
    scenes = torch.tensor([0, 1] * 9)
    for figures in floor.windowed(both, both, scenes, 5).values():
        assert figures["pos_median_m"] == pytest.approx(0.0, abs=1e-4)
