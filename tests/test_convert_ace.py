"""``pae-data convert ace``: the synthetic benchmark's own cameras and images written in the
ACE / DSAC* layout convert back to its poses and focal length; bad frames stop with one line
naming the file."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pae.core.geometry import quaternion_to_matrix
from pae.data.holdout import natural_key
from pae.data.labels import LabelTable, read_labels
from pae.data_cli import main
from pae.synthetic import PinholeCamera
from tests.conftest import TINY

SIZE = TINY["size"]
FOCAL = PinholeCamera(SIZE).focal_px
CENTRE = (SIZE - 1) / 2


def benchmark_scene(tiny_root: Path, scene: str = "scene00") -> dict[str, LabelTable]:
    """The train and test rows of one scene of the tiny benchmark."""
    tables = {}
    for split in ("train", "test"):
        table = read_labels(tiny_root / "labels" / f"all_{split}.csv")
        tables[split] = table.select([i for i, s in enumerate(table.scene) if s == scene])
    return tables


def write_ace_scene(tiny_root: Path, root: Path) -> dict[str, LabelTable]:
    """scene00 of the tiny benchmark in the ACE layout: train calibrations one focal length,
    test ones a 3×3 matrix (principal point at the image centre in ACE's pixel convention,
    ``SIZE / 2``: the top-left pixel's centre at (0.5, 0.5))."""
    tables = benchmark_scene(tiny_root)
    for split, table in tables.items():
        rotations = quaternion_to_matrix(torch.from_numpy(table.poses[:, 3:])).numpy()
        for i, (seq, img_path) in enumerate(zip(table.seq, table.img_path, strict=True)):
            name = f"{seq}-{Path(img_path).stem}"
            folder = root / split
            for sub in ("rgb", "poses", "calibration"):
                (folder / sub).mkdir(parents=True, exist_ok=True)
            shutil.copy(tiny_root / img_path, folder / "rgb" / f"{name}.color.png")
            matrix = np.eye(4)
            matrix[:3, :3], matrix[:3, 3] = rotations[i], table.poses[i, :3]
            np.savetxt(folder / "poses" / f"{name}.pose.txt", matrix)
            calibration = [[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1]]
            np.savetxt(
                folder / "calibration" / f"{name}.calibration.txt",
                [[FOCAL]] if split == "train" else calibration,
            )
    return tables


def test_ace_layout_of_the_benchmark_converts_to_its_poses_and_focal_length(
    tiny_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "7scenes_scene00"
    tables = write_ace_scene(tiny_root, root)
    (root / "train" / "depth").mkdir()
    assert main(["convert", "ace", str(root), str(root / "labels")]) == 0
    printed = capsys.readouterr().out
    assert "cx: 15.5, cy: 15.5, width: 32, height: 32}" in printed  # CENTRE: pae's convention
    assert f"data.root={root} 'data.camera=" in printed  # OUT_DIR is ROOT/labels: no label paths
    for split, original in tables.items():
        converted = read_labels(root / "labels" / f"7scenes_scene00_{split}.csv")
        assert converted.seq == original.seq and converted.split == [split] * len(original)
        assert [Path(p).parent.as_posix() for p in converted.img_path] == [f"{split}/rgb"] * len(
            original
        )
        np.testing.assert_allclose(converted.poses, original.poses, rtol=0, atol=1e-6)
        np.testing.assert_allclose(converted.focal, FOCAL, rtol=1e-12)


def test_ace_bad_frames_are_one_line_naming_the_file(
    tiny_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "scene"
    write_ace_scene(tiny_root, root)
    out = tmp_path / "out"
    frame = "seq-01-frame-000001"
    pose = root / "train" / "poses" / f"{frame}.pose.txt"
    calibration = root / "train" / "calibration" / f"{frame}.calibration.txt"
    image = root / "train" / "rgb" / f"{frame}.color.png"
    text = pose.read_text()

    def fails(expected: str) -> None:
        assert main(["convert", "ace", str(root), str(out)]) == 1
        err = capsys.readouterr().err
        assert expected in err and err.count("\n") == 1, err
        assert not out.exists()

    pose.write_text(text.replace(text.split()[0], "1.1", 1))
    fails(f"{pose}: not a rigid transform")
    pose.write_text(text.replace(text.split()[3], "nan", 1))
    fails(f"{pose}:1: not a finite number: 'nan'")
    pose.unlink()
    fails(f"{image}: no pose file in poses/ for this frame")
    pose.write_text(text)
    calibration.write_text("1 2 3 4\n")
    fails(f"{calibration}: expected a focal length or a 3×3 matrix, got 4 numbers")
    calibration.write_text("30\n")
    image.rename(tmp_path / "moved.png")
    fails(f"{pose}: no image in rgb/ for this frame")
    (tmp_path / "moved.png").rename(image)
    first_test = min((root / "test" / "rgb").iterdir(), key=lambda p: natural_key(p.name))
    first_train = min((root / "train" / "rgb").iterdir(), key=lambda p: natural_key(p.name))
    kept = first_test.read_bytes()
    cv2.imwrite(str(first_test), np.zeros((SIZE - 8, SIZE, 3), np.uint8))
    fails(f"{first_test}: {SIZE}x{SIZE - 8} px, but {first_train} is {SIZE}x{SIZE} px")
    first_test.write_bytes(kept)
    shutil.rmtree(root / "test" / "calibration")
    fails(f"{root / 'test' / 'calibration'}: folder not found")
