"""Tests of the synthetic benchmark's surfaces and capture of real data: off by default (the
plain renders and folder names unchanged), each option doing what it says, deterministic by
seed, bad values refused in one line naming the setting."""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from pae import CONFIG_DIR
from pae.config.validation import validate_data
from pae.core.errors import ConfigError
from pae.core.geometry import matrix_to_quaternion
from pae.synthetic import (
    REPEAT_PERIOD_M,
    TEXEL_SIZE_M,
    CaptureOptions,
    FrameConditions,
    Nuisances,
    PinholeCamera,
    SurfaceOptions,
    SyntheticScene,
    SyntheticSettings,
    dress_surfaces,
    jpeg_roundtrip,
    make_scene,
    make_sequences,
    render_batch,
    sequence_capture,
    shade_rays,
    surface_seed,
    vignette,
    write_synthetic_dataset,
)
from pae.synthetic.camera import look_rotations
from pae.synthetic.datamodule import SyntheticDataModule, default_root

TINY = {"scenes": 1, "train_frames": 12, "test_frames": 6, "size": 16}
ALL_ON = {
    "plain_surface_share": 0.3,
    "repeated_surface_share": 0.2,
    "glossy_surface_share": 0.3,
    "camera_pipeline": 1.0,
    "jpeg_quality": 75,
    "render_scale": 2,
}
OFF = {key: 1 if key == "render_scale" else 0 for key in ALL_ON}
SIZE = 32


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def _uniform(image: np.ndarray) -> bool:
    """Whether every texel of ``image`` ``[rows, cols, 3]`` has the same colour."""
    return bool(np.ptp(image.reshape(-1, 3), axis=0).max() == 0)


def _scene(**shares: float) -> SyntheticScene:
    """Scene 0 of seed 0, dressed with ``shares``."""
    scene = make_scene(0, 0)
    return dress_surfaces(scene, SurfaceOptions(**shares), surface_seed(0, 0))


def _facing_wall(scene: SyntheticScene, distance_m: float) -> np.ndarray:
    """Pose ``[7]`` of a level camera ``distance_m`` in front of the room's x-lo wall, at
    1.4 m, looking at it."""
    rotation = look_rotations(np.array([np.pi]), np.zeros(1), np.zeros(1))
    quaternion = matrix_to_quaternion(torch.from_numpy(rotation)).numpy()[0]
    position = [scene.room.lo[0] + distance_m, 0.0, 1.4]
    return np.array([*position, *quaternion])


@pytest.fixture(scope="module")
def sequence() -> tuple:
    """Scene 0, its first train sequence's first 16 frames and a 32 px camera."""
    scene = make_scene(0, 0)
    first = make_sequences(0, scene, SyntheticSettings(train_frames=120, test_frames=10))[0]
    return scene, dataclasses.replace(first, poses=first.poses[:16]), PinholeCamera(SIZE)


def test_default_folder_names_are_unchanged() -> None:
    plain = "data/synthetic/scenes2_train1600_test250_px64_seed0_offset0_lane0.5_yaw0.15_stray0.1"
    assert default_root(SyntheticSettings(**OFF)) == plain
    assert str(SyntheticDataModule(**OFF).root) == plain
    module = SyntheticDataModule(**ALL_ON, lighting_change=1.0)
    assert str(module.root) == f"{plain}_light1_plain0.3_repeat0.2_gloss0.3_pipe1_jpeg75_x2"
    assert module.render_settings == SyntheticSettings(**ALL_ON, lighting_change=1.0)
    assert (module.camera.width, module.camera.height) == (128, 128)
    assert module.camera.cx == 63.5 and SyntheticDataModule().camera.width == 64


def test_options_off_render_the_plain_benchmark(tmp_path: Path) -> None:
    write_synthetic_dataset(tmp_path / "omitted", seed=1, **TINY)
    write_synthetic_dataset(tmp_path / "off", seed=1, **TINY, **OFF)
    assert _files(tmp_path / "omitted") == _files(tmp_path / "off")
    scene = make_scene(0, 1)
    assert dress_surfaces(scene, SurfaceOptions(), surface_seed(1, 0)) is scene


