"""`pae-eval`: evaluate trained checkpoints with test-time refinement, and the methods of
rpr, rpr_image and iapr checkpoints (`method_ckpts`) (Hydra; conf/eval.yaml).

Torch, Lightning and the evaluations (`pae.apps.checkpoint_evaluation`) are imported when a run
starts, as in `pae-train`.
"""

from __future__ import annotations

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from pae import CONFIG_DIR
from pae.config.schemas import register_schemas
from pae.config.validation import apply_renamed_keys, validate_eval_config
from pae.core.atomic import write_json_atomic
from pae.core.error_reporting import in_one_line, reporting_errors
from pae.core.provenance import save_corrected_config
from pae.core.run_context import start_run
from pae.report.tables import format_results_table

register_schemas()  # conf/<group>/*.yaml start from them


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="eval")
def hydra_main(cfg: DictConfig) -> float | None:
    from pae.core.console import quiet_third_party

    quiet_third_party()
    with reporting_errors("pae-eval"):
        import lightning as L
        from lightning.pytorch.utilities import rank_zero_only

        from pae.apps.checkpoint_evaluation import evaluate_checkpoints, evaluate_methods
        from pae.core.checkpoints import check_checkpoint_kinds
        from pae.core.console import say
        from pae.core.threads import configure_threads
        from pae.runs.inputs import other_data_record, record_dataset

        say(configure_threads().summary())
        apply_renamed_keys(cfg, "pae-eval")
        validate_eval_config(cfg)
        check_checkpoint_kinds(
            {key: cfg.get(key) for key in ("student_ckpt", "teacher_ckpt", "scene_model_ckpt")}
        )
        start_run()
        L.seed_everything(cfg.seed, verbose=False)
        run_dir = Path(HydraConfig.get().runtime.output_dir)
        if rank_zero_only.rank == 0:
            save_corrected_config(cfg, run_dir)
        metrics = record_dataset(cfg, run_dir) | evaluate_checkpoints(cfg, run_dir)
        metrics |= evaluate_methods(cfg, run_dir) | other_data_record(cfg)
        if rank_zero_only.rank == 0:  # under DDP every process holds the same figures
            write_json_atomic(run_dir / "metrics.json", metrics)
        say(format_results_table(metrics, "val"))
        say(format_results_table(metrics))
        say(f"metrics: {run_dir / 'metrics.json'}")
        return metrics.get("val/refined/pos_median_m")  # a sweeper's objective: never test


main = in_one_line("pae-eval", hydra_main)
"""The console entry point: a config Hydra cannot compose is said in one line."""

if __name__ == "__main__":
    main()
