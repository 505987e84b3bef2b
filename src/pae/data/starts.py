"""Starting poses from any APR (``pae-localize --init FILE``, ``pae-eval
render_compare.init=FILE``): a pae label file, or the field's result files (:data:`FORMATS`:
``name x y z qw qx qy qz`` camera-to-world, hloc's ``name qw qx qy qz tx ty tz``
world-to-camera, or ``name`` and a row-major 4×4 camera-to-world matrix), matched to the
queries by the longest common path suffix. Lines of 7 numbers read either way, so a file of
them must state its convention: pae's header (``pae-localize --format lines``) or the
format given with the file (``--init-format``)."""

from __future__ import annotations

import warnings
from collections import Counter
from collections.abc import Sequence
from pathlib import Path, PurePath
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from pae.core.errors import ConfigError, LabelError, RepeatedImageWarning
from pae.core.geometry import matrix_to_quaternion
from pae.data.colmap import camera_to_world
from pae.data.labels import LABEL_COLUMNS, read_labels
from pae.data.pose_files import LINES_CONVENTION
from pae.data.raw import rigid_problem

AXES = ("pae", "opengl")
"""The camera axes of a starts file: pae's (x right, y down, z forward) or OpenGL's (x right,
y up, z backward: DFNet's and NeFeS's result files)."""
FORMATS = ("pae", "lines", "hloc", "matrix")
"""What a starts file holds: ``pae``, a pae label file (its header names the columns);
``lines``, ``NAME x y z qw qx qy qz`` (camera-to-world, ``pae-localize --format lines``);
``hloc``, ``NAME qw qx qy qz tx ty tz`` (world-to-camera, ``x_cam = R(q) x_world + t``, as
hloc's ``localize_sfm`` and COLMAP's ``images.txt`` write it); ``matrix``, ``NAME`` and a
row-major 4×4 camera-to-world matrix."""
LAYOUTS = {
    "lines": "NAME x y z qw qx qy qz",
    "hloc": "NAME qw qx qy qz tx ty tz",
    "matrix": "NAME and a row-major 4x4 matrix (16 numbers)",
}
"""The line of each line format."""
COUNTS = {"lines": 7, "hloc": 7, "matrix": 16}
"""The numbers after the name on a line of each line format."""
SHOWN = 5
"""How many unmatched names an error lists."""


class Starts(NamedTuple):
    """Poses [N, 7] (camera-to-world, pae's axes) by image name, their scenes where the file
    names them (else None), the file's line of each and the recording each frame came from
    where the file has a column of them (a pae label file's ``seq``; else None)."""

    names: list[str]
    poses: np.ndarray
    scenes: list[str] | None
    lines: list[int]
    recordings: list[str] | None = None


def opengl_to_pae(quaternions: np.ndarray) -> np.ndarray:
    """Camera-to-world quaternions [N, 4] of cameras with OpenGL axes -> the same cameras with
    pae's axes (the rotation turned by 180° about the camera's x axis: q ⊗ (0, 1, 0, 0))."""
    w, x, y, z = quaternions.T
    return np.stack([-x, w, z, -y], 1)


def _line_numbers(tokens: list[str], path: Path, line: int) -> np.ndarray:
    """The numbers after a line's name [K]; LabelError naming the line if one is not a finite
    number."""
    try:
        numbers = np.array([float(token) for token in tokens[1:]])
    except ValueError as error:
        raise LabelError(path, line, f"not a number: {error}") from None
    if not np.isfinite(numbers).all():
        raise LabelError(path, line, "a value is NaN or infinite")
    return numbers


def _line_pose(numbers: np.ndarray, form: str, path: Path, line: int) -> np.ndarray:
    """The camera-to-world pose [7] of a line's ``numbers`` in the line format ``form``."""
    if form == "matrix":
        matrix = numbers.reshape(4, 4)
        problem = rigid_problem(matrix)
        if problem is not None:
            raise LabelError(path, line, problem)
        rotation = torch.from_numpy(matrix[:3, :3])
        return np.concatenate([matrix[:3, 3], matrix_to_quaternion(rotation).numpy()])
    quaternion = numbers[:4] if form == "hloc" else numbers[3:]
    if float(np.linalg.norm(quaternion)) < 1e-8:
        raise LabelError(path, line, "zero quaternion")
    if form == "hloc":
        return camera_to_world(numbers[None, :4], numbers[None, 4:])[0]
    return np.concatenate([numbers[:3], quaternion / np.linalg.norm(quaternion)])


