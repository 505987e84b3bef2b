"""``pae-data``: check, convert (raw Cambridge / 7-Scenes layouts) and synth."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import types
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import pae.data
from pae.data.labels import LABEL_COLUMNS, read_labels
from pae.data_cli import main

from .conftest import REFERENCE_LABELS

HEADER = ",".join(LABEL_COLUMNS)
SRC = Path(__file__).resolve().parents[1] / "src"


def write_png(path: Path, value: int = 100) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full((4, 6, 3), value, dtype=np.uint8))


def label_row(img_path: str, t1: str = "1.0", q: str = "1.0,0.0,0.0,0.0", scene: str = "s") -> str:
    return f"{scene},train,seq1,{img_path},{t1},2.0,3.0,{q}"


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    """A root with two good images (scenes ``s`` and ``t``)."""
    root = tmp_path / "root"
    write_png(root / "s" / "seq1" / "0.png")
    write_png(root / "t" / "seq1" / "0.png")
    return root


def write_labels_text(root: Path, *lines: str) -> Path:
    path = root.parent / "labels.csv"
    path.write_text("".join(line + "\n" for line in lines))
    return path


def run_check(capsys: pytest.CaptureFixture[str], labels: Path, root: Path) -> tuple[int, str]:
    code = main(["check", str(labels), str(root)])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err + captured.out
    return code, captured.out + captured.err


def test_check_accepts_good_labels(capsys: pytest.CaptureFixture[str], dataset: Path) -> None:
    labels = write_labels_text(
        dataset, HEADER, label_row("s/seq1/0.png"), label_row("t/seq1/0.png", scene="t")
    )
    code, output = run_check(capsys, labels, dataset)
    assert code == 0
    assert output.strip() == "OK: 2 rows, 2 scenes"


DEFECTS = {
    "missing-column": (
        (HEADER.replace(",t2", ""), "s,train,seq1,s/seq1/0.png,1,3,1,0,0,0"),
        "labels.csv:1: missing column t2",
    ),
    "empty-file": ((), "labels.csv: empty file"),
    "header-only": ((HEADER,), "labels.csv:1: no data rows"),
    "non-numeric": ((HEADER, label_row("s/seq1/0.png", t1="abc")), "labels.csv:2: column t1"),
    "nan": ((HEADER, label_row("s/seq1/0.png", t1="NaN")), "labels.csv:2: column t1 is not finite"),
    "inf": ((HEADER, label_row("s/seq1/0.png", t1="inf")), "labels.csv:2: column t1 is not finite"),
    "zero-quaternion": (
        (HEADER, label_row("s/seq1/0.png", q="0,0,0,0")),
        "labels.csv:2: quaternion (q1..q4) has zero norm",
    ),
    "missing-image": (
        (HEADER, label_row("s/seq1/0.png"), label_row("s/seq1/1.png")),
        "labels.csv:3: image not found: 's/seq1/1.png'",
    ),
    "corrupt-image": ((HEADER, label_row("s/garbage.png")), "labels.csv:2: image is corrupt"),
    "escaping-path": (
        (HEADER, label_row("s/../../outside.png")),
        "labels.csv:2: image path escapes the root",
    ),
}


@pytest.mark.parametrize("defect", sorted(DEFECTS))
def test_check_rejects_each_defect(
    capsys: pytest.CaptureFixture[str], dataset: Path, defect: str
) -> None:
    (dataset / "s" / "garbage.png").write_bytes(os.urandom(64))
    write_png(dataset.parent / "outside.png")
    lines, expected = DEFECTS[defect]
    code, output = run_check(capsys, write_labels_text(dataset, *lines), dataset)
    assert code == 1
    assert expected in output


def test_check_lists_every_bad_row(capsys: pytest.CaptureFixture[str], dataset: Path) -> None:
    labels = write_labels_text(
        dataset,
        HEADER,
        label_row("s/seq1/0.png"),
        label_row("s/seq1/0.png", t1="x"),
        label_row("s/nope.png"),
        label_row("s/seq1/0.png", q="0,0,0,0"),
        label_row("/etc/hostname"),
    )
    code, output = run_check(capsys, labels, dataset)
    assert code == 1
    for line in (3, 4, 5, 6):
        assert f"labels.csv:{line}:" in output
    assert "labels.csv:2:" not in output
    assert "FAILED: 4 of 5 rows" in output


def test_check_warns_once_about_non_unit_quaternions(
    capsys: pytest.CaptureFixture[str], dataset: Path
) -> None:
    labels = write_labels_text(
        dataset,
        HEADER,
        label_row("s/seq1/0.png", q="2,0,0,0"),
        label_row("t/seq1/0.png", q="0,3,0,4", scene="t"),
    )
    code = main(["check", str(labels), str(dataset)])
    captured = capsys.readouterr()
    assert code == 0
    assert captured.err.count("pae-data: warning:") == 1
    assert "2 quaternions in" in captured.err


def test_check_missing_labels_file(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code = main(["check", str(tmp_path / "none.csv"), str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 1
    assert err.startswith("pae-data: error: ") and "none.csv: file not found" in err
    assert err.count("\n") == 1


def test_subprocess_reports_error_without_traceback(dataset: Path) -> None:
    labels = write_labels_text(dataset, HEADER.replace(",q3", ""), "s,train,a,b,1,2,3,1,0,0")
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]),
    }
    result = subprocess.run(
        [sys.executable, "-m", "pae.data_cli", "check", str(labels), str(dataset)],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
        check=False,
    )
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    assert result.stderr.strip().endswith(
        "labels.csv:1: missing column q3 (header: " + (HEADER.replace(",q3", "") + ")")
    )


def test_usage_errors_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    for argv in ([], ["check", "only-one-arg"], ["convert", "kitti", "a", "b"]):
        with pytest.raises(SystemExit) as info:
            main(argv)
        assert info.value.code == 2
    assert "usage: pae-data" in capsys.readouterr().err


def write_pose_file(path: Path, matrix: np.ndarray) -> None:
    """A 7-Scenes-style pose file: 4 rows of tab-separated ``%.7e`` numbers."""
    path.write_text("".join("\t".join(f"{v:.7e}" for v in row) + "\t\n" for row in matrix))


def build_seven_scenes(root: Path) -> dict[str, list[tuple[str, Path]]]:
    """Two scenes with random poses; returns the expected (img_path, pose file) per split."""
    rng = np.random.default_rng(0)
    rotations = iter(Rotation.random(30, random_state=1).as_matrix())
    expected: dict[str, list[tuple[str, Path]]] = {"train": [], "test": []}
    for scene, train_seqs, test_seqs in (("chess", (2, 1), (3,)), ("fire", (1,), (2,))):
        scene_dir = root / scene
        scene_dir.mkdir(parents=True)
        (scene_dir / "TrainSplit.txt").write_text("".join(f"sequence{s}\n" for s in train_seqs))
        (scene_dir / "TestSplit.txt").write_text("".join(f"sequence{s}\r\n" for s in test_seqs))
        for split, seqs in (("train", train_seqs), ("test", test_seqs)):
            for s in seqs:
                seq_dir = scene_dir / f"seq-{s:02d}"
                for frame in range(3):
                    matrix = np.eye(4)
                    matrix[:3, :3] = next(rotations)
                    matrix[:3, 3] = rng.normal(size=3)
                    pose_file = seq_dir / f"frame-{frame:06d}.pose.txt"
                    write_png(seq_dir / f"frame-{frame:06d}.color.png")
                    write_pose_file(pose_file, matrix)
                    img_path = f"{scene}/seq-{s:02d}/frame-{frame:06d}.color.png"
                    expected[split].append((img_path, pose_file))
    return expected


def test_convert_seven_scenes(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    raw = tmp_path / "7scenes"
    expected = build_seven_scenes(raw)
    out = tmp_path / "labels"
    assert main(["convert", "7scenes", str(raw), str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "2 scenes" in stdout and "all_train.csv" in stdout
    assert sorted(p.name for p in out.iterdir()) == [
        "all_test.csv",
        "all_train.csv",
        "chess_test.csv",
        "chess_train.csv",
        "fire_test.csv",
        "fire_train.csv",
    ]
    for split in ("train", "test"):
        table = read_labels(out / f"all_{split}.csv")
        assert table.img_path == [img for img, _ in expected[split]]
        matrices = np.stack([np.loadtxt(pose_file) for _, pose_file in expected[split]])
        np.testing.assert_array_equal(table.poses[:, :3], matrices[:, :3, 3])
        scipy_quats = np.roll(Rotation.from_matrix(matrices[:, :3, :3]).as_quat(), 1, axis=1)
        signs = np.sign(np.sum(scipy_quats * table.poses[:, 3:], axis=1, keepdims=True))
        np.testing.assert_allclose(table.poses[:, 3:], signs * scipy_quats, atol=1e-6)
    chess_train = read_labels(out / "chess_train.csv")
    assert chess_train.seq == ["seq-02"] * 3 + ["seq-01"] * 3
    assert set(chess_train.split) == {"train"}

    assert main(["check", str(out / "all_train.csv"), str(raw)]) == 0
    assert "OK: 9 rows, 2 scenes" in capsys.readouterr().out


CAMBRIDGE_HEADER = (
    "Visual Landmark Dataset V1\n"
    "ImageFile, Camera Position [X Y Z], Camera Orientation [W P Q R]\n"
    "\n"
)


def test_convert_cambridge_conjugates_the_world_to_camera_quaternions(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    raw = tmp_path / "cambridge"
    rng = np.random.default_rng(3)
    raw_rows = {}
    for split, count in (("train", 5), ("test", 3)):
        rows = []
        for i in range(count):
            numbers = [repr(round(float(v), 6)) for v in rng.uniform(-50, 50, size=3)]
            quat = rng.normal(size=4)
            quat /= np.linalg.norm(quat)
            quat[0] = (-1) ** i * (abs(quat[0]) + 0.01)  # some rows store W < 0
            numbers += [repr(round(float(v), 6)) for v in quat]
            rows.append((f"seq{i % 2 + 1}/frame{i + 1:05d}.png", numbers))
        raw_rows[split] = rows
        text = "".join(f"{img} {' '.join(nums)}\n" for img, nums in rows)
        (raw / "ShopFacade").mkdir(parents=True, exist_ok=True)
        (raw / "ShopFacade" / f"dataset_{split}.txt").write_text(CAMBRIDGE_HEADER + text)
    (raw / "not_a_scene").mkdir()
    out = tmp_path / "labels"
    assert main(["convert", "cambridge", str(raw), str(out)]) == 0
    assert "1 scenes" in capsys.readouterr().out

    for split in ("train", "test"):
        with open(out / f"ShopFacade_{split}.csv", newline="") as handle:
            written = list(csv.reader(handle))
        assert written[0] == [*LABEL_COLUMNS, "orientation"]
        assert len(written) == len(raw_rows[split]) + 1
        for fields, (img, numbers) in zip(written[1:], raw_rows[split], strict=True):
            assert fields[:4] == ["ShopFacade", split, img.split("/")[0], f"ShopFacade/{img}"]
            # the conjugate (x, y, z negated), then the sign that makes W >= 0
            flip = numbers[3].startswith("-")
            negated = [n[1:] if n.startswith("-") else "-" + n for n in numbers[3:]]
            expected = [negated[0], *numbers[4:]] if flip else [numbers[3], *negated[1:]]
            assert fields[4:] == [*numbers[:3], *expected, "camera_to_world"]
        assert (out / f"all_{split}.csv").read_text() == (
            out / f"ShopFacade_{split}.csv"
        ).read_text()


def test_convert_cambridge_gives_back_known_camera_to_world_poses(tmp_path: Path) -> None:
    """Known camera-to-world poses written as Cambridge does (camera centre, world-to-camera
    quaternion) convert back to themselves."""
    rng = np.random.default_rng(5)
    rotations = Rotation.random(6, random_state=7)
    centres = rng.uniform(-20, 20, size=(6, 3))
    world_to_camera = rotations.inv().as_quat(scalar_first=True)
    lines = "".join(
        f"seq1/frame{i:05d}.png {' '.join(repr(float(v)) for v in (*c, *q))}\n"
        for i, (c, q) in enumerate(zip(centres, world_to_camera, strict=True))
    )
    scene = tmp_path / "raw" / "ShopFacade"
    scene.mkdir(parents=True)
    for split in ("train", "test"):
        (scene / f"dataset_{split}.txt").write_text(CAMBRIDGE_HEADER + lines)
    assert main(["convert", "cambridge", str(tmp_path / "raw"), str(tmp_path / "out")]) == 0
    table = read_labels(tmp_path / "out" / "ShopFacade_train.csv")
    np.testing.assert_allclose(table.poses[:, :3], centres, atol=1e-6)
    got = Rotation.from_quat(table.poses[:, 3:], scalar_first=True)
    np.testing.assert_allclose((got * rotations.inv()).magnitude(), 0.0, atol=1e-6)


def test_check_warns_on_world_to_camera_orientations(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """Upright cameras (y axes near one world direction) read as camera-to-world pass; the
    same file written world-to-camera is flagged with the command that fixes it, and that
    command's output passes."""
    rng = np.random.default_rng(2)
    yaw = Rotation.from_euler("y", rng.uniform(-180, 180, (40, 1)), degrees=True)
    tilt = Rotation.from_euler("xz", rng.normal(0, 3, (40, 2)), degrees=True)
    z_up = Rotation.from_euler("x", 90, degrees=True)  # the world's up is z, as in SfM frames
    upright = (z_up * yaw * tilt).as_quat(scalar_first=True)
    rows = [",".join(LABEL_COLUMNS)]
    for label, quats in (("c2w", upright), ("w2c", upright * [1, -1, -1, -1])):
        body = [
            f"s,train,seq1,a{i}.png,{i},0,0,{','.join(map(str, q))}" for i, q in enumerate(quats)
        ]
        (tmp_path / f"{label}.csv").write_text("\n".join([*rows, *body]) + "\n")
    main(["check", str(tmp_path / "c2w.csv"), str(tmp_path)])
    assert "world-to-camera" not in capsys.readouterr().err
    main(["check", str(tmp_path / "w2c.csv"), str(tmp_path)])
    err = capsys.readouterr().err
    assert "w2c.csv: its orientations look world-to-camera" in err
    assert "pae-data convert authors-csv" in err
    assert main(["convert", "authors-csv", str(tmp_path / "w2c.csv"), str(tmp_path / "fixed")]) == 0
    main(["check", str(tmp_path / "fixed" / "w2c.csv"), str(tmp_path)])
    assert "world-to-camera" not in capsys.readouterr().err


