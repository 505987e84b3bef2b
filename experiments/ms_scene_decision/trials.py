"""Every val and test query of a finished MS-Transformer run tried in every scene, exactly as
its scene-model step tries them (the run's checkpoints and settings, every start of
pae.render_compare.scene_starts, every probe scale), saved for the study of scene rules in
``rules.py``. The test split's true scenes are saved beside them: an audit of the test
labels, never an input of a rule.

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

CAPTURED: dict[str, dict[str, Any]] = {}


def _capture_val(trials, prior, predicted, truth, check_below=None):
    CAPTURED["val"] = {"trials": trials, "prior": prior, "predicted": predicted, "truth": truth}
    return choose_scene_rule(trials, prior, predicted, truth, check_below)


def _every_scale(refine, probe, images, intrinsics, poses, predicted, first, query, scales):
    return try_scenes(
        refine,
        probe,
        images,
        intrinsics,
        poses,
        predicted,
        first,
        query,
        scene_decision.PROBE_SCALES,
    )


def _capture_test(first, predicted, query, trials, log_prior, rule):
    CAPTURED["test"] = {"trials": trials, "prior": log_prior, "predicted": predicted}
    return apply(first, predicted, query, trials, log_prior, rule)


choose_scene_rule = api.choose_scene_rule
try_scenes = scene_decision.try_scenes
apply = scene_decision.apply


def main(run_dir: Path, out: Path) -> None:
    run = loc.read_run(run_dir)
    api.choose_scene_rule = _capture_val
    scene_decision.try_scenes = _every_scale
    scene_decision.apply = _capture_test
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
