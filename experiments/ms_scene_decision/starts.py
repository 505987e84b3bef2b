"""An audit of the scene decision's starts on a finished MS-Transformer run (reads the test
labels): each mispredicted query refined in its true scene from every start the scene
decision tries there (:func:`pae.render_compare.scene_starts.latent_starts`: the teacher's
pose at each heading, then the nearest train poses by latent): how far the teacher's own pose
for that room lies from the truth (m / °), and which start the decision keeps (the
best-scoring one), with the headings and without them (the teacher's pose and the latent
starts only, as before the headings): that start's distance and angle from the truth, where
its refinement ended and its score.

    PYTHONPATH=src python experiments/ms_scene_decision/starts.py outputs/ms52_seed1 [SPLIT]
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from evidence import split_outputs  # beside this script

from pae.apps import localization as loc
from pae.core.checkpoints import load_scene_model, load_teacher
from pae.core.geometry import pose_errors
from pae.render_compare.api import build_refiner
from pae.render_compare.calibration import steps_from_errors
from pae.render_compare.scene_starts import HEADINGS


def main(folder: Path, split: str = "test") -> None:
    run = loc.read_run(folder)
    teacher = load_teacher(run.checkpoint("teacher", "the audit")).model.eval()
    model = load_scene_model(loc.scene_model_path(run), "scene_model_ckpt").model
    settings = loc.render_compare_settings(run)[0]
    val = split_outputs(run, teacher, "val")
    q = val if split == "val" else split_outputs(run, teacher, split)
    steps = steps_from_errors(
        val["estimate"], val["pose"], dict(run.config.render_compare.step_from_val)
    )
    refiner = build_refiner(model, settings, steps)
    wrong = (q["predicted"] != q["scene"]).nonzero().flatten()
    if not len(wrong):
        print(f"{split}: no mispredicted query")
        return
    true = q["scene"][wrong]
    starts = q["scene_poses"][wrong, true]  # [W, K, 7]
    w, k = starts.shape[:2]
    out = refiner(
        q["image"][wrong].repeat_interleave(k, 0),
        q["intrinsics"][wrong].repeat_interleave(k, 0),
        starts.reshape(-1, 7),
        true.repeat_interleave(k),
    )
    truth = q["pose"][wrong].repeat_interleave(k, 0)
    start_m, start_deg = (e.view(w, k) for e in pose_errors(starts.reshape(-1, 7).float(), truth))
    end_m, end_deg = (e.view(w, k) for e in pose_errors(out.poses, truth))
    score = out.score.view(w, k)
    old = torch.cat([torch.zeros(1, dtype=torch.long), torch.arange(HEADINGS, k)])
    print(
        f"| {split} query | true → predicted scene | the teacher's pose there "
        "| start kept without headings | with |"
    )
    print("|---|---|---|---|---|")
    for i, row in enumerate(wrong.tolist()):
        cells = []
        for columns in (old, torch.arange(k)):
            j = int(columns[score[i, columns].argmax()])
            cells.append(
                f"{start_m[i, j]:.2f} m / {start_deg[i, j]:.0f}° → {end_m[i, j]:.2f} m / "
                f"{end_deg[i, j]:.1f}° (score {score[i, j]:.3f})"
            )
        scenes = f"{int(q['scene'][row])} → {int(q['predicted'][row])}"
        own = f"{start_m[i, 0]:.2f} m / {start_deg[i, 0]:.0f}°"
        print(f"| {row} | {scenes} | {own} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(Path(sys.argv[1]), *sys.argv[2:3])
