"""kapture folders (NAVER LABS' format) of one scene as frames (``pae-data convert kapture
ROOT OUT_DIR``), read from their text files (the ``kapture`` package is not needed)::

    ROOT/mapping/sensors/sensors.txt          id, name, camera, MODEL, w, h, params... (px)
    ROOT/mapping/sensors/records_camera.txt   timestamp, camera id, image path
    ROOT/mapping/sensors/trajectories.txt     timestamp, device id, qw, qx, qy, qz, tx, ty, tz
    ROOT/mapping/sensors/records_data/...     the images (the paths above are relative to it)
    ROOT/query/sensors/...                    the same for the test split

The train and test splits are two kapture folders under ROOT (``mapping`` and ``query`` as
kapture-localization lays them out; ``--train`` and ``--test`` name others); ``img_path`` is
relative to ROOT (``mapping/sensors/records_data/...``) and a frame's sequence is its image's
folder under ``records_data/``. Lines are comma-separated (spaces around a comma ignored),
``#`` starts a comment; other sensors, records and ``reconstruction/`` are not read. A pose is
world-to-camera, as COLMAP's: ``q_c2w = conj(q)``, centre ``-R(q)^T t``. kapture's cameras
are COLMAP's models with the image size first, and COLMAP's pixel convention (top-left pixel
centre at ``(0.5, 0.5)``): the principal point is moved by ``-0.5`` px to pae's
(``CORNER_CENTRE_PX``), as :mod:`pae.data.colmap` does; pinhole cameras only (or distorted
ones whose distortion is zero). Poses of camera rigs (``rigs.txt``) are not read: each image
needs its own camera's trajectory.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pae.core.errors import LabelError
from pae.data.colmap import ColmapCamera, ColmapModel, checked_camera, model_frames
from pae.data.converted import SceneFrames, sequence_of
from pae.data.holdout import natural_key
from pae.data.raw import parse_numbers

__all__ = ["read_kapture_scene"]

UNDISTORT = (
    "export the kapture to COLMAP (kapture_export_colmap.py), undistort it with colmap "
    "image_undistorter and convert that with pae-data convert colmap"
)
"""How to turn distorted kapture cameras into pinhole ones."""


def _rows(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, comma-separated fields stripped of spaces) of every line of a kapture
    text file that is neither blank nor a ``#`` comment; LabelError if the file is missing."""
    if not path.is_file():
        raise LabelError(path, None, "file not found (a kapture folder holds sensors/*.txt)")
    rows = []
    text = path.read_text(encoding="utf-8", errors="replace")
    for number, line in enumerate(text.splitlines(), start=1):
        if line.strip() and not line.lstrip().startswith("#"):
            rows.append((number, [field.strip() for field in line.split(",")]))
    return rows


def _timestamp(field: str, path: Path, line: int) -> int:
    """A record's timestamp (an integer); LabelError naming ``path:line`` otherwise."""
    try:
        return int(field)
    except ValueError:
        raise LabelError(path, line, f"timestamp {field!r} is not an integer") from None


def _cameras(path: Path, first_id: int) -> dict[str, ColmapCamera]:
    """The cameras of ``sensors.txt`` by sensor id, numbered from ``first_id``; other sensor
    types are skipped. LabelError (ValueError) naming the line of a malformed or repeated
    camera."""
    cameras: dict[str, ColmapCamera] = {}
    for line, fields in _rows(path):
        if len(fields) < 3:
            raise LabelError(path, line, "expected 'sensor_device_id, name, sensor_type, ...'")
        if fields[2] != "camera":
            continue
        if len(fields) < 6:
            raise LabelError(path, line, "expected 'id, name, camera, MODEL, width, height, ...'")
        if fields[0] in cameras:
            raise LabelError(path, line, f"camera {fields[0]} is listed twice")
        width, height, *params = parse_numbers(fields[4:], path, line)
        if width != int(width) or height != int(height) or min(width, height) < 1:
            raise LabelError(path, line, f"image size {width:g}x{height:g} px is not whole")
        where = f"{path}:{line}: camera {fields[0]}"
        size = (int(width), int(height))
        cameras[fields[0]] = checked_camera(first_id + len(cameras), fields[3], size, params, where)
    return cameras


