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
from pae.atomic import write_json_atomic
from pae.provenance import save_corrected_config
from pae.reporting import format_results_table, reporting_errors, step_figures
from pae.validation import apply_renamed_keys, validate_train_config


def run(cfg: DictConfig, run_dir: Path) -> dict[str, float | int | str]:
    """Check every setting, then say which dataset the run reads and run the stage's steps,
    each ending in a summary line; metrics.json (with the dataset's `data/...` keys) is
    rewritten atomically after each finished step (by the first process only under DDP)."""
    import lightning as L
    from lightning.pytorch.utilities import rank_zero_only

    from pae.console import duration, quiet_third_party, say
    from pae.pipeline import fit_decoder, fit_rpr, fit_student, fit_teacher, record_dataset
    from pae.pipeline_relative import fit_iapr, fit_rpr_image
    from pae.pipeline_scene import fit_scene_model

    quiet_third_party()
    apply_renamed_keys(cfg, "pae-train")
    validate_train_config(cfg)
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    if rank_zero_only.rank == 0:
        save_corrected_config(cfg, run_dir)
    metrics: dict[str, float | int | str] = dict(record_dataset(cfg, run_dir))
    ckpt = {"teacher": cfg.teacher_ckpt, "student": cfg.student_ckpt, "decoder": cfg.decoder_ckpt}
    several = len(cfg.stage.steps) > 1
    for step in cfg.stage.steps:
        step_dir = run_dir / step if several else run_dir
        started = time.perf_counter()
        if step == "teacher":
            step_metrics, last = fit_teacher(cfg, step_dir)
        elif step == "student":
            step_metrics, last = fit_student(cfg, step_dir, ckpt["teacher"])
        elif step == "decoder":
            step_metrics, last = fit_decoder(cfg, step_dir, ckpt["student"])
        elif step == "rpr_image":
            step_metrics, last = fit_rpr_image(cfg, step_dir, ckpt["teacher"])
        elif step == "iapr":
            step_metrics, last = fit_iapr(cfg, step_dir, ckpt["student"])
        elif step == "scene_model":
            step_metrics, last = fit_scene_model(cfg, step_dir, ckpt)
        else:
            step_metrics, last = fit_rpr(cfg, step_dir, ckpt["student"], ckpt["decoder"])
        if step in ckpt:
            ckpt[step] = last
        metrics |= step_metrics
        if rank_zero_only.rank == 0:
            write_json_atomic(run_dir / "metrics.json", metrics)
        figures = step_figures(step, step_metrics)
        say(
            f"{step}: done in {duration(time.perf_counter() - started)}"
            + (f"; test {figures}" if figures else "")
            + (f"; {last}" if last else "")
        )
    return metrics


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="train")
def main(cfg: DictConfig) -> float | None:
    from lightning.pytorch.utilities import rank_zero_only

    with reporting_errors("pae-train"):
        run_dir = Path(HydraConfig.get().runtime.output_dir)
        metrics = run(cfg, run_dir)
        if rank_zero_only.rank == 0:
            print(format_results_table(metrics, "val"))
            print(format_results_table(metrics))
            if cfg.get("table_footnote"):
                print(cfg.table_footnote)
            print(f"metrics: {run_dir / 'metrics.json'}")
        return objective(metrics)


def objective(metrics: dict[str, float]) -> float | None:
    """What an optimising sweeper minimises: a validation figure, never a test one (the
    student's median position error, else the teacher's)."""
    return metrics.get("val/student/pos_median_m", metrics.get("val/teacher/pos_median_m"))


if __name__ == "__main__":
    main()