def test_all_options_are_deterministic_and_keep_the_labels(tmp_path: Path) -> None:
    for name, seed in (("a", 1), ("b", 1), ("other", 2)):
        write_synthetic_dataset(tmp_path / name, seed=seed, **TINY, **ALL_ON)
    write_synthetic_dataset(tmp_path / "plain", seed=1, **TINY)
    files, plain = _files(tmp_path / "a"), _files(tmp_path / "plain")
    assert files == _files(tmp_path / "b")
    assert files != _files(tmp_path / "other")
    labels = [name for name in plain if name.startswith("labels/")]
    assert all(files[name] == plain[name] for name in labels), "the label files stay as they are"
    images = [name for name in plain if name.endswith(".png")]
    assert sorted(name for name in files if name.endswith(".png")) == images
    image = cv2.imread(str(tmp_path / "a" / images[0]))
    assert image.shape == (2 * TINY["size"], 2 * TINY["size"], 3), "stored at render_scale"
    assert "labels/nuisances.csv" in files, "the camera pipeline's gains are listed"


def test_plain_surfaces_lose_their_texture(sequence: tuple) -> None:
    _, seq, camera = sequence
    textured, plain = _scene(), _scene(plain_surface_share=1.0)
    surfaces = [*plain.room.textures, *(t for box in plain.boxes for t in box.textures)]
    assert all(_uniform(t.image) for t in surfaces)
    units = 6 + len(textured.boxes)
    some = _scene(plain_surface_share=0.5)
    flat = [_uniform(t.image) for t in some.room.textures]
    flat += [_uniform(box.textures[0].image) for box in some.boxes]
    assert sum(flat) == round(0.5 * units)

    def detail(images: np.ndarray) -> float:
        """Median |Laplacian|: the surfaces' texture, not their smooth shading (a linear
        ramp has none) nor the sparse edges between them."""
        grey = images.astype(np.float64).mean(-1)
        return float(np.median([np.abs(cv2.Laplacian(x, cv2.CV_64F)) for x in grey]))

    before = detail(render_batch(textured, seq.poses, camera, seq.appearance))
    after = detail(render_batch(plain, seq.poses, camera, seq.appearance))
    assert after < 0.25 * before, (after, before)


def test_repeated_surfaces_repeat_at_their_period() -> None:
    scene = dataclasses.replace(_scene(repeated_surface_share=1.0), boxes=())
    wall = scene.room.textures[0].image.mean(-1)  # the x-lo wall, upright: b is height
    profile = wall.mean(1) - wall.mean()
    correlation = np.correlate(profile, profile, "full")[len(profile) - 1 :]
    correlation /= correlation[0]
    low, high = (round(p / TEXEL_SIZE_M) for p in REPEAT_PERIOD_M)
    lag = low + int(np.argmax(correlation[low : 2 * high]))
    assert correlation[lag] > 0.7, "one period along the height"

    distance = 1.5
    camera = PinholeCamera(64)
    image = render_batch(scene, _facing_wall(scene, distance)[None], camera)[0]
    column = image[:, 20:44].astype(np.float64).mean((1, 2))
    column -= column.mean()
    seen = np.correlate(column, column, "full")[len(column) - 1 :]
    period_px = camera.focal_px * lag * TEXEL_SIZE_M / distance
    window = slice(int(0.6 * period_px), int(1.5 * period_px) + 1)
    peak = window.start + int(np.argmax(seen[window]))
    assert abs(peak - period_px) <= 1.0, (peak, period_px)
    assert seen[peak] > 0.4 * seen[0]


def test_glossy_surfaces_change_with_the_viewpoint() -> None:
    matte, glossy = _scene(), _scene(glossy_surface_share=1.0)
    assert glossy.face_tables.glossy and not matte.face_tables.glossy
    assert glossy.lamps.shape == (2, 3) and matte.lamps.shape == (0, 3)
    point = np.array([glossy.room.lo[0], 0.3, 1.2])  # on the x-lo wall
    rng = np.random.default_rng(0)
    origins = np.column_stack([rng.uniform(-1.5, 1.5, (24, 2)), rng.uniform(1.1, 1.7, 24)])
    colours = {}
    for name, scene in (("matte", matte), ("glossy", glossy)):
        colour, t = shade_rays(scene, origins, point - origins)
        assert np.allclose(t, 1.0, atol=1e-3), "every ray reaches the point"
        colours[name] = colour
    assert np.ptp(colours["matte"], axis=0).max() < 2e-3, "matte: the same from every view"
    assert np.ptp(colours["glossy"], axis=0).min() > 0.05, "glossy: a highlight that moves"
    assert np.all(colours["glossy"] >= colours["matte"] - 1e-4), "highlights only add light"


