"""COLMAP sparse models (``cameras`` and ``images``, text or binary) as one scene's frames.

A model folder (``sparse/0``, or the ``sparse`` folder ``colmap image_undistorter`` writes)
holds ``cameras.bin`` / ``cameras.txt`` (one camera model, size and parameters per camera id)
and ``images.bin`` / ``images.txt`` (each registered image's world-to-camera rotation
``QW QX QY QZ``, translation ``TX TY TZ``, camera id and name relative to the image folder);
binary files are read where both exist, as COLMAP does, and ``points3D`` is not needed. The
camera frame is pae's (x right, y down, z forward); each pose is turned camera-to-world:
``q_c2w = conj(q)``, centre ``-R(q)^T t``. COLMAP puts the centre of the top-left pixel at
``(0.5, 0.5)`` and pae at ``(0, 0)``: the principal point is moved by ``-0.5`` px on both axes
(``CORNER_CENTRE_PX``; COLMAP's image centre ``W/2`` is pae's ``(W - 1)/2``).

pae renders and compares with pinhole cameras: ``SIMPLE_PINHOLE`` and ``PINHOLE`` are read as
they are, ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV`` and ``FULL_OPENCV`` only with zero
distortion; other cameras are refused with the ``colmap image_undistorter`` command that
writes an undistorted model and images.
"""

from __future__ import annotations

import dataclasses
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pae.core.errors import LabelError
from pae.core.quaternion_sign import canonical_sign
from pae.data.converted import CORNER_CENTRE_PX, SceneFrames, sequence_of, unequal_focal_lengths
from pae.data.holdout import natural_key
from pae.data.orientation import conjugate

__all__ = ["CAMERA_MODELS", "ColmapCamera", "ColmapModel", "read_colmap_model", "read_colmap_scene"]

CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    12: ("SIMPLE_DIVISION", 4),
    13: ("DIVISION", 5),
    14: ("SIMPLE_FISHEYE", 3),
    15: ("FISHEYE", 4),
    16: ("EUCM", 6),
    17: ("EQUIRECTANGULAR", 2),
}
"""COLMAP's camera model ids -> (name, number of parameters)."""
_PARAMETER_COUNTS = dict(CAMERA_MODELS.values())
_ONE_FOCAL = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
"""Parameters ``f, cx, cy, distortion...``."""
_TWO_FOCAL = ("PINHOLE", "OPENCV", "FULL_OPENCV")
"""Parameters ``fx, fy, cx, cy, distortion...``."""
_CAMERA_RECORD = struct.Struct("<iiQQ")
_IMAGE_RECORD = struct.Struct("<I7dI")
_COUNT = struct.Struct("<Q")
_POINT2D_BYTES = 24
"""x, y (float64) and a point id (int64) per 2-D point of an image record."""


@dataclass(frozen=True)
class ColmapCamera:
    """One camera of a model: ``model`` name, ``width × height`` px, ``params`` as COLMAP
    orders them; ``origin`` names its file and entry for messages."""

    camera_id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]
    origin: str


@dataclass(frozen=True)
class ColmapModel:
    """A model's cameras by id and its registered images: ``names`` [N] relative to the image
    folder, ``camera_ids`` [N], world-to-camera ``rotations`` [N, 4] (``qw, qx, qy, qz``) and
    ``translations`` [N, 3]; ``origins`` [N] name each image's file and entry."""

    cameras: dict[int, ColmapCamera]
    names: list[str]
    camera_ids: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    origins: list[str]


def _model_file(model_dir: Path, stem: str) -> Path:
    """``stem``.bin in ``model_dir``, else ``stem``.txt; LabelError naming the folder if neither."""
    for suffix in (".bin", ".txt"):
        if (model_dir / f"{stem}{suffix}").is_file():
            return model_dir / f"{stem}{suffix}"
    raise LabelError(
        model_dir, None, f"no {stem}.bin or {stem}.txt: not a COLMAP model folder (e.g. sparse/0)"
    )


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of every line of a text model file, comments included."""
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    return [(number, text.strip()) for number, text in enumerate(lines, start=1)]


def _numbers(tokens: Sequence[str], where: str) -> list[float]:
    """Finite floats of ``tokens``; ValueError naming ``where`` (file, line, entry) otherwise."""
    try:
        values = [float(token) for token in tokens]
    except ValueError:
        raise ValueError(f"{where}: not a number in {' '.join(tokens)!r}") from None
    return _finite(values, where)


def _finite(values: Sequence[float], where: str) -> list[float]:
    """``values`` as a list; ValueError naming ``where`` if one is NaN or infinite."""
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{where}: not finite: {' '.join(f'{v:g}' for v in values)}")
    return list(values)


def checked_camera(
    camera_id: int, model: str, size: tuple[int, int], params: Sequence[float], where: str
) -> ColmapCamera:
    """A checked camera (``where`` names its file, line and id): its model known and its
    parameter count that model's."""
    if model not in _PARAMETER_COUNTS:
        raise ValueError(f"{where}: unknown camera model {model}")
    if len(params) != _PARAMETER_COUNTS[model]:
        raise ValueError(
            f"{where}: {model} has {_PARAMETER_COUNTS[model]} parameters, got {len(params)}"
        )
    return ColmapCamera(camera_id, model, *size, tuple(params), where)


