"""Starting poses from other APRs' files (pae.data.starts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pae.core.errors import ConfigError, LabelError
from pae.data.starts import match_starts, opengl_to_pae, read_starts


def test_result_lines_and_matrices_read_alike(tmp_path: Path) -> None:
    rotation = Rotation.from_euler("xyz", [10, -20, 30], degrees=True)
    q = rotation.as_quat(scalar_first=True)
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation.as_matrix(), [1.0, 2.0, 3.0]
    lines = tmp_path / "r.txt"
    lines.write_text(f"# comment\nseq-01/frame-000.color.png 1 2 3 {' '.join(map(str, q))}\n")
    grid = tmp_path / "m.txt"
    grid.write_text(f"seq-01/frame-000.color.png {' '.join(map(str, matrix.ravel()))}\n")
    a, b = read_starts(lines, form="lines"), read_starts(grid)
    assert a.names == b.names == ["seq-01/frame-000.color.png"]
    np.testing.assert_allclose(a.poses, b.poses, atol=1e-9)


def test_opengl_axes_turn_the_camera_about_x() -> None:
    q = Rotation.random(4, random_state=1)
    turned = Rotation.from_quat(opengl_to_pae(q.as_quat(scalar_first=True)), scalar_first=True)
    expected = q.as_matrix() @ np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(turned.as_matrix(), expected, atol=1e-9)


def test_matching_by_the_longest_path_suffix(tmp_path: Path) -> None:
    path = tmp_path / "r.txt"
    path.write_text("seq-01/f.png 0 0 0 1 0 0 0\nseq-02/f.png 1 0 0 1 0 0 0\n")
    starts = read_starts(path, form="lines")
    rows = match_starts(["/data/chess/seq-02/f.png", "/data/chess/seq-01/f.png"], starts, "r")
    assert rows.tolist() == [1, 0]
    with pytest.raises(ConfigError, match="1 images have no unique start"):
        match_starts(["f.png"], starts, "r")
    with pytest.raises(ConfigError, match="2 images have no unique start"):
        match_starts(["/a/seq-01/f.png", "/b/seq-01/f.png", "seq-02/f.png"], starts, "r")
    with pytest.raises(ConfigError, match=r"no start for 1 of 2 images, e\.g\. /x/g\.png"):
        match_starts(["/x/seq-01/f.png", "/x/g.png"], starts, "r")
    with pytest.raises(ConfigError, match=r"^r:2: 1 starts match no image, e\.g\. seq-02/f\.png$"):
        match_starts(["/x/seq-01/f.png"], starts, "r")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("a.png 1 2 3 0 0 0 0\n", r"r.txt:1: zero quaternion"),
        ("a.png 1 2 3 nan 0 0 1\n", r"r.txt:1: a value is NaN"),
        ("a.png 1 2 3\n", r"r.txt:1: expected 'NAME x y z qw qx qy qz' \(lines\), got 3"),
        ("a.png 1 2 x 1 0 0 0\n", r"r.txt:1: not a number"),
    ],
)
def test_bad_lines_are_named(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "r.txt"
    path.write_text(text)
    with pytest.raises(LabelError, match=message):
        read_starts(path, form="lines")


def _matrix_line(matrix: np.ndarray, name: str = "a.png") -> str:
    return f"{name} " + " ".join(f"{value:.9g}" for value in matrix.ravel()) + "\n"


def _rigid(scale: float = 1.0, shear: float = 0.0, last: float = 1.0) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    matrix[:3, :3] = matrix[:3, :3] @ np.array([[scale, shear, 0], [0, 1, 0], [0, 0, 1]])
    matrix[3, 3] = last
    return matrix


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (_matrix_line(_rigid(scale=1.2)), r"r.txt:1: not a rigid transform: .* not orthonormal"),
        (_matrix_line(_rigid(shear=0.3)), r"r.txt:1: not a rigid transform: .* not orthonormal"),
        (_matrix_line(_rigid() @ np.diag([1.0, 1.0, -1.0, 1.0])), r"r.txt:1: .* determinant -1"),
        (_matrix_line(_rigid(last=2.0)), r"r.txt:1: .* its last row is 0 0 0 2, not 0 0 0 1"),
        (
            "".join(_matrix_line(_rigid(), name) for name in ("a.png", "b.png", "a.png")),
            r"r.txt:3: image a.png repeats line 1",
        ),
    ],
)
def test_non_rigid_matrices_and_repeated_images_are_named(
    tmp_path: Path, text: str, message: str
) -> None:
    path = tmp_path / "r.txt"
    path.write_text(text)
    with pytest.raises(LabelError, match=f"^{tmp_path}/{message}"):
        read_starts(path)


LABEL_HEADER = "scene,split,seq,img_path,t1,t2,t3,q1,q2,q3,q4\n"


def _label_row(name: str, quaternion: str = "1,0,0,0") -> str:
    return f"s,test,seq-01,seq-01/{name},0,0,0,{quaternion}\n"


@pytest.mark.parametrize(
    ("second_row", "message"),
    [
        (_label_row("a.png"), r":3: image seq-01/a\.png repeats line 2$"),
        (_label_row("c.png", "nan,0,0,1"), r":3: column q1 is not finite"),
        (_label_row("c.png", "0,0,0,0"), r":3: quaternion \(q1\.\.q4\) has zero norm"),
    ],
)
def test_a_label_file_of_starts_names_its_bad_rows(
    tmp_path: Path, second_row: str, message: str
) -> None:
    """A starts file in pae's label format: a repeated image is an error (not the training
    data's warning), as is a NaN or zero quaternion, each naming the file's line."""
    import warnings

    path = tmp_path / "starts.csv"
    path.write_text(LABEL_HEADER + _label_row("a.png") + second_row)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(LabelError, match=f"^{path}{message}"):
            read_starts(path)


def test_a_start_for_no_query_names_its_line(tmp_path: Path) -> None:
    path = tmp_path / "starts.csv"
    path.write_text(LABEL_HEADER + _label_row("a.png") + _label_row("b.png"))
    message = rf"^{path}:3: 1 starts match no image, e\.g\. seq-01/b\.png$"
    with pytest.raises(ConfigError, match=message):
        match_starts(["/q/seq-01/a.png"], read_starts(path), str(path))


def test_pose_files_name_ace_poses_as_the_layout_does_and_refuse_what_they_cannot_hold(
    tmp_path: Path,
) -> None:
    from pae.data.labels import LabelTable
    from pae.data.pose_files import ace_pose_name, write_poses

    assert ace_pose_name("seq-01/frame-000000.color.png") == "seq-01-frame-000000.pose.txt"
    poses = np.tile([0.0, 0, 0, 1, 0, 0, 0], (2, 1))

    def table(paths: list[str]) -> LabelTable:
        return LabelTable(["s"] * 2, ["test"] * 2, ["q"] * 2, paths, poses)

    with pytest.raises(ConfigError, match="holds whitespace"):
        write_poses(tmp_path / "out.txt", table(["a b.png", "c.png"]), "lines")
    with pytest.raises(ConfigError, match=r"would both write poses/x-f\.pose\.txt"):
        write_poses(tmp_path / "ace", table(["x/f.png", "x/f.jpg"]), "ace")
    assert not (tmp_path / "out.txt").exists() and not (tmp_path / "ace").exists()


def _world_to_camera_line(name: str, rotation: Rotation, centre: np.ndarray) -> str:
    """hloc's line of a camera with camera-to-world ``rotation`` and ``centre``, computed as
    hloc does from COLMAP's world-to-camera pose (``x_cam = R x_world + t``)."""
    to_camera = rotation.inv()
    t = -to_camera.apply(centre)
    numbers = [*to_camera.as_quat(scalar_first=True), *t]
    return " ".join([name, *(repr(float(value)) for value in numbers)])


