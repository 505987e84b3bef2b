"""``pae-data convert kapture``: the synthetic benchmark's own cameras written as two kapture
folders (mapping and query) convert back to its poses and focal length, with COLMAP's image
centre as pae's; a malformed line stops with one line naming the file and line."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from pae.data.labels import LabelTable, read_labels
from pae.data_cli import main
from tests.test_convert_ace import FOCAL, SIZE, benchmark_scene
from tests.test_convert_colmap import world_to_camera

HEADER = "# kapture format: 1.1\n"


def write_kapture(tiny_root: Path, root: Path) -> dict[str, LabelTable]:
    """scene00 of the tiny benchmark as the kapture folders ``root/mapping`` (train, a
    PINHOLE camera) and ``root/query`` (test, a SIMPLE_PINHOLE one), principal points at the
    image centre in COLMAP's convention (``SIZE / 2``), a wifi sensor beside the cameras."""
    tables = benchmark_scene(tiny_root)
    for table, folder, camera in zip(
        tables.values(),
        ("mapping", "query"),
        (
            f"PINHOLE, {SIZE}, {SIZE}, {FOCAL!r}, {FOCAL!r}, {SIZE / 2}, {SIZE / 2}",
            f"SIMPLE_PINHOLE, {SIZE}, {SIZE}, {FOCAL!r}, {SIZE / 2}, {SIZE / 2}",
        ),
        strict=True,
    ):
        sensors = root / folder / "sensors"
        (sensors / "records_data").mkdir(parents=True)
        (sensors / "sensors.txt").write_text(
            f"{HEADER}# sensor_device_id, name, sensor_type, [sensor_params]+\n"
            f"cam0, phone, camera, {camera}\nwifi0, , wifi\n"
        )
        q, t = world_to_camera(table.poses)
        records, poses = [HEADER], [HEADER]
        for i, (seq, img_path) in enumerate(zip(table.seq, table.img_path, strict=True)):
            name = f"{seq}/{Path(img_path).name}"
            (sensors / "records_data" / seq).mkdir(exist_ok=True)
            shutil.copy(tiny_root / img_path, sensors / "records_data" / name)
            records.append(f"{i:04d}, cam0, {name}\n")
            poses.append(f"{i}, cam0, " + ", ".join(repr(float(v)) for v in (*q[i], *t[i])) + "\n")
        (sensors / "records_camera.txt").write_text("".join(records))
        (sensors / "trajectories.txt").write_text(HEADER + "".join(reversed(poses[1:])))
    return tables


def test_kapture_of_the_benchmark_converts_to_its_poses_and_focal_length(
    tiny_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "kapture_scene00"
    tables = write_kapture(tiny_root, root)
    assert main(["convert", "kapture", str(root), str(root / "labels")]) == 0
    printed = capsys.readouterr().out
    assert "cx: 15.5, cy: 15.5, width: 32, height: 32}" in printed  # pae's image centre
    for split, original in tables.items():
        converted = read_labels(root / "labels" / f"kapture_scene00_{split}.csv")
        folder = "mapping" if split == "train" else "query"
        assert converted.img_path == [
            f"{folder}/sensors/records_data/{seq}/{Path(path).name}"
            for seq, path in zip(original.seq, original.img_path, strict=True)
        ]
        assert converted.seq == original.seq and converted.split == [split] * len(original)
        np.testing.assert_allclose(converted.poses, original.poses, rtol=0, atol=1e-6)
        np.testing.assert_allclose(converted.focal, FOCAL, rtol=1e-12)


@pytest.mark.parametrize(
    ("file", "line", "text", "problem"),
    [
        ("trajectories.txt", 2, "0, cam0, 1, 0, 0, 0, 0, 0", "expected 'timestamp, device_id, qw"),
        ("trajectories.txt", 2, "0, cam0, 1, 0, 0, 0, 0, x, 0", "not a number: 'x'"),
        ("trajectories.txt", 2, "0, cam0, 0, 0, 0, 0, 0, 0, 0", "quaternion has zero norm"),
        ("trajectories.txt", 2, "t0, cam0, 1, 0, 0, 0, 0, 0, 0", "timestamp 't0' is not an"),
        ("records_camera.txt", 2, "0, cam0", "expected 'timestamp, device_id, image_path'"),
        ("records_camera.txt", 2, "0, cam9, a.png", "cam9 is not a camera of sensors.txt"),
        ("records_camera.txt", 2, "999, cam0, a.png", "no pose of cam0 at timestamp 999"),
        ("sensors.txt", 3, "cam0, , camera, PINHOLE, 32, 32, 30, 30, 16", "PINHOLE has 4 param"),
        ("sensors.txt", 3, "cam0, , camera, PINHOLE, 32.5, 32, 30, 30, 16, 16", "not whole"),
    ],
)
def test_a_malformed_kapture_line_is_one_line_naming_the_file_and_line(
    tiny_root: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    file: str,
    line: int,
    text: str,
    problem: str,
) -> None:
    root = tmp_path / "kapture"
    write_kapture(tiny_root, root)
    path = root / "query" / "sensors" / file
    lines = path.read_text().splitlines()
    lines[line - 1] = text
    path.write_text("\n".join(lines) + "\n")
    assert main(["convert", "kapture", str(root), str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"pae-data: error: {path}:{line}: ") and err.count("\n") == 1, err
    assert problem in err


def test_kapture_folders_and_cameras_pae_cannot_read_are_named(
    tiny_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "kapture"
    write_kapture(tiny_root, root)
    assert main(["convert", "kapture", str(root), str(tmp_path / "out"), "--test", "test"]) == 1
    err = capsys.readouterr().err
    assert f"{root / 'test' / 'sensors'}: not found: ROOT's kapture folders are" in err
    assert "['mapping', 'query']" in err

    sensors = root / "mapping" / "sensors" / "sensors.txt"
    distorted = f"cam0, , camera, OPENCV, {SIZE}, {SIZE}, 30, 30, 16, 16, 0.1, 0, 0, 0\n"
    sensors.write_text(HEADER + distorted)
    assert main(["convert", "kapture", str(root), str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert f"{sensors}:2: camera cam0 is a distorted OPENCV camera" in err
    assert "kapture_export_colmap.py" in err and err.count("\n") == 1
