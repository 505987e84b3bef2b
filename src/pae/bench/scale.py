"""Render-and-compare at 7-Scenes size: the peak resident memory and the time of the
scene-model step (fit the voxel grid on every train image, then refine every test query) on
a dataset of 7-Scenes' shape, run as a user runs it (`pae-train` in a fresh process).

The dataset copies 7-Scenes' layout: its scenes and sequences (``SEVEN_SCENES``: 26,000
train and 17,000 test frames of 640x480 px), label files in pae's format and poses that
wander a few metres through a room. Its images are cheap: a few dozen unique frames per
scene from the synthetic renderer (rendered small, upsampled to 640x480, PNG), every label
row a hard link to one of them. The images do not match the poses: the figures are the
step's memory and time at that size, not its accuracy.

The harness first decodes every image once into an image store (``pae-data store``, as a
user does once per dataset, or as the teacher's training does on its first epoch), which
the teacher and the step then read (``data.image_store``). It trains a teacher checkpoint
in the cheapest valid way (one epoch of two batches), then runs ``stage=render_compare``
with the default scene model and refiner, one short scene-model epoch
(``batches_per_epoch`` ray batches) and a few validation batches; every train image is
read into the ray store and every test query refined. Children inherit the environment
(pae's own settings: ``pae.core.threads``). Each command's peak resident set size is read
from ``os.wait4`` (ru_maxrss: the largest of the process and the children it waited for,
such as its loader workers, not their sum).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
from omegaconf import OmegaConf

from pae.core.geometry import matrix_to_quaternion
from pae.data.holdout import held_out_rows
from pae.data.labels import LabelTable, read_labels
from pae.data.settings import PoseDataSettings
from pae.synthetic import write_label_files, write_synthetic_dataset
from pae.synthetic.camera import look_rotations

SEVEN_SCENES: tuple[tuple[str, tuple[int, ...], tuple[int, ...], int], ...] = (
    ("chess", (1, 2, 4, 6), (3, 5), 1000),
    ("fire", (1, 2), (3, 4), 1000),
    ("heads", (2,), (1,), 1000),
    ("office", (1, 3, 4, 5, 8, 10), (2, 6, 7, 9), 1000),
    ("pumpkin", (2, 3, 6, 8), (1, 7), 1000),
    ("redkitchen", (1, 2, 5, 7, 8, 11, 13), (3, 4, 6, 12, 14), 1000),
    ("stairs", (2, 3, 5, 6), (1, 4), 500),
)
"""7-Scenes' scenes: train sequences, test sequences, frames per sequence (26,000 train and
17,000 test frames in all)."""
SEVEN_SCENES_TRAIN = sum(len(train) * n for _, train, _, n in SEVEN_SCENES)
SEVEN_SCENES_TEST = sum(len(test) * n for _, _, test, n in SEVEN_SCENES)
ROOM_HALF_M = (1.5, 1.3)
"""Half the width and depth (m) of the box the cameras wander in (height 1.1-1.7 m)."""
PREFIX = "bench/render_compare"
SPLITS = ("train", "test")


def sequence_frames(
    train: int, test: int, scenes: int = len(SEVEN_SCENES)
) -> list[tuple[str, str, str, int]]:
    """(scene, split, sequence, frames) of the first ``scenes`` 7-Scenes scenes with
    ``train`` and ``test`` frames in all, shared out among the sequences in proportion to
    7-Scenes' own (largest remainders; at least one frame each)."""
    if not 1 <= scenes <= len(SEVEN_SCENES):
        raise ValueError(f"scenes must lie in [1, {len(SEVEN_SCENES)}], got {scenes}")
    rows: list[tuple[str, str, str, int]] = []
    for split, total in zip(SPLITS, (train, test), strict=True):
        sequences = [
            (name, f"seq-{seq:02d}", frames)
            for name, train_seqs, test_seqs, frames in SEVEN_SCENES[:scenes]
            for seq in (train_seqs if split == "train" else test_seqs)
        ]
        if total < len(sequences):
            raise ValueError(f"{split}: {total} frames for {len(sequences)} sequences")
        weights = np.array([frames for _, _, frames in sequences], dtype=np.float64)
        spare = total - len(sequences)
        share = spare * weights / weights.sum()
        counts = np.floor(share).astype(int)
        order = np.argsort(-(share - counts), kind="stable")
        counts[order[: spare - counts.sum()]] += 1
        rows += [
            (name, split, seq, 1 + int(count))
            for (name, seq, _), count in zip(sequences, counts, strict=True)
        ]
    return rows


