"""Tests of the synthetic benchmark's nuisances: off by default (the plain renders, folder
names unchanged), each family doing what it says, deterministic by seed, bad values refused."""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from pae import CONFIG_DIR
from pae.config.validation import validate_data
from pae.core.errors import ConfigError
from pae.synthetic import (
    NUISANCE_COLUMNS,
    OCCLUDER_DISTANCE_M,
    FrameConditions,
    Nuisances,
    PinholeCamera,
    SyntheticSettings,
    make_scene,
    make_sequences,
    motion_kernel,
    render_batch,
    sequence_nuisances,
    world_to_camera,
    write_synthetic_dataset,
)
from pae.synthetic.datamodule import SyntheticDataModule, default_root

TINY = {"scenes": 1, "train_frames": 12, "test_frames": 6, "size": 16}
ALL_ON = {
    "lighting_change": 1.0,
    "occluder_fraction": 0.3,
    "sensor_noise_std": 0.02,
    "motion_blur_px": 3.0,
}
SIZE = 24


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def _nuisance_rows(root: Path) -> list[dict[str, str]]:
    with (root / "labels" / "nuisances.csv").open(newline="") as file:
        return list(csv.DictReader(file))


@pytest.fixture(scope="module")
def sequence() -> tuple:
    """Scene 0, its first train sequence's first 20 frames and a 24 px camera."""
    scene = make_scene(0, 0)
    first = make_sequences(0, scene, SyntheticSettings(train_frames=120, test_frames=10))[0]
    first = dataclasses.replace(first, poses=first.poses[:20])
    return scene, first, PinholeCamera(SIZE)


def _draw(sequence: tuple, **settings: float) -> tuple:
    scene, seq, camera = sequence
    return sequence_nuisances(
        Nuisances(**settings), scene, seq.poses, camera, seq.appearance, seq.nuisance_seed
    )


def test_default_folder_names_are_unchanged() -> None:
    plain = "data/synthetic/scenes2_train1600_test250_px64_seed0_offset0_lane0.5_yaw0.15_stray0.1"
    assert default_root(SyntheticSettings()) == plain
    assert str(SyntheticDataModule().root) == plain
    zeros = dict.fromkeys(ALL_ON, 0.0)
    assert str(SyntheticDataModule(**zeros).root) == plain
    assert default_root(SyntheticSettings(**ALL_ON)) == f"{plain}_light1_occl0.3_noise0.02_blur3"
    assert str(SyntheticDataModule(occluder_fraction=0.3).root) == f"{plain}_occl0.3"
    assert str(SyntheticDataModule(val_lane_m=0.0).root) == f"{plain}_val0"
    assert str(SyntheticDataModule(val_lane_m=None).root) == plain
    walks = SyntheticDataModule(val_lane_m=0.0, val_walks=3)
    assert str(walks.root) == f"{plain}_val0_walks3" and walks.holdout == (4, 0.1)
    assert SyntheticDataModule(**ALL_ON).render_settings == SyntheticSettings(**ALL_ON)


def test_nuisances_at_zero_render_the_plain_benchmark(tmp_path: Path) -> None:
    write_synthetic_dataset(tmp_path / "omitted", seed=1, **TINY)
    write_synthetic_dataset(tmp_path / "zero", seed=1, **TINY, **dict.fromkeys(ALL_ON, 0))
    omitted = _files(tmp_path / "omitted")
    assert omitted == _files(tmp_path / "zero")
    assert "labels/nuisances.csv" not in omitted


