"""Poses out in the files other tools read (``pae-localize --format``): pae's label CSV, the
field's result-file lines (``name x y z qw qx qy qz``, as HR-APR's and NeFeS's result files
and ``pae-localize --init`` read them), hloc's results (``name qw qx qy qz tx ty tz``,
world-to-camera, as ``localize_sfm`` writes them and localisation benchmarks take them) and
the ACE / DSAC* layout's ``poses/`` folder (one 4×4 camera-to-world matrix per image). All in
metres and pae's camera axes (x right, y down, z forward), camera-to-world but hloc's; each
file written atomically."""

from __future__ import annotations

from pathlib import Path, PurePosixPath

import numpy as np
import torch

from pae.core.atomic import atomic_write
from pae.core.errors import ConfigError
from pae.core.geometry import quaternion_to_matrix
from pae.data.colmap import camera_to_world
from pae.data.labels import LabelTable, write_labels

FORMATS = ("csv", "lines", "hloc", "ace")
"""``csv``: a pae label file; ``lines``: one ``name x y z qw qx qy qz`` line per image
(camera-to-world); ``hloc``: one ``name qw qx qy qz tx ty tz`` line per image
(world-to-camera, no header); ``ace``: ``OUT/poses/<name>.pose.txt``, a 4×4 camera-to-world
matrix per image."""
LINES_CONVENTION = "# name x y z qw qx qy qz: camera-to-world"
"""How the header of a ``lines`` file begins: what ``pae-localize --init`` knows it by."""
LINES_HEADER = (
    f"{LINES_CONVENTION}, metres; camera axes x right, y down, z forward (read with "
    "pae-localize --init FILE --init-axes pae)\n"
)


def pose_matrices(poses: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [N, 7] (x y z qw qx qy qz) -> 4×4 matrices [N, 4, 4]."""
    matrices = np.zeros((len(poses), 4, 4))
    rotation = quaternion_to_matrix(torch.from_numpy(np.asarray(poses, dtype=np.float64)[:, 3:]))
    matrices[:, :3, :3] = rotation.numpy()
    matrices[:, :3, 3] = poses[:, :3]
    matrices[:, 3, 3] = 1.0
    return matrices


def ace_pose_name(img_path: str) -> str:
    """The ACE pose file of an image: its path's folders and name joined by ``-``, without its
    extension and a ``.color`` suffix, then ``.pose.txt`` (``seq-01/frame-000000.color.png``
    -> ``seq-01-frame-000000.pose.txt``, the layout's own naming)."""
    path = PurePosixPath(img_path.replace("\\", "/"))
    stem = path.name.split(".")[0]
    parts = [part for part in path.parent.parts if part not in ("/", "..", ".")]
    return "-".join([*parts, stem]) + ".pose.txt"


def world_to_camera(poses: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [N, 7] (``x y z qw qx qy qz``) -> world-to-camera ``qw qx qy qz
    tx ty tz`` [N, 7] (``q = conj(q_c2w)``, ``qw >= 0``; ``t = -R(q) c``), hloc's and
    COLMAP's order."""
    inverse = camera_to_world(poses[:, 3:], poses[:, :3])  # a rigid transform's inverse alike
    return np.concatenate([inverse[:, 3:], inverse[:, :3]], axis=1)


def write_pose_lines(path: str | Path, table: LabelTable, form: str = "lines") -> None:
    """``table``'s poses as result-file lines: ``lines``, camera-to-world after a header
    stating the convention, or ``hloc``, world-to-camera without a header (as hloc writes
    them); an image path holding whitespace (the lines split on it) is a ConfigError naming
    it."""
    spaced = [name for name in table.img_path if len(name.split()) != 1]
    if spaced:
        raise ConfigError(
            f"--format {form}: image path {spaced[0]!r} holds whitespace, which the format "
            "separates fields with; write --format csv"
        )
    poses = world_to_camera(table.poses) if form == "hloc" else table.poses
    with atomic_write(path, newline="\n", encoding="utf-8") as handle:
        if form == "lines":
            handle.write(LINES_HEADER)
        for name, pose in zip(table.img_path, poses.tolist(), strict=True):
            handle.write(" ".join([name, *map(repr, pose)]) + "\n")


def write_ace_poses(folder: str | Path, table: LabelTable) -> None:
    """``table``'s poses as ``folder/poses/<name>.pose.txt`` (:func:`ace_pose_name`), one
    4×4 camera-to-world matrix per image; two images with one pose file name are a
    ConfigError naming both, before anything is written."""
    names = [ace_pose_name(path) for path in table.img_path]
    first: dict[str, str] = {}
    for name, image in zip(names, table.img_path, strict=True):
        if name in first:
            raise ConfigError(
                f"--format ace: {first[name]} and {image} would both write poses/{name}"
            )
        first[name] = image
    poses = Path(folder) / "poses"
    for name, matrix in zip(names, pose_matrices(table.poses), strict=True):
        with atomic_write(poses / name, encoding="utf-8") as handle:
            handle.write("\n".join(" ".join(map(repr, row)) for row in matrix.tolist()) + "\n")


def write_poses(out: str | Path, table: LabelTable, form: str) -> None:
    """``table`` written to ``out`` in the format ``form`` (:data:`FORMATS`)."""
    if form == "csv":
        write_labels(out, table)
    elif form in ("lines", "hloc"):
        write_pose_lines(out, table, form)
    elif form == "ace":
        write_ace_poses(out, table)
    else:
        raise ConfigError(f"--format {form!r}: choose one of {FORMATS}")