def room_walk(frames: int, rng: np.random.Generator) -> np.ndarray:
    """Poses [frames, 7] of a hand-held camera wandering through a room: a smooth random
    walk (about 2 cm a frame) in ``ROOM_HALF_M`` x [1.1, 1.7] m, reflected at the walls,
    heading drifting, pitch and roll a few degrees."""
    low = np.array([-ROOM_HALF_M[0], -ROOM_HALF_M[1], 1.1])
    high = np.array([ROOM_HALF_M[0], ROOM_HALF_M[1], 1.7])
    position = rng.uniform(low, high)
    velocity = np.zeros(3)
    positions = np.empty((frames, 3))
    for i in range(frames):
        velocity = 0.9 * velocity + rng.normal(0.0, [0.004, 0.004, 0.001])
        position = position + velocity
        for axis in range(3):  # reflect at the walls
            if not low[axis] <= position[axis] <= high[axis]:
                position[axis] = np.clip(
                    2 * np.clip(position[axis], low[axis], high[axis]) - position[axis],
                    low[axis],
                    high[axis],
                )
                velocity[axis] = -velocity[axis]
        positions[i] = position
    yaw = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0.0, 0.02, frames))
    pitch = np.radians(8.0) * np.sin(np.cumsum(rng.normal(0.0, 0.05, frames)))
    roll = np.radians(3.0) * np.sin(np.cumsum(rng.normal(0.0, 0.05, frames)))
    rotations = torch.from_numpy(look_rotations(yaw, pitch, roll))
    quaternions = matrix_to_quaternion(rotations).numpy()
    quaternions *= np.where(quaternions[:, :1] < 0, -1.0, 1.0)
    return np.concatenate([positions, quaternions], 1)