def test_hloc_results_read_as_world_to_camera_and_write_back(tmp_path: Path) -> None:
    """A results file as hloc's localize_sfm writes it (``name qw qx qy qz tx ty tz``,
    world-to-camera) gives the cameras' camera-to-world poses; pae-localize's --format hloc
    writes the same lines back."""
    from pae.data.labels import LabelTable
    from pae.data.pose_files import write_poses

    rotations = Rotation.random(6, random_state=3)
    centres = np.random.default_rng(3).normal(0.0, 5.0, (6, 3))
    names = [f"query/night/IMG_{i:04d}.jpg" for i in range(6)]
    path = tmp_path / "results_hloc.txt"
    lines = [
        _world_to_camera_line(n, r, c) for n, r, c in zip(names, rotations, centres, strict=True)
    ]
    path.write_text("\n".join(lines) + "\n")
    starts = read_starts(path, form="hloc")
    assert starts.names == names and starts.scenes is None
    np.testing.assert_allclose(starts.poses[:, :3], centres, atol=1e-6)
    found = Rotation.from_quat(starts.poses[:, 3:], scalar_first=True)
    np.testing.assert_allclose(found.as_matrix(), rotations.as_matrix(), atol=1e-6)

    table = LabelTable(["s"] * 6, ["query"] * 6, ["night"] * 6, names, starts.poses)
    out = tmp_path / "written.txt"
    write_poses(out, table, "hloc")
    written = [line.split() for line in out.read_text().splitlines()]
    assert [row[0] for row in written] == names  # no header: hloc's own format
    numbers = np.array([[float(v) for v in row[1:]] for row in written])
    expected = np.array([[float(v) for v in line.split()[1:]] for line in lines])
    sign = np.sign(expected[:, :1] * numbers[:, :1])  # q and -q: one rotation
    np.testing.assert_allclose(
        numbers * np.c_[np.tile(sign, 4), np.ones((6, 3))], expected, atol=1e-6
    )
    np.testing.assert_allclose(read_starts(out, form="hloc").poses, starts.poses, atol=1e-6)


