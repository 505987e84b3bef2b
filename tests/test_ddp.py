"""DDP: 2 CPU processes (gloo) count every test sample once, as one process does."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import tiny_data_overrides, tiny_overrides
from tests.figures import WORSE_THAN_MEAN_POSE, assert_error_figure, label_reference

pytestmark = pytest.mark.slow


def _odd_test_split(tiny_root: Path, root: Path) -> Path:
    """A copy of the tiny dataset whose test split has an odd number of rows, so that a
    2-process sampler must pad it with a repeated sample."""
    shutil.copytree(tiny_root, root)
    labels = root / "labels" / "all_test.csv"
    lines = labels.read_text().splitlines(keepends=True)
    labels.write_text("".join(lines[:-1]))
    return root


def _data_overrides(root: Path) -> list[str]:
    return [
        *tiny_data_overrides(root),
        "data.eval_batch_size=5",
        "+trainer.enable_progress_bar=false",
    ]


def _run(program: str, run_dir: Path, *overrides: str) -> dict[str, float]:
    command = [sys.executable, "-m", program, *overrides, f"hydra.run.dir={run_dir}"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads((run_dir / "metrics.json").read_text())


def test_ddp_evaluation_counts_every_sample_once(tiny_root: Path, tmp_path: Path) -> None:
    trained = _run(
        "pae.train",
        tmp_path / "pipeline",
        *tiny_overrides(tiny_root),
        "stage=pipeline",
        "trainer=ddp_sim",
    )
    reference = label_reference(tiny_root, "test")  # every test sample counted once
    for figure in ("pos_median_m", "rot_median_deg", "pos_mean_m", "rot_mean_deg"):
        assert trained[f"test/mean_pose/{figure}"] == pytest.approx(reference[figure], rel=1e-5)
    upper = WORSE_THAN_MEAN_POSE * reference["pos_median_m"]
    assert_error_figure(trained, "test/refined/pos_median_m", upper)
    checkpoint = tmp_path / "pipeline" / "student" / "checkpoints" / "last.ckpt"
    data = _data_overrides(_odd_test_split(tiny_root, tmp_path / "odd"))
    one = _run("pae.evaluate", tmp_path / "one", f"student_ckpt={checkpoint}", *data)
    two = _run(
        "pae.evaluate", tmp_path / "two", f"student_ckpt={checkpoint}", *data, "trainer=ddp_sim"
    )
    figures = sorted(key for key in one if key.startswith("test/"))
    assert "test/refined/pos_median_m" in figures and "test/teacher/pos_median_m" in figures
    assert figures == sorted(key for key in two if key.startswith("test/"))
    for key in figures:
        assert two[key] == pytest.approx(one[key], rel=1e-5, abs=1e-6), key