def write_scale_dataset(
    root: Path,
    train: int = SEVEN_SCENES_TRAIN,
    test: int = SEVEN_SCENES_TEST,
    scenes: int = len(SEVEN_SCENES),
    width: int = 640,
    height: int = 480,
    unique: int = 32,
    render_size: int = 64,
    seed: int = 0,
) -> dict[str, int]:
    """A dataset of 7-Scenes' shape under ``root`` (:func:`sequence_frames`): per scene
    ``unique`` frames of a synthetic room (``render_size`` px) upsampled to ``width`` x
    ``height`` in ``root/_unique/``, every label row's image a hard link to one of them
    (train rows to the room's train frames, test rows to its test frames), poses from
    :func:`room_walk`; label files ``root/labels/{scene}_{split}.csv`` and
    ``all_{split}.csv`` -> the counts written (``train``, ``test``, ``files``)."""
    root = Path(root)
    rendered = root / "_rendered"
    test_unique = max(2, unique // 4)
    write_synthetic_dataset(
        rendered, scenes=scenes, train_frames=unique, test_frames=test_unique, size=render_size
    )
    names = [name for name, *_ in SEVEN_SCENES[:scenes]]
    sources: dict[tuple[str, str], list[str]] = {}
    for index, name in enumerate(names):
        for split in SPLITS:
            frames = sorted((rendered / f"scene{index:02d}").glob("*/*.png"))
            frames = frames[:unique] if split == "train" else frames[unique:]
            folder = root / "_unique" / name
            folder.mkdir(parents=True, exist_ok=True)
            sources[name, split] = []
            for i, frame in enumerate(frames):
                image = cv2.imread(str(frame), cv2.IMREAD_COLOR)
                big = cv2.resize(image, (width, height), interpolation=cv2.INTER_LINEAR)
                path = folder / f"{split}-{i:03d}.color.png"
                if not cv2.imwrite(str(path), big):
                    raise OSError(f"could not write {path}")
                sources[name, split].append(str(path))
    shutil.rmtree(rendered)
    rng = np.random.default_rng(seed)
    rows: dict[tuple[str, str], list[tuple[str, str, np.ndarray]]] = {}
    for name, split, seq, frames in sequence_frames(train, test, scenes):
        (root / name / seq).mkdir(parents=True, exist_ok=True)
        poses = room_walk(frames, rng)
        files = sources[name, split]
        for frame in range(frames):
            img_path = f"{name}/{seq}/frame-{frame:06d}.color.png"
            os.link(files[frame % len(files)], root / img_path)
            rows.setdefault((name, split), []).append((seq, img_path, poses[frame]))
    tables = {
        key: LabelTable(
            scene=[key[0]] * len(value),
            split=[key[1]] * len(value),
            seq=[r[0] for r in value],
            img_path=[r[1] for r in value],
            poses=np.stack([r[2] for r in value]),
        )
        for key, value in rows.items()
    }
    write_label_files(root / "labels", tables)
    counts = {split: sum(len(v) for (_, s), v in rows.items() if s == split) for split in SPLITS}
    return {**counts, "files": sum(len(files) for files in sources.values())}


LAUNCHER = """
import os, subprocess, sys
process = subprocess.Popen(sys.argv[2:])
_, status, usage = os.wait4(process.pid, 0)
with open(sys.argv[1], "w") as out:
    out.write(str(usage.ru_maxrss))
sys.exit(os.waitstatus_to_exitcode(status))
"""
"""Runs a command and writes its ru_maxrss (KiB): a process that holds next to nothing, so
that the command's figure is its own. A child's ru_maxrss includes the memory of the
process it was forked from as it was before the child's exec: measured from the bench's
process (torch and the dataset's writer loaded) it would read at least that process's
peak."""


def _terminated(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)


def run_measured(command: Sequence[str], log: Path) -> dict[str, float]:
    """Run ``command`` (output to ``log``) -> its wall seconds (``s``) and peak RSS
    (``rss_mb``, MB = 10^6 bytes: ru_maxrss of ``os.wait4``, the largest of the process and
    its waited-for children such as loader workers, not their sum; started from
    ``LAUNCHER``). A failed command is a RuntimeError with its output's tail; interrupted
    or sent SIGTERM (`timeout`), the bench stops the command's whole process group (its own
    session) before it exits. Call it from the main thread."""
    peak_file = log.with_suffix(".maxrss")
    start = time.perf_counter()
    with open(log, "w") as out:
        launcher = [sys.executable, "-S", "-c", LAUNCHER, str(peak_file), *command]
        process = subprocess.Popen(
            launcher, stdout=out, stderr=subprocess.STDOUT, start_new_session=True
        )
        previous = signal.signal(signal.SIGTERM, _terminated)
        try:
            returncode = process.wait()
        except BaseException:  # interrupted or terminated: stop the command and its workers
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
            raise
        finally:
            signal.signal(signal.SIGTERM, previous)
    seconds = time.perf_counter() - start
    if returncode != 0 or not peak_file.is_file():
        tail = log.read_text(errors="replace")[-3000:]
        raise RuntimeError(f"{' '.join(command[:4])} ... failed ({returncode}): {tail}")
    return {"s": seconds, "rss_mb": int(peak_file.read_text()) * 1024 / 1e6}


def _say(message: str) -> None:
    print(f"pae-bench: render_compare_scale: {message}", file=sys.stderr, flush=True)


def bench_render_compare_scale(
    train: int = SEVEN_SCENES_TRAIN,
    test: int = SEVEN_SCENES_TEST,
    scenes: int = len(SEVEN_SCENES),
    width: int = 640,
    height: int = 480,
    root: Path | None = None,
    batches_per_epoch: int = 20,
    val_batches: int = 4,
) -> dict[str, float]:
    """The scene-model step at 7-Scenes size (see the module's docstring) on a dataset of
    ``train`` and ``test`` frames over ``scenes`` scenes at ``width`` x ``height`` px,
    written under ``root`` (None: a temporary folder; either way removed afterwards) ->
    ``bench/render_compare/peak_rss_mb`` (the step's process), ``scale_fit_s`` (its
    ``bench/scene_model/fit_s``: reading the train images into the ray store and the fit),
    ``scale_refine_s`` (the refiner's measured seconds over the test queries),
    ``scale_step_s`` (the whole command), ``scale_store_s`` and ``scale_store_peak_rss_mb``
    (decoding every image into the image store beforehand), the counts
    (``scale_train_images`` in the label files, ``scale_fit_images`` in the ray store after
    the validation split's hold-out, ``scale_test_images`` refined) and the teacher
    command's ``scale_teacher_peak_rss_mb`` and ``scale_teacher_s``."""
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=root) as tmp:
        folder = Path(tmp)
        data_root = folder / "data"
        _say(f"writing {train} train and {test} test frames ({scenes} scenes) to {data_root}")
        counts = write_scale_dataset(data_root, train, test, scenes, width, height)
        write_s = time.perf_counter() - started
        names = ",".join(name for name, *_ in SEVEN_SCENES[:scenes])
        store_dir = folder / "image_store"
        _say(f"decoding every image into {store_dir}")
        labels = [str(data_root / "labels" / f"all_{split}.csv") for split in SPLITS]
        store = run_measured(
            [
                sys.executable,
                "-m",
                "pae.data_cli",
                "store",
                *labels,
                str(data_root),
                "--store",
                str(store_dir),
                "--shorter-edge",
                str(PoseDataSettings().shorter_edge),  # data=seven_scenes reads them at this
            ],
            folder / "store.log",
        )
        data = [
            "data=seven_scenes",
            f"data.root={data_root}",
            f"data.scenes=[{names}]",
            f"data.image_store={store_dir}",
            "callbacks=minimal",
            "+trainer.enable_progress_bar=false",
        ]
        train_command = [sys.executable, "-m", "pae.train"]
        _say("teacher checkpoint (1 epoch, 2 batches)")
        teacher = run_measured(
            [
                *train_command,
                "stage=teacher",
                "teacher=posenet",
                "backbone=small_cnn",
                "teacher.max_epochs=1",
                "+trainer.limit_train_batches=2",
                "+trainer.limit_val_batches=1",
                "+trainer.limit_test_batches=1",
                f"hydra.run.dir={folder / 'teacher'}",
                *data,
            ],
            folder / "teacher.log",
        )
        step_dir = folder / "render_compare"
        _say(f"scene-model step ({teacher['s']:.0f} s for the teacher)")
        step = run_measured(
            [
                *train_command,
                "stage=render_compare",
                f"teacher_ckpt={folder / 'teacher' / 'checkpoints' / 'last.ckpt'}",
                "scene_model.max_epochs=1",
                f"scene_model.batches_per_epoch={batches_per_epoch}",
                f"+trainer.limit_val_batches={val_batches}",
                f"hydra.run.dir={step_dir}",
                *data,
            ],
            folder / "render_compare.log",
        )
        metrics = json.loads((step_dir / "metrics.json").read_text())
        missing = [
            name
            for name, *_ in SEVEN_SCENES[: scenes if scenes > 1 else 0]
            if f"test/render_compare/{name}/pos_median_m" not in metrics
        ]
        if missing or f"{PREFIX}/ms_per_query" not in metrics:
            raise RuntimeError(f"the step refined no test queries of scenes {missing}")
        settings = OmegaConf.load(step_dir / ".hydra" / "config.yaml").data
        table = read_labels(data_root / "labels" / "all_train.csv")
        held, _ = held_out_rows(table, settings.val_sequences, settings.val_fraction)
    ms = metrics[f"{PREFIX}/ms_per_query"]
    figures = {
        f"{PREFIX}/peak_rss_mb": step["rss_mb"],
        f"{PREFIX}/scale_fit_s": metrics["bench/scene_model/fit_s"],
        f"{PREFIX}/scale_refine_s": ms * counts["test"] / 1000,
        f"{PREFIX}/scale_ms_per_query": ms,
        f"{PREFIX}/scale_step_s": step["s"],
        f"{PREFIX}/scale_train_images": counts["train"],
        f"{PREFIX}/scale_fit_images": int((~held).sum()),
        f"{PREFIX}/scale_test_images": counts["test"],
        f"{PREFIX}/scale_unique_files": counts["files"],
        f"{PREFIX}/scale_teacher_peak_rss_mb": teacher["rss_mb"],
        f"{PREFIX}/scale_teacher_s": teacher["s"],
        f"{PREFIX}/scale_store_s": store["s"],
        f"{PREFIX}/scale_store_peak_rss_mb": store["rss_mb"],
        f"{PREFIX}/scale_write_s": write_s,
        f"{PREFIX}/scale_total_s": time.perf_counter() - started,
    }
    return figures