def test_camera_pipeline_drifts_within_a_sequence(sequence: tuple) -> None:
    scene, seq, camera = sequence
    plain = FrameConditions.plain(scene, len(seq.poses))
    appearance, conditions = sequence_capture(
        CaptureOptions(camera_pipeline=1.0), seq.appearance, plain, seq.nuisance_seed
    )
    assert 0.25 <= appearance.vignetting <= 0.45 and 0.6 <= appearance.metering <= 0.9
    assert appearance.gamma < seq.appearance.gamma
    static = np.repeat(seq.poses[:1], len(seq.poses), axis=0)
    images = render_batch(scene, static, camera, appearance, conditions=conditions)
    means = images.reshape(len(images), -1, 3).mean(1)
    assert np.ptp(means.mean(1)) > 5, "the exposure drifts"
    assert np.all(np.abs(np.diff(means.mean(1))) < 0.5 * np.ptp(means.mean(1))), "slowly"
    balance = np.log(means[:, 0] / means[:, 1]) - np.log(means[:, 2] / means[:, 1])
    assert np.ptp(balance) > 0.02, "the white balance drifts"
    unchanged = render_batch(scene, static, camera, seq.appearance)
    assert np.ptp(unchanged.reshape(len(unchanged), -1).mean(1)) == 0

    shading = vignette(SIZE, 0.4)
    assert shading.max() <= 1 and np.isclose(shading[0, 0], 0.6) and shading[16, 16] > 0.99
    gains = np.zeros(len(seq.poses))
    metered = dataclasses.replace(seq.appearance, metering=0.9)
    plain_images = render_batch(scene, seq.poses, camera, seq.appearance)
    metered_images = render_batch(scene, seq.poses, camera, metered, exposed=gains)
    spread = [np.log(x.reshape(len(x), -1).mean(1)).std() for x in (plain_images, metered_images)]
    assert spread[1] < 0.5 * spread[0], "the auto-exposure evens out the frames' levels"
    assert np.ptp(gains) > 0


def test_jpeg_compresses_with_loss_and_8x8_blocks(sequence: tuple) -> None:
    scene, seq, _ = sequence
    camera = PinholeCamera(64)
    plain = render_batch(scene, seq.poses[:4], camera, seq.appearance)
    compressed = render_batch(
        scene, seq.poses[:4], camera, dataclasses.replace(seq.appearance, jpeg_quality=75)
    )
    assert np.array_equal(compressed, np.stack([jpeg_roundtrip(x, 75) for x in plain]))
    assert np.abs(compressed.astype(int) - plain).mean() > 0.5, "decoded with loss"

    def blockiness(images: np.ndarray) -> float:
        """Mean step across the 8 px block edges over the mean step elsewhere."""
        step = np.abs(np.diff(images.astype(np.float64).mean(-1), axis=2)).mean((0, 1))
        edges = np.arange(7, len(step), 8)
        return float(step[edges].mean() / np.delete(step, edges).mean())

    coarse = np.stack([jpeg_roundtrip(x, 20) for x in plain])
    assert blockiness(coarse) > 1.2 * blockiness(plain)


def test_render_scale_stores_larger_images_with_finer_detail(sequence: tuple) -> None:
    scene, seq, camera = sequence
    small = render_batch(scene, seq.poses[:4], camera, seq.appearance).astype(np.float64)
    large = render_batch(scene, seq.poses[:4], PinholeCamera(4 * SIZE), seq.appearance)
    assert large.shape[1:3] == (4 * SIZE, 4 * SIZE)
    down = np.stack([cv2.resize(x, (SIZE, SIZE), interpolation=cv2.INTER_AREA) for x in large])
    assert np.abs(down - small).mean() < 4, "the same view, downsampled"
    up = np.stack([cv2.resize(x, (4 * SIZE, 4 * SIZE)) for x in small.astype(np.uint8)])
    assert (
        np.abs(np.diff(large.astype(float), axis=2)).mean()
        > np.abs(np.diff(up.astype(float), axis=2)).mean()
    ), "more detail than the small image enlarged"


