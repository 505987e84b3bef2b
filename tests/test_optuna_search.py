"""The Optuna study as a Hydra sweep (hparams_search=..., pae.config.optuna_study): its search
space, its trials counted across a stopped and a continued run, the configs' keys, and
pae-train's study on the tiny benchmark read back by pae-report."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.utils import JobReturn, JobStatus
from omegaconf import DictConfig, OmegaConf

from pae import CONFIG_DIR
from pae.core.errors import ConfigError
from pae.report.tables import sweep_report
from tests.conftest import tiny_overrides

optuna = pytest.importorskip("optuna")

from optuna.distributions import (  # noqa: E402 (after the skip when optuna is absent)
    CategoricalDistribution,
    FloatDistribution,
    IntDistribution,
)
from optuna.trial import TrialState  # noqa: E402

from pae.config.optuna_study import (  # noqa: E402
    ERROR_ATTR,
    finished_trials,
    open_study,
    run_study,
    search_space,
)


def test_search_space_reads_hydra_sweep_syntax() -> None:
    params = {
        "pae.L": "range(0, 11, 2)",
        "pae.hidden": "choice([32,64],[64,128])",
        "student.optimizer.lr": "tag(log, interval(1e-4, 1e-2))",
        "student.loss.s_x": "interval(-4, 1)",
        "seed": "0,1",
    }
    space, fixed = search_space(params, ["stage=student", "seed=3", "pae.L=range(2, 5)"])
    assert space["pae.L"] == IntDistribution(2, 4, step=1)  # the command line's space wins
    assert space["pae.hidden"] == CategoricalDistribution(["[32,64]", "[64,128]"])
    assert space["student.optimizer.lr"] == FloatDistribution(1e-4, 1e-2, log=True)
    assert space["student.loss.s_x"] == FloatDistribution(-4.0, 1.0)
    assert "seed" not in space and fixed == ["stage=student", "seed=3"]


def test_a_space_the_study_cannot_sample_names_its_key() -> None:
    with pytest.raises(ConfigError, match=r"^backbone=glob\(\*\): not a search space"):
        search_space({"backbone": "glob(*)"}, [])


def _returns(values: list[float | Exception]) -> list[JobReturn]:
    results = []
    for value in values:
        failed = isinstance(value, Exception)
        status = JobStatus.FAILED if failed else JobStatus.COMPLETED
        results.append(JobReturn(status=status, _return_value=value))
    return results


def _random_sampler(seed: int) -> DictConfig:
    return OmegaConf.create({"_target_": "optuna.samplers.RandomSampler", "seed": seed})


def test_a_stopped_study_continues_to_n_trials(tmp_path: Path) -> None:
    """A trial left running (the sweep was killed) is failed and not counted; the trials of
    the first run count; a job that fails is counted and keeps its error; jobs are numbered
    by their trial."""
    storage = f"sqlite:///{tmp_path / 'sweep' / 'optuna.db'}"
    space = {"x": FloatDistribution(0.0, 1.0)}
    launched: list[tuple[int, list[str]]] = []

    def launch(jobs: list[list[str]], first: int) -> list[JobReturn]:
        launched.extend((first + i, job) for i, job in enumerate(jobs))
        values = [float(job[-1].split("=")[1]) for job in jobs]
        return _returns(
            [ConfigError("diverged") if first + i == 3 else v for i, v in enumerate(values)]
        )

    study = open_study(storage, "s", "minimize", _random_sampler(seed=0))
    assert run_study(study, space, ["stage=student"], 2, launch) is None
    study.ask(space)  # trial 2: the sweep is killed while it runs
    again = open_study(storage, "s", "minimize", _random_sampler(seed=1))
    failure = run_study(again, space, ["stage=student"], 5, launch, batch=2)
    assert isinstance(failure, ConfigError)
    states = [t.state for t in again.get_trials()]
    assert states == [TrialState.COMPLETE] * 2 + [TrialState.FAIL] * 2 + [TrialState.COMPLETE] * 2
    trials = again.get_trials()
    assert ERROR_ATTR not in trials[2].user_attrs and trials[3].user_attrs[ERROR_ATTR] == "diverged"
    assert finished_trials(again) == 5
    assert [number for number, _ in launched] == [0, 1, 3, 4, 5]
    assert all(job[0] == "stage=student" and job[1].startswith("x=") for _, job in launched)


@pytest.mark.parametrize("name", ["student_optuna", "teacher_optuna"])
def test_each_searched_key_is_a_setting(name: str) -> None:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", [f"hparams_search={name}"], return_hydra_config=True)
    assert cfg.hydra.sweeper.study_name == name
    space, fixed = search_space(OmegaConf.to_container(cfg.hydra.sweeper.params), [])
    assert len(space) >= 4 and not fixed
    groups = cfg.hydra.runtime.choices
    absent = object()
    missing = [
        k for k in space if k not in groups and OmegaConf.select(cfg, k, default=absent) is absent
    ]
    assert not missing


@pytest.fixture(scope="module")
def teacher_ckpt(tmp_path_factory: pytest.TempPathFactory, tiny_root: Path) -> Path:
    from omegaconf import open_dict

    from pae.train import run

    run_dir = tmp_path_factory.mktemp("teacher")
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=tiny_overrides(tiny_root), return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(run_dir)
    run(cfg, run_dir)
    return run_dir / "checkpoints" / "last.ckpt"


def _search(tiny_root: Path, sweep_dir: Path, teacher: Path, n_trials: int) -> list[str]:
    """The issue's command line on the tiny benchmark: a student search of 1-epoch trials."""
    tiny = [o for o in tiny_overrides(tiny_root) if not o.startswith("+trainer.")]
    return [
        sys.executable,
        "-m",
        "pae.train",
        "-m",
        "hparams_search=student_optuna",
        "experiment=demo",
        "stage=student",
        f"teacher_ckpt={teacher}",
        f"hydra.sweeper.n_trials={n_trials}",
        *tiny,
        "student.max_epochs=1",
        f"hydra.sweep.dir={sweep_dir}",
    ]