def test_all_nuisances_are_deterministic_by_seed_in_train_and_test(tmp_path: Path) -> None:
    write_synthetic_dataset(tmp_path / "a", seed=1, **TINY, **ALL_ON)
    write_synthetic_dataset(tmp_path / "b", seed=1, **TINY, **ALL_ON)
    write_synthetic_dataset(tmp_path / "plain", seed=1, **TINY)
    write_synthetic_dataset(tmp_path / "other", seed=2, **TINY, **ALL_ON)
    files = _files(tmp_path / "a")
    assert files == _files(tmp_path / "b")
    plain, other = _files(tmp_path / "plain"), _files(tmp_path / "other")
    labels = [name for name in plain if name.startswith("labels/")]
    assert all(files[name] == plain[name] for name in labels), "the label files stay as they are"
    images = [name for name in plain if name.endswith(".png")]
    assert all(files[name] != plain[name] for name in images)
    assert files["labels/nuisances.csv"] != other["labels/nuisances.csv"]

    rows = _nuisance_rows(tmp_path / "a")
    assert tuple(rows[0]) == NUISANCE_COLUMNS
    assert sorted(r["img_path"] for r in rows) == sorted(images)
    for split in ("train", "test"):
        table = (tmp_path / "a" / "labels" / f"all_{split}.csv").read_text().splitlines()[1:]
        paths = {line.split(",")[3] for line in table}
        chosen = [r for r in rows if r["img_path"] in paths]
        assert len(chosen) == len(paths)
        assert len({r["exposure_gain"] for r in chosen}) == len(chosen), "exposure drifts"
        assert any(float(r["occluder_share"]) > 0 for r in chosen), split
        blur = np.array([float(r["blur_px"]) for r in chosen])
        assert np.all((blur >= 0) & (blur <= 3.0)) and blur.std() > 0


def test_occluders_appear_in_the_requested_share_and_only_where_they_stand(
    sequence: tuple,
) -> None:
    scene, seq, camera = sequence
    appearance, conditions = _draw(sequence, occluder_fraction=0.3)
    assert appearance == seq.appearance
    occluded = [i for i, box in enumerate(conditions.occluders) if box is not None]
    assert len(occluded) == round(0.3 * len(seq.poses))
    shares = np.empty(len(seq.poses))
    images = render_batch(
        scene, seq.poses, camera, appearance, conditions=conditions, occluded=shares
    )
    plain = render_batch(scene, seq.poses, camera, appearance)
    assert np.all(shares[occluded] > 0.03) and np.all(shares[occluded] < 0.7)
    free = np.setdiff1d(np.arange(len(seq.poses)), occluded)
    assert np.all(shares[free] == 0)
    np.testing.assert_array_equal(images[free], plain[free])
    for i in occluded:
        box = conditions.occluders[i]
        size = box.hi - box.lo
        assert np.all(np.abs(size - [0.5, 0.4, 1.7]) <= [0.2, 0.2, 0.26]) or np.all(
            np.abs(size - [0.4, 0.5, 1.7]) <= [0.2, 0.2, 0.26]
        )
        corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)])
        corners = box.lo + corners * size
        assert world_to_camera(corners, seq.poses[i])[:, 2].min() > 0.3
        centre = world_to_camera(((box.lo + box.hi) / 2)[None], seq.poses[i])[0]
        assert OCCLUDER_DISTANCE_M[0] - 0.2 < centre[2] < OCCLUDER_DISTANCE_M[1] + 0.2
        pixels = camera.project(corners, seq.poses[i])
        lo, hi = np.floor(pixels.min(0)) - 1, np.ceil(pixels.max(0)) + 1
        changed = np.any(images[i] != plain[i], axis=-1)
        rows, cols = np.nonzero(changed)
        assert len(rows) > 0
        assert cols.min() >= lo[0] and cols.max() <= hi[0]
        assert rows.min() >= lo[1] and rows.max() <= hi[1]
        assert abs(changed.mean() - shares[i]) < 0.1


def test_lighting_change_varies_the_frames_within_and_between_sequences(
    sequence: tuple,
) -> None:
    scene, seq, camera = sequence
    appearance, conditions = _draw(sequence, lighting_change=1.0)
    static = np.repeat(seq.poses[:1], len(seq.poses), axis=0)
    lit = render_batch(scene, static, camera, appearance, conditions=conditions)
    plain = render_batch(scene, static, camera, seq.appearance)
    means = lit.reshape(len(lit), -1).mean(axis=1)
    assert np.ptp(plain.reshape(len(plain), -1).mean(axis=1)) == 0
    assert np.ptp(means) > 8 and np.all(np.abs(np.diff(means)) < 0.5 * np.ptp(means))
    assert np.ptp(conditions.light_position, axis=0).max() > 0.1
    assert np.ptp(conditions.exposure) > 0.05 and np.ptp(conditions.light_intensity) > 0.05

    gains = {0.0: [], 1.0: []}
    for strength, found in gains.items():
        for number in range(40):
            seed = (0, 0, 3, number)
            varied, _ = sequence_nuisances(
                Nuisances(lighting_change=strength, motion_blur_px=1),
                scene,
                seq.poses[:2],
                camera,
                seq.appearance,
                seed,
            )
            found.append(math.log(varied.gain))
    assert np.std(gains[1.0]) > 0.1 and np.std(gains[0.0]) == 0


