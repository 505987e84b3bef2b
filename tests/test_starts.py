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
    a, b = read_starts(lines), read_starts(grid)
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
    starts = read_starts(path)
    rows = match_starts(["/data/chess/seq-02/f.png", "/data/chess/seq-01/f.png"], starts, "r")
    assert rows.tolist() == [1, 0]
    with pytest.raises(ConfigError, match="1 images have no unique start"):
        match_starts(["f.png"], read_starts(path), "r")
    with pytest.raises(ConfigError, match="2 images have no unique start"):
        match_starts(["/a/seq-01/f.png", "/b/seq-01/f.png", "seq-02/f.png"], starts, "r")
    with pytest.raises(ConfigError, match=r"no start for 1 of 2 images, e\.g\. /x/g\.png"):
        match_starts(["/x/seq-01/f.png", "/x/g.png"], starts, "r")
    with pytest.raises(ConfigError, match=r"1 starts match no image, e\.g\. seq-02/f\.png"):
        match_starts(["/x/seq-01/f.png"], starts, "r")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("a.png 1 2 3 0 0 0 0\n", r"r.txt:1: zero quaternion"),
        ("a.png 1 2 3 nan 0 0 1\n", r"r.txt:1: a value is NaN"),
        ("a.png 1 2 3\n", r"r.txt:1: expected 'NAME x y z qw qx qy qz'"),
        ("a.png 1 2 x 1 0 0 0\n", r"r.txt:1: not a number"),
    ],
)
def test_bad_lines_are_named(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "r.txt"
    path.write_text(text)
    with pytest.raises(LabelError, match=message):
        read_starts(path)