def _read_cameras_text(path: Path) -> dict[int, ColmapCamera]:
    cameras = {}
    for line, text in _data_lines(path):
        if not text or text.startswith("#"):
            continue
        tokens = text.split()
        if len(tokens) < 4 or not all(t.isdigit() for t in (tokens[0], tokens[2], tokens[3])):
            raise LabelError(path, line, "expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'")
        params = _numbers(tokens[4:], f"{path}:{line}: camera {tokens[0]}")
        size = (int(tokens[2]), int(tokens[3]))
        where = f"{path}:{line}: camera {tokens[0]}"
        cameras[int(tokens[0])] = checked_camera(int(tokens[0]), tokens[1], size, params, where)
    return cameras


def _read_cameras_binary(path: Path) -> dict[int, ColmapCamera]:
    data, cameras = path.read_bytes(), {}
    offset = 0
    try:
        (count,), offset = _COUNT.unpack_from(data, 0), _COUNT.size
        for _ in range(count):
            camera_id, model_id, width, height = _CAMERA_RECORD.unpack_from(data, offset)
            offset += _CAMERA_RECORD.size
            if model_id not in CAMERA_MODELS:
                raise LabelError(
                    path, None, f"camera {camera_id}: unknown camera model id {model_id}"
                )
            model, n_params = CAMERA_MODELS[model_id]
            params = struct.unpack_from(f"<{n_params}d", data, offset)
            offset += 8 * n_params
            values = _finite(params, f"{path}: camera {camera_id}")
            where = f"{path}: camera {camera_id}"
            cameras[camera_id] = checked_camera(camera_id, model, (width, height), values, where)
    except struct.error:
        raise LabelError(
            path, None, f"ends early (byte {offset}): not a COLMAP cameras.bin"
        ) from None
    return cameras


def _read_images_text(path: Path) -> list[tuple[int, list[float], int, str, str]]:
    """(image id, q and t [7], camera id, name, origin) per image: two lines each, the second
    (its 2-D points, possibly empty) skipped."""
    images = []
    lines = iter(_data_lines(path))
    for line, text in lines:
        if not text or text.startswith("#"):
            continue
        tokens = text.split()
        if len(tokens) < 10 or not tokens[0].isdigit() or not tokens[8].isdigit():
            raise LabelError(path, line, "expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'")
        pose = _numbers(tokens[1:8], f"{path}:{line}: image {tokens[0]} ({' '.join(tokens[9:])})")
        images.append(
            (int(tokens[0]), pose, int(tokens[8]), " ".join(tokens[9:]), f"{path}:{line}")
        )
        next(lines, None)
    return images


def _read_images_binary(path: Path) -> list[tuple[int, list[float], int, str, str]]:
    data, images = path.read_bytes(), []
    offset = 0
    try:
        (count,), offset = _COUNT.unpack_from(data, 0), _COUNT.size
        for _ in range(count):
            image_id, *pose, camera_id = _IMAGE_RECORD.unpack_from(data, offset)
            offset += _IMAGE_RECORD.size
            end = data.find(b"\x00", offset)
            if end < 0:
                raise struct.error
            name = data[offset:end].decode("utf-8", errors="replace")
            offset = end + 1
            (n_points,) = _COUNT.unpack_from(data, offset)
            offset += _COUNT.size + _POINT2D_BYTES * n_points
            if offset > len(data):
                raise struct.error
            values = _finite(pose, f"{path}: image {image_id} ({name})")
            images.append((image_id, values, camera_id, name, str(path)))
    except struct.error:
        raise LabelError(
            path, None, f"ends early (byte {offset}): not a COLMAP images.bin"
        ) from None
    return images


