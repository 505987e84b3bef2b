"""Runs that survive: a bad sweep job, an interrupted or damaged run, a bad value, foreign data."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import lightning as L
import numpy as np
import pytest
import torch

import pae.pipeline
from pae.checkpoints import read_checkpoint
from pae.data.cli import main as pae_data
from pae.data.dataset import PoseDataset
from pae.data.labels import LabelTable, read_labels, write_labels
from pae.data.synthetic import write_synthetic_dataset
from pae.errors import CheckpointError, ConfigError, ImageError, LabelError
from pae.reporting import sweep_table
from pae.train import run
from tests.conftest import TINY, tiny_overrides

SRC = Path(__file__).resolve().parents[1] / "src"


def pae_command(module: str, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run `python -m pae.<module> ARGS` as a user would, with this checkout's sources."""
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]),
        "OMP_NUM_THREADS": "1",
    }
    return subprocess.run(
        [sys.executable, "-m", f"pae.{module}", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=cwd,
        timeout=300,
        check=False,
    )


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if "error:" in line]


@pytest.fixture(scope="module")
def teacher_run(tmp_path_factory: pytest.TempPathFactory, tiny_root: Path) -> Path:
    """A finished 2-epoch teacher run made by `pae-train` (with its .hydra/ files)."""
    run_dir = tmp_path_factory.mktemp("faults") / "teacher"
    result = pae_command(
        "train",
        *tiny_overrides(tiny_root),
        f"hydra.run.dir={run_dir}",
        cwd=run_dir.parent,
    )
    assert result.returncode == 0, result.stderr
    (run_dir.parent / "output.txt").write_text(result.stdout + result.stderr)
    return run_dir


def test_a_batch_run_prints_progress_and_each_line_once(teacher_run: Path) -> None:
    """callbacks=minimal, no progress bar (a batch run): the dataset, a line per epoch, a
    summary; Lightning's lines once, without its advertisement or deprecation warnings."""
    output = (teacher_run.parent / "output.txt").read_text()
    lines = output.splitlines()
    assert (
        lines[0].startswith("data: ") and "2 scenes (scene00, scene01); train 48 frames" in lines[0]
    )
    epochs = [line for line in lines if line.startswith("teacher: epoch ")]
    assert len(epochs) == 2
    assert epochs[0].startswith("teacher: epoch 1/2, loss ") and ", val teacher " in epochs[0]
    assert "elapsed, ETA " in epochs[0] and "ETA" not in epochs[1]
    done = [line for line in lines if line.startswith("teacher: done in ")]
    assert len(done) == 1 and done[0].endswith(str(teacher_run / "checkpoints" / "last.ckpt"))
    assert "; test teacher " in done[0]
    assert output.count("GPU available") == 1
    for noise in ("INFO:", "[INFO]", "💡", "litlogger", "LeafSpec", "Warning"):
        assert noise not in output, noise
    assert "teacher: epoch 1/2" in (teacher_run / "train.log").read_text()


