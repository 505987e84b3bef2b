"""Runs that survive: a bad sweep job, an interrupted or damaged run, a bad value, foreign data."""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import cv2
import lightning as L
import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

import pae.runs.trainer
from pae.core.checkpoints import read_checkpoint
from pae.core.errors import CheckpointError, ConfigError, ImageError, LabelError, LabelWarning
from pae.data.dataset import PoseDataset
from pae.data.labels import LabelTable, read_labels, write_labels
from pae.data_cli import main as pae_data
from pae.report.tables import format_results_table, sweep_report, sweep_table
from pae.report.tables import main as reporting_main
from pae.synthetic import write_synthetic_dataset
from pae.train import run
from tests.conftest import TINY, tiny_data_overrides, tiny_overrides
from tests.figures import WORSE_THAN_MEAN_POSE, assert_error_figure, label_reference

SRC = Path(__file__).resolve().parents[1] / "src"


def pae_env() -> dict[str, str]:
    """The environment of a subprocess that runs this checkout's sources."""
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]),
        "OMP_NUM_THREADS": "1",
    }


def pae_command(module: str, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run `python -m pae.<module> ARGS` as a user would, with this checkout's sources."""
    return subprocess.run(
        [sys.executable, "-m", f"pae.{module}", *args],
        capture_output=True,
        text=True,
        env=pae_env(),
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
    """callbacks=minimal, no progress bar (a batch run): the threads, the dataset, a line per
    epoch, a summary; Lightning's lines once, without its advertisement or deprecation
    warnings."""
    output = (teacher_run.parent / "output.txt").read_text()
    lines = output.splitlines()
    assert lines[0].startswith("threads: ")
    assert (
        lines[1].startswith("data: ") and "2 scenes (scene00, scene01); train 48 frames" in lines[1]
    )
    epochs = [
        line for line in lines if line.startswith("teacher: epoch ") and ", batch " not in line
    ]
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
    report = pae_command("report.tables", str(sweep_dir), cwd=tmp_path)
    assert report.returncode == 1, "a sweep with a failed job is reported as failed"
    failed = report.stdout.split("1 failed job:\n")[1]
    assert "teacher.max_epochs=-1" in failed and "must be an integer >= 0" in failed
    assert "| " in report.stdout.split("1 failed job:")[0], "the finished job's row"
    shutil.rmtree(sweep_dir / "1")  # as if the sweep had been stopped before its last job
    report = pae_command("report.tables", str(sweep_dir), cwd=tmp_path)
    assert report.returncode == 1
    [missing] = [line for line in report.stdout.splitlines() if "never started" in line]
    assert "teacher.max_epochs=0 " in missing
    assert missing.endswith(f": never started (job 1, no {sweep_dir / '1'})")


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
    build_trainer = pae.runs.trainer.build_trainer
    monkeypatch.setattr(
        pae.runs.trainer,
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
    train_rows = TINY["scenes"] * TINY["train_frames"] * 5 // 6  # seq-06 of 6 is held out
    assert steps == 3 * (train_rows // 8), "epochs 0-2 are kept"


def test_checkpoints_are_written_whole(
    compose_train, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pae.core.checkpoints import AtomicCheckpointIO

    trainer = pae.runs.trainer.build_trainer(compose_train(), tmp_path, 1, [])
    assert isinstance(trainer.strategy.checkpoint_io, AtomicCheckpointIO)
    path = tmp_path / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint({"global_step": 1}, path)

    def disk_full(obj: object, handle: object) -> None:
        handle.write(b"PK\x03\x04 half a checkpoint")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", disk_full)
    with pytest.raises(OSError, match=f"no space left on .* while writing {path}$"):
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
    "growth",
    [(), ("scene_model.model.grow_from=0.125", "scene_model.model.grow_at_epoch=1")],
    ids=["one_size", "grown"],
)
def test_a_resumed_scene_model_run_gives_the_figures_of_an_uninterrupted_one(
    teacher_run: Path,
    compose_train,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    growth: tuple[str, ...],
) -> None:
    """Every random draw of the scene-model step (ray batches, the samples' jitter) comes
    from (seed, epoch, batch): a run stopped after its first epoch and resumed reports every
    figure of a run that was never stopped (timings aside); ``grown``: the checkpoint holds
    the coarse grid the fit grows from at the second epoch."""
    scene_model = (
        *growth,
        "stage=render_compare",
        f"teacher_ckpt={teacher_run / 'checkpoints' / 'last.ckpt'}",
        "scene_model.max_epochs=2",
        "scene_model.batches_per_epoch=2",
        "scene_model.rays_per_batch=512",
        "scene_model.model.num_voxels=4000",
        "scene_model.image_size=16",
        "render_compare.oracle=false",
        "render_compare.refiner.rounds=1",
        "render_compare.refiner.candidates=4",
        "render_compare.refiner.polish_steps=2",
    )
    whole = run(compose_train(*scene_model), tmp_path / "whole")
    with monkeypatch.context() as patch:
        interrupted_at(patch, 1)
        with pytest.raises(RuntimeError, match="interrupted"):
            run(compose_train(*scene_model), tmp_path / "resumed")
    last = tmp_path / "resumed" / "checkpoints" / "last.ckpt"

    def voxels() -> int:
        grids = read_checkpoint(last)["state_dict"]
        return sum(v[0, 0].numel() for k, v in grids.items() if k.endswith(".grid"))

    saved = voxels()
    resumed = run(compose_train(*scene_model, "resume=true"), tmp_path / "resumed")
    assert (saved < voxels() / 6) if growth else (saved == voxels())

    def figures(metrics: dict[str, float | int | str]) -> dict[str, float | int | str]:
        return {key: value for key, value in metrics.items() if not key.startswith("bench/")}

    assert "test/scene_model/psnr_db" in whole and "val/render_compare/pos_median_m" in whole
    assert figures(resumed) == figures(whole)


def test_a_resumed_teacher_and_student_give_the_figures_of_uninterrupted_ones(
    compose_train, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Data order (scenes balanced), augmentation and dropout come from (seed, epoch, batch):
    a teacher and a student stopped after their first epoch and resumed report every test/
    figure of runs that were never stopped."""

    def whole_and_resumed(*overrides: str, name: str) -> tuple[dict, dict]:
        whole = run(compose_train(*overrides), tmp_path / name / "whole")
        with monkeypatch.context() as patch:
            interrupted_at(patch, 1)
            with pytest.raises(RuntimeError, match="interrupted"):
                run(compose_train(*overrides), tmp_path / name / "resumed")
        resumed = run(compose_train(*overrides, "resume=true"), tmp_path / name / "resumed")
        return tuple(
            {k: v for k, v in m.items() if k.startswith("test/")} for m in (whole, resumed)
        )

    whole, resumed = whole_and_resumed("teacher.model.dropout=0.3", name="teacher")
    assert "test/teacher/pos_median_m" in whole and resumed == whole
    teacher_ckpt = tmp_path / "teacher" / "whole" / "checkpoints" / "last.ckpt"
    student = ("stage=student", f"teacher_ckpt={teacher_ckpt}", "refine=none")
    whole, resumed = whole_and_resumed(*student, name="student")
    assert "test/student/pos_median_m" in whole and resumed == whole


def test_resume_without_a_complete_checkpoint_says_so_and_clears_unfinished_files(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A run killed while writing its first checkpoint left only a temporary file: resuming
    removes it and says, in one line, that the step starts from epoch 0."""
    from pae.runs.trainer import _resume_path

    folder = tmp_path / "scene_model" / "checkpoints"
    folder.mkdir(parents=True)
    (folder / ".last.ckpt.k3x9.tmp").write_bytes(b"PK\x03\x04 half a checkpoint")
    with caplog.at_level("INFO"):
        assert _resume_path(OmegaConf.create({"resume": True}), folder.parent, data=None) is None
    assert list(folder.iterdir()) == []
    lines = [r.getMessage() for r in caplog.records if "resume:" in r.getMessage()]
    assert lines == [
        f"resume: no complete checkpoint in {folder} (removed 1 unfinished .tmp file(s)); "
        "the step starts from epoch 0"
    ]


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


def test_pae_eval_into_a_training_run_names_what_pae_eval_can_do(
    teacher_run: Path, tiny_root: Path, tmp_path: Path
) -> None:
    """pae-eval takes no resume=true: its refusal of a run directory with checkpoints says
    to choose another directory, and touches nothing there."""
    run_dir = copy_run(teacher_run, tmp_path)
    before = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    student = f"student_ckpt={run_dir / 'checkpoints' / 'last.ckpt'}"
    result = pae_command(
        "evaluate",
        *tiny_data_overrides(tiny_root),
        student,
        f"hydra.run.dir={run_dir}",
        cwd=tmp_path,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert error_lines(result.stderr) == [
        f"pae-eval: error: hydra.run.dir={run_dir} already holds the checkpoints of a run "
        f"({run_dir / 'checkpoints'}): pae-eval would write its metrics.json and .hydra/ over "
        "that run's; choose another directory (the checkpoints are read from student_ckpt, "
        "scene_model_ckpt, ...)"
    ]
    assert {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()} == before


def test_pae_eval_refuses_a_checkpoint_of_the_wrong_kind_before_reading_data(
    teacher_run: Path, tiny_root: Path, tmp_path: Path
) -> None:
    """A teacher's checkpoint given as scene_model_ckpt is refused in one line before any
    evaluation runs (nothing is written: no table, no metrics.json)."""
    teacher = teacher_run / "checkpoints" / "last.ckpt"
    result = pae_command(
        "evaluate",
        *tiny_data_overrides(tiny_root),
        f"teacher_ckpt={teacher}",
        f"scene_model_ckpt={teacher}",
        f"hydra.run.dir={tmp_path / 'eval'}",
        cwd=tmp_path,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert error_lines(result.stderr) == [
        f"pae-eval: error: scene_model_ckpt={teacher}: a stage=teacher checkpoint, but "
        "scene_model_ckpt takes a stage=render_compare checkpoint"
    ]
    assert "median position" not in result.stdout + result.stderr
    assert not (tmp_path / "eval" / "metrics.json").exists()


def test_pae_train_refuses_a_checkpoint_of_the_wrong_kind_before_reading_data(
    teacher_run: Path, compose_train, tmp_path: Path
) -> None:
    """A teacher's checkpoint given as student_ckpt (stage=decoder) is refused in one line by
    the train config's checks, before any data is read or anything written."""
    teacher = teacher_run / "checkpoints" / "last.ckpt"
    cfg = compose_train("stage=decoder", f"student_ckpt={teacher}", run_dir=tmp_path)
    message = (
        f"student_ckpt={teacher}: a stage=teacher checkpoint, but student_ckpt takes a "
        "stage=student checkpoint"
    )
    with pytest.raises(CheckpointError, match=re.escape(message)):
        run(cfg, tmp_path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("refine.k=0", "refine.k must be an integer >= 1, got 0"),
        ("refine.lr=-1", "refine.lr must be a number > 0, got -1"),
        ("data.batch_size=0", "data.batch_size must be an integer >= 1, got 0"),
        ("data.batch_size=100", "data.batch_size=100 is larger than the train set (48 rows)"),
        ("teacher.max_epochs=-1", "teacher.max_epochs must be an integer >= 0, got -1"),
        ("student.optimizer.lr=0", "student.optimizer.lr must be a number > 0, got 0"),
        ("pae.L=-1", "pae.L must be an integer >= 0, got -1"),
        (
            "data.crop=40",
            "data.crop=40 is larger than the images' shorter edge after resizing "
            "(data.shorter_edge=32)",
        ),
        ("data.train_lane_m=-0.5", "data.train_lane_m must lie in [0, 1] m, got -0.5"),
        ("data.yaw_stray_rad=2", "data.yaw_stray_rad must lie in [0, pi/2], got 2"),
        (
            "data.val_lane_m=0.8",
            "data.val_lane_m must lie in [-data.train_lane_m, data.train_lane_m] = [-0.5, 0.5] m",
        ),
        ("data.val_walks=-1", "data.val_walks must be an integer >= 0, got -1"),
        ("backbone.weights_path=/nope.pt", "backbone.weights_path=/nope.pt: no such file"),
        ("teacher_ckpt=/nope.ckpt", "teacher_ckpt=/nope.ckpt: no such file"),
        ("data.val_sequences=0", "data.val_sequences must be null, an integer >= 1"),
        ("data.val_sequences=true", "data.val_sequences must be null, an integer >= 1"),
        ("data.val_fraction=1", "data.val_fraction must be null or a number in (0, 1), got 1"),
    ],
)
def test_values_are_checked_before_anything_trains(
    compose_train, tmp_path: Path, override: str, message: str
) -> None:
    with pytest.raises(ConfigError, match=re.escape(message)):
        run(compose_train("stage=pipeline", override, run_dir=tmp_path), tmp_path)
    assert list(tmp_path.iterdir()) == [], "nothing was trained or written"


def test_a_config_hydra_cannot_compose_is_one_line(tmp_path: Path) -> None:
    """A key no schema has, or a value of another type than its setting's, stops pae-train
    in one line naming the key, before anything is written."""
    for override, line in (
        ("data.batch_size=abc", "data.batch_size: Value 'abc' of type 'str' could not be"),
        ("data.val_walk=2", "data.val_walk: not a setting of data; did you mean data.val_walks?"),
        ("data=nope", "In 'train': Could not find 'data/nope' Available options in 'data':"),
    ):
        result = pae_command("train", override, f"hydra.run.dir={tmp_path}/run", cwd=tmp_path)
        assert result.returncode == 1 and "Traceback" not in result.stderr
        assert error_lines(result.stderr) == result.stderr.splitlines()
        assert error_lines(result.stderr)[0].startswith(f"pae-train: error: {line}")
    assert list(tmp_path.iterdir()) == []


def test_validation_walks_need_a_count_of_held_out_sequences(compose_train, tmp_path: Path) -> None:
    """Walks are held out on top of an integer data.val_sequences: named sequences would
    leave them in the train split, so the run stops before any work."""
    overrides = ("stage=pipeline", "data.val_walks=2", "data.val_sequences=[seq-06]")
    with pytest.raises(ConfigError, match=r"data.val_walks=2 holds its walks out on top of"):
        run(compose_train(*overrides, run_dir=tmp_path), tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_run_dir_and_checkpoint_files_fail_in_one_line(tiny_root: Path, tmp_path: Path) -> None:
    (tmp_path / "file").write_text("not a folder")
    result = pae_command(
        "train", *tiny_overrides(tiny_root), f"hydra.run.dir={tmp_path}/file/run", cwd=tmp_path
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert error_lines(result.stderr) == [
        f"pae-train: error: hydra.run.dir={tmp_path}/file/run: cannot be written "
        f"({tmp_path}/file is a file, not a folder)"
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
    out = capsys.readouterr().out
    assert "wide.csv:7: image is 32x48 px, unlike the 32x32 px of most images (47 of 48" in out
    message = r"wide\.png \(.*wide\.csv:7\): image is 32x48 px, unlike the 32x32 px of most"
    with pytest.raises(ImageError, match=message):
        PoseDataset(read_labels(labels), root, table.scene_names, 32, cache=True).load()
    dataset = PoseDataset(read_labels(labels), root, table.scene_names, 32, cache=False)
    message = r"wide\.png: image is 32x48 px, unlike the 32x32 px of the label file's first"
    with pytest.raises(ImageError, match=message):
        dataset.__getitems__(list(range(8)))


def test_an_odd_first_image_is_the_one_blamed(
    tiny_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "data"
    shutil.copytree(tiny_root, root)
    table = read_labels(root / "labels" / "all_train.csv")
    labels = _with_image(root, table, 0, np.zeros((48, 32, 3), np.uint8), "wide.png")
    assert pae_data(["check", str(labels), str(root)]) == 1
    out = capsys.readouterr().out
    assert "wide.csv:2: image is 32x48 px, unlike the 32x32 px of most images (47 of 48" in out
    assert "FAILED: 1 of 48 rows" in out, "the other 47 rows are not blamed"
    with pytest.raises(ImageError, match=r"wide\.png \(.*wide\.csv:2\): image is 32x48 px"):
        PoseDataset(read_labels(labels), root, table.scene_names, 32, cache=True).load()


def test_repeated_rows_are_reported_by_check_and_loaders(
    tiny_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    labels = tmp_path / "twice.csv"
    lines = (tiny_root / "labels" / "all_train.csv").read_text().splitlines(keepends=True)
    labels.write_text("".join([*lines, lines[1], lines[3]]))  # rows 1 and 3 again
    n = len(lines) - 1
    assert pae_data(["check", str(labels), str(tiny_root)]) == 0
    err = capsys.readouterr().err
    expected = f"2 rows repeat an earlier row's image (line {n + 2} repeats line 2, line {n + 3}"
    assert f"pae-data: warning: {labels}: {expected} repeats line 4)" in err
    with pytest.warns(LabelWarning, match=re.escape(expected)):
        read_labels(labels)


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
    from pae.core.checkpoints import DATA_FINGERPRINT_KEY

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


def test_checkpoints_remember_their_train_images(
    teacher_run: Path,
    compose_train,
    tiny_root: Path,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Images rendered at the same poses with another seed are other data: the fingerprint
    tells them apart, a checkpoint trained on the first refuses the second (naming both),
    allow_other_data=true is said and recorded, and a checkpoint written before images were
    fingerprinted loads with a warning line."""
    from pae.core.checkpoints import DATA_FINGERPRINT_KEY

    labels = [str(tiny_root / "labels" / f"all_{split}.csv") for split in ("train", "test")]
    fingerprints = []
    for seed in (0, 1):
        root = tmp_path / f"seed{seed}"
        synth = ["synth", str(root), "--poses", *labels, "--size", "32", "--seed", str(seed)]
        assert pae_data(synth) == 0
        data = instantiate(compose_train(f"data.root={root}").data)
        data.setup()
        fingerprints.append(data.fingerprint())
    assert fingerprints[0]["train_poses_sha256"] == fingerprints[1]["train_poses_sha256"]
    assert fingerprints[0]["train_images_blake2b"] != fingerprints[1]["train_images_blake2b"]

    teacher_ckpt = teacher_run / "checkpoints" / "last.ckpt"
    other = tmp_path / "seed1"
    student = ("stage=student", f"teacher_ckpt={teacher_ckpt}", "student.max_epochs=0")
    cfg = compose_train(*student, f"data.root={other}")
    message = (
        f"{teacher_ckpt}: trained on other train images than those of the data at {other} "
        "(allow_other_data=true uses it anyway)"
    )
    with pytest.raises(CheckpointError, match=f"^{re.escape(message)}$"):
        run(cfg, tmp_path / "refused")
    cfg = compose_train(*student, f"data.root={other}", "allow_other_data=true")
    with caplog.at_level("INFO"):
        run(cfg, tmp_path / "allowed")
    assert (
        f"data: warning: allow_other_data=true: {teacher_ckpt} was trained on other train "
        f"images than those of the data at {other}; used anyway"
    ) in caplog.messages
    written = json.loads((tmp_path / "allowed" / "metrics.json").read_text())
    assert written["data/other_data_checkpoints"] == 1
    assert "allow_other_data=true: 1 checkpoint(s) read were trained on other data" in (
        format_results_table(written)
    )

    old = tmp_path / "old.ckpt"  # as pae wrote checkpoints before it hashed the images
    checkpoint = read_checkpoint(teacher_ckpt)
    del checkpoint[DATA_FINGERPRINT_KEY]["train_images_blake2b"]
    torch.save(checkpoint, old)
    caplog.clear()
    with caplog.at_level("INFO"):
        metrics = run(
            compose_train(*student[:1], f"teacher_ckpt={old}", student[2]), tmp_path / "c"
        )
    assert "test/student/pos_median_m" in metrics and "data/other_data_checkpoints" not in metrics
    assert (
        f"data: warning: {old} records no fingerprint of its train images (written before pae "
        f"recorded one): its images are not checked against those of the data at {tiny_root}"
    ) in caplog.messages


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


# Runs that cannot lie: installs that import anywhere, no result from a diverged model, one
# run per directory, checkpoints of the kind asked for, reports that say what is missing.


def _bound_by_permissions() -> list[str] | None:
    """A command prefix under which read-only files cannot be written: none for a user other
    than root (permissions hold for it); for root, `setpriv` without the capabilities that
    override permissions; None where root has no such tool."""
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        return None
    return [setpriv, "--bounding-set=-dac_override,-dac_read_search", "--"]


@pytest.fixture
def shared_dir(tmp_path: Path) -> Iterator[Path]:
    """A temporary folder whose files can be made read-only and given back afterwards."""
    folder = tmp_path / "shared"
    folder.mkdir()
    yield folder
    for path in [folder, *folder.rglob("*")]:
        if path.is_dir() and not path.is_symlink():
            path.chmod(0o755)
    shutil.rmtree(folder, ignore_errors=True)


def _set_mode(root: Path, folders: int, files: int) -> None:
    for path in [root, *root.rglob("*")]:
        path.chmod(folders if path.is_dir() else files)


def test_a_read_only_install_and_home_train_a_teacher(tiny_root: Path, shared_dir: Path) -> None:
    prefix = _bound_by_permissions()
    if prefix is None:
        pytest.skip("running as root without setpriv to give up overriding permissions")
    install, home, work = shared_dir / "install", shared_dir / "home", shared_dir / "work"
    shutil.copytree(SRC / "pae", install / "src" / "pae", ignore=shutil.ignore_patterns("__py*"))
    shutil.copytree(SRC.parent / "conf", install / "conf")
    shutil.copytree(tiny_root, work / "data")
    home.mkdir()
    _set_mode(install, 0o555, 0o444)
    _set_mode(work, 0o777, 0o644)
    home.chmod(0o555)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_", "XDG_"))}
    env |= {"HOME": str(home), "PYTHONPATH": str(install / "src"), "OMP_NUM_THREADS": "1"}
    overrides = [*tiny_overrides(work / "data"), "teacher.max_epochs=1"]
    result = subprocess.run(
        [*prefix, sys.executable, "-m", "pae.train", *overrides, f"hydra.run.dir={work / 'run'}"],
        capture_output=True,
        text=True,
        env=env,
        cwd=work,
        timeout=300,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stderr.count("numba's compiled loops are not cached") == 1, result.stderr
    assert "test/teacher/pos_median_m" in json.loads((work / "run" / "metrics.json").read_text())
    assert not [p for p in install.rglob("*") if p.suffix in (".nbi", ".nbc", ".pyc")]


def test_compiled_loops_run_uncached_where_no_folder_can_be_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import pae.core.compiled

    blocked = tmp_path / "a file"
    blocked.write_text("no folder can be made below a file")
    monkeypatch.setattr(pae.core.compiled, "candidate_folders", lambda source: [blocked / "cache"])
    monkeypatch.setattr(pae.core.compiled, "_SAID", set())
    pae.core.compiled.cache_folder.cache_clear()
    try:
        with pytest.warns(pae.core.compiled.CompileCacheWarning, match="not cached") as said:
            doubled = pae.core.compiled.jit(nogil=True)(lambda x: 2 * x)
            tripled = pae.core.compiled.jit()(lambda x: 3 * x)
        assert doubled(2) == 4 and tripled(2) == 6
        assert len(said) == 1
    finally:
        pae.core.compiled.cache_folder.cache_clear()


def test_a_changed_helper_module_is_not_run_from_a_stale_cache(tmp_path: Path) -> None:
    """A compiled function whose compiled helper lives in another module of its package:
    changing only the helper's file changes what the cached caller computes (numba keys a
    function's cache on its own file)."""
    package = tmp_path / "toy"
    package.mkdir()
    (package / "__init__.py").write_text("")
    helper = package / "helpers.py"
    helper.write_text(
        "from pae.core.compiled import jit\n\n@jit()\ndef step(x):\n    return x + 1\n"
    )
    (package / "main.py").write_text(
        "from pae.core.compiled import jit\nfrom toy.helpers import step\n\n"
        "@jit()\ndef twice(x):\n    return 2 * step(x)\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env["PYTHONPATH"] = os.pathsep.join([str(SRC), str(tmp_path)])

    def twice_one() -> str:
        command = [sys.executable, "-c", "from toy.main import twice; print(twice(1))"]
        result = subprocess.run(command, capture_output=True, text=True, env=env, check=False)
        assert result.returncode == 0, result.stderr[-3000:]
        return result.stdout.strip()

    assert twice_one() == "4"
    assert list((package / "__pycache__").glob("main.twice-*.nbi")), "the caller was cached"
    assert twice_one() == "4"
    helper.write_text(helper.read_text().replace("x + 1", "x + 2"))
    assert twice_one() == "6"


@pytest.mark.slow
def test_a_changed_helper_is_not_run_from_a_stale_cache(tmp_path: Path) -> None:
    """index._nearest calls insert_sorted, which another module defines: a change to the
    helper's file alone must reach the caller (numba keys a function's own cache on its own
    file only)."""
    shutil.copytree(SRC / "pae", tmp_path / "pae", ignore=shutil.ignore_patterns("__py*"))
    script = (
        "import torch\n"
        "from pae.refine.index import PoseIndex\n"
        "poses = torch.zeros(40, 7)\n"
        "poses[:, 0] = torch.arange(40.0)\n"
        "poses[:, 3] = 1\n"
        "fused = PoseIndex(poses, engine='numba').query(poses[[3, 17]] + 0.1, k=3)[0]\n"
        "batched = PoseIndex(poses, engine='torch').query(poses[[3, 17]] + 0.1, k=3)[0]\n"
        "print(fused.tolist(), batched.tolist())\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env |= {"PYTHONPATH": str(tmp_path), "OMP_NUM_THREADS": "1"}

    def search() -> str:
        result = subprocess.run(
            [sys.executable, "-c", script],
            capture_output=True,
            text=True,
            env=env,
            cwd=tmp_path,
            timeout=300,
            check=False,
        )
        assert result.returncode == 0, result.stderr[-3000:]
        return result.stdout.strip()

    fused, batched = search().split("] [")
    assert fused + "]" == "[" + batched, "the compiled search finds the tensor search's neighbours"
    assert list((tmp_path / "pae" / "refine" / "__pycache__").glob("index._nearest-*.nbi"))
    sorting = "while slot > 0 and values[slot - 1] > value:"
    [helper] = [p for p in (tmp_path / "pae").rglob("*.py") if sorting in p.read_text()]
    assert helper.name != "index.py", "the helper lives in another module than its caller"
    helper.write_text(helper.read_text().replace(sorting, "while slot > 0 and False:"))
    changed, _ = search().split("] [")
    assert changed != fused, "the caller runs the changed helper, not its cached old copy"


def test_a_diverging_run_stops_at_once_and_writes_no_result(
    tiny_root: Path, tmp_path: Path
) -> None:
    run_dir = tmp_path / "run"
    result = pae_command(
        "train",
        *tiny_overrides(tiny_root),
        "teacher.optimizer.lr=1e6",
        f"hydra.run.dir={run_dir}",
        cwd=tmp_path,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    [line] = error_lines(result.stderr)
    assert re.fullmatch(
        r"pae-train: error: teacher: training diverged: the loss is (nan|inf) at step \d+ "
        r"\(epoch 0, batch \d+, learning rate \S+ at that step\); a learning rate too high is "
        r"the common cause: lower teacher\.optimizer\.lr=1000000\.0",
        line,
    ), line
    assert not (run_dir / "metrics.json").exists(), "no figure of a diverged model is written"
    assert not (run_dir / "checkpoints" / "last.ckpt").exists(), "it stopped in its first epoch"
    assert (run_dir / "error.txt").read_text() == line + "\n"
    report = pae_command("report.tables", str(run_dir), cwd=tmp_path)
    assert report.returncode == 1
    assert "1 failed job:" in report.stdout and "training diverged" in report.stdout


def test_non_finite_figures_are_never_results(tmp_path: Path) -> None:
    from types import SimpleNamespace

    from pae.core.atomic import write_json_atomic
    from pae.core.errors import DivergenceError
    from pae.runs.trainer import collect_metrics

    trainer = SimpleNamespace(
        callback_metrics={"test/teacher/pos_median_m": torch.tensor(float("nan"))}
    )
    with pytest.raises(DivergenceError, match=r"teacher: test/teacher/pos_median_m is nan: "):
        collect_metrics(trainer, step="teacher", hint="lower teacher.optimizer.lr")
    with pytest.raises(ValueError, match="not JSON compliant"):
        write_json_atomic(tmp_path / "metrics.json", {"test/teacher/pos_median_m": float("inf")})
    assert list(tmp_path.iterdir()) == []
    old = tmp_path / "old"  # a run written before NaN was refused
    old.mkdir()
    (old / "metrics.json").write_text('{"test/teacher/pos_median_m": NaN}')
    table, problems = sweep_report(old)
    assert problems == 1
    assert "metrics.json holds non-finite figures (NaN): a run that diverged" in table
    assert reporting_main([str(old)]) == 1


def test_a_run_directory_holds_one_run_at_a_time(tiny_root: Path, tmp_path: Path) -> None:
    from pae.core.run_lock import LOCK_FILE, RunDirLock

    run_dir = tmp_path / "run"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from pathlib import Path; from pae.core.run_lock import RunDirLock; "
            "lock = RunDirLock(Path(sys.argv[1]), 'hydra.run.dir'); lock.acquire(); "
            "print('locked', flush=True); "
            "sys.stdin.read()",
            str(run_dir),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=pae_env(),
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        result = pae_command(
            "train", *tiny_overrides(tiny_root), f"hydra.run.dir={run_dir}", cwd=tmp_path
        )
    finally:
        holder.kill()  # a crash: the operating system releases its lock
        holder.wait()
    assert result.returncode == 1 and "Traceback" not in result.stderr
    [line] = error_lines(result.stderr)
    assert line.startswith(
        f"pae-train: error: hydra.run.dir={run_dir} is in use by another run (pid {holder.pid} on"
    )
    assert line.endswith("): wait for it to end, or choose another directory")
    assert [p.name for p in run_dir.iterdir()] == [LOCK_FILE], "the other run's files are intact"
    lock = RunDirLock(run_dir, "hydra.run.dir")
    lock.acquire()  # free again once the holder died
    lock.release()


def _ms_transformer_teacher(compose_train, path: Path) -> Path:
    """A checkpoint of an (untrained) MS-Transformer teacher with PoseNet's latent size, in
    the layout stage=teacher writes."""
    from hydra.utils import instantiate

    from pae.runs.relative import stored_model_config

    cfg = compose_train("teacher=ms_transformer_small", "teacher.model.latent_dim=256")
    config = stored_model_config(cfg.teacher.model) | {"n_scenes": TINY["scenes"]}
    model = instantiate(config)
    hparams = {"teacher_config": config, "scene_names": ["scene00", "scene01"]}
    state = {f"teacher.{key}": value for key, value in model.state_dict().items()}
    torch.save({"hyper_parameters": hparams, "state_dict": state}, path)
    return path


def test_pae_eval_takes_a_teacher_of_the_students_architecture_only(
    teacher_run: Path, compose_train, tiny_root: Path, tmp_path: Path
) -> None:
    from hydra import compose, initialize_config_dir

    from pae import CONFIG_DIR
    from pae.apps.checkpoint_evaluation import evaluate_checkpoints
    from tests.conftest import tiny_data_overrides

    teacher_ckpt = teacher_run / "checkpoints" / "last.ckpt"
    student = ("stage=student", f"teacher_ckpt={teacher_ckpt}", "student.max_epochs=1")
    trained = run(compose_train(*student, "refine=none", run_dir=tmp_path / "s"), tmp_path / "s")
    student_ckpt = tmp_path / "s" / "checkpoints" / "last.ckpt"
    other = _ms_transformer_teacher(compose_train, tmp_path / "ms_transformer.ckpt")

    def evaluate(*overrides: str) -> dict[str, float]:
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            cfg = compose(
                "eval",
                overrides=[*tiny_data_overrides(tiny_root), "refine=none", *overrides],
            )
        return evaluate_checkpoints(cfg, tmp_path / "eval")

    with pytest.raises(
        CheckpointError,
        match=rf"teacher_ckpt={other}: another architecture than the teacher the PAE of "
        rf"{student_ckpt} was trained on \(_target_: pae\.models\.posenet\.PoseNet -> "
        r"pae\.models\.ms_transformer\.MSTransformer; ",
    ):
        evaluate(f"student_ckpt={student_ckpt}", f"teacher_ckpt={other}")
    with pytest.raises(
        CheckpointError,
        match=rf"teacher_ckpt={student_ckpt}: a stage=student checkpoint, but teacher_ckpt takes "
        "a stage=teacher checkpoint; a student checkpoint holds its teacher: pass it as",
    ):
        evaluate(f"student_ckpt={student_ckpt}", f"teacher_ckpt={student_ckpt}")
    with pytest.raises(
        CheckpointError,
        match=rf"student_ckpt={teacher_ckpt}: a stage=teacher checkpoint, but student_ckpt takes",
    ):
        evaluate(f"student_ckpt={teacher_ckpt}")
    same = evaluate(f"student_ckpt={student_ckpt}", f"teacher_ckpt={teacher_ckpt}")
    upper = WORSE_THAN_MEAN_POSE * label_reference(tiny_root, "test")["pos_median_m"]
    assert_error_figure(same, "test/student/pos_median_m", upper)
    for method in ("teacher", "student"):  # the teacher passed is the one the student learnt
        key = f"test/{method}/pos_median_m"
        assert same[key] == pytest.approx(trained[key], rel=1e-5), key


def test_report_lists_every_job_of_a_sweep_that_has_no_result(tmp_path: Path) -> None:
    task = ["stage=teacher", "pae.L=3,6,9"]
    sweeper = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"
    multirun = {"sweep": {"dir": str(tmp_path), "subdir": "${hydra.job.num}"}}
    multirun |= {"sweeper": {"_target_": sweeper, "params": None}, "overrides": {"task": task}}
    OmegaConf.save({"hydra": multirun}, tmp_path / "multirun.yaml")
    for job, length in ((0, 3), (1, 6)):  # job 1 was stopped, job 2 never started
        (tmp_path / str(job) / ".hydra").mkdir(parents=True)
        OmegaConf.save(
            ["stage=teacher", f"pae.L={length}"], tmp_path / str(job) / ".hydra" / "overrides.yaml"
        )
    (tmp_path / "0" / "metrics.json").write_text(
        json.dumps({"test/teacher/pos_median_m": 1.0, "test/teacher/rot_median_deg": 2.0})
    )
    table, problems = sweep_report(tmp_path)
    assert problems == 2
    assert "| stage=teacher pae.L=3 | 1.000 / 2.00 |" in table
    assert table.splitlines()[-3:] == [
        "2 failed jobs:",
        f"- stage=teacher pae.L=6: no metrics.json: unfinished, or stopped without a recorded "
        f"error ({tmp_path / '1'})",
        f"- stage=teacher pae.L=9: never started (job 2, no {tmp_path / '2'})",
    ]
    assert reporting_main([str(tmp_path)]) == 1


def test_a_full_disk_is_one_line_naming_the_device_and_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from pae.core.atomic import device_of
    from pae.core.checkpoints import AtomicCheckpointIO
    from pae.core.error_reporting import reporting_errors

    class FullDisk:
        """A file that takes 100 bytes, then finds no space left (as torch.save sees it)."""

        def __init__(self, handle: object) -> None:
            self.handle, self.room = handle, 100

        def write(self, data: bytes) -> int:
            if len(data) > self.room:
                raise OSError(errno.ENOSPC, "No space left on device")
            self.room -= len(data)
            return self.handle.write(data)

        def flush(self) -> None:
            self.handle.flush()

    save = torch.save
    monkeypatch.setattr(torch, "save", lambda obj, handle: save(obj, FullDisk(handle)))
    path = tmp_path / "checkpoints" / "last.ckpt"
    with pytest.raises(SystemExit), reporting_errors("pae-train"):
        AtomicCheckpointIO().save_checkpoint({"weights": torch.zeros(1000)}, path)
    device = device_of(tmp_path)
    line = f"pae-train: error: no space left on {device} while writing {path}"
    assert capsys.readouterr().err.splitlines() == [line]
    assert list(path.parent.iterdir()) == [], "no partial file is left"
    elsewhere = tmp_path / "events.out.tfevents"  # a write outside pae's own writer
    with pytest.raises(SystemExit), reporting_errors("pae-train"):
        raise OSError(errno.ENOSPC, "No space left on device", str(elsewhere))
    assert capsys.readouterr().err.splitlines() == [
        f"pae-train: error: no space left on {device} while writing {elsewhere}"
    ]


def test_a_full_disk_under_tensorboard_is_one_line_naming_the_event_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """TensorBoard writes its event file from a thread of its own: a full disk there is no
    thread traceback but the run's one-line error, naming the event file."""
    from tensorboard.summary.writer.record_writer import RecordWriter
    from torch.utils.tensorboard import SummaryWriter

    from pae.core.atomic import device_of
    from pae.core.error_reporting import reporting_errors

    with reporting_errors("pae-train"):  # installs the writer threads' hook, as every run does
        writer = SummaryWriter(str(tmp_path))
    writer.flush()
    (events,) = tmp_path.glob("events.out.tfevents.*")

    def disk_full(self: RecordWriter, data: bytes) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(RecordWriter, "write", disk_full)
    writer.add_scalar("train/loss", 1.0)
    writer.file_writer.event_writer._async_writer._worker.join()  # the thread met the full disk
    with pytest.raises(SystemExit), reporting_errors("pae-train"):
        writer.add_scalar("train/loss", 2.0)
    assert capsys.readouterr().err.splitlines() == [
        f"pae-train: error: no space left on {device_of(events)} while writing {events}"
    ]


def test_a_missing_scene_is_named_with_the_scenes_present(tiny_root: Path) -> None:
    from hydra import compose, initialize_config_dir

    from pae import CONFIG_DIR
    from pae.config.validation import validate_train_config

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=["data=cambridge", f"data.root={tiny_root}"])
    message = (
        f"data.scenes=['KingsCollege']: no rows of KingsCollege in data.train_labels="
        f"{tiny_root}/labels/all_train.csv, which has the scenes ['scene00', 'scene01']"
    )
    for batch_size in (32, 1):
        cfg.data.batch_size = batch_size
        with pytest.raises(ConfigError, match=re.escape(message)):
            validate_train_config(cfg)


def test_a_killed_cache_write_leaves_no_temporary_behind(tmp_path: Path) -> None:
    from pae.models.latents import LATENT_KEYS, LatentCache, TeacherLatents

    cache = LatentCache(tmp_path)
    key = {"format": 1, "teacher": "a"}
    mine = tmp_path / f".{cache.path(key).name}.k1ll3d.tmp"  # its writer was killed
    dead = tmp_path / f".{'0' * 32}.pt.k1ll3d.tmp"  # another file's writer, killed too
    live = tmp_path / f".{'f' * 32}.pt.wr1t1ng.tmp"  # another file's writer, still writing
    for temporary in (mine, dead, live):
        temporary.write_bytes(b"half a file")
    writer = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, sys; lock = open(sys.argv[1], 'a'); fcntl.flock(lock, fcntl.LOCK_EX); "
            "print('locked', flush=True); sys.stdin.read()",
            str(tmp_path / f"{'f' * 32}.lock"),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert writer.stdout is not None and writer.stdout.readline().strip() == "locked"
        tensors = {name: torch.zeros(2, 7) for name in LATENT_KEYS}
        latents, hit = cache.load_or_compute(key, 2, lambda: TeacherLatents(tensors))
    finally:
        writer.kill()
        writer.wait()
    assert not hit and len(latents) == 2
    assert not mine.exists() and not dead.exists()
    assert live.exists(), "a live writer's temporary file is left to it"


def test_a_failing_start_check_stops_the_run(
    compose_train, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Hydra turns an exception in a callback into a warning and runs on: a start check that
    fails for any reason ends the process, with its traceback when it is not a user error."""
    import pae.config.preflight

    def broken(cfg: object) -> None:
        raise RuntimeError("a bug in a check")

    monkeypatch.setattr(pae.config.preflight, "validate_train_config", broken)
    cfg = compose_train()
    with pytest.raises(SystemExit) as stopped:
        pae.config.preflight.Preflight("pae-train").on_run_start(cfg)
    assert stopped.value.code == 1
    assert "RuntimeError: a bug in a check" in capsys.readouterr().err


# Runs that cannot be fooled: damaged checkpoints, intrinsics that disagree, scenes a split lacks.


def _tiny_teacher_checkpoint(path: Path) -> Path:
    """An untrained small_cnn PoseNet teacher saved as pae's teacher step saves it (its
    config and scene names as hyper-parameters, its weights under `teacher.`): nothing trains."""
    backbone = {"_target_": "pae.models.backbones.Backbone", "name": "small_cnn"}
    config = {"_target_": "pae.models.posenet.PoseNet", "backbone": backbone, "n_scenes": 2}
    teacher = instantiate(config)
    checkpoint = {
        "epoch": 0,
        "global_step": 0,
        "state_dict": {f"teacher.{key}": value for key, value in teacher.state_dict().items()},
        "hyper_parameters": {"teacher_config": config, "scene_names": ["scene00", "scene01"]},
    }
    torch.save(checkpoint, path)
    return path


def _with_flipped_bits(path: Path, copy: Path, n_bytes: int = 40_000) -> Path:
    """`copy`: `path` with the lowest bit of `n_bytes` bytes in its middle flipped."""
    data = bytearray(path.read_bytes())
    start = (len(data) - n_bytes) // 2
    data[start : start + n_bytes] = bytes(byte ^ 1 for byte in data[start : start + n_bytes])
    copy.write_bytes(bytes(data))
    return copy


def test_a_damaged_checkpoint_is_refused_wherever_it_is_loaded(tmp_path: Path) -> None:
    from pae.core.checkpoints import load_teacher
    from pae.runs.trainer import _resume_path

    intact = _tiny_teacher_checkpoint(tmp_path / "intact.ckpt")
    assert load_teacher(intact, "teacher_ckpt").scene_names == ["scene00", "scene01"]
    step_dir = tmp_path / "teacher"
    (step_dir / "checkpoints").mkdir(parents=True)
    last = _with_flipped_bits(intact, step_dir / "checkpoints" / "last.ckpt")
    damaged = rf"{last}: damaged checkpoint file \(\S+ fails its CRC check\): copy it again"
    with pytest.raises(CheckpointError, match=damaged):  # its weights stay finite
        load_teacher(last, "teacher_ckpt")
    with pytest.raises(
        CheckpointError, match=rf"no readable checkpoint to resume from \({damaged}"
    ):
        _resume_path(OmegaConf.create({"resume": True}), step_dir, data=None)
    checkpoint = read_checkpoint(intact)
    checkpoint["state_dict"]["teacher.head_x.weight"][1, 2] = float("nan")
    torch.save(checkpoint, last)
    nan_weight = r"damaged checkpoint file \(weight teacher\.head_x\.weight holds nan\)"
    with pytest.raises(CheckpointError, match=rf"^{last}: {nan_weight}: copy it again, or retrain"):
        load_teacher(last, "teacher_ckpt")


def _with_focal(
    labels: Path, copy: Path, focal: float | None, odd: dict[int, float] | None = None
) -> Path:
    """`copy`: the label file `labels` with a focal column of `focal` px (None: without one),
    but `odd[i]` px in row i."""
    table = read_labels(labels)
    column = None if focal is None else np.full(len(table), focal)
    for row, value in (odd or {}).items():
        column[row] = value
    write_labels(copy, dataclasses.replace(table, focal=column))
    return copy


def test_intrinsics_are_checked_by_check_and_loaders(
    tiny_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from pae.data.datamodule import PoseDataModule

    labels = tiny_root / "labels"
    train = _with_focal(labels / "all_train.csv", tmp_path / "train.csv", 25.0)
    test = _with_focal(labels / "all_test.csv", tmp_path / "test.csv", None)
    mismatch = f"{test}: no focal column, unlike {train}: the label files of all splits give"
    assert pae_data(["check", str(train), str(test), str(tiny_root)]) == 1
    assert mismatch in capsys.readouterr().out
    with pytest.raises(LabelError, match=re.escape(mismatch)):
        PoseDataModule(str(tiny_root), str(train), str(test)).setup()
    val = _with_focal(labels / "all_test.csv", tmp_path / "val.csv", None)
    test = _with_focal(labels / "all_test.csv", tmp_path / "test.csv", 25.0)
    with pytest.raises(LabelError, match=re.escape(f"{val}: no focal column, unlike {train}")):
        PoseDataModule(str(tiny_root), str(train), str(test), val_labels=str(val)).setup()
    odd = _with_focal(labels / "all_train.csv", tmp_path / "odd.csv", 25.0, {3: 1e-9, 7: 1e12})
    assert pae_data(["check", str(odd), str(test), str(tiny_root)]) == 1
    out = capsys.readouterr().out
    implausible = "px is implausible for images 32 px wide (expected 3.2 to 320 px: 0.1 to 10"
    assert f"odd.csv:5: focal length 1e-09 {implausible}" in out
    assert f"odd.csv:9: focal length 1e+12 {implausible}" in out
    nominal = {"fx": 25.0, "fy": 25.0, "cx": 15.5, "cy": 15.5, "width": 32, "height": 32}
    for camera in (None, nominal, {**nominal, "width": 64, "height": 64}):
        width = camera["width"] if camera else 32  # the focal lengths are px at this width
        message = rf"odd\.csv:5: focal length 1e-09 px is implausible for images {width} px wide"
        with pytest.raises(LabelError, match=message):
            PoseDataModule(str(tiny_root), str(odd), str(test), camera=camera).setup()


def test_val_sequences_as_many_as_a_scene_has_is_said_in_a_warning(
    tiny_root: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """data.val_sequences=6 on scenes of six train sequences cannot hold out whole sequences:
    the fallback to a row holdout is said in a warning line that names a sequence instead."""
    from pae.data.datamodule import PoseDataModule

    labels = [str(tiny_root / "labels" / f"all_{split}.csv") for split in ("train", "test")]
    with caplog.at_level("INFO"):
        PoseDataModule(str(tiny_root), *labels, crop=28, shorter_edge=32, val_sequences=6).setup()
    assert (
        "data: warning: data.val_sequences=6 holds out the last 6 train sequences of each "
        "scene, but scene00, scene01 have no more than 6 (scene00: seq-01 to seq-06): they "
        "hold out their last 10 % of rows instead (data.val_sequences=[seq-06] names a sequence)"
    ) in caplog.messages
    caplog.clear()
    with caplog.at_level("INFO"):
        PoseDataModule(str(tiny_root), *labels, crop=28, shorter_edge=32, val_sequences=5).setup()
    assert not [line for line in caplog.messages if "warning" in line]


def test_a_missing_scene_in_an_evaluated_split_is_said_and_recorded(
    compose_train, tiny_root: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    root = tmp_path / "data"
    shutil.copytree(tiny_root, root)
    test = read_labels(root / "labels" / "all_test.csv")
    kept = [i for i, scene in enumerate(test.scene) if scene != "scene01"]
    write_labels(root / "labels" / "all_test.csv", test.select(kept))
    cfg = compose_train("teacher.max_epochs=0", f"data.root={root}", run_dir=tmp_path / "run")
    with caplog.at_level("INFO"):
        metrics = run(cfg, tmp_path / "run")
    assert metrics["test/missing_scenes"] == 1 and "val/missing_scenes" not in metrics
    written = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert written["test/missing_scenes"] == 1
    assert (
        "teacher: warning: the test split has no rows of the train scenes scene01: its figures "
        "and their overall average cover the other scenes only"
    ) in caplog.messages
    assert "1 train scene(s) have no test rows" in format_results_table(written)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("scene_model.appearance=frame", "unknown scene_model.appearance 'frame'"),
        ("scene_model.fit_trim=1.0", r"scene_model.fit_trim must be a number in \[0, 1\)"),
        (
            "render_compare.refiner.highpass_sigma_px=-1",
            "needs blur_sigma_px, highpass_sigma_px and contrast_sigma_px >= 0",
        ),
    ],
)
def test_scene_model_and_score_settings_are_checked_before_any_work(
    compose_train, override: str, message: str
) -> None:
    from pae.config.validation import validate_train_config

    cfg = compose_train("stage=render_compare", override)
    with pytest.raises(ConfigError, match=message):
        validate_train_config(cfg)


@pytest.mark.parametrize("held_out", ["data.val_sequences=null", "data.val_labels=TEST"])
def test_render_compare_never_calibrates_on_the_test_split(
    compose_train, tiny_root: Path, tmp_path: Path, held_out: str
) -> None:
    """Validation on the test split (data.val_sequences=null, or the test labels as
    data.val_labels) would choose render-and-compare's gate, filters and scene rule on the
    test labels: pae-train's scene-model step and pae-eval with a scene model stop in one line
    naming data.val_sequences before anything is written; a run without render-and-compare
    still validates on the test split (with the data module's warning)."""
    from hydra import compose, initialize_config_dir

    from pae import CONFIG_DIR
    from pae.config.validation import validate_eval_config, validate_train_config

    override = held_out.replace("TEST", str(tiny_root / "labels" / "all_test.csv"))
    message = r"^render_compare: the validation split is the test split \(data.val_sequences="
    for stage in ("render_compare", "full"):
        with pytest.raises(ConfigError, match=message) as refused:
            run(compose_train(f"stage={stage}", override, run_dir=tmp_path), tmp_path)
        assert "\n" not in str(refused.value) and "data.val_sequences=1" in str(refused.value)
    assert list(tmp_path.iterdir()) == [], "nothing was trained or written"
    validate_train_config(compose_train("stage=pipeline", override))
    checkpoint = tmp_path / "scene_model.ckpt"
    checkpoint.touch()
    overrides = [*tiny_data_overrides(tiny_root), "student_ckpt=" + str(checkpoint)]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("eval", overrides=[*overrides, override, f"scene_model_ckpt={checkpoint}"])
        without = compose("eval", overrides=[*overrides, override])
    with pytest.raises(ConfigError, match=message):
        validate_eval_config(cfg)
    validate_eval_config(without)


def test_the_render_compare_callback_refuses_a_data_module_that_validates_on_test(
    tiny_root: Path,
) -> None:
    """The callback itself, given a data module whose validation split is its test split,
    stops at the setup of a fit or a validation (before any work) in that one line; a test
    alone calibrates nothing and runs."""
    from types import SimpleNamespace

    from pae.callbacks.render_compare import RenderCompareCallback
    from pae.data.datamodule import PoseDataModule

    labels = [str(tiny_root / "labels" / f"all_{split}.csv") for split in ("train", "test")]
    callback = RenderCompareCallback({"rounds": 2})
    for settings in ({"val_sequences": None}, {"val_labels": labels[1]}):
        data = PoseDataModule(str(tiny_root), *labels, crop=28, shorter_edge=32, **settings)
        trainer = SimpleNamespace(datamodule=data)
        assert data.val_is_test
        for stage in ("fit", "validate"):
            with pytest.raises(ConfigError, match=r"^render_compare: the validation split is"):
                callback.setup(trainer, None, stage)
        callback.setup(trainer, None, "test")
    held = PoseDataModule(str(tiny_root), *labels, crop=28, shorter_edge=32)
    assert not held.val_is_test
    callback.setup(SimpleNamespace(datamodule=held), None, "fit")


@pytest.mark.slow
def test_a_teacher_killed_after_an_epoch_and_resumed_reports_the_uninterrupted_figures(
    tiny_root: Path, tmp_path: Path
) -> None:
    """pae-train as a user runs it: one teacher never stopped; another SIGKILLed once its first
    checkpoint exists, then run again with resume=true. Every test/teacher figure is equal."""
    import time

    from tests.conftest import tiny_overrides

    def command(run_dir: Path, *extra: str) -> list[str]:
        overrides = [*tiny_overrides(tiny_root), "teacher.max_epochs=4", "stage=teacher"]
        return [sys.executable, "-m", "pae.train", *overrides, f"hydra.run.dir={run_dir}", *extra]

    whole, killed = tmp_path / "whole", tmp_path / "killed"
    subprocess.run(command(whole), check=True, capture_output=True)
    process = subprocess.Popen(
        command(killed), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    checkpoint = killed / "checkpoints" / "last.ckpt"
    while process.poll() is None and not checkpoint.exists():
        time.sleep(0.05)
    process.kill()
    process.wait()
    assert process.returncode == -9, "the run ended before its first checkpoint was seen"
    subprocess.run(command(killed, "resume=true"), check=True, capture_output=True)

    def figures(run_dir: Path) -> dict[str, float]:
        metrics = json.loads((run_dir / "metrics.json").read_text())
        return {k: v for k, v in metrics.items() if k.startswith("test/teacher/")}

    assert figures(whole) and figures(killed) == figures(whole)


def test_preflight_pickles_for_a_sweep_launcher_without_its_locks(tmp_path: Path) -> None:
    """joblib and submitit pickle Hydra's callbacks for each job: Preflight goes without the
    run-directory locks, which stay with the launching process."""
    import pickle

    from pae.config.preflight import Preflight
    from pae.core.run_lock import RunDirLock

    preflight = Preflight("pae-train")
    lock = preflight.locks.setdefault(tmp_path, RunDirLock(tmp_path, "hydra.sweep.dir"))
    lock.acquire()
    sent = pickle.loads(pickle.dumps(preflight))
    assert sent.program == "pae-train" and sent.locks == {}
    assert preflight.locks[tmp_path] is lock
    lock.release()