def read_colmap_model(model_dir: str | os.PathLike[str]) -> ColmapModel:
    """The cameras and registered images of the model in ``model_dir`` (binary files where
    they exist, else text). ValueError, one line naming the file and entry, for a folder
    without a model, a model without images, a malformed or unknown camera, an image whose
    camera is missing or whose quaternion is zero, and a name given to two images."""
    model_dir = Path(model_dir)
    cameras_file, images_file = _model_file(model_dir, "cameras"), _model_file(model_dir, "images")
    binary_cameras = cameras_file.suffix == ".bin"
    cameras = (_read_cameras_binary if binary_cameras else _read_cameras_text)(cameras_file)
    binary = images_file.suffix == ".bin"
    images = (_read_images_binary if binary else _read_images_text)(images_file)
    if not images:
        raise LabelError(images_file, None, "no images: the model registered none")
    first: dict[str, str] = {}
    for image_id, pose, camera_id, name, origin in images:
        where = f"{origin}: image {image_id} ({name})"
        if camera_id not in cameras:
            raise ValueError(f"{where}: camera {camera_id} is not in {cameras_file}")
        if np.linalg.norm(pose[:4]) < 1e-8:
            raise ValueError(f"{where}: quaternion has zero norm")
        if name in first:
            raise ValueError(f"{where}: the name of {first[name]} too")
        first[name] = f"image {image_id}"
    return ColmapModel(
        cameras=cameras,
        names=[image[3] for image in images],
        camera_ids=np.array([image[2] for image in images], dtype=np.int64),
        rotations=np.array([image[1][:4] for image in images], dtype=np.float64),
        translations=np.array([image[1][4:] for image in images], dtype=np.float64),
        origins=[f"{image[4]}: image {image[0]} ({image[3]})" for image in images],
    )


def undistort_command(model_dir: Path, image_dir: Path) -> str:
    """The command line that writes an undistorted (pinhole) model and images of a model."""
    out = model_dir.parent / "undistorted"
    return (
        f"colmap image_undistorter --image_path {image_dir} --input_path {model_dir} "
        f"--output_path {out} --output_type COLMAP, then pae-data convert colmap {out}/sparse "
        f"{out}/images OUT_DIR"
    )


def pinhole(camera: ColmapCamera, remedy: str) -> tuple[float, ...]:
    """``fx, fy, cx, cy`` (px, COLMAP's pixel centres) of a pinhole camera, or of one whose
    distortion is zero; ValueError naming the camera, and ``remedy`` (how to undistort the
    images), otherwise."""
    params = camera.params
    if camera.model in _ONE_FOCAL:
        intrinsics, distortion = (params[0], params[0], params[1], params[2]), params[3:]
    elif camera.model in _TWO_FOCAL:
        intrinsics, distortion = params[:4], params[4:]
    else:
        intrinsics, distortion = (), ()
    if not intrinsics or any(distortion):
        what = "a non-pinhole" if not intrinsics else "a distorted"
        raise ValueError(
            f"{camera.origin} is {what} {camera.model} camera: pae needs undistorted pinhole "
            f"images: {remedy}"
        )
    return tuple(float(v) for v in intrinsics)