def _stated_format(path: Path, first: str, form: str | None, option: str) -> str | None:
    """The format of the file at ``path`` whose first line is ``first``: the one its header
    states (a pae label file's, or ``pae-localize --format lines``'s), which ``form`` (the
    user's, None: not given) must not contradict, else ``form``."""
    if first.replace(" ", "").startswith(",".join(LABEL_COLUMNS[:4])):
        header = "pae"
    elif first.startswith(LINES_CONVENTION):
        header = "lines"
    else:
        header = None
    if form is not None and form not in FORMATS:
        raise ConfigError(f"{option.format(form)}: choose one of {FORMATS}")
    if header is not None and form not in (None, header):
        raise ConfigError(
            f"{path}: {option.format(form)}, but its header states the {header} format"
        )
    if form == "pae" and header is None:
        raise ConfigError(
            f"{path}: {option.format(form)}, but it has no label-file header "
            f"({','.join(LABEL_COLUMNS)})"
        )
    return header or form


def _lines(
    text: str, path: Path, form: str | None, option: str
) -> tuple[list[str], np.ndarray, list[int]]:
    """Names, camera-to-world poses [N, 7] and line numbers of a file of pose lines in the
    format ``form`` (None: not stated, then lines of 16 numbers are matrices and lines of 7 a
    ConfigError naming the line and the choices)."""
    names, rows, lines = [], [], []
    for line, row_text in enumerate(text.splitlines(), start=1):
        tokens = row_text.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        numbers = _line_numbers(tokens, path, line)
        if form is None:
            if len(numbers) == 7:
                raise ConfigError(
                    f"{path}:{line}: 7 numbers a line and no header stating their convention: "
                    f"give {option.format('lines')} ({LAYOUTS['lines']}, camera-to-world) or "
                    f"{option.format('hloc')} ({LAYOUTS['hloc']}, world-to-camera); formats: "
                    f"{', '.join(FORMATS)}"
                )
            if len(numbers) != COUNTS["matrix"]:
                raise LabelError(
                    path,
                    line,
                    f"expected '{LAYOUTS['matrix']}', or 7 numbers in a stated format "
                    f"({option.format('lines')} or hloc), got {len(numbers)} numbers",
                )
            form = "matrix"
        if len(numbers) != COUNTS[form]:
            raise LabelError(
                path, line, f"expected '{LAYOUTS[form]}' ({form}), got {len(numbers)} numbers"
            )
        names.append(tokens[0])
        rows.append(_line_pose(numbers, form, path, line))
        lines.append(line)
    if not rows:
        raise LabelError(path, None, "no poses")
    return names, np.stack(rows), lines


def read_starts(
    path: str | Path, axes: str = "pae", form: str | None = None, option: str = "--init-format {}"
) -> Starts:
    """The starting poses in ``path``: a pae label file (its ``img_path`` and ``scene``
    columns), or pose lines (``#`` comments and blank lines skipped) in the format ``form``
    (:data:`FORMATS`; None: the one the file's header states, else 4×4 matrices); ``axes``:
    the camera axes of the file's orientations (``AXES``); ``option``: how errors name the
    format's setting, ``{}`` for its value. A NaN or zero quaternion, a matrix that is not a
    rigid transform or an image named twice is a LabelError naming the file's line; lines of
    7 numbers of no stated format, or a format the header contradicts, a ConfigError naming
    the file."""
    path = Path(path)
    if axes not in AXES:
        raise ConfigError(f"--init-axes {axes!r}: choose one of {AXES}")
    if not path.is_file():
        raise ConfigError(f"{path}: no such starts file")
    text = path.read_text()
    form = _stated_format(path, text.lstrip().split("\n", 1)[0], form, option)
    if form == "pae":
        with warnings.catch_warnings():  # a repeated image is an error here, not a warning
            warnings.simplefilter("ignore", RepeatedImageWarning)
            table = read_labels(path)
        names, poses, scenes = list(table.img_path), table.poses.copy(), list(table.scene)
        lines = [table.file_line(row) for row in range(len(names))]
        recordings = list(table.seq)
    else:
        (names, poses, lines), scenes = _lines(text, path, form, option), None
        recordings = None
    first_line: dict[str, int] = {}
    for name, line in zip(names, lines, strict=True):
        if name in first_line:
            raise LabelError(path, line, f"image {name} repeats line {first_line[name]}")
        first_line[name] = line
    if axes == "opengl":
        poses[:, 3:] = opengl_to_pae(poses[:, 3:])
    return Starts(names, poses, scenes, lines, recordings)