def _states(sweep_dir: Path) -> list[str]:
    with sqlite3.connect(sweep_dir / "optuna.db") as db:
        return [row[0] for row in db.execute("SELECT state FROM trials ORDER BY number")]


def test_student_search_writes_its_study_and_pae_report_reads_it(
    tiny_root: Path, teacher_ckpt: Path, tmp_path: Path
) -> None:
    sweep_dir = tmp_path / "search"
    command = _search(tiny_root, sweep_dir, teacher_ckpt, 2)
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert _states(sweep_dir) == ["COMPLETE", "COMPLETE"]
    assert "study student_optuna: best trial" in result.stderr + result.stdout
    table, problems = sweep_report(sweep_dir, "val")
    rows = [line for line in table.splitlines() if "pae.L=" in line]
    assert problems == 0 and len(rows) == 2
    assert rows[0].split(" | ")[0] in (sweep_dir / "report.md").read_text()  # SweepReport
    assert all("student.optimizer.lr=" in row for row in rows)


@pytest.mark.slow
def test_a_killed_search_resumes_where_it_stopped(
    tiny_root: Path, teacher_ckpt: Path, tmp_path: Path
) -> None:
    """The issue's command with 4 trials, killed during its second trial, then run again:
    4 trials finish in all, the killed one is failed and listed by pae-report."""
    sweep_dir = tmp_path / "search"
    command = _search(tiny_root, sweep_dir, teacher_ckpt, 4)
    first = subprocess.Popen(
        command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and first.poll() is None:
        if (sweep_dir / "1" / ".hydra" / "overrides.yaml").is_file():
            break
        time.sleep(0.2)
    os.killpg(first.pid, signal.SIGKILL)
    first.wait()
    assert _states(sweep_dir) == ["COMPLETE", "RUNNING"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert _states(sweep_dir) == ["COMPLETE", "FAIL", "COMPLETE", "COMPLETE", "COMPLETE"]
    assert "left running by a stopped sweep" in result.stderr + result.stdout
    table, problems = sweep_report(sweep_dir, "val")
    assert problems == 1 and "no metrics.json: unfinished, or stopped" in table
    assert sorted(p.parent.name for p in sweep_dir.glob("*/metrics.json")) == ["0", "2", "3", "4"]