def camera_to_world(rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [N, 7] of world-to-camera ``rotations`` [N, 4] (``qw, qx, qy,
    qz``, normalised here) and ``translations`` [N, 3]: ``conj(q)`` (``qw >= 0``) and the
    camera centre ``-R(q)^T t``."""
    import torch

    from pae.core.geometry import quaternion_to_matrix

    unit = rotations / np.linalg.norm(rotations, axis=1, keepdims=True)
    world_to_camera = quaternion_to_matrix(torch.from_numpy(unit)).numpy()
    centres = -np.einsum("nji,nj->ni", world_to_camera, translations)
    return np.concatenate([centres, canonical_sign(conjugate(unit))], axis=1)


def split_images(
    names: Sequence[str],
    origins: Sequence[str],
    split_list: Path | None = None,
    every: int | None = None,
    test_folders: Sequence[str] | None = None,
) -> tuple[list[str], list[str]]:
    """Each image's split and sequence -> (split [N], seq [N]) from its name relative to the
    image folder: listed in ``split_list`` (test; the rest train), every ``every``-th in name
    order (test), under one of the top folders ``test_folders`` (test), or by default under
    ``train/`` or ``test/``. The sequence is the image's folder (below ``train/`` or ``test/``
    by default), its parts joined by ``-``. ``origins`` [N] name each image's file and entry
    for messages."""
    seqs = [sequence_of(name) for name in names]
    if split_list is not None:
        if not split_list.is_file():
            raise LabelError(split_list, None, "--split-list: file not found")
        known, test = set(names), set()
        for line, text in _data_lines(split_list):
            if text and not text.startswith("#"):
                if text not in known:
                    raise LabelError(split_list, line, f"{text} is not an image of the model")
                test.add(text)
        return ["test" if name in test else "train" for name in names], seqs
    if every is not None:
        if every < 2:
            raise ValueError(f"--every must be at least 2, got {every}")
        order = sorted(range(len(names)), key=lambda i: natural_key(names[i]))
        split = ["train"] * len(names)
        for rank, i in enumerate(order):
            if rank % every == every - 1:
                split[i] = "test"
        return split, seqs
    tops = [name.split("/", 1)[0] if "/" in name else "" for name in names]
    if test_folders is not None:
        unknown = sorted(set(test_folders) - set(tops))
        if unknown:
            raise ValueError(f"--test-folders: no image of the model lies under {unknown[0]}/")
        return ["test" if top in test_folders else "train" for top in tops], seqs
    for origin, top in zip(origins, tops, strict=True):
        if top not in ("train", "test"):
            raise ValueError(
                f"{origin} lies under neither train/ nor test/: give --split-list FILE, "
                "--every K or --test-folders NAME"
            )
    return tops, [sequence_of(name.split("/", 1)[1]) for name in names]


def model_frames(
    model: ColmapModel,
    image_dir: Path,
    split: Sequence[str],
    seqs: Sequence[str],
    remedy: str,
) -> SceneFrames:
    """The images of ``model`` in its order as frames (``img_path`` its names, relative to
    ``image_dir``; ``split`` [N] and ``seqs`` [N] as given), camera-to-world poses in the
    model's units, principal points in pae's pixel convention. ValueError, one line naming
    the file and entry, for a distorted or non-pinhole camera (with ``remedy``), ``fx !=
    fy``, cameras of several sizes, an image missing from ``image_dir`` or of another size
    than its camera (one image per camera is read)."""
    from pae.data.transforms import image_size

    used = [model.cameras[int(c)] for c in dict.fromkeys(model.camera_ids.tolist())]
    intrinsics = {c.camera_id: pinhole(c, remedy) for c in used}
    table = np.array([intrinsics[int(c)] for c in model.camera_ids], dtype=np.float64)
    unequal = unequal_focal_lengths(table[:, 0], table[:, 1])
    if unequal.size:
        camera = model.cameras[int(model.camera_ids[unequal[0]])]
        fx, fy = table[unequal[0], :2]
        raise ValueError(
            f"{camera.origin}: fx {fx:g} != fy {fy:g} px: pae's label files hold one focal "
            "length per image (non-square pixels: resample the images)"
        )
    sizes = {(c.width, c.height): c for c in used}
    if len(sizes) > 1:
        (w0, h0), (w1, h1) = list(sizes)[:2]
        raise ValueError(
            f"{sizes[(w1, h1)].origin} is {w1}x{h1} px, {sizes[(w0, h0)].origin} {w0}x{h0} px: "
            "pae reads one image size per scene"
        )
    (width, height), checked = next(iter(sizes)), set()
    for name, origin, camera_id in zip(
        model.names, model.origins, model.camera_ids.tolist(), strict=True
    ):
        path = image_dir / name
        if not path.is_file():
            raise ValueError(f"{origin}: no image {path}")
        if camera_id not in checked:
            checked.add(camera_id)
            h, w = image_size(str(path))
            if (w, h) != (width, height):
                raise ValueError(
                    f"{origin}: {path} is {w}x{h} px, its camera {camera_id} {width}x{height} "
                    "px: convert the model that was reconstructed from these images"
                )
    return SceneFrames(
        img_path=list(model.names),
        seq=list(seqs),
        split=list(split),
        poses=camera_to_world(model.rotations, model.translations),
        focal=table[:, :2].mean(1),
        principal=table[:, 2:] - CORNER_CENTRE_PX,
        width=width,
        height=height,
        origin=list(model.origins),
    )


def read_colmap_scene(
    model_dir: str | os.PathLike[str],
    image_dir: str | os.PathLike[str],
    scale: float = 1.0,
    split_list: Path | None = None,
    every: int | None = None,
    test_folders: Sequence[str] | None = None,
) -> SceneFrames:
    """The registered images of a model as frames in name order (see :func:`split_images`
    for the splits), positions times ``scale``, principal points in pae's pixel convention.
    ValueError (LabelError), one line naming the file and entry, for what
    :func:`model_frames` refuses (a distorted camera with the ``colmap image_undistorter``
    command)."""
    model_dir, image_dir = Path(model_dir), Path(image_dir)
    if not scale > 0:
        raise ValueError(f"--scale must be > 0, got {scale}")
    if not image_dir.is_dir():
        raise ValueError(f"{image_dir}: IMAGE_DIR is not a directory")
    model = read_colmap_model(model_dir)
    order = sorted(range(len(model.names)), key=lambda i: natural_key(model.names[i]))
    model = dataclasses.replace(
        model,
        names=[model.names[i] for i in order],
        camera_ids=model.camera_ids[order],
        rotations=model.rotations[order],
        translations=model.translations[order],
        origins=[model.origins[i] for i in order],
    )
    split, seqs = split_images(model.names, model.origins, split_list, every, test_folders)
    frames = model_frames(model, image_dir, split, seqs, undistort_command(model_dir, image_dir))
    frames.poses[:, :3] *= scale
    return frames