def _parts(name: str) -> tuple[str, ...]:
    return tuple(reversed(PurePath(name.replace("\\", "/")).parts))


def _common(a: tuple[str, ...], b: tuple[str, ...]) -> int:
    count = 0
    for x, y in zip(a, b, strict=False):
        if x != y:
            break
        count += 1
    return count


def match_starts(images: Sequence[str], starts: Starts, source: str) -> np.ndarray:
    """Row of ``starts`` for each image path [N]: the start whose name shares the longest
    path suffix with it (at least the file name; a start fitting several images goes to the
    one it fits best); a ConfigError naming the first few images without a start, or starts
    without an image, or images two starts fit equally well."""
    by_file: dict[str, list[int]] = {}
    keys = [_parts(name) for name in starts.names]
    for row, key in enumerate(keys):
        by_file.setdefault(key[0], []).append(row)
    rows, lengths, ambiguous = [], [], []
    for image in images:
        key = _parts(image)
        candidates = by_file.get(key[0], [])
        common = [_common(key, keys[row]) for row in candidates]
        best = max(common, default=0)
        if common.count(best) > 1:
            ambiguous.append(image)
        rows.append(candidates[common.index(best)] if candidates else -1)
        lengths.append(best)
    # a start taken by several images belongs to the one it fits best; the others have none
    best_fit: dict[int, int] = {}
    for row, length in zip(rows, lengths, strict=True):
        best_fit[row] = max(best_fit.get(row, 0), length)
    missing, taken = [], Counter()
    for image, row, length in zip(images, rows, lengths, strict=True):
        if row < 0 or length < best_fit[row]:
            missing.append(image)
        else:
            taken[row] += 1
    ambiguous += [
        image for image, row in zip(images, rows, strict=True) if row >= 0 and taken[row] > 1
    ]
    if missing:
        raise ConfigError(
            f"{source}: no start for {len(missing)} of {len(images)} images, e.g. "
            + ", ".join(missing[:SHOWN])
        )
    if ambiguous:
        raise ConfigError(
            f"{source}: {len(ambiguous)} images have no unique start (two fit equally well), e.g. "
            + ", ".join(ambiguous[:SHOWN])
        )
    unused = sorted(set(range(len(keys))) - set(rows))
    if unused:
        names = [starts.names[row] for row in unused[:SHOWN]]
        raise ConfigError(
            f"{source}:{starts.lines[unused[0]]}: {len(unused)} starts match no image, e.g. "
            + ", ".join(names)
        )
    return np.asarray(rows)


def placed_starts(
    images: Sequence[str], starts: Starts, source: str, scene_names: Sequence[str]
) -> tuple[Tensor, Tensor | None]:
    """The starting poses [N, 7] of ``images`` from ``starts`` (read from the file
    ``source``), and their scene ids [N] into ``scene_names`` where the file names scenes
    (None otherwise)."""
    rows = match_starts(images, starts, source)
    poses = torch.as_tensor(starts.poses[rows], dtype=torch.float32)
    if starts.scenes is None:
        return poses, None
    unknown = sorted({starts.scenes[r] for r in rows} - set(scene_names))
    if unknown:
        raise ConfigError(f"{source}: scenes {unknown} are not the run's {list(scene_names)}")
    scene = torch.as_tensor([list(scene_names).index(starts.scenes[r]) for r in rows])
    return poses, scene


def starts_for(
    images: Sequence[str],
    path: str | Path,
    scene_names: Sequence[str],
    axes: str = "pae",
    form: str | None = None,
) -> tuple[Tensor, Tensor | None]:
    """:func:`placed_starts` of the file at ``path`` (:func:`read_starts`)."""
    return placed_starts(images, read_starts(path, axes, form), str(path), scene_names)
