"""What a finished tiny `pae-train stage=pipeline` run leaves to read: its train.log (every
line once, the final tables in it) and its TensorBoard event files."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest

from tests.conftest import tiny_overrides
from tests.test_faults import pae_command


@pytest.fixture(scope="module")
def pipeline_cli_run(tmp_path_factory: pytest.TempPathFactory, tiny_root: Path) -> Path:
    """A teacher -> student run made by `pae-train` as a user starts it (Hydra's logging)."""
    run_dir = tmp_path_factory.mktemp("story") / "run"
    result = pae_command(
        "train",
        *tiny_overrides(tiny_root),
        "stage=pipeline",
        f"hydra.run.dir={run_dir}",
        cwd=run_dir.parent,
    )
    assert result.returncode == 0, result.stderr
    (run_dir.parent / "output.txt").write_text(result.stdout + result.stderr)
    return run_dir


def _log_lines(run_dir: Path) -> list[str]:
    """train.log's lines without their time stamps."""
    lines = (run_dir / "train.log").read_text().splitlines()
    return [line.split("] ", 1)[1] if line.startswith("[") else line for line in lines]


def _records(run_dir: Path) -> list[str]:
    """train.log's records (a table is one), each without its time stamp."""
    text = (run_dir / "train.log").read_text()
    return [record.split("] ", 1)[1] for record in text.split("\n[") if "] " in record]


def test_train_log_holds_every_line_once_and_the_final_tables(pipeline_cli_run: Path) -> None:
    log = (pipeline_cli_run / "train.log").read_text()
    lines = _log_lines(pipeline_cli_run)
    assert "rank_zero" not in log and "[INFO]" not in log
    stamped = [line for line in log.splitlines() if line.startswith("[")]
    assert len(stamped) > 10 and all(line[1:5].isdigit() for line in stamped)
    repeated = [record for record, n in Counter(_records(pipeline_cli_run)).items() if n > 1]
    assert not repeated, repeated
    assert "GPU available: False, used: False" in lines
    assert not [line for line in lines if "Trainer.fit` stopped" in line]
    for split in ("val", "test"):
        assert f"median position [m] / orientation [deg] on the {split} split" in lines
    assert any(line.startswith("refined_test_store *") for line in lines)
    assert any(line.startswith("guess_initial ‡") for line in lines)
    assert any(line.startswith("* uses test labels") for line in lines)
    assert any(line.startswith("‡ starts from the true pose") for line in lines)
    assert lines[-1] == f"metrics: {pipeline_cli_run / 'metrics.json'}"
    console = (pipeline_cli_run.parent / "output.txt").read_text()
    assert console.count("on the test split") == 1 and console.count("GPU available") == 1
    metrics = json.loads((pipeline_cli_run / "metrics.json").read_text())
    assert f"{metrics['test/teacher/pos_median_m']:.3f} / " in log


def _events(folder: Path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(folder), size_guidance={"images": 0, "tensors": 0})
    events.Reload()
    return events


def _hparams(events) -> tuple[list[str], dict[str, str]]:
    """The HParams metrics' tags and the run's settings (as strings) of one event folder."""
    from tensorboard.plugins.hparams import plugin_data_pb2

    tags, settings = [], {}
    for blob in events.PluginTagToContent("hparams").values():
        data = plugin_data_pb2.HParamsPluginData.FromString(blob)
        if data.HasField("experiment"):
            tags = [m.name.tag for m in data.experiment.metric_infos]
        if data.HasField("session_start_info"):
            for key, value in data.session_start_info.hparams.items():
                settings[key] = value.string_value or str(value.number_value)
    return tags, settings


def _layout(events):
    from tensorboard.plugins.custom_scalar import layout_pb2

    [tag] = [t for t in events.Tags()["tensors"] if t.startswith("custom_scalars")]
    blob = events.Tensors(tag)[-1].tensor_proto.string_val[0]
    return layout_pb2.Layout.FromString(blob)


def test_tensorboard_tells_the_runs_story(pipeline_cli_run: Path) -> None:
    """HParams metrics are the val curves (no one-point copies), a Custom Scalars layout puts
    the methods side by side, the learning rate is logged, best_refinement is chosen on val
    and never worse than the teacher."""
    import re

    import cv2
    import numpy as np

    from pae.callbacks.trajectory import METHOD_RGB

    metrics = json.loads((pipeline_cli_run / "metrics.json").read_text())
    for step in ("teacher", "student"):
        events = _events(pipeline_cli_run / step)
        scalars = events.Tags()["scalars"]
        assert not [t for t in scalars if t.startswith(("hparams/", "test/", "bench/"))]
        assert [t for t in scalars if t.startswith("lr-")], f"{step}: no learning rate"
        tags, settings = _hparams(events)
        assert tags[:2] == ["val/teacher/pos_median_m", "val/teacher/rot_median_deg"]
        for tag in tags:  # each a curve over the epochs, none per scene
            assert len(events.Scalars(tag)) >= 2 and tag.count("/") == 2, tag
        assert settings["stage"] == "pipeline"
    assert {"val/cumulative_errors", "test/cumulative_errors"} <= set(events.Tags()["images"])
    encoded = events.Images("test/cumulative_errors")[-1].encoded_image_string
    curves = cv2.imdecode(np.frombuffer(encoded, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    colours = {tuple(c) for c in curves.reshape(-1, 3)}
    assert set(METHOD_RGB[:5]) <= colours  # teacher, refined, knn_mean, two alternatives
    assert tags[2:4] == ["val/student/pos_median_m", "val/student/rot_median_deg"]
    best = settings["best_refinement"]
    honest = ("refined", "knn_mean", "closed_form_k10", "latent_knn", "pose_descent")
    better = [
        m for m in honest if metrics[f"val/{m}/pos_median_m"] < metrics["val/teacher/pos_median_m"]
    ]
    assert best == min(better, key=lambda m: metrics[f"val/{m}/pos_median_m"], default="none")
    if best != "none":
        assert tags[4:6] == [f"val/{best}/pos_median_m", f"val/{best}/rot_median_deg"]

    charts = {
        chart.title: [re.compile(r) for r in chart.multiline.tag]
        for category in _layout(events).category
        if category.title.startswith("methods side by side")
        for chart in category.chart
    }
    position = charts["median position error [m]"]

    def shown(tag: str) -> bool:
        return any(r.search(tag) for r in position)

    for method in ("teacher", "student", "refined", "knn_mean", "latent_knn"):
        assert shown(f"val/{method}/pos_median_m"), method
    for tag in (
        "val/refined_test_store/pos_median_m",
        "val/guess_refined/pos_median_m",
        "val/refined/scene00/pos_median_m",
        "val/student_gt/pos_median_m",
    ):
        assert not shown(tag), tag