def copy_run(run_dir: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    return copy


def test_a_bad_sweep_job_does_not_stop_the_others(tiny_root: Path, tmp_path: Path) -> None:
    sweep_dir = tmp_path / "sweep"
    result = pae_command(
        "train",
        "-m",
        *tiny_overrides(tiny_root),
        "teacher.max_epochs=-1,0",
        f"hydra.sweep.dir={sweep_dir}",
        cwd=tmp_path,
    )
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    assert error_lines(result.stderr)[0] == (
        "pae-train: error: teacher.max_epochs must be an integer >= 0, got -1"
    )
    assert (sweep_dir / "1" / "metrics.json").is_file(), "the job after the bad one ran"
    assert "teacher.max_epochs must be" in (sweep_dir / "0" / "error.txt").read_text()
    report = pae_command("reporting", str(sweep_dir), cwd=tmp_path)
    assert report.returncode == 0
    failed = report.stdout.split("1 failed job:\n")[1]
    assert "teacher.max_epochs=-1" in failed and "must be an integer >= 0" in failed
    assert "| " in report.stdout.split("1 failed job:")[0], "the finished job has its row"


def test_report_names_failed_jobs_and_corrupt_metrics(tmp_path: Path) -> None:
    (tmp_path / "0").mkdir()
    (tmp_path / "0" / "metrics.json").write_text(
        json.dumps({"test/teacher/pos_median_m": 1.0, "test/teacher/rot_median_deg": 2.0})
    )
    (tmp_path / "1").mkdir()
    (tmp_path / "1" / "error.txt").write_text("pae-train: error: refine.k must be ...\n")
    (tmp_path / "2").mkdir()
    (tmp_path / "2" / "metrics.json").write_text('{"test/teacher/pos_median_m": 1.')
    table = sweep_table(tmp_path)
    assert "| 0 | 1.000 / 2.00 |" in table
    assert "- 1: pae-train: error: refine.k must be ..." in table
    assert f"- 2: {tmp_path / '2' / 'metrics.json'}: unreadable metrics.json" in table


class Interrupt(L.Callback):
    def __init__(self, epoch: int) -> None:
        self.epoch = epoch

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.current_epoch == self.epoch:
            raise RuntimeError("interrupted")


def interrupted_at(monkeypatch: pytest.MonkeyPatch, epoch: int) -> None:
    build_trainer = pae.pipeline.build_trainer
    monkeypatch.setattr(
        pae.pipeline,
        "build_trainer",
        lambda cfg, step_dir, epochs, callbacks, **kw: build_trainer(
            cfg, step_dir, epochs, [*callbacks, Interrupt(epoch)], **kw
        ),
    )


def test_last_checkpoint_after_every_training_epoch(
    compose_train, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = compose_train(
        "teacher.max_epochs=4", "trainer.check_val_every_n_epoch=10", run_dir=tmp_path
    )
    interrupted_at(monkeypatch, 3)
    with pytest.raises(RuntimeError, match="interrupted"):
        run(cfg, tmp_path)
    steps = read_checkpoint(tmp_path / "checkpoints" / "last.ckpt")["global_step"]
    assert steps == 3 * (TINY["scenes"] * TINY["train_frames"] // 8), "epochs 0-2 are kept"


def test_checkpoints_are_written_whole(
    compose_train, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pae.checkpoints import AtomicCheckpointIO

    trainer = pae.pipeline.build_trainer(compose_train(), tmp_path, 1, [])
    assert isinstance(trainer.strategy.checkpoint_io, AtomicCheckpointIO)
    path = tmp_path / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint({"global_step": 1}, path)

    def disk_full(obj: object, handle: object) -> None:
        handle.write(b"PK\x03\x04 half a checkpoint")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", disk_full)
    with pytest.raises(OSError, match="No space left"):
        AtomicCheckpointIO().save_checkpoint({"global_step": 2}, path)
    assert read_checkpoint(path)["global_step"] == 1
    assert [p.name for p in tmp_path.iterdir() if p.suffix == ".tmp"] == []


def test_each_checkpoint_is_stored_once(teacher_run: Path) -> None:
    assert [p.name for p in (teacher_run / "checkpoints").iterdir()] == ["last.ckpt"]


def test_resume_falls_back_and_continues_a_longer_schedule(
    teacher_run: Path, tiny_root: Path, tmp_path: Path
) -> None:
    run_dir = copy_run(teacher_run, tmp_path)
    checkpoints = run_dir / "checkpoints"
    last = checkpoints / "last.ckpt"
    steps_per_epoch = read_checkpoint(last)["global_step"] // 2
    # an older checkpoint beside it (a run that kept one per epoch), then a damaged last.ckpt
    shutil.copy(last, checkpoints / "epoch001.ckpt")
    last.write_bytes(last.read_bytes()[: last.stat().st_size // 3])  # what a full disk leaves
    os.utime(last, ns=(last.stat().st_atime_ns, last.stat().st_mtime_ns + 10**9))
    result = pae_command(
        "train",
        *tiny_overrides(tiny_root),
        "teacher.max_epochs=3",  # OneCycleLR over more steps than the checkpoint's schedule
        "resume=true",
        f"hydra.run.dir={run_dir}",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert "last.ckpt: not a readable checkpoint" in result.stderr + result.stdout
    assert "resuming from epoch001.ckpt instead" in result.stderr + result.stdout
    assert read_checkpoint(last)["global_step"] == 3 * steps_per_epoch
    assert "teacher.max_epochs=3" in (run_dir / ".hydra" / "overrides.yaml").read_text()


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("changed", "trained with other settings (data.batch_size: 8 -> 4; pae.L: 6 -> 3)"),
        ("fresh", "already holds the checkpoints of a run"),
        ("elsewhere", "is not an earlier run (no .hydra/config.yaml)"),
        ("unreadable", "no readable checkpoint in"),
    ],
)
def test_resume_that_cannot_work_stops_before_the_run_dir_is_touched(
    teacher_run: Path, tiny_root: Path, tmp_path: Path, case: str, message: str
) -> None:
    run_dir = copy_run(teacher_run, tmp_path)
    overrides = {
        "changed": ["resume=true", f"hydra.run.dir={run_dir}", "pae.L=3", "data.batch_size=4"],
        "fresh": [f"hydra.run.dir={run_dir}"],
        "elsewhere": ["resume=true", f"hydra.run.dir={tmp_path / 'missing'}"],
        "unreadable": ["resume=true", f"hydra.run.dir={run_dir}"],
    }[case]
    if case == "unreadable":
        for path in (run_dir / "checkpoints").iterdir():
            path.write_bytes(path.read_bytes()[:1000])
    before = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    result = pae_command("train", *tiny_overrides(tiny_root), *overrides, cwd=tmp_path)
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    assert len(error_lines(result.stderr)) == 1 and message in result.stderr
    assert {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "missing").exists()


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("refine.k=0", "refine.k must be an integer >= 1, got 0"),
        ("refine.lr=-1", "refine.lr must be a number > 0, got -1"),
        ("data.batch_size=abc", "data.batch_size must be an integer >= 1, got 'abc'"),
        ("data.batch_size=0", "data.batch_size must be an integer >= 1, got 0"),
        ("data.batch_size=100", "data.batch_size=100 is larger than the train set (48 rows)"),
        ("teacher.max_epochs=-1", "teacher.max_epochs must be an integer >= 0, got -1"),
        ("student.optimizer.lr=0", "student.optimizer.lr must be a number > 0, got 0"),
        ("pae.L=abc", "pae.L must be an integer >= 0, got 'abc'"),
        ("pae.L=-1", "pae.L must be an integer >= 0, got -1"),
        ("data.crop=40", "data.crop=40 is larger than data.shorter_edge=32"),
        ("data.train_lane_m=-0.5", "data.train_lane_m must be a number >= 0, got -0.5"),
        ("data.yaw_stray_rad=2", "data.yaw_stray_rad must be <= 1.5708, got 2"),
        ("backbone.weights_path=/nope.pt", "backbone.weights_path=/nope.pt: no such file"),
        ("teacher_ckpt=/nope.ckpt", "teacher_ckpt=/nope.ckpt: no such file"),
    ],
)
def test_values_are_checked_before_anything_trains(
    compose_train, tmp_path: Path, override: str, message: str
) -> None:
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        run(compose_train("stage=pipeline", override, run_dir=tmp_path), tmp_path)
    assert list(tmp_path.iterdir()) == [], "nothing was trained or written"


def test_run_dir_and_checkpoint_files_fail_in_one_line(tiny_root: Path, tmp_path: Path) -> None:
    (tmp_path / "file").write_text("not a folder")
    result = pae_command(
        "train", *tiny_overrides(tiny_root), f"hydra.run.dir={tmp_path}/file/run", cwd=tmp_path
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert error_lines(result.stderr) == [
        f"pae-train: error: hydra.run.dir={tmp_path}/file/run: cannot be created "
        f"({tmp_path}/file is not a directory)"
    ]
    with pytest.raises(CheckpointError, match=r"file: not a readable checkpoint \(not a complete"):
        read_checkpoint(tmp_path / "file")


def _with_image(root: Path, table: LabelTable, row: int, image: np.ndarray, name: str) -> Path:
    """A copy of `table` whose row `row` points at a new image `name` (relative to root)."""
    cv2.imwrite(str(root / name), image)
    paths = list(table.img_path)
    paths[row] = name
    labels = root / "labels" / f"{Path(name).stem}.csv"
    write_labels(labels, LabelTable(table.scene, table.split, table.seq, paths, table.poses))
    return labels


def test_check_and_loaders_agree_on_image_size(
    tiny_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "data"
    shutil.copytree(tiny_root, root)
    table = read_labels(root / "labels" / "all_train.csv")
    labels = _with_image(root, table, 5, np.zeros((48, 32, 3), np.uint8), "wide.png")
    assert pae_data(["check", str(labels), str(root)]) == 1
    assert "wide.csv:7: image is 32x48 px, unlike the 32x32 px" in capsys.readouterr().out
    message = r"wide\.png: image is 32x48 px, unlike the 32x32 px of the first image"
    with pytest.raises(ImageError, match=message):
        PoseDataset(read_labels(labels), root, table.scene_names, 32, cache=True).load()
    dataset = PoseDataset(read_labels(labels), root, table.scene_names, 32, cache=False)
    with pytest.raises(ImageError, match=message):
        dataset.__getitems__(list(range(8)))


def test_check_and_loaders_agree_on_paths_outside_the_root(
    tiny_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "data"
    shutil.copytree(tiny_root, root)
    table = read_labels(root / "labels" / "all_train.csv")
    outside = cv2.imread(str(root / table.img_path[0]))
    labels = _with_image(root, table, 2, outside, "../outside.png")
    assert pae_data(["check", str(labels), str(root)]) == 1
    assert "outside.csv:4: image path escapes the root" in capsys.readouterr().out
    with pytest.raises(LabelError, match=r"outside\.csv:4: image path escapes the root"):
        PoseDataset(read_labels(labels), root, table.scene_names, 32)


def test_checkpoints_remember_their_data(
    teacher_run: Path, compose_train, tiny_root: Path, tmp_path: Path
) -> None:
    from pae.checkpoints import DATA_FINGERPRINT_KEY

    teacher_ckpt = teacher_run / "checkpoints" / "last.ckpt"
    fingerprint = read_checkpoint(teacher_ckpt)[DATA_FINGERPRINT_KEY]
    assert fingerprint["scenes"] == ["scene00", "scene01"]
    other = tmp_path / "other_rooms"  # the same scene names, other rooms
    write_synthetic_dataset(other, seed=1, **TINY)
    student = ("stage=student", f"teacher_ckpt={teacher_ckpt}", "student.max_epochs=0")
    cfg = compose_train(*student, f"data.root={other}", run_dir=tmp_path / "a")
    with pytest.raises(CheckpointError, match="trained on other train poses"):
        run(cfg, tmp_path / "a")
    cfg = compose_train(*student, f"data.root={other}", "allow_other_data=true")
    assert "test/student/pos_median_m" in run(cfg, tmp_path / "b")
    assert "test/student/pos_median_m" in run(compose_train(*student), tmp_path / "c")


def test_synth_into_a_used_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    small = ["--train-frames", "3", "--test-frames", "2", "--size", "16"]
    fresh, used = tmp_path / "fresh", tmp_path / "used"
    assert pae_data(["synth", str(fresh), "--scenes", "1", *small]) == 0
    assert pae_data(["synth", str(used), "--scenes", "2", *small]) == 0
    (used / "scene01" / "notes.png").write_bytes(b"stale")
    capsys.readouterr()
    assert pae_data(["synth", str(used), "--scenes", "1", *small]) == 1
    assert "folder is not empty; --overwrite replaces" in capsys.readouterr().err
    assert pae_data(["synth", str(used), "--scenes", "1", *small, "--overwrite"]) == 0

    def files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}

    assert files(used) == files(fresh)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fresh", "used"]
    assert pae_data(["synth", str(tmp_path), "--overwrite", *small]) == 1
    assert "holds no dataset" in capsys.readouterr().err


def test_old_checkpoint_key_still_works_with_a_deprecation_line(tmp_path: Path) -> None:
    result = pae_command("evaluate", f"pae_ckpt={tmp_path / 'nope.ckpt'}", cwd=tmp_path)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert "pae-eval: warning: pae_ckpt is deprecated, use student_ckpt" in result.stderr
    assert error_lines(result.stderr) == [
        f"pae-eval: error: student_ckpt={tmp_path / 'nope.ckpt'}: no such file"
    ]
