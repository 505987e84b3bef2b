"""Synthetic images at given camera poses: a real dataset's camera geometry, rendered.

``write_dataset_at_poses`` reads label files (e.g. the real Cambridge Landmarks or 7-Scenes
labels, poses only) and renders one image per row at exactly that row's pose, in a textured
world built around each scene's camera positions: a room whose camera region spans at most
``ROOM_EXTENT_M`` room metres, furnished like the benchmark's rooms, then scaled to the
poses' extent (a 3 m 7-Scenes room stays a room; a 100 m Cambridge street becomes a room
about 35 times larger, textures and light fall-off included). Every camera lies at least
``ROOM_MARGIN_M`` room metres inside the world's walls, and the world is closed, so every
ray hits a textured face.

The label files written keep each row's scene, split, seq and pose; ``img_path`` points at
the rendered image ``<scene>/<split>-<seq>/frame-NNNNNN.png``. With the benchmark's surfaces,
nuisances and capture (:class:`~pae.synthetic.settings.SyntheticSettings`), each world is
dressed as the benchmark's rooms are and each recording (scene, split, seq: its frames in the
file's order, the walk the nuisances drift along) gets its own light, exposure, white balance
and occluders, as :func:`~pae.synthetic.write_synthetic_dataset` gives each sequence.
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pae.data.labels import LabelError, LabelTable, read_labels
from pae.synthetic import (
    Appearance,
    Box,
    FaceTexture,
    PinholeCamera,
    RenderProgress,
    SurfaceOptions,
    SyntheticScene,
    SyntheticSettings,
    SyntheticSummary,
    dress_surfaces,
    furnish,
    render_sequence,
    room_textures,
    surface_seed,
    write_label_files,
    write_nuisance_table,
    write_whole,
)
from pae.synthetic.trajectories import CameraSequence
from pae.synthetic.writer import NUISANCE_FILE

ROOM_EXTENT_M = 3.0
"""Largest side of the camera region in room metres; larger regions are scaled down to it."""
ROOM_MARGIN_M = 1.5
"""Room metres between the camera region and each wall, floor and ceiling."""
FURNITURE_KEEP_OUT_M = 0.3
"""Room metres between the camera region and the furniture's footprints."""


def _scaled(scene: SyntheticScene, factor: float) -> SyntheticScene:
    """``scene`` with every length (geometry, texel size, light position) times ``factor``."""

    def scale_box(box: Box) -> Box:
        textures = tuple(FaceTexture(t.image, t.texel_size * factor) for t in box.textures)
        return Box(box.lo * factor, box.hi * factor, textures)

    return SyntheticScene(
        scene.name,
        scale_box(scene.room),
        tuple(scale_box(box) for box in scene.boxes),
        scene.light_position * factor,
        None,
        scene.scale * factor,
    )


def make_scene_around(
    name: str, index: int, positions: np.ndarray, seed: int = 0
) -> SyntheticScene:
    """A closed, furnished world around camera ``positions`` ``[N, 3]`` (m).

    Built in room metres around the positions divided by the scale
    ``max(1, largest side of their bounding box / ROOM_EXTENT_M)``, then scaled back.
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(positions) == 0 or not np.isfinite(positions).all():
        raise ValueError(f"scene {name}: camera positions must be finite and not empty")
    rng = np.random.default_rng([seed, index, 6])
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    scale = max(1.0, float((hi - lo).max()) / ROOM_EXTENT_M)
    region_lo, region_hi = lo / scale, hi / scale
    room_lo, room_hi = region_lo - ROOM_MARGIN_M, region_hi + ROOM_MARGIN_M
    room = Box(room_lo, room_hi, room_textures(rng, room_hi - room_lo))
    boxes = furnish(rng, room, region_lo, region_hi, FURNITURE_KEEP_OUT_M)
    centre = (room_lo + room_hi) / 2
    light = np.array([*(centre[:2] + rng.uniform(-1.0, 1.0, 2)), room_hi[2] - 0.5])
    return _scaled(SyntheticScene(name, room, boxes, light, None), scale)


def _folder_name(text: str) -> str:
    """``text`` with every character outside ``[A-Za-z0-9._-]`` replaced by ``_``."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", text) or "_"


