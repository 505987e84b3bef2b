"""Label files: reading the public label files, defects, round trips and image checks."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from pae.core.errors import OrientationWarning
from pae.data.label_images import find_image_problems
from pae.data.labels import (
    LABEL_COLUMNS,
    LabelError,
    LabelTable,
    LabelWarning,
    read_labels,
    read_labels_lenient,
    write_labels,
)
from tests.conftest import REFERENCE_LABELS

REFERENCE_ROWS = {
    "7Scenes/chess_test.csv": 2000,
    "7Scenes/chess_train.csv": 4000,
    "7Scenes/fire_test.csv": 2000,
    "7Scenes/fire_train.csv": 2000,
    "7Scenes/heads_test.csv": 1000,
    "7Scenes/heads_train.csv": 1000,
    "7Scenes/office_test.csv": 4000,
    "7Scenes/office_train.csv": 6000,
    "7Scenes/pumpkin_test.csv": 2000,
    "7Scenes/pumpkin_train.csv": 4000,
    "7Scenes/redkitchen_test.csv": 5000,
    "7Scenes/redkitchen_train.csv": 7000,
    "7Scenes/stairs_test.csv": 1000,
    "7Scenes/stairs_train.csv": 2000,
    "CambridgeLandmarks/GreatCourt_test.csv": 760,
    "CambridgeLandmarks/GreatCourt_train.csv": 1532,
    "CambridgeLandmarks/KingsCollege_test.csv": 343,
    "CambridgeLandmarks/KingsCollege_train.csv": 1220,
    "CambridgeLandmarks/OldHospital_test.csv": 182,
    "CambridgeLandmarks/OldHospital_train.csv": 895,
    "CambridgeLandmarks/ShopFacade_test.csv": 103,
    "CambridgeLandmarks/ShopFacade_train.csv": 231,
    "CambridgeLandmarks/StMarysChurch_test.csv": 530,
    "CambridgeLandmarks/StMarysChurch_train.csv": 1487,
    "CambridgeLandmarks/Street_test.csv": 2923,
    "CambridgeLandmarks/Street_train.csv": 3015,
}
# Rows whose quaternion norm is off by more than 1e-3 in the public files.
REFERENCE_NON_UNIT = {
    "CambridgeLandmarks/StMarysChurch_test.csv": 2,
    "CambridgeLandmarks/StMarysChurch_train.csv": 5,
    "CambridgeLandmarks/Street_test.csv": 26,
    "CambridgeLandmarks/Street_train.csv": 15,
}

HEADER = ",".join(LABEL_COLUMNS)
GOOD_ROW = "s1,train,seq1,s1/a.png,1.5,-2.0,0.25,1.0,0.0,0.0,0.0"


def reference_file(name: str) -> Path:
    """A reference label file (its test is marked ``reference_labels``)."""
    return REFERENCE_LABELS / name


def write_text(path: Path, *lines: str) -> Path:
    path.write_text("".join(line + "\n" for line in lines))
    return path


def read_quietly(path: Path) -> LabelTable:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LabelWarning)
        return read_labels(path)


def small_table() -> LabelTable:
    return LabelTable(
        scene=["b", "a", "b"],
        split=["train"] * 3,
        seq=["s1", "s1", "s2"],
        img_path=["b/1.png", "a/1.png", "b/2.png"],
        poses=np.array([[i, 0, 0, 1, 0, 0, 0] for i in range(3)], dtype=float),
        source="x.csv",
    )


@pytest.mark.reference_labels
@pytest.mark.parametrize("name", sorted(REFERENCE_ROWS))
def test_reads_every_reference_file(name: str) -> None:
    path = reference_file(name)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        table = read_labels(path)
    assert len(table) == REFERENCE_ROWS[name]
    assert table.poses.shape == (REFERENCE_ROWS[name], 7) and table.poses.dtype == np.float64
    scene, split = Path(name).stem.rsplit("_", 1)
    assert table.scene_names == [scene]
    assert set(table.split) == {split}
    assert all(p.startswith(f"{scene}/") for p in table.img_path)
    np.testing.assert_allclose(np.linalg.norm(table.poses[:, 3:], axis=1), 1.0, atol=1e-12)
    assert (table.poses[:, 3] >= 0).all()
    label_warnings = [w for w in caught if issubclass(w.category, LabelWarning)]
    upright = [w for w in label_warnings if issubclass(w.category, OrientationWarning)]
    label_warnings = [w for w in label_warnings if w not in upright]
    # Cambridge's quaternions are world-to-camera; the test reads them as they are: the four
    # scenes whose cameras are held upright (not OldHospital's and StMarysChurch's, whose
    # world up is the camera's y) say so
    assert len(upright) == (scene in ("GreatCourt", "KingsCollege", "ShopFacade", "Street"))
    if name in REFERENCE_NON_UNIT:
        assert len(label_warnings) == 1
        assert f"{REFERENCE_NON_UNIT[name]} quaternions in" in str(label_warnings[0].message)
    else:
        assert not label_warnings


@pytest.mark.reference_labels
def test_reference_known_values() -> None:
    chess = read_labels(reference_file("7Scenes/chess_test.csv"))
    assert (chess.scene[0], chess.split[0], chess.seq[0]) == ("chess", "test", "seq-03")
    assert chess.img_path[0] == "chess/seq-03/frame-000000.color.png"
    np.testing.assert_array_equal(chess.poses[0, :3], [-0.0513658, -0.7848635, -0.7011286999999999])
    np.testing.assert_allclose(
        chess.poses[0, 3:], [0.9823382, -0.1831518, 0.0323652, -0.0204851], atol=1e-6
    )
    assert chess.file_line(0) == 2 and chess.file_line(-1) == 2001

    street = read_quietly(reference_file("CambridgeLandmarks/Street_test.csv"))
    row = street.img_path.index("Street/img/image2_002008.png")  # stored with qw < 0
    assert street.file_line(row) == 2425
    raw_q = np.array([-0.000244, -0.045319, -0.658037, 0.751621])
    np.testing.assert_allclose(street.poses[row, 3:], -raw_q / np.linalg.norm(raw_q))


@pytest.mark.reference_labels
def test_round_trip_is_exact(tmp_path: Path) -> None:
    table = read_quietly(reference_file("CambridgeLandmarks/Street_test.csv"))
    out = tmp_path / "nested" / "dir" / "copy.csv"
    write_labels(out, table)
    again = read_labels(out)
    np.testing.assert_array_equal(again.poses, table.poses)
    assert again.img_path == table.img_path and again.seq == table.seq
    assert [p.name for p in out.parent.iterdir()] == ["copy.csv"]  # no temporary left behind
    write_labels(out, again)
    assert read_labels(out).poses.tobytes() == table.poses.tobytes()


def test_columns_are_found_by_name(tmp_path: Path) -> None:
    path = write_text(
        tmp_path / "l.csv",
        "img_path,extra,q1,q2,q3,q4,t1,t2,t3,seq,split,scene",
        "s/a.png,zzz,-1,0,0,0,1,2,3,q,test,s",
    )
    table = read_labels(path)
    np.testing.assert_array_equal(table.poses, [[1, 2, 3, 1, 0, 0, 0]])
    assert (table.scene, table.split, table.seq) == (["s"], ["test"], ["q"])


def test_crlf_bom_and_blank_lines(tmp_path: Path) -> None:
    path = tmp_path / "l.csv"
    path.write_bytes(("\ufeff" + HEADER + "\r\n\r\n" + GOOD_ROW + "\r\n").encode())
    table = read_labels(path)
    assert len(table) == 1 and table.file_line(0) == 3


@pytest.mark.parametrize(
    ("lines", "expected"),
    [
        ((), r"l\.csv: empty file"),
        ((HEADER,), r"l\.csv:1: no data rows"),
        ((HEADER.replace(",q2", ""), "a,b,c,d,1,2,3,1,0,0"), r"l\.csv:1: missing column q2\b"),
        ((HEADER, GOOD_ROW, GOOD_ROW.replace("-2.0", "abc")), r"l\.csv:3: column t2 .*'abc'"),
        ((HEADER, GOOD_ROW.replace("1.5", "nan")), r"l\.csv:2: column t1 is not finite: 'nan'"),
        ((HEADER, GOOD_ROW.replace("0.25", "-inf")), r"l\.csv:2: column t3 is not finite"),
        ((HEADER, GOOD_ROW.replace("1.0,0.0", "0.0,0.0")), r"l\.csv:2: quaternion .*zero norm"),
        ((HEADER, GOOD_ROW + ",7"), r"l\.csv:2: expected 11 fields, got 12"),
        ((HEADER, GOOD_ROW.replace("s1/a.png", "")), r"l\.csv:2: column img_path is empty"),
    ],
    ids=[
        "empty",
        "header-only",
        "missing-column",
        "non-numeric",
        "nan",
        "inf",
        "zero-quaternion",
        "extra-field",
        "empty-path",
    ],
)
def test_defects_raise_one_line_label_error(
    tmp_path: Path, lines: tuple[str, ...], expected: str
) -> None:
    path = write_text(tmp_path / "l.csv", *lines)
    with pytest.raises(LabelError, match=expected) as info:
        read_labels(path)
    assert "\n" not in str(info.value)
    assert isinstance(info.value, ValueError)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(LabelError, match=r"nope\.csv: file not found"):
        read_labels(tmp_path / "nope.csv")


def test_lenient_reading_reports_every_bad_row(tmp_path: Path) -> None:
    path = write_text(
        tmp_path / "l.csv",
        HEADER,
        GOOD_ROW,
        GOOD_ROW.replace("1.5", "x"),
        GOOD_ROW.replace("a.png", "b.png"),
        GOOD_ROW.replace("1.5", "inf"),
    )
    table, errors = read_labels_lenient(path)
    assert len(table) == 2 and list(table.lines) == [2, 4]
    assert [e.line for e in errors] == [3, 5]


def test_non_unit_quaternions_are_normalised_with_one_warning(tmp_path: Path) -> None:
    path = write_text(
        tmp_path / "l.csv",
        HEADER,
        *(
            GOOD_ROW.replace("1.0,0.0,0.0,0.0", q).replace("a.png", f"{i}.png")
            for i, q in enumerate(
                ("2.0,0.0,0.0,0.0", "-0.6,0.0,0.8,0.0", "0.0,0.0,-3.0,4.0", "1.0000001,0.0,0.0,0.0")
            )
        ),
    )
    with pytest.warns(LabelWarning) as record:
        table = read_labels(path)
    assert len(record) == 1
    assert str(record[0].message) == (
        f"2 quaternions in {path} were not unit norm and were normalised"
    )
    np.testing.assert_allclose(
        table.poses[:, 3:], [[1, 0, 0, 0], [0.6, 0, -0.8, 0], [0, 0, -0.6, 0.8], [1, 0, 0, 0]]
    )


def test_table_select_concat_and_scene_ids() -> None:
    table = small_table()
    assert table.scene_names == ["a", "b"]
    assert table.scene_ids().tolist() == [1, 0, 1]
    assert table.scene_ids(["b", "a", "c"]).tolist() == [0, 1, 0]
    with pytest.raises(ValueError, match="not among"):
        table.scene_ids(["a"])

    picked = table.select([2, 0])
    assert picked.img_path == ["b/2.png", "b/1.png"]
    assert picked.poses[:, 0].tolist() == [2.0, 0.0]
    assert [picked.file_line(i) for i in range(2)] == [4, 2]
    masked = table.select(np.array([False, True, False]))
    assert masked.scene == ["a"]

    both = LabelTable.concat([table, picked])
    assert len(both) == 5 and both.source == "x.csv"
    assert both.poses[:, 0].tolist() == [0.0, 1.0, 2.0, 2.0, 0.0]
    assert len(LabelTable.concat([])) == 0


def test_table_checks_lengths() -> None:
    with pytest.raises(ValueError, match="column scene has 1 rows, poses have 2"):
        LabelTable(["a"], ["t"], ["s"], ["p"] * 1, np.zeros((2, 7)))


def write_png(path: Path, value: int = 128) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full((4, 4, 3), value, dtype=np.uint8))


def test_find_image_problems(tmp_path: Path) -> None:
    root = tmp_path / "root"
    write_png(root / "s1" / "good.png")
    write_png(root / "s1" / "sub" / "good.png")
    (root / "s1" / "bad.png").write_bytes(b"\x89PNG this is not an image")
    (root / "s1" / "empty.png").write_bytes(b"")
    write_png(tmp_path / "outside.png")
    paths = [
        "s1/good.png",
        "s1/sub/../good.png",
        "s1/missing.png",
        "s1/bad.png",
        "s1/empty.png",
        "../outside.png",
        str(tmp_path / "outside.png"),
    ]
    table = LabelTable(
        scene=["s1"] * len(paths),
        split=["train"] * len(paths),
        seq=[""] * len(paths),
        img_path=paths,
        poses=np.tile([0, 0, 0, 1, 0, 0, 0], (len(paths), 1)),
        source="l.csv",
    )
    problems = find_image_problems(table, root)
    assert len(problems) == 5
    assert problems[0] == "l.csv:4: image not found: 's1/missing.png'"
    assert problems[1].startswith("l.csv:5: image is corrupt") and "s1/bad.png" in problems[1]
    assert problems[2].startswith("l.csv:6: image file is empty")
    assert problems[3].startswith("l.csv:7: image path escapes the root")
    assert "../outside.png" in problems[3]
    assert problems[4].startswith("l.csv:8: image path escapes the root")
    assert find_image_problems(table.select([0, 1]), root) == []


def test_the_orientation_column_records_each_rows_convention(tmp_path: Path) -> None:
    """pae writes ``orientation=camera_to_world`` on every row; a row marked
    ``world_to_camera`` is conjugated on reading; any other value names its row."""
    header = "scene,split,seq,img_path,t1,t2,t3,q1,q2,q3,q4,orientation\n"
    q = np.array([0.8, 0.2, -0.5, 0.26]) / np.linalg.norm([0.8, 0.2, -0.5, 0.26])
    numbers = ",".join(str(v) for v in [1.0, 2.0, 3.0, *q])
    path = tmp_path / "marked.csv"
    path.write_text(
        header + f"a,train,s,a/1.png,{numbers},camera_to_world\n"
        f"a,train,s,a/2.png,{numbers},world_to_camera\n"
    )
    table = read_labels(path)
    np.testing.assert_allclose(table.poses[0, 3:], q, atol=1e-12)
    np.testing.assert_allclose(table.poses[1, 3:], q * [1, -1, -1, -1], atol=1e-12)
    write_labels(tmp_path / "written.csv", table)
    lines = (tmp_path / "written.csv").read_text().splitlines()
    assert lines[0].endswith(",orientation") and all(
        line.endswith(",camera_to_world") for line in lines[1:]
    )
    np.testing.assert_array_equal(read_labels(tmp_path / "written.csv").poses, table.poses)
    path.write_text(header + f"a,train,s,a/1.png,{numbers},c2w\n")
    with pytest.raises(LabelError, match=r"marked.csv:2: column orientation must be"):
        read_labels(path)
