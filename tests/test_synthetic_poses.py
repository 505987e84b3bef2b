"""Rendering at given poses: the label files written reproduce the input rows, and worlds
built for a 3 m room and a 100 m street both put textured geometry in every frame."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from pae.core.geometry import matrix_to_quaternion
from pae.data.labels import LabelTable, read_labels, write_labels
from pae.data_cli import main
from pae.synthetic import pose_rotation_translation
from pae.synthetic.poses import ROOM_MARGIN_M, make_scene_around, write_dataset_at_poses
from tests.conftest import REFERENCE_LABELS


def _walk(extent_m: float, frames: int, seed: int) -> np.ndarray:
    """Poses [frames, 7] of a camera walking a curve of about ``extent_m`` metres, turning
    and tilting freely (any orientation must see texture)."""
    import torch

    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, frames)
    positions = np.stack(
        [extent_m * t, 0.2 * extent_m * np.sin(3 * t), 0.05 * extent_m * np.cos(5 * t)], axis=1
    )
    angles = rng.uniform(-np.pi, np.pi, (frames, 3))
    c, s = np.cos(angles), np.sin(angles)
    zero, one = np.zeros(frames), np.ones(frames)
    rz = np.stack([c[:, 0], -s[:, 0], zero, s[:, 0], c[:, 0], zero, zero, zero, one], 1)
    rx = np.stack([one, zero, zero, zero, c[:, 1], -s[:, 1], zero, s[:, 1], c[:, 1]], 1)
    rotations = rz.reshape(-1, 3, 3) @ rx.reshape(-1, 3, 3)
    quaternions = matrix_to_quaternion(torch.from_numpy(rotations)).numpy()
    return np.concatenate([positions, quaternions], axis=1)


def _labels(path: Path, scene: str, poses: np.ndarray, test_every: int = 3) -> Path:
    split = ["test" if i % test_every == 0 else "train" for i in range(len(poses))]
    seq = [f"seq{1 + (i % test_every == 0)}" for i in range(len(poses))]
    write_labels(
        path,
        LabelTable(
            scene=[scene] * len(poses),
            split=split,
            seq=seq,
            img_path=[f"raw/{scene}/{i}.jpg" for i in range(len(poses))],
            poses=poses,
        ),
    )
    return path


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path]]:
    folder = tmp_path_factory.mktemp("at_poses")
    inputs = [
        _labels(folder / "room.csv", "room", _walk(3.0, 24, 0)),
        _labels(folder / "street.csv", "street", _walk(100.0, 24, 1)),
    ]
    write_dataset_at_poses(folder / "out", inputs, size=32, seed=0)
    return folder / "out", inputs


def test_label_files_keep_every_row(rendered: tuple[Path, list[Path]]) -> None:
    out, inputs = rendered
    source = LabelTable.concat(read_labels(p) for p in inputs)
    written = LabelTable.concat(
        read_labels(out / "labels" / f"all_{split}.csv") for split in ("train", "test")
    )
    assert len(written) == len(source)
    key = lambda t, i: (t.scene[i], t.split[i], t.seq[i])  # noqa: E731
    order_source = sorted(range(len(source)), key=lambda i: (key(source, i), i))
    order_written = sorted(range(len(written)), key=lambda i: (key(written, i), i))
    for i, j in zip(order_source, order_written, strict=True):
        assert key(source, i) == key(written, j)
    np.testing.assert_allclose(
        written.poses[order_written], source.poses[order_source], rtol=0, atol=1e-6
    )
    for scene in ("room", "street"):
        for split in ("train", "test"):
            table = read_labels(out / "labels" / f"{scene}_{split}.csv")
            assert set(table.scene) == {scene} and set(table.split) == {split}
    for path in written.img_path:
        assert (out / path).is_file()


@pytest.mark.parametrize("scene", ["room", "street"])
def test_every_frame_sees_textured_geometry(rendered: tuple[Path, list[Path]], scene: str) -> None:
    out, _ = rendered
    table = read_labels(out / "labels" / f"{scene}_train.csv")
    for path in table.img_path:
        image = cv2.imread(str(out / path)).astype(np.float64)
        assert image.std() > 8, path
        assert np.abs(np.diff(image, axis=1)).mean() > 1.5, path


@pytest.mark.parametrize("extent", [3.0, 100.0])
def test_world_encloses_the_cameras_with_its_margin(extent: float) -> None:
    poses = _walk(extent, 50, 2)
    scene = make_scene_around("s", 0, poses[:, :3])
    margin = ROOM_MARGIN_M * scene.scale
    assert scene.scale == pytest.approx(max(1.0, np.ptp(poses[:, :3], axis=0).max() / 3.0))
    assert np.all(poses[:, :3] >= scene.room.lo + margin - 1e-9)
    assert np.all(poses[:, :3] <= scene.room.hi - margin + 1e-9)
    rotations, _ = pose_rotation_translation(poses)
    assert rotations.shape == (50, 3, 3)


def test_bad_pose_row_is_one_line_naming_file_and_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _labels(tmp_path / "bad.csv", "room", _walk(3.0, 4, 0))
    lines = path.read_text().splitlines()
    fields = lines[3].split(",")
    fields[7:11] = ["0", "0", "0", "0"]
    lines[3] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    assert main(["synth", str(tmp_path / "out"), "--poses", str(path)]) == 1
    *before, err = capsys.readouterr().err.strip().splitlines()
    assert [line.split(" ", 1)[0] for line in before] == ["threads:"]  # the renderer's
    assert err.startswith("pae-data: error:") and f"{path}:4:" in err
    assert not (tmp_path / "out" / "labels").exists()


@pytest.mark.reference_labels
def test_renders_real_7scenes_and_cambridge_geometry(tmp_path: Path) -> None:
    inputs = []
    for name in ("7Scenes/heads_test.csv", "CambridgeLandmarks/ShopFacade_test.csv"):
        table = read_labels(REFERENCE_LABELS / name)
        inputs.append(tmp_path / Path(name).name)
        write_labels(inputs[-1], table.select(np.arange(0, len(table), 40)))
    summary = write_dataset_at_poses(tmp_path / "out", inputs, size=32)
    assert summary.scenes == ["ShopFacade", "heads"]
    written = read_labels(tmp_path / "out" / "labels" / "all_test.csv")
    for path in written.img_path:
        assert cv2.imread(str(tmp_path / "out" / path)).std() > 8, path


def test_a_missing_split_is_reported_before_rendering(tmp_path: Path) -> None:
    from pae.data.labels import LabelError

    path = tmp_path / "train_only.csv"
    write_labels(path, read_labels(_labels(tmp_path / "all.csv", "room", _walk(3.0, 6, 0))))
    table = read_labels(path)
    write_labels(path, table.select(np.asarray(table.split) == "train"))
    with pytest.raises(LabelError, match=r"no rows of the split\(s\) \['test'\]"):
        write_dataset_at_poses(tmp_path / "out", [path], size=16, required_splits=("train", "test"))
    assert not (tmp_path / "out").exists()


def test_given_poses_render_with_the_benchmark_s_options(tmp_path: Path) -> None:
    """With demo_hard's options the given rows are rendered render_scale times larger, dressed
    and captured, each recording with nuisances of its own (labels/nuisances.csv); options
    off render exactly what no options render."""
    from pae.synthetic import SyntheticSettings
    from pae.synthetic.writer import NUISANCE_FILE

    inputs = [_labels(tmp_path / "room.csv", "room", _walk(3.0, 12, 0))]
    hard = SyntheticSettings(
        glossy_surface_share=0.5,
        plain_surface_share=0.3,
        camera_pipeline=1.0,
        jpeg_quality=75,
        render_scale=2,
        lighting_change=1.0,
        occluder_fraction=0.3,
    )
    plain = write_dataset_at_poses(tmp_path / "plain", inputs, size=16)
    same = write_dataset_at_poses(tmp_path / "off", inputs, size=16, options=SyntheticSettings())
    dressed = write_dataset_at_poses(tmp_path / "hard", inputs, size=16, options=hard)
    assert (plain.size, same.size, dressed.size) == (16, 16, 32)
    names = read_labels(tmp_path / "plain" / "labels" / "all_test.csv").img_path
    for name in names:
        first = cv2.imread(str(tmp_path / "plain" / name))
        np.testing.assert_array_equal(first, cv2.imread(str(tmp_path / "off" / name)))
        image = cv2.imread(str(tmp_path / "hard" / name))
        assert image.shape == (32, 32, 3)
        small = cv2.resize(image, (16, 16), interpolation=cv2.INTER_AREA).astype(float)
        assert np.abs(small - first).mean() > 2.0, name
    table = (tmp_path / "hard" / "labels" / NUISANCE_FILE).read_text().splitlines()
    assert len(table) == 1 + 12 and not (tmp_path / "plain" / "labels" / NUISANCE_FILE).exists()
    gains = [float(line.split(",")[-1]) for line in table[1:]]
    assert len(set(np.round(gains, 4))) > 2, "each frame's exposure drifts"


def test_a_street_s_occluders_keep_a_room_s_texels() -> None:
    """In a world scaled up around a street's cameras (here 40 times), an occluder is 40
    times a person's size but its textures hold as many texels as a person's in a room, each
    40 times larger: rendering a street's recording with occluders stays within memory."""
    from pae.synthetic import PinholeCamera
    from pae.synthetic.nuisances import _occluders

    def occluders(extent: float) -> list:
        poses = _walk(extent, 40, 1)
        scene = make_scene_around("s", 0, poses[:, :3])
        rng = np.random.default_rng(3)
        found = _occluders(rng, 0.5, scene, poses, PinholeCamera(64))
        return [(box, scene.scale) for box in found if box is not None]

    room, street = occluders(3.0), occluders(120.0)
    assert room[0][1] == 1.0 and street[0][1] == pytest.approx(40.0, rel=0.05)
    for found in (room, street):
        for box, scale in found:
            height = (box.hi - box.lo)[2]
            assert 1.7 * 0.85 * scale <= height <= 1.7 * 1.15 * scale
            for texture in box.textures:
                assert texture.texel_size == pytest.approx(0.02 * scale)
                assert texture.image.shape[0] * texture.image.shape[1] <= 100 * 60


def test_an_occluder_nearer_than_its_nearest_distance_stands_there_at_any_scale() -> None:
    """Where what is ahead is nearer than the occluder's nearest distance, the occluder
    stands at that distance: at a scale whose nearest distance a float32 rounds down, the
    farthest distance computed in float32 fell below the nearest and the draw between them
    failed (StMarysChurch's world, 25.6 times a room)."""
    from pae.synthetic.nuisances import OCCLUDER_DISTANCE_M, occluder_distances

    scales = np.linspace(20.0, 30.0, 1001)
    rounded_down = np.float32(OCCLUDER_DISTANCE_M[0] * scales) < OCCLUDER_DISTANCE_M[0] * scales
    scale = float(scales[rounded_down][0])
    free = np.array([0.5, 1.0, 200.0], dtype=np.float32) * scale
    near, far = occluder_distances(free, scale)
    assert far.dtype == np.float64 and bool((far >= near).all())
    assert far[0] == near and far[2] == OCCLUDER_DISTANCE_M[1] * scale
    np.random.default_rng(0).uniform(near, far)