def write_dataset_at_poses(
    out: Path | str,
    label_paths: Sequence[Path | str],
    size: int = 64,
    seed: int = 0,
    overwrite: bool = False,
    required_splits: Sequence[str] = (),
    progress: RenderProgress | None = None,
    options: SyntheticSettings | None = None,
) -> SyntheticSummary:
    """Render one image per row of ``label_paths`` at that row's pose into ``out``, with the
    surfaces, nuisances and capture of ``options`` (None: the plain benchmark's; its size
    and seed are ``size`` and ``seed``'s).

    Writes ``out/labels/<scene>_<split>.csv`` and ``out/labels/all_<split>.csv`` (label
    files last) and the images, whole or not at all (``overwrite``: see
    :func:`~pae.synthetic.write_whole`); each (scene, split, seq) gets its own
    :class:`Appearance` and sensor noise. A bad row raises the
    :class:`~pae.data.labels.LabelError` of ``pae-data check`` (``FILE:LINE: problem``), and
    so does a split of ``required_splits`` without rows, before anything is rendered.
    ``progress(done, total)`` is called after each sequence with the frames rendered so far.
    """
    if int(size) != size or size < 8:
        raise ValueError(f"size must be an integer >= 8, got {size!r}")
    if not label_paths:
        raise ValueError("no label files given")
    table = LabelTable.concat(read_labels(path) for path in label_paths)
    missing = [split for split in required_splits if split not in table.split]
    if missing:
        files = ", ".join(str(path) for path in label_paths)
        raise LabelError(files, None, f"no rows of the split(s) {missing}; rows of each are needed")
    settings = SyntheticSettings(size=int(size), seed=seed)
    if options is not None:
        settings = dataclasses.replace(options, size=int(size), seed=seed)
    return write_whole(
        out, overwrite, lambda folder: _render_rows(folder, table, settings, progress)
    )


def scenes_at_poses(
    table: LabelTable, seed: int = 0, surfaces: SurfaceOptions | None = None
) -> list[SyntheticScene]:
    """The worlds :func:`write_dataset_at_poses` renders ``table``'s rows in, one per scene
    (sorted names), each built around all of that scene's camera positions and dressed with
    ``surfaces`` (None: the plain benchmark's)."""
    scene_column = np.asarray(table.scene)
    surfaces = surfaces or SurfaceOptions()
    return [
        dress_surfaces(
            make_scene_around(name, index, table.poses[scene_column == name, :3], seed),
            surfaces,
            surface_seed(seed, index),
        )
        for index, name in enumerate(table.scene_names)
    ]


def _render_rows(
    out: Path, table: LabelTable, settings: SyntheticSettings, progress: RenderProgress | None
) -> SyntheticSummary:
    """Render every row of ``table`` into ``out`` (see :func:`write_dataset_at_poses`)."""
    started = time.perf_counter()
    seed = settings.seed
    camera = PinholeCamera(settings.size)
    scene_column = np.asarray(table.scene)
    tables: dict[tuple[str, str], LabelTable] = {}
    img_path = list(table.img_path)
    worlds = scenes_at_poses(table, seed, settings.surfaces)
    nuisance_rows: list[tuple[str, float, float, float]] = []
    done = 0
    for index, name in enumerate(table.scene_names):
        rows = np.flatnonzero(scene_column == name)
        scene = worlds[index]
        sequences: dict[tuple[str, str], list[int]] = {}
        for row in rows.tolist():
            sequences.setdefault((table.split[row], table.seq[row]), []).append(row)
        for number, ((split, seq), members) in enumerate(sequences.items()):
            folder = f"{_folder_name(name)}/{_folder_name(split)}-{_folder_name(seq)}"
            paths = [f"{folder}/frame-{frame:06d}.png" for frame in range(len(members))]
            recording = CameraSequence(
                seq,
                split,
                table.poses[members],
                Appearance.random(np.random.default_rng([seed, index, 7, number])),
                (seed, index, 8, number),
                (seed, index, 9, number),
            )
            nuisance_rows += render_sequence(out, paths, scene, recording, camera, settings)
            done += len(members)
            if progress is not None:
                progress(done, len(table))
            for row, path in zip(members, paths, strict=True):
                img_path[row] = path
    if nuisance_rows:
        write_nuisance_table(out / "labels" / NUISANCE_FILE, nuisance_rows)
    rendered = LabelTable(
        table.scene, table.split, table.seq, img_path, table.poses, source=str(out)
    )
    split_column = np.asarray(table.split)
    for name in table.scene_names:
        for split in dict.fromkeys(table.split):
            rows = np.flatnonzero((scene_column == name) & (split_column == split))
            if len(rows):
                tables[name, split] = rendered.select(rows)
    write_label_files(out / "labels", tables)
    seconds = time.perf_counter() - started
    return SyntheticSummary(
        root=str(out),
        scenes=table.scene_names,
        train_frames=int(np.count_nonzero(split_column == "train")),
        test_frames=int(np.count_nonzero(split_column == "test")),
        size=settings.size * settings.capture.render_scale,
        seconds=seconds,
        frames_per_second=len(table) / max(seconds, 1e-9),
    )