def test_motion_blur_reduces_high_frequency_energy(sequence: tuple) -> None:
    scene, seq, camera = sequence
    for angle in (0.0, np.pi / 4, np.pi / 2):
        kernel = motion_kernel(4.0, angle)
        assert kernel.shape[0] == kernel.shape[1] and kernel.shape[0] % 2 == 1
        assert math.isclose(kernel.sum(), 1.0, rel_tol=1e-5)
        np.testing.assert_allclose(kernel, kernel[::-1, ::-1], atol=1e-6)
    horizontal = motion_kernel(4.0, 0.0)
    centre = horizontal.shape[0] // 2
    assert horizontal[centre].sum() > 0.999 and np.count_nonzero(horizontal[centre]) >= 4
    assert motion_kernel(0.0, 1.0).max() == 1.0

    plain = render_batch(scene, seq.poses, camera, seq.appearance).astype(np.float64)
    conditions = FrameConditions.plain(scene, len(seq.poses))
    conditions = dataclasses.replace(conditions, blur_px=np.full(len(seq.poses), 4.0))
    blurred = render_batch(scene, seq.poses, camera, seq.appearance, conditions=conditions)
    blurred = blurred.astype(np.float64)

    def energy(images: np.ndarray) -> np.ndarray:
        return np.array([np.abs(cv2.Laplacian(image, cv2.CV_64F)).mean() for image in images])

    assert np.all(energy(blurred) < 0.8 * energy(plain))
    along = np.abs(np.diff(blurred, axis=2)).mean() / np.abs(np.diff(plain, axis=2)).mean()
    across = np.abs(np.diff(blurred, axis=1)).mean() / np.abs(np.diff(plain, axis=1)).mean()
    assert along < 0.8 * across, "blur at angle 0 smooths along the rows"

    _, drawn = _draw(sequence, motion_blur_px=3.0)
    assert np.all((drawn.blur_px >= 0) & (drawn.blur_px <= 3.0)) and drawn.blur_px.std() > 0
    assert np.isfinite(drawn.blur_angle).all() and np.ptp(drawn.blur_angle) > 0


def test_sensor_noise_adds_to_each_sequences_noise(sequence: tuple) -> None:
    scene, seq, camera = sequence
    noisy, conditions = _draw(sequence, sensor_noise_std=0.05)
    assert math.isclose(noisy.noise_std, math.hypot(seq.appearance.noise_std, 0.05))
    assert np.all(conditions.exposure == 1) and not any(conditions.occluders)
    clean = render_batch(scene, seq.poses, camera, noisy).astype(np.float64)
    image = render_batch(scene, seq.poses, camera, noisy, np.random.default_rng(0))
    residual = (image - clean)[(clean > 30) & (clean < 225)] / 255
    assert abs(residual.std() - noisy.noise_std) < 0.01


@pytest.mark.parametrize(
    ("setting", "value"),
    [
        ("lighting_change", -0.1),
        ("lighting_change", 1.5),
        ("occluder_fraction", 1.2),
        ("occluder_fraction", -0.3),
        ("sensor_noise_std", -0.01),
        ("sensor_noise_std", float("nan")),
        ("motion_blur_px", -1.0),
        ("motion_blur_px", 100.0),
    ],
)
def test_bad_values_are_refused_in_one_line_naming_the_setting(
    tmp_path: Path, setting: str, value: float
) -> None:
    for make in (
        lambda: write_synthetic_dataset(tmp_path / "out", **TINY, **{setting: value}),
        lambda: SyntheticDataModule(**{setting: value}),
    ):
        with pytest.raises(ValueError, match=f"^{setting} must be a number in") as error:
            make()
        assert "\n" not in str(error.value)
    assert not any(tmp_path.iterdir())
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", [f"data.{setting}={value}"])
    with pytest.raises(ConfigError, match=f"data.{setting} must be"):
        validate_data(cfg)
