"""Sweeps through Hydra's launchers: joblib in parallel, SLURM settings on submitit's local
executor; a failed job is reported without stopping the others."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from pae.report.tables import sweep_table
from tests.conftest import tiny_overrides

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def teacher_ckpt(tmp_path_factory: pytest.TempPathFactory, tiny_root: Path) -> Path:
    from hydra import compose, initialize_config_dir
    from omegaconf import open_dict

    from pae import CONFIG_DIR
    from pae.train import run

    run_dir = tmp_path_factory.mktemp("teacher")
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=tiny_overrides(tiny_root), return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(run_dir)
    run(cfg, run_dir)
    return run_dir / "checkpoints" / "last.ckpt"


def _sweep(tiny_root: Path, sweep_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    command = [
        sys.executable,
        "-m",
        "pae.train",
        "-m",
        "stage=student",
        "student.max_epochs=1",
        *tiny_overrides(tiny_root),
        f"hydra.sweep.dir={sweep_dir}",
        *overrides,
    ]
    return subprocess.run(command, capture_output=True, text=True, timeout=900)


def test_joblib_sweep_runs_jobs_in_parallel_on_one_latent_cache(
    tiny_root: Path, teacher_ckpt: Path, tmp_path: Path
) -> None:
    cache = tmp_path / "cache"
    result = _sweep(
        tiny_root,
        tmp_path / "sweep",
        f"teacher_ckpt={teacher_ckpt}",
        "pae.L=0,3",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        f"student.latent_cache_dir={cache}",
    )
    assert result.returncode == 0, result.stderr[-3000:]
    files = sorted((tmp_path / "sweep").glob("*/metrics.json"))
    assert len(files) == 2
    hits = sorted(json.loads(f.read_text())["bench/student/latent_cache_hit"] for f in files)
    assert hits == [0.0, 1.0]  # one job computed the teacher latents, the other read them
    assert len(list(cache.glob("*.pt"))) == 1


def test_slurm_settings_on_the_local_executor_report_a_failed_job(
    tiny_root: Path, teacher_ckpt: Path, tmp_path: Path
) -> None:
    sweep_dir = tmp_path / "sweep"
    missing = tmp_path / "missing.ckpt"
    result = _sweep(
        tiny_root, sweep_dir, f"teacher_ckpt={teacher_ckpt},{missing}", "hydra/launcher=slurm_local"
    )
    assert result.returncode != 0
    assert len(list(sweep_dir.glob("*/metrics.json"))) == 1
    table = sweep_table(sweep_dir)
    assert "1 failed job" in table and "missing.ckpt" in table
