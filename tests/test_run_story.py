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
