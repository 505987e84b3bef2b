"""Writing a synthetic dataset: images rendered in batches and written whole (atomically),
label files in the format of ``pae.data.labels`` (``write_synthetic_dataset``), and, when a
nuisance or the camera pipeline is on, ``labels/nuisances.csv`` (``NUISANCE_COLUMNS``): each
frame's occluder share, blur and exposure, for analysis only (the label files stay as they
are)."""

from __future__ import annotations

import dataclasses
import shutil
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pae.data.labels import LabelTable, write_labels
from pae.synthetic.camera import PinholeCamera
from pae.synthetic.capture import sequence_capture
from pae.synthetic.nuisances import sequence_nuisances
from pae.synthetic.raycast import Appearance, FrameConditions, render_batch
from pae.synthetic.scene import SyntheticScene, make_scene, scene_name
from pae.synthetic.settings import CaptureOptions, Nuisances, SyntheticSettings
from pae.synthetic.surfaces import dress_surfaces
from pae.synthetic.trajectories import CameraSequence, make_sequences, walk_frames

FRAMES_PER_WRITE = 64
"""Frames rendered before they are written, bounding memory for large images."""
NUISANCE_FILE = "nuisances.csv"
"""Name of the per-frame nuisance table in ``labels/`` (only written when a nuisance is on)."""
NUISANCE_COLUMNS = ("img_path", "occluder_share", "blur_px", "exposure_gain")
"""Its columns: the image (as in the label files), the share of the image its occluder covers
(0–1, 0: none), its motion blur's length (px of the nominal size) and its total gain (the
sequence's gain times the frame's exposure and auto-exposure)."""


@dataclass(frozen=True)
class SyntheticSummary:
    """What :func:`write_synthetic_dataset` wrote and how fast."""

    root: str
    scenes: list[str]
    train_frames: int
    """Training frames over all scenes."""
    test_frames: int
    """Test frames over all scenes."""
    size: int
    """Side (px) of the stored images."""
    seconds: float
    frames_per_second: float

    def summary(self) -> str:
        """Short human-readable multi-line summary."""
        return "\n".join(
            [
                f"synthetic dataset at {self.root}",
                f"  scenes: {len(self.scenes)} ({', '.join(self.scenes)})",
                f"  frames: {self.train_frames} train, {self.test_frames} test "
                f"({self.size}x{self.size} px)",
                f"  time:   {self.seconds:.1f} s ({self.frames_per_second:.1f} frames/s)",
            ]
        )


def _write_png(path: Path, image_rgb: np.ndarray) -> None:
    """Write an RGB image as PNG (into the rendering folder, renamed into place when whole)."""
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"could not encode {path}")
    path.write_bytes(encoded.tobytes())


def _prepare_output(out: Path, overwrite: bool) -> None:
    """Refuse a used folder unless `overwrite`, and even then one that holds no dataset."""
    if not out.exists():
        return
    if not out.is_dir():
        raise FileExistsError(f"{out}: exists and is not a folder")
    if not any(out.iterdir()):
        return
    if not overwrite:
        raise FileExistsError(f"{out}: folder is not empty; --overwrite replaces the dataset in it")
    if not (out / "labels").is_dir():
        raise FileExistsError(
            f"{out}: folder is not empty and holds no dataset (no labels/); not replacing it"
        )


def _replace_folder(new: Path, out: Path) -> None:
    """Put the folder `new` in place of `out` (moved aside, then deleted if it existed)."""
    old = out.with_name(f".{out.name}.old-{uuid.uuid4().hex}")
    if out.exists():
        out.rename(old)
    new.rename(out)
    shutil.rmtree(old, ignore_errors=True)


RenderProgress = Callable[[int, int], None]
"""``progress(done, total)``: frames rendered so far, of all the dataset's frames."""


