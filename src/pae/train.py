"""`pae-train`: train a teacher APR, a student PAE, or any of the later steps (Hydra; see
conf/train.yaml).

Torch, Lightning and the steps are imported when a run starts, in the process that trains: the
process that launches a sweep's jobs (joblib, submitit) starts them without loading those.
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from pae import CONFIG_DIR
from pae.config.schemas import register_schemas
from pae.config.validation import apply_renamed_keys, validate_train_config
from pae.core.atomic import write_json_atomic
from pae.core.error_reporting import in_one_line, reporting_errors
from pae.core.provenance import save_corrected_config
from pae.core.run_context import start_run
from pae.report.tables import format_results_table, step_figures
from pae.steps import CHECKPOINTS, steps_of


def run(cfg: DictConfig, run_dir: Path) -> dict[str, float | int | str]:
    """Check every setting, then say which dataset the run reads and run the stage's steps
    (``pae.steps``, each given the checkpoints it needs), each ending in a summary line;
    metrics.json (with the dataset's `data/...` keys, and with allow_other_data=true the count
    of checkpoints read that were trained on other data) is rewritten atomically after each
    finished step (by the first process only under DDP)."""
    import lightning as L
    from lightning.pytorch.utilities import rank_zero_only

    from pae.core.console import duration, quiet_third_party, say
    from pae.core.threads import configure_threads
    from pae.runs.inputs import other_data_record, record_dataset

    quiet_third_party()
    say(configure_threads().summary())
    apply_renamed_keys(cfg, "pae-train")
    overrides = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
    validate_train_config(cfg, overrides)
    start_run()
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    if rank_zero_only.rank == 0:
        save_corrected_config(cfg, run_dir)
    metrics: dict[str, float | int | str] = dict(record_dataset(cfg, run_dir))
    checkpoints = {key: cfg[key] for key in CHECKPOINTS}
    steps = steps_of(cfg.stage.steps)
    for step in steps:
        step_dir = run_dir / step.name if len(steps) > 1 else run_dir
        started = time.perf_counter()
        step_metrics, last = step.run(cfg, step_dir, checkpoints)
        if step.produces:
            checkpoints[step.produces] = last
        metrics |= step_metrics | other_data_record(cfg)
        if rank_zero_only.rank == 0:
            write_json_atomic(run_dir / "metrics.json", metrics)
        figures = step_figures(step.name, step_metrics)
        say(
            f"{step.name}: done in {duration(time.perf_counter() - started)}"
            + (f"; test {figures}" if figures else "")
            + (f"; {last}" if last else "")
        )
    return metrics


register_schemas()  # conf/<group>/*.yaml start from them


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="train")
def hydra_main(cfg: DictConfig) -> float | None:
    with reporting_errors("pae-train"):
        from pae.core.console import say

        run_dir = Path(HydraConfig.get().runtime.output_dir)
        metrics = run(cfg, run_dir)
        say(format_results_table(metrics, "val"))
        say(format_results_table(metrics))
        say(f"metrics: {run_dir / 'metrics.json'}")
        return objective(metrics)


def objective(metrics: dict[str, float]) -> float | None:
    """What an optimising sweeper minimises: a validation figure, never a test one (the
    student's median position error, else the teacher's)."""
    return metrics.get("val/student/pos_median_m", metrics.get("val/teacher/pos_median_m"))


main = in_one_line("pae-train", hydra_main)
"""The console entry point: a config Hydra cannot compose is said in one line."""

if __name__ == "__main__":
    main()