def _trajectories(path: Path) -> dict[tuple[int, str], list[float]]:
    """World-to-device ``qw, qx, qy, qz, tx, ty, tz`` [7] by (timestamp, device id);
    LabelError naming the line of a malformed pose, a zero quaternion or a repeated key."""
    poses: dict[tuple[int, str], list[float]] = {}
    for line, fields in _rows(path):
        if len(fields) != 9:
            raise LabelError(
                path, line, "expected 'timestamp, device_id, qw, qx, qy, qz, tx, ty, tz'"
            )
        key = (_timestamp(fields[0], path, line), fields[1])
        pose = parse_numbers(fields[2:], path, line)
        if np.linalg.norm(pose[:4]) < 1e-8:
            raise LabelError(path, line, "quaternion has zero norm")
        if key in poses:
            raise LabelError(path, line, f"a second pose for timestamp {key[0]}, {key[1]}")
        poses[key] = pose
    return poses


def _split_model(root: Path, folder: str, first_id: int) -> tuple[ColmapModel, list[str]]:
    """The camera records of the kapture ``root/folder`` in image-path order as a model
    (names relative to ``root``; camera ids numbered from ``first_id``) and each one's
    sequence. LabelError naming the file and line of a record whose camera or pose is
    missing."""
    sensors = root / folder / "sensors"
    if not sensors.is_dir():
        found = sorted(p.name for p in root.iterdir() if (p / "sensors").is_dir())
        raise LabelError(sensors, None, f"not found: ROOT's kapture folders are {found or 'none'}")
    cameras = _cameras(sensors / "sensors.txt", first_id)
    poses = _trajectories(sensors / "trajectories.txt")
    records_file = sensors / "records_camera.txt"
    records = []
    for line, fields in _rows(records_file):
        if len(fields) != 3 or not fields[2]:
            raise LabelError(records_file, line, "expected 'timestamp, device_id, image_path'")
        timestamp, device, image = _timestamp(fields[0], records_file, line), *fields[1:]
        if device not in cameras:
            raise LabelError(records_file, line, f"{device} is not a camera of sensors.txt")
        if (timestamp, device) not in poses:
            rigs = " (rig poses are not read)" if (sensors / "rigs.txt").is_file() else ""
            raise LabelError(
                records_file,
                line,
                f"no pose of {device} at timestamp {timestamp} in trajectories.txt{rigs}",
            )
        records.append((image, cameras[device].camera_id, poses[(timestamp, device)], line))
    if not records:
        raise LabelError(records_file, None, "no images")
    records.sort(key=lambda record: natural_key(record[0]))
    pose_table = np.array([record[2] for record in records], dtype=np.float64)
    model = ColmapModel(
        cameras={camera.camera_id: camera for camera in cameras.values()},
        names=[f"{folder}/sensors/records_data/{record[0]}" for record in records],
        camera_ids=np.array([record[1] for record in records], dtype=np.int64),
        rotations=pose_table[:, :4],
        translations=pose_table[:, 4:],
        origins=[f"{records_file}:{record[3]}" for record in records],
    )
    return model, [sequence_of(record[0]) for record in records]


def read_kapture_scene(
    root: str | os.PathLike[str], train: str = "mapping", test: str = "query"
) -> SceneFrames:
    """The frames of the kapture folders ``root/train`` (the train split) and ``root/test``
    (the test split), each in image-path order, ``img_path`` relative to ``root``,
    camera-to-world poses in the kapture's units, principal points in pae's pixel
    convention. ValueError (LabelError), one line naming the file and line, for a missing
    folder or file, a malformed line, a record without its camera or pose, and what
    :func:`pae.data.colmap.model_frames` refuses (a distorted camera, ``fx != fy``, images
    of several sizes, a missing image)."""
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"{root}: ROOT is not a directory")
    if train == test:
        raise ValueError(f"--train and --test name one kapture folder ({train})")
    train_model, train_seqs = _split_model(root, train, 0)
    test_model, test_seqs = _split_model(root, test, len(train_model.cameras))
    models = (train_model, test_model)
    model = ColmapModel(
        cameras={**train_model.cameras, **test_model.cameras},
        names=[name for m in models for name in m.names],
        camera_ids=np.concatenate([m.camera_ids for m in models]),
        rotations=np.concatenate([m.rotations for m in models]),
        translations=np.concatenate([m.translations for m in models]),
        origins=[origin for m in models for origin in m.origins],
    )
    split = ["train"] * len(train_model.names) + ["test"] * len(test_model.names)
    return model_frames(model, root, split, train_seqs + test_seqs, UNDISTORT)
