"""Every val and test query of a finished MS-Transformer run tried in every scene, exactly as
its scene-model step tries them against the learned scene model (the run's checkpoints and
settings, every start of pae.render_compare.scene_starts, every probe scale), saved for the
study of scene rules in ``rules.py``. The test split's true scenes are saved beside them:
an audit of the test labels, never an input of a rule.

    PYTHONPATH=src python experiments/ms_scene_decision/trials.py outputs/ms54_seed0 trials0.pt
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import torch

import pae.train
from pae.apps import localization as loc
from pae.render_compare import api, scene_decision
from pae.scene_model.oracle import OracleSceneModel

CAPTURED: dict[str, dict[str, Any]] = {"val": {}, "test": {}}
"""Per split: the learned scene model's trials and the queries' predicted scenes (the oracle
bound, which decides scenes with the benchmark's own renderer, is left out), the teacher's
scene log-probabilities and, for val, the true scenes."""


def _learned(refine: Any) -> bool:
    return not isinstance(getattr(refine, "scene_model", None), OracleSceneModel)


def _val_trials(refine, probe, images, intrinsics, poses, predicted, first, query, scales):
    trials = try_scenes(refine, probe, images, intrinsics, poses, predicted, first, query, scales)
    if _learned(refine):
        CAPTURED["val"] |= {"trials": trials, "predicted": predicted}
    return trials


def _val_rule(trials, prior, predicted, truth, check_below=None):
    CAPTURED["val"] |= {"prior": prior, "truth": truth}
    return choose_scene_rule(trials, prior, predicted, truth, check_below)


def _test_trials(refine, probe, images, intrinsics, poses, predicted, first, query, scales):
    every_scale = scene_decision.PROBE_SCALES
    trials = try_scenes(
        refine, probe, images, intrinsics, poses, predicted, first, query, every_scale
    )
    if _learned(refine):
        CAPTURED["test"] |= {"trials": trials, "predicted": predicted}
    return trials


def _test_prior(first, predicted, query, trials, log_prior, rule):
    CAPTURED["test"]["prior"] = log_prior
    return apply(first, predicted, query, trials, log_prior, rule)


choose_scene_rule = api.choose_scene_rule
try_scenes = scene_decision.try_scenes
apply = scene_decision.apply


def main(run_dir: Path, out: Path) -> None:
    run = loc.read_run(run_dir)
    api.choose_scene_rule, api.try_scenes = _val_rule, _val_trials
    scene_decision.try_scenes, scene_decision.apply = _test_trials, _test_prior
    checkpoints = {
        "teacher_ckpt": run_dir / "teacher" / "checkpoints" / "last.ckpt",
        "scene_model_ckpt": run_dir / "scene_model" / "checkpoints" / "last.ckpt",
    }
    sys.argv = [
        "pae-train",
        "experiment=demo_ms_transformer",
        f"seed={run.config.seed}",
        "stage.steps=[scene_model]",
        *(f"{key}={path}" for key, path in checkpoints.items()),
        "render_compare.scene_check_below=2",  # every test query tried in every scene
        f"hydra.run.dir={out.with_suffix('')}_run",
    ]
    try:
        pae.train.main()
    except SystemExit as done:
        if done.code:
            raise
    data = loc.data_module(run, cache_images=False)
    data.setup()
    test_truth = data.tables["test"].scene_ids(data.scene_names)
    CAPTURED["test"]["truth"] = torch.as_tensor(test_truth, dtype=torch.long)
    torch.save(CAPTURED, out)
    for split, found in CAPTURED.items():
        accuracy = float((found["predicted"] == found["truth"]).float().mean())
        print(f"{split}: {len(found['truth'])} queries, teacher scene accuracy {accuracy:.3f}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