def render_frames(
    out: Path,
    paths: list[str],
    scene: SyntheticScene,
    poses: np.ndarray,
    camera: PinholeCamera,
    appearance: Appearance,
    noise: np.random.Generator,
    conditions: FrameConditions | None = None,
    exposed: np.ndarray | None = None,
) -> np.ndarray:
    """Render ``poses`` ``[n, 7]`` of one sequence (with its frames' nuisances ``conditions``,
    if any) and write them as PNGs at ``out / paths[i]``, ``FRAMES_PER_WRITE`` frames at a
    time: -> the share ``[n]`` of each image its occluder covers (``exposed`` ``[n]``, when
    given, receives each frame's total gain)."""
    for folder in sorted({(out / path).parent for path in paths}):
        folder.mkdir(parents=True, exist_ok=True)
    shares = np.zeros(len(poses))
    for start in range(0, len(poses), FRAMES_PER_WRITE):
        batch = slice(start, start + FRAMES_PER_WRITE)
        images = render_batch(
            scene,
            poses[batch],
            camera,
            appearance,
            noise,
            conditions=None if conditions is None else conditions[batch],
            occluded=shares[batch],
            exposed=None if exposed is None else exposed[batch],
        )
        for path, image in zip(paths[batch], images, strict=True):
            _write_png(out / path, image)
    return shares


def write_nuisance_table(path: Path, rows: list[tuple[str, float, float, float]]) -> None:
    """Write ``rows`` ``(img_path, occluder_share, blur_px, exposure_gain)`` to ``path`` as
    CSV with a header of ``NUISANCE_COLUMNS``."""
    lines = [",".join(NUISANCE_COLUMNS)]
    lines += [f"{img},{share:.4f},{blur:.3f},{gain:.4f}" for img, share, blur, gain in rows]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def write_label_files(folder: Path, tables: dict[tuple[str, str], LabelTable]) -> None:
    """``folder/<scene>_<split>.csv`` for each ``(scene, split)`` table, then
    ``folder/all_<split>.csv`` for each split (the data modules read those last)."""
    for (name, split), table in tables.items():
        write_labels(folder / f"{name}_{split}.csv", table)
    for split in dict.fromkeys(split for _, split in tables):
        write_labels(
            folder / f"all_{split}.csv",
            LabelTable.concat(t for (_, s), t in tables.items() if s == split),
        )


def write_whole(
    out: Path | str, overwrite: bool, render: Callable[[Path], SyntheticSummary]
) -> SyntheticSummary:
    """Run ``render(folder)`` into a hidden folder beside ``out``, then put it in place of
    ``out``: ``out`` ends as exactly the new dataset, or unchanged when rendering fails.

    A non-empty ``out`` is refused (FileExistsError) unless ``overwrite``, which replaces a
    folder holding a dataset (``labels/``) as a whole, stale files included. The summary's
    ``root`` names ``out``.
    """
    final = Path(out)
    _prepare_output(final, overwrite)
    final.parent.mkdir(parents=True, exist_ok=True)
    folder = final.with_name(f".{final.name}.rendering-{uuid.uuid4().hex}")
    try:
        summary = render(folder)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    _replace_folder(folder, final)
    return dataclasses.replace(summary, root=str(final))


def write_synthetic_dataset(
    out: Path | str,
    settings: SyntheticSettings | None = None,
    *,
    overwrite: bool = False,
    progress: RenderProgress | None = None,
    **overrides: Any,
) -> SyntheticSummary:
    """Render the benchmark of ``settings`` (None: the defaults), with ``overrides`` (any of
    :class:`~pae.synthetic.settings.SyntheticSettings`' names) replacing its values, into
    ``out`` (see :func:`write_whole`): images first, label files last. The same settings
    give byte-identical files. ``progress(done, total)`` is called after each sequence with
    the frames rendered so far. With a nuisance or the camera pipeline on, each frame's
    nuisances go to ``labels/nuisances.csv``. The validation walks' frames come on top of
    ``train_frames``.
    """
    settings = dataclasses.replace(settings or SyntheticSettings(), **overrides)
    train_and_walks = settings.train_frames + settings.val_walks * walk_frames(
        settings.train_frames
    )
    scenes = settings.scenes

    def render(folder: Path) -> SyntheticSummary:
        started = time.perf_counter()
        _render(folder, settings, progress)
        seconds = time.perf_counter() - started
        return SyntheticSummary(
            root=str(folder),
            scenes=[scene_name(i) for i in range(scenes)],
            train_frames=scenes * train_and_walks,
            test_frames=scenes * settings.test_frames,
            size=settings.size * settings.render_scale,
            seconds=seconds,
            frames_per_second=scenes * (train_and_walks + settings.test_frames) / seconds,
        )

    return write_whole(out, overwrite, render)


def surface_seed(seed: int, index: int) -> tuple[int, int, int]:
    """Seed of scene ``index``'s surface draws (:func:`dress_surfaces`)."""
    return (seed, index, 4)


