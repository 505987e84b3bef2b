"""How well each kind of scene evidence names the true scene on a finished MS-Transformer run:
every val and test query refined in every scene (the run's scene model and teacher, the first
steps from the val errors as the run's step_from_val, the starts of
pae.render_compare.scene_starts), and per evidence (the refined score,
its sharpness at each probe scale) and prior weight the share of queries whose evidence is
highest in their true scene, and the scene accuracy of checking every query with margin 0;
then, per mispredicted query, how far the teacher's pose for its true scene was, how far the
refinement there ended and its scores.

    PYTHONPATH=src python experiments/ms_scene_decision/evidence.py outputs/ms_seed0
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import torch
from torch import Tensor

from pae.apps import localization as loc
from pae.core.checkpoints import load_scene_model, load_teacher
from pae.core.geometry import pose_errors
from pae.data.transforms import ImageTransform
from pae.lit.scene_model import compare_queries
from pae.models.latents import compute_teacher_latents
from pae.render_compare.api import build_refiner
from pae.render_compare.calibration import steps_from_errors
from pae.render_compare.scene_decision import (
    PRIOR_WEIGHTS,
    PROBE_SCALES,
    evidence,
    moves,
    sharpness,
    try_scenes,
)
from pae.render_compare.scene_starts import latent_starts


@torch.no_grad()
def split_outputs(run: loc.Run, teacher: torch.nn.Module, split: str) -> dict[str, Tensor]:
    """The split's queries at the compare width with the teacher's answers and the starts in
    every scene, as the run's scene-model step keeps them."""
    data = loc.data_module(run, cache_images=False)
    data.setup()
    store = compute_teacher_latents(teacher, data).tensors
    joint = torch.cat([store["z_x"], store["z_q"]], -1)
    width = loc.compare_width(loc.render_compare_settings(run)[0])
    loader = data.val_dataloader() if split == "val" else data.test_dataloader()
    intrinsics = data.intrinsics(split)
    parts: dict[str, list[Tensor]] = {}
    for batch in loader:
        images = data.preprocess(batch["image"], False)
        answer = teacher.estimate(images, batch["scene"])
        rgb = ImageTransform.unnormalize_batch(images)
        small, vectors = compare_queries(rgb, intrinsics[batch["index"]], width)
        found = {
            "image": small,
            "intrinsics": vectors,
            "pose": batch["pose"].float(),
            "scene": batch["scene"],
            "estimate": answer.pose,
            "predicted": answer.scene,
            "scene_poses": latent_starts(
                teacher.scene_poses(images),
                teacher.scene_latents(images),
                joint,
                store["pose"],
                store["scene"],
            ),
            "log_prior": answer.latents.scene_logits.log_softmax(-1),
        }
        for key, value in found.items():
            parts.setdefault(key, []).append(value)
    return {key: torch.cat(value) for key, value in parts.items()}


def main(folder: Path) -> None:
    run = loc.read_run(folder)
    teacher = load_teacher(run.checkpoint("teacher", "the evidence")).model.eval()
    model = load_scene_model(loc.scene_model_path(run), "scene_model_ckpt").model
    settings = loc.render_compare_settings(run)[0]
    outputs = {split: split_outputs(run, teacher, split) for split in ("val", "test")}
    val = outputs["val"]
    fractions = dict(run.config.render_compare.step_from_val)
    steps = steps_from_errors(val["estimate"], val["pose"], fractions)
    refiner = build_refiner(model, settings, steps)
    probe = functools.partial(sharpness, refiner)
    print("| split | evidence | " + " | ".join(f"prior {w:g}" for w in PRIOR_WEIGHTS) + " |")
    print("|---" * (len(PRIOR_WEIGHTS) + 2) + "|")
    for split, q in outputs.items():
        first = refiner(q["image"], q["intrinsics"], q["estimate"], q["predicted"])
        every = torch.arange(len(first.score))
        trials = try_scenes(
            refiner, probe, q["image"], q["intrinsics"], q["scene_poses"], q["predicted"],
            first, every, PROBE_SCALES,
        )  # fmt: skip
        teacher_accuracy = 100 * float((q["predicted"] == q["scene"]).float().mean())
        for scale in (0.0, *PROBE_SCALES):
            cells = []
            for weight in PRIOR_WEIGHTS:
                values = evidence(trials, q["log_prior"], scale, weight)
                alone = 100 * float((values.argmax(1) == q["scene"]).float().mean())
                decided = moves(values, q["predicted"], 0.0)
                checked = 100 * float((decided == q["scene"]).float().mean())
                cells.append(f"{alone:.1f} / {checked:.1f}")
            name = "refined score" if scale == 0 else f"sharpness x{scale:g}"
            label = f"{split} (teacher {teacher_accuracy:.1f} %)"
            print(f"| {label} | {name} | " + " | ".join(cells) + " |")
        wrong = (q["predicted"] != q["scene"]).nonzero().flatten()
        true_start = q["scene_poses"][wrong, q["scene"][wrong], 0]
        start_error, _ = pose_errors(true_start.float(), q["pose"][wrong])
        refined_error, _ = pose_errors(
            trials.result.poses[wrong, q["scene"][wrong]], q["pose"][wrong]
        )
        scores = trials.result.score
        for i, row in enumerate(wrong.tolist()):
            true, predicted = int(q["scene"][row]), int(q["predicted"][row])
            print(
                f"{split} query {row} (scene {true} taken for {predicted}): the teacher's pose for "
                f"its scene {float(start_error[i]):.2f} m off, refined there to "
                f"{float(refined_error[i]):.2f} m, score {float(scores[row, true]):.3f} there "
                f"against {float(scores[row, predicted]):.3f} in scene {predicted}, the "
                f"teacher's probability of its scene {float(q['log_prior'][row, true].exp()):.3f}"
            )


if __name__ == "__main__":
    main(Path(sys.argv[1]))