@pytest.mark.reference_labels
def test_check_flags_the_authors_cambridge_files_only(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    shop = REFERENCE_LABELS / "CambridgeLandmarks" / "ShopFacade_train.csv"
    chess = REFERENCE_LABELS / "7Scenes" / "chess_train.csv"
    main(["check", str(shop), str(tmp_path)])
    assert "ShopFacade_train.csv: its orientations look world-to-camera" in capsys.readouterr().err
    if chess.is_file():
        main(["check", str(chess), str(tmp_path)])
        assert "world-to-camera" not in capsys.readouterr().err


def test_convert_reports_malformed_raw_lines(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    scene = tmp_path / "raw" / "KingsCollege"
    scene.mkdir(parents=True)
    (scene / "dataset_train.txt").write_text(
        CAMBRIDGE_HEADER + "seq1/frame00001.png 1 2 3 1 0 0 0\nseq1/frame00002.png 1 2 3 1 0 0\n"
    )
    (scene / "dataset_test.txt").write_text(CAMBRIDGE_HEADER + "seq2/f.png 1 2 3 1 0 0 x\n")
    out = tmp_path / "out"
    assert main(["convert", "cambridge", str(tmp_path / "raw"), str(out)]) == 1
    err = capsys.readouterr().err
    assert "dataset_train.txt:5: expected 'IMAGE X Y Z W P Q R' (8 fields), got 7" in err
    assert "Traceback" not in err and not out.exists()

    seven = tmp_path / "seven" / "heads"
    (seven / "seq-01").mkdir(parents=True)
    (seven / "TrainSplit.txt").write_text("sequence1\n")
    (seven / "TestSplit.txt").write_text("sequence1\n")
    write_pose_file(seven / "seq-01" / "frame-000000.pose.txt", np.eye(4))
    (seven / "seq-01" / "frame-000001.pose.txt").write_text(
        "1 0 0 0\n0 1 0 0\n0 0 one 0\n0 0 0 1\n"
    )
    assert main(["convert", "7scenes", str(tmp_path / "seven"), str(out)]) == 1
    err = capsys.readouterr().err
    assert "frame-000001.pose.txt:3: not a number: 'one'" in err

    assert main(["convert", "7scenes", str(tmp_path / "raw"), str(out)]) == 1
    assert "no 7scenes scene folders" in capsys.readouterr().err


def test_convert_refuses_repeated_images_and_non_rigid_matrices(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """A Cambridge image listed twice, a 7-Scenes sequence listed twice and a 7-Scenes pose
    that is not a rigid transform (a scaled rotation, a shear of determinant 1): one line
    naming the file (and line), nothing written."""
    scene = tmp_path / "raw" / "KingsCollege"
    scene.mkdir(parents=True)
    rows = "seq1/frame00001.png 1 2 3 1 0 0 0\nseq1/frame00002.png 1 2 3 1 0 0 0\n"
    (scene / "dataset_train.txt").write_text(CAMBRIDGE_HEADER + rows + rows.split("\n")[0])
    (scene / "dataset_test.txt").write_text(CAMBRIDGE_HEADER + "seq2/f.png 1 2 3 1 0 0 0\n")
    out = tmp_path / "out"
    assert main(["convert", "cambridge", str(tmp_path / "raw"), str(out)]) == 1
    err = capsys.readouterr().err
    assert err.endswith("dataset_train.txt:6: image seq1/frame00001.png repeats line 4\n")
    assert err.count("\n") == 1 and not out.exists()

    raw = tmp_path / "7scenes"
    build_seven_scenes(raw)
    (raw / "chess" / "TrainSplit.txt").write_text("sequence2\nsequence1\nsequence2\n")
    assert main(["convert", "7scenes", str(raw), str(out)]) == 1
    err = capsys.readouterr().err
    assert err.endswith("TrainSplit.txt:3: sequence2 repeats line 1\n") and not out.exists()
    (raw / "chess" / "TrainSplit.txt").write_text("sequence2\nsequence1\n")
    pose_file = raw / "fire" / "seq-02" / "frame-000001.pose.txt"
    for linear, says in (
        (np.diag([1.1, 1.1, 1.1]), "not orthonormal"),
        (np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "not orthonormal"),
    ):
        matrix = np.eye(4)
        matrix[:3, :3] = linear
        write_pose_file(pose_file, matrix)
        assert main(["convert", "7scenes", str(raw), str(out)]) == 1
        err = capsys.readouterr().err
        assert f"error: {pose_file}: not a rigid transform: " in err and says in err
        assert err.count("\n") == 1 and not out.exists()


def test_synth_passes_arguments_and_prints_summary(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    calls = []

    class Written:
        def summary(self) -> str:
            return "synthetic summary"

    def write_synthetic_dataset(
        out: Path, progress: Callable[[int, int], None], **kwargs: int
    ) -> Written:
        calls.append((out, kwargs))
        progress(1, 2)
        return Written()

    fake = types.ModuleType("pae.synthetic")
    fake.write_synthetic_dataset = write_synthetic_dataset
    monkeypatch.setitem(sys.modules, "pae.synthetic", fake)
    monkeypatch.setattr(pae, "synthetic", fake, raising=False)

    assert main(["synth", str(tmp_path / "a"), "--scenes", "2", "--size", "32", "--seed", "7"]) == 0
    nuisances = ["--lighting-change", "0.5", "--occluder-fraction", "0.3"]
    nuisances += ["--sensor-noise", "0.02", "--motion-blur", "3"]
    b = ["synth", str(tmp_path / "b"), "--test-offset", "0", "--train-lane", "0.5", *nuisances]
    b += ["--val-lane", "-0.25", "--val-walks", "2"]
    b += ["--plain-surfaces", "0.3", "--repeated-surfaces", "0.2", "--glossy-surfaces", "0.4"]
    b += ["--camera-pipeline", "1", "--jpeg-quality", "75", "--render-scale", "4"]
    assert main(b) == 0
    written = capsys.readouterr()
    assert written.out == "synthetic summary\n" * 2
    assert f"rendering {tmp_path / 'a'}: 1/2 frames (50 %)" in written.err
    assert calls == [
        (tmp_path / "a", dict(seed=7, overwrite=False, scenes=2, size=32)),
        (
            tmp_path / "b",
            dict(
                seed=0,
                overwrite=False,
                test_offset_m=0.0,
                train_lane_m=0.5,
                val_lane_m=-0.25,
                val_walks=2,
                lighting_change=0.5,
                occluder_fraction=0.3,
                sensor_noise_std=0.02,
                motion_blur_px=3.0,
                plain_surface_share=0.3,
                repeated_surface_share=0.2,
                glossy_surface_share=0.4,
                camera_pipeline=1.0,
                jpeg_quality=75,
                render_scale=4,
            ),
        ),
    ]
    layout = "--poses takes no layout option: drop"
    assert main(["synth", str(tmp_path / "c"), "--poses", "x.csv", "--scenes", "2"]) == 1
    assert f"{layout} --scenes" in capsys.readouterr().err
    argv = ["synth", str(tmp_path / "c"), "--poses", "x.csv", "--stray", "0.1"]
    assert main([*argv, "--motion-blur", "2"]) == 1
    assert f"{layout} --stray" in capsys.readouterr().err


def test_convert_into_a_file_is_one_line_before_any_work(tmp_path: Path, capsys) -> None:
    """OUT_DIR that is a file: one line naming it, and the file is left as it was."""
    from pae.data_cli import main

    blocker = tmp_path / "labels"
    blocker.write_text("a file\n")
    source = tmp_path / "w2c.csv"
    source.write_text(
        "scene,split,seq,img_path,t1,t2,t3,q1,q2,q3,q4\na,train,s,a/1.png,0,0,0,1,0,0,0\n"
    )
    assert main(["convert", "authors-csv", str(source), str(blocker)]) == 1
    errors = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(errors) == 1 and "OUT_DIR" in errors[0] and "is a file" in errors[0], errors
    assert blocker.read_text() == "a file\n"