def sequence_conditions(
    scene: SyntheticScene,
    sequence: CameraSequence,
    camera: PinholeCamera,
    nuisances: Nuisances,
    capture: CaptureOptions,
) -> tuple[Appearance, FrameConditions | None]:
    """The appearance and frame conditions ``sequence`` of ``scene`` is rendered with, seen
    by ``camera`` at the nominal size (conditions None: no nuisance and no camera pipeline
    on): its nuisances, then its capture; blur lengths in pixels of the nominal size
    (:func:`scaled_blur` scales them to the stored images)."""
    appearance, conditions = sequence.appearance, None
    if nuisances.active or capture.camera_pipeline:
        appearance, conditions = sequence_nuisances(
            nuisances, scene, sequence.poses, camera, appearance, sequence.nuisance_seed
        )
    return sequence_capture(capture, appearance, conditions, sequence.nuisance_seed)


def scaled_blur(conditions: FrameConditions | None, render_scale: int) -> FrameConditions | None:
    """``conditions`` with their blur lengths in pixels of images ``render_scale`` times
    larger (None: None)."""
    if conditions is None or render_scale == 1:
        return conditions
    return dataclasses.replace(conditions, blur_px=conditions.blur_px * render_scale)


def render_sequence(
    out: Path,
    paths: list[str],
    scene: SyntheticScene,
    sequence: CameraSequence,
    camera: PinholeCamera,
    settings: SyntheticSettings,
) -> list[tuple[str, float, float, float]]:
    """Render ``sequence`` of ``scene`` (seen by ``camera`` at the nominal size, stored
    ``render_scale`` times larger) with the nuisances and capture of ``settings`` as PNGs at
    ``out / paths[i]`` -> its frames' rows of the nuisance table (none where no nuisance and
    no camera pipeline is on)."""
    capture = settings.capture
    appearance, conditions = sequence_conditions(
        scene, sequence, camera, settings.nuisances, capture
    )
    exposed = np.zeros(len(paths))
    shares = render_frames(
        out,
        paths,
        scene,
        sequence.poses,
        dataclasses.replace(camera, size=camera.size * capture.render_scale),
        appearance,
        np.random.default_rng(list(sequence.noise_seed)),
        scaled_blur(conditions, capture.render_scale),
        exposed,
    )
    if conditions is None:
        return []
    blur = conditions.blur_px.tolist()
    return list(zip(paths, shares.tolist(), blur, exposed.tolist(), strict=True))


def _render(out: Path, settings: SyntheticSettings, progress: RenderProgress | None) -> None:
    """Render every scene of ``settings`` into `out`: images first, label files last (with
    a nuisance or the camera pipeline on, ``labels/nuisances.csv`` too)."""
    seed, size = settings.seed, settings.size
    walks = settings.val_walks * walk_frames(settings.train_frames)
    frames = settings.train_frames + walks + settings.test_frames
    total, done = settings.scenes * frames, 0
    camera = PinholeCamera(size)
    label_tables: dict[tuple[str, str], LabelTable] = {}
    nuisance_rows: list[tuple[str, float, float, float]] = []
    for index in range(settings.scenes):
        scene = make_scene(index, seed, settings.test_offset_m, settings.train_lane_m)
        scene = dress_surfaces(scene, settings.surfaces, surface_seed(seed, index))
        rows: dict[str, list[tuple[str, str, np.ndarray]]] = {"train": [], "test": []}
        sequences = make_sequences(index, scene, settings)
        for sequence in sequences:
            paths = [
                f"{scene.name}/{sequence.name}/frame-{frame:06d}.png"
                for frame in range(len(sequence.poses))
            ]
            nuisance_rows += render_sequence(out, paths, scene, sequence, camera, settings)
            done += len(paths)
            if progress is not None:
                progress(done, total)
            rows[sequence.split] += [
                (sequence.name, path, pose)
                for path, pose in zip(paths, sequence.poses, strict=True)
            ]
        for split, split_rows in rows.items():
            label_tables[scene.name, split] = LabelTable(
                scene=[scene.name] * len(split_rows),
                split=[split] * len(split_rows),
                seq=[r[0] for r in split_rows],
                img_path=[r[1] for r in split_rows],
                poses=np.array([r[2] for r in split_rows]),
                source=f"synthetic seed={seed}",
            )
    if nuisance_rows:
        write_nuisance_table(out / "labels" / NUISANCE_FILE, nuisance_rows)
    write_label_files(out / "labels", label_tables)