def test_seven_numbers_a_line_need_a_stated_convention(tmp_path: Path) -> None:
    """Lines of 7 numbers read as camera-to-world ``x y z q`` and as hloc's world-to-camera
    ``q t`` alike: without pae's header or a stated format they are refused in one line
    naming the file and the choices; a header the stated format contradicts is refused too."""
    from pae.data.pose_files import LINES_HEADER

    bare = tmp_path / "results.txt"
    bare.write_text("# some APR\nseq-01/a.png 1 2 3 1 0 0 0\n")
    message = (
        rf"^{bare}:2: 7 numbers a line and no header stating their convention: give "
        r"--init-format lines \(NAME x y z qw qx qy qz, camera-to-world\) or --init-format "
        r"hloc \(NAME qw qx qy qz tx ty tz, world-to-camera\); formats: pae, lines, hloc, "
        r"matrix$"
    )
    with pytest.raises(ConfigError, match=message):
        read_starts(bare)
    with pytest.raises(ConfigError, match=r"or render_compare.init_format=hloc \(NAME"):
        read_starts(bare, option="render_compare.init_format={}")
    assert read_starts(bare, form="lines").poses[0, :3].tolist() == [1.0, 2.0, 3.0]

    headed = tmp_path / "pae_lines.txt"
    headed.write_text(LINES_HEADER + "seq-01/a.png 1 2 3 1 0 0 0\n")
    assert read_starts(headed).poses[0, :3].tolist() == [1.0, 2.0, 3.0]
    with pytest.raises(ConfigError, match=rf"^{headed}: --init-format hloc, but its header "):
        read_starts(headed, form="hloc")
    labels = tmp_path / "starts.csv"
    labels.write_text(LABEL_HEADER + _label_row("a.png"))
    with pytest.raises(ConfigError, match=rf"^{labels}: --init-format lines, but .* pae format$"):
        read_starts(labels, form="lines")
    with pytest.raises(ConfigError, match=rf"^{bare}: --init-format pae, but it has no label"):
        read_starts(bare, form="pae")
    assert read_starts(labels, form="pae").names == ["seq-01/a.png"]