@pytest.mark.parametrize(
    ("setting", "value", "message"),
    [
        ("plain_surface_share", -0.1, "must be a number in"),
        ("repeated_surface_share", 1.5, "must be a number in"),
        ("glossy_surface_share", float("nan"), "must be a number in"),
        ("camera_pipeline", 2.0, "must be a number in"),
        ("jpeg_quality", 101, "must be 0"),
        ("jpeg_quality", -5, "must be 0"),
        ("render_scale", 0, "must be an integer in"),
        ("render_scale", 9, "must be an integer in"),
    ],
)
def test_bad_values_are_refused_in_one_line_naming_the_setting(
    tmp_path: Path, setting: str, value: float, message: str
) -> None:
    for make in (
        lambda: write_synthetic_dataset(tmp_path / "out", **TINY, **{setting: value}),
        lambda: SyntheticDataModule(**{setting: value}),
    ):
        with pytest.raises(ValueError, match=f"^{setting} {message}") as error:
            make()
        assert "\n" not in str(error.value)
    assert not any(tmp_path.iterdir())
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", [f"data.{setting}={value}"])
    with pytest.raises(ConfigError, match=f"data.{setting} must be"):
        validate_data(cfg)


def test_plain_and_repeated_shares_sum_to_at_most_one() -> None:
    with pytest.raises(ValueError, match=r"^plain_surface_share \+ repeated_surface_share"):
        SurfaceOptions(plain_surface_share=0.6, repeated_surface_share=0.5)
    overrides = ["data.plain_surface_share=0.6", "data.repeated_surface_share=0.5"]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides)
    with pytest.raises(ConfigError, match=r"data\.plain_surface_share \+ data\.repeated"):
        validate_data(cfg)


def test_given_poses_render_into_a_folder_named_by_their_options(tmp_path: Path) -> None:
    labels = tmp_path / "poses.csv"
    labels.write_text("scene,split,seq,img_path,t1,t2,t3,q1,q2,q3,q4\n")
    plain = SyntheticDataModule(poses=[str(labels)])
    hard = SyntheticDataModule(poses=[str(labels)], render_scale=2, jpeg_quality=75)
    assert Path(plain.root).name.endswith("_px64_seed0")
    assert Path(hard.root).name == Path(plain.root).name + "_jpeg75_x2"
    assert hard.camera.width == 128
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", ["experiment=real_starts_hard", f"data.poses=[{labels}]"])
    assert all(cfg.data[key] != OFF[key] for key in ALL_ON)


def test_the_oracle_sees_the_dressed_surfaces() -> None:
    module = SyntheticDataModule(glossy_surface_share=1.0, scenes=1)
    module.scene_names = ["scene00"]
    assert module.oracle_scenes()[0].face_tables.glossy, "the oracle sees the glossy surfaces"


def test_demo_hard_turns_every_option_on() -> None:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", ["experiment=demo_hard"])
    assert all(cfg.data[key] != OFF[key] for key in ALL_ON)
    assert all(cfg.data[key] for key in Nuisances.__dataclass_fields__)
    validate_data(cfg)


def test_options_table_turns_on_each_row_alone() -> None:
    """experiments/benchmark_hard/options_table.py: each row's benchmark differs from the easy
    demo's in that row's options only, and "all" is demo_hard itself."""
    script = Path(__file__).resolve().parents[1] / "experiments/benchmark_hard/options_table.py"
    spec = importlib.util.spec_from_file_location("options_table", script)
    assert spec is not None and spec.loader is not None
    table = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(table)
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        easy = compose("train", ["experiment=demo"]).data
        for row, options in table.ROWS.items():
            data = compose("train", ["experiment=demo_hard", *table.overrides(row)]).data
            changed = {key for key in easy if key != "poses" and data[key] != easy[key]}
            assert changed == set(options), row
        assert set(table.ROWS["all"]) == set(ALL_ON) | set(Nuisances.__dataclass_fields__)
