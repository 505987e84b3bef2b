"""``pae-data convert colmap``: the synthetic benchmark's own cameras written as a COLMAP model
(text and binary) convert back to its poses and focal length; bad cameras and models stop with
one line naming the file and entry."""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from pae.core.geometry import quaternion_to_matrix
from pae.data.colmap import CAMERA_MODELS, camera_to_world, read_colmap_model
from pae.data.labels import read_labels
from pae.data_cli import main
from tests.test_convert_ace import CENTRE, FOCAL, SIZE, benchmark_scene

MODEL_IDS = {name: model_id for model_id, (name, _) in CAMERA_MODELS.items()}
COLMAP_CENTRE = SIZE / 2
"""The benchmark's principal point in COLMAP's pixel convention (top-left pixel centre at
(0.5, 0.5)): the image centre, pae's ``CENTRE`` + 0.5."""


def world_to_camera(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's ``QW QX QY QZ`` [N, 4] and ``TX TY TZ`` [N, 3] of camera-to-world poses [N, 7]."""
    rotations = quaternion_to_matrix(torch.from_numpy(poses[:, 3:])).numpy()
    translations = -np.einsum("nji,nj->ni", rotations, poses[:, :3])
    return poses[:, 3:] * np.array([1.0, -1.0, -1.0, -1.0]), translations


def write_colmap_text(
    model: Path, cameras: dict[int, tuple[str, int, int, list[float]]], images: list[tuple]
) -> None:
    """``cameras.txt``, ``images.txt`` (every other image with 2-D points, the others with an
    empty points line) and an empty ``points3D.txt`` of ``cameras`` (id -> model, width,
    height, params) and ``images`` ((id, q [4], t [3], camera id, name))."""
    model.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:"]
    for camera_id, (name, width, height, params) in cameras.items():
        lines.append(" ".join([str(camera_id), name, str(width), str(height), *map(repr, params)]))
    (model / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:", "#   POINTS2D[] as (X, Y, ID)"]
    for k, (image_id, q, t, camera_id, name) in enumerate(images):
        numbers = " ".join(repr(float(v)) for v in (*q, *t))
        lines += [f"{image_id} {numbers} {camera_id} {name}", "" if k % 2 else "1.5 2.5 -1 3 4 7"]
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    (model / "points3D.txt").write_text("# 3D point list (none: pae does not read it)\n")


def write_colmap_binary(
    model: Path, cameras: dict[int, tuple[str, int, int, list[float]]], images: list[tuple]
) -> None:
    """``cameras.bin``, ``images.bin`` (every other image with two 2-D points) and an empty
    ``points3D.bin`` of the same."""
    model.mkdir(parents=True, exist_ok=True)
    data = struct.pack("<Q", len(cameras))
    for camera_id, (name, width, height, params) in cameras.items():
        data += struct.pack("<iiQQ", camera_id, MODEL_IDS[name], width, height)
        data += struct.pack(f"<{len(params)}d", *params)
    (model / "cameras.bin").write_bytes(data)
    data = struct.pack("<Q", len(images))
    for k, (image_id, q, t, camera_id, name) in enumerate(images):
        data += struct.pack("<I7dI", image_id, *q, *t, camera_id) + name.encode() + b"\0"
        points = 0 if k % 2 else 2
        data += struct.pack("<Q", points) + struct.pack("<ddq", 1.5, 2.5, -1) * points
    (model / "images.bin").write_bytes(data)
    (model / "points3D.bin").write_bytes(struct.pack("<Q", 0))


WRITERS = {"text": write_colmap_text, "binary": write_colmap_binary}


def benchmark_model(tiny_root: Path, model: Path, kind: str) -> Path:
    """A COLMAP model of scene00's cameras (one PINHOLE camera, image ids in reverse name
    order) and the list of its test images -> that list's path."""
    tables = benchmark_scene(tiny_root)
    names = [*tables["train"].img_path, *tables["test"].img_path]
    q, t = world_to_camera(np.concatenate([tables["train"].poses, tables["test"].poses]))
    images = [(len(names) - i, q[i], t[i], 1, names[i]) for i in range(len(names))][::-1]
    cameras = {1: ("PINHOLE", SIZE, SIZE, [FOCAL, FOCAL, COLMAP_CENTRE, COLMAP_CENTRE])}
    WRITERS[kind](model, cameras, images)
    split_list = model.parent / "test_images.txt"
    split_list.write_text("# the test sequences\n" + "\n".join(tables["test"].img_path) + "\n")
    return split_list


@pytest.mark.parametrize("kind", ["text", "binary"])
def test_colmap_model_of_the_benchmark_converts_to_its_poses_and_focal_length(
    tiny_root: Path, tmp_path: Path, kind: str, capsys: pytest.CaptureFixture[str]
) -> None:
    split_list = benchmark_model(tiny_root, tmp_path / "sparse", kind)
    out = tmp_path / "labels"
    argv = ["convert", "colmap", str(tmp_path / "sparse"), str(tiny_root), str(out)]
    assert main([*argv, "--split-list", str(split_list), "--scene", "scene00"]) == 0
    printed = capsys.readouterr().out
    assert CENTRE == 15.5  # the benchmark's own camera: pixel centres at integers
    assert f"data.camera={{fx: {FOCAL:.10g}, fy: {FOCAL:.10g}, cx: 15.5, cy: 15.5, width: 32" in (
        printed
    )
    assert "nearest world axis +z" in printed and "data=converted" in printed
    for split, original in benchmark_scene(tiny_root).items():
        converted = read_labels(out / f"scene00_{split}.csv")
        assert read_labels(out / f"all_{split}.csv").img_path == converted.img_path
        assert converted.img_path == original.img_path
        assert converted.seq == [f"scene00-{seq}" for seq in original.seq]
        np.testing.assert_allclose(converted.poses, original.poses, rtol=0, atol=1e-6)
        np.testing.assert_allclose(converted.focal, FOCAL, rtol=1e-12)


def test_colmap_scale_multiplies_positions(tiny_root: Path, tmp_path: Path) -> None:
    split_list = benchmark_model(tiny_root, tmp_path / "sparse", "binary")
    out = tmp_path / "labels"
    argv = ["convert", "colmap", str(tmp_path / "sparse"), str(tiny_root), str(out)]
    assert main([*argv, "--split-list", str(split_list), "--scale", "2.5"]) == 0
    original = benchmark_scene(tiny_root)["test"]
    converted = read_labels(out / "all_test.csv")
    np.testing.assert_allclose(converted.poses[:, :3], 2.5 * original.poses[:, :3], atol=1e-6)
    np.testing.assert_allclose(converted.poses[:, 3:], original.poses[:, 3:], atol=1e-9)


def test_colmap_reader_agrees_with_pycolmap(tiny_root: Path, tmp_path: Path) -> None:
    """Where pycolmap is installed: it reads the test's text and binary models as pae does."""
    pycolmap = pytest.importorskip("pycolmap")
    for kind in WRITERS:
        benchmark_model(tiny_root, tmp_path / kind / "sparse", kind)
        model = read_colmap_model(tmp_path / kind / "sparse")
        reconstruction = pycolmap.Reconstruction(str(tmp_path / kind / "sparse"))
        by_name = {image.name: image for image in reconstruction.images.values()}
        centres = camera_to_world(model.rotations, model.translations)[:, :3]
        for i, name in enumerate(model.names):
            image = by_name[name]
            pose = image.cam_from_world  # a method since the frames of pycolmap 3.12
            pose = pose() if callable(pose) else pose
            xyzw = np.asarray(pose.rotation.quat)
            np.testing.assert_allclose(model.rotations[i], xyzw[[3, 0, 1, 2]], atol=1e-12)
            np.testing.assert_allclose(model.translations[i], pose.translation, atol=1e-12)
            np.testing.assert_allclose(centres[i], image.projection_center(), atol=1e-9)
        camera = reconstruction.cameras[1]
        assert camera.model.name == "PINHOLE" and list(camera.params) == list(
            model.cameras[1].params
        )


def write_png(path: Path, size: tuple[int, int] = (SIZE, SIZE)) -> None:
    """A small grey PNG of ``size`` (width, height) px."""
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full((size[1], size[0], 3), 128, np.uint8))


def small_model(
    tmp_path: Path, names: list[str], camera: tuple[str, int, int, list[float]] | None = None
) -> tuple[Path, Path]:
    """A text model of ``names`` (random poses, one camera) and their PNGs -> (model, images)."""
    rotations = np.random.default_rng(0).normal(size=(len(names), 4))
    positions = np.random.default_rng(1).normal(size=(len(names), 3))
    poses = np.concatenate([positions, rotations / np.linalg.norm(rotations, axis=1)[:, None]], 1)
    q, t = world_to_camera(poses)
    images = [(i + 1, q[i], t[i], 1, name) for i, name in enumerate(names)]
    camera = camera or ("SIMPLE_PINHOLE", SIZE, SIZE, [FOCAL, COLMAP_CENTRE, COLMAP_CENTRE])
    write_colmap_text(tmp_path / "sparse", {1: camera}, images)
    for name in names:
        write_png(tmp_path / "images" / name)
    return tmp_path / "sparse", tmp_path / "images"


def convert_colmap(tmp_path: Path, *options: str) -> int:
    argv = [str(tmp_path / "sparse"), str(tmp_path / "images"), str(tmp_path / "out")]
    return main(["convert", "colmap", *argv, *options])


def test_colmap_splits_by_folder_list_and_every_kth_image(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The three splits; --every K, whose test images lie between train images of their
    walk, says in one warning line that the split is leaky for localisation."""
    names = ["train/a/000.png", "test/b/001.png", "train/b/000.png", "train/b/001.png"]
    names += ["test/c/000.png"]
    small_model(tmp_path, names)
    assert convert_colmap(tmp_path) == 0
    assert "warning" not in capsys.readouterr().err
    test = read_labels(tmp_path / "out" / "all_test.csv")
    train = read_labels(tmp_path / "out" / "all_train.csv")
    assert test.img_path == ["test/b/001.png", "test/c/000.png"] and test.seq == ["b", "c"]
    assert train.seq == ["a", "b", "b"] and train.focal.tolist() == [FOCAL] * 3

    shutil.rmtree(tmp_path / "out")
    assert convert_colmap(tmp_path, "--every", "2") == 0
    test = read_labels(tmp_path / "out" / "all_test.csv")
    assert test.img_path == ["test/c/000.png", "train/b/000.png"]  # 2nd and 4th by name
    err = capsys.readouterr().err
    assert err.startswith("pae-data: warning: --every 2 puts each test image between train")
    assert "a leaky split for localisation" in err and err.count("\n") == 1, err

    shutil.rmtree(tmp_path / "out")
    assert convert_colmap(tmp_path, "--test-folders", "test") == 0
    test = read_labels(tmp_path / "out" / "all_test.csv")
    assert test.seq == ["test-b", "test-c"]


def test_colmap_accepts_a_radial_camera_without_distortion(tmp_path: Path) -> None:
    camera = ("OPENCV", SIZE, SIZE, [30.0, 30.0, 16.0, 16.0, 0.0, 0.0, 0.0, 0.0])
    small_model(tmp_path, ["train/0.png", "test/0.png"], camera)
    assert convert_colmap(tmp_path) == 0
    assert read_labels(tmp_path / "out" / "all_test.csv").focal.tolist() == [30.0]


def test_colmap_s_image_centre_is_pae_s_image_centre(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 40 × 24 model whose principal point is the image centre in COLMAP's convention (the
    top-left pixel's centre at (0.5, 0.5): ``W/2, H/2``) converts to pae's image centre (the
    top-left pixel's centre at (0, 0): ``(W - 1)/2, (H - 1)/2``)."""
    from pae.data.colmap import read_colmap_scene

    width, height = 40, 24
    camera = ("PINHOLE", width, height, [30.0, 30.0, width / 2, height / 2])
    small_model(tmp_path, ["train/0.png", "test/0.png"], camera)
    for name in ("train/0.png", "test/0.png"):
        write_png(tmp_path / "images" / name, size=(width, height))
    frames = read_colmap_scene(tmp_path / "sparse", tmp_path / "images")
    np.testing.assert_array_equal(frames.principal, [[19.5, 11.5]] * 2)
    assert convert_colmap(tmp_path) == 0
    assert "cx: 19.5, cy: 11.5, width: 40, height: 24}" in capsys.readouterr().out


BAD_CAMERAS = {
    "distorted": (
        ("OPENCV", SIZE, SIZE, [30.0, 30.0, 16.0, 16.0, 0.1, 0.0, 0.0, 0.0]),
        "cameras.txt:2: camera 1 is a distorted OPENCV camera: pae needs undistorted pinhole "
        "images: colmap image_undistorter --image_path",
    ),
    "fisheye": (
        ("OPENCV_FISHEYE", SIZE, SIZE, [30.0, 30.0, 16.0, 16.0, 0.0, 0.0, 0.0, 0.0]),
        "camera 1 is a non-pinhole OPENCV_FISHEYE camera",
    ),
    "unknown": (("WEIRD", SIZE, SIZE, [30.0]), "cameras.txt:2: camera 1: unknown camera model"),
    "fx_fy": (
        ("PINHOLE", SIZE, SIZE, [30.0, 31.0, 16.0, 16.0]),
        "cameras.txt:2: camera 1: fx 30 != fy 31 px",
    ),
    "size": (("PINHOLE", 64, 48, [30.0, 30.0, 32.0, 24.0]), "is 32x32 px, its camera 1 64x48"),
}


@pytest.mark.parametrize("case", sorted(BAD_CAMERAS))
def test_colmap_bad_cameras_are_one_line_naming_the_camera(
    tmp_path: Path, case: str, capsys: pytest.CaptureFixture[str]
) -> None:
    camera, expected = BAD_CAMERAS[case]
    small_model(tmp_path, ["train/0.png", "test/0.png"], camera)
    assert convert_colmap(tmp_path) == 1
    err = capsys.readouterr().err
    assert expected in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_colmap_bad_models_are_one_line_naming_file_and_entry(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def fails(expected: str, *options: str) -> None:
        assert convert_colmap(tmp_path, *options) == 1
        err = capsys.readouterr().err
        assert expected in err and err.count("\n") == 1, err
        assert not (tmp_path / "out").exists()

    model, images = small_model(tmp_path, ["train/0.png", "test/0.png", "x.png"])
    fails(
        "images.txt:7: image 3 (x.png) lies under neither train/ nor test/: give --split-list FILE"
    )
    (tmp_path / "list.txt").write_text("x.png\nnot-there.png\n")
    split_list = str(tmp_path / "list.txt")
    fails("list.txt:2: not-there.png is not an image of the model", "--split-list", split_list)
    (images / "x.png").unlink()
    fails(f"images.txt:7: image 3 (x.png): no image {images / 'x.png'}", "--every", "2")
    text = (model / "images.txt").read_text()
    (model / "images.txt").write_text(text.replace(" 1 x.png", " 9 x.png"))
    fails("images.txt:7: image 3 (x.png): camera 9 is not in", "--every", "2")
    first = text.splitlines()[2].split()
    (model / "images.txt").write_text(text.replace(first[1], "nan", 1))
    fails("images.txt:3: image 1 (train/0.png): not finite", "--every", "2")
    (model / "images.txt").write_text("# no images\n")
    fails("images.txt: no images: the model registered none")
    (model / "images.txt").unlink()
    fails(f"{model}: no images.bin or images.txt: not a COLMAP model folder")


def test_colmap_binary_problems_name_the_file_and_entry(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    names = ["train/0.png", "test/0.png"]
    images = [(i + 1, [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, i], 1, n) for i, n in enumerate(names)]
    for name in names:
        write_png(tmp_path / "images" / name)
    write_colmap_binary(tmp_path / "sparse", {1: ("PINHOLE", SIZE, SIZE, [30.0] * 4)}, images)
    data = (tmp_path / "sparse" / "cameras.bin").read_bytes()
    (tmp_path / "sparse" / "cameras.bin").write_bytes(data[:8] + struct.pack("<i", 1) + b"\x2a")
    assert convert_colmap(tmp_path) == 1
    assert "cameras.bin: ends early (byte 8)" in capsys.readouterr().err
    patched = data[:12] + struct.pack("<i", 42) + data[16:]
    (tmp_path / "sparse" / "cameras.bin").write_bytes(patched)
    assert convert_colmap(tmp_path) == 1
    assert "cameras.bin: camera 1: unknown camera model id 42" in capsys.readouterr().err
    (tmp_path / "sparse" / "cameras.bin").write_bytes(data)
    images[1] = (2, [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 1, names[1])
    write_colmap_binary(tmp_path / "sparse", {1: ("PINHOLE", SIZE, SIZE, [30.0] * 4)}, images)
    assert convert_colmap(tmp_path) == 1
    assert "images.bin: image 2 (test/0.png): quaternion has zero norm" in capsys.readouterr().err


@pytest.mark.slow
def test_converted_colmap_scene_trains_with_the_converted_data_config(
    tiny_root: Path, tmp_path: Path
) -> None:
    """pae-train data=converted with the overrides the conversion printed: a teacher trains
    on the converted labels and tests on the benchmark's test images, with the figures of
    the same run on the benchmark's own labels of the scene (the conversion is exact)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import open_dict

    from pae import CONFIG_DIR
    from pae.data.labels import write_labels
    from pae.train import run

    split_list = benchmark_model(tiny_root, tmp_path / "sparse", "binary")
    out = tmp_path / "labels"
    argv = ["convert", "colmap", str(tmp_path / "sparse"), str(tiny_root), str(out)]
    assert main([*argv, "--split-list", str(split_list)]) == 0
    original = tmp_path / "original"
    original.mkdir()
    for split, table in benchmark_scene(tiny_root).items():
        write_labels(original / f"all_{split}.csv", table)

    def teacher_run(labels: Path) -> dict:
        overrides = [
            "data=converted",
            f"data.root={tiny_root}",
            f"data.train_labels={labels / 'all_train.csv'}",
            f"data.test_labels={labels / 'all_test.csv'}",
            f"data.camera={{fx: {FOCAL}, fy: {FOCAL}, cx: 15.5, cy: 15.5, width: 32, height: 32}}",
            "data.shorter_edge=32",
            "data.crop=28",
            "data.batch_size=8",
            "data.num_workers=0",
            "teacher.max_epochs=1",
            "trainer.check_val_every_n_epoch=1",
            "callbacks=minimal",
            "logger=csv",
            "+trainer.enable_progress_bar=false",
        ]
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            cfg = compose("train", overrides=overrides, return_hydra_config=True)
        run_dir = tmp_path / labels.name / "run"
        with open_dict(cfg):
            cfg.hydra.runtime.output_dir = str(run_dir)
        return run(cfg, run_dir)

    converted, reference = teacher_run(out), teacher_run(original)
    for key in ("test/teacher/pos_median_m", "test/teacher/rot_median_deg"):
        assert converted[key] == pytest.approx(reference[key], rel=1e-3, abs=1e-4), key
