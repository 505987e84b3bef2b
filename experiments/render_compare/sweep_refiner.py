"""Render-and-compare's refiner settings compared on the validation split of a finished run.

    python experiments/render_compare/sweep_refiner.py \
        outputs/demo/scene_model/checkpoints/last.ckpt \
        defaults blur_sigma_px=1.0 final_reference_size=32,final_fov_scale=1.3 ...

Runs ``pae-eval scene_model_ckpt=CHECKPOINT`` once; where the
render-and-compare callback would refine the val queries, each setting (``defaults``, or
comma-joined ``key=value`` overrides of ``render_compare.refiner``) refines them instead, from
the same teacher estimates and with the search steps the callback chooses on val
(``step_from_val``) and the gate at margin 0, and prints one table row. The test split is
never refined. Figures: the
median position / orientation error averaged over scenes (as the results tables), the mean
position error, the shares within (5 cm, 5°) and (10 cm, 10°), the share of queries ending
farther from the truth than the teacher, and milliseconds per query (one process, the
machine as it is: compare rows of one run only).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from pae.callbacks import render_compare as callback
from pae.core.geometry import pose_errors
from pae.core.metrics import summarise_errors
from pae.lit.eval_outputs import EVAL, collect_outputs


def parse(setting: str) -> dict[str, Any]:
    """``defaults`` or ``a=1,b=0.5,c=name`` -> overrides."""
    if setting == "defaults":
        return {}
    overrides: dict[str, Any] = {}
    for item in setting.split(","):
        key, _, text = item.partition("=")
        value: Any = text
        for kind in (int, float):
            try:
                value = kind(text)
                break
            except ValueError:
                continue
        overrides[key] = value
    return overrides


def sweep(settings: list[str]) -> Any:
    """A replacement for the callback's refine that compares ``settings`` on val."""

    def refine(self: Any, trainer: Any, pl_module: Any, split: str) -> None:
        outputs = collect_outputs(trainer, pl_module, gather=False)
        if split != "val" or outputs is None:
            return
        self.choose_steps(outputs[EVAL.estimate], outputs[EVAL.pose])
        truth, estimate = outputs[EVAL.pose].float(), outputs[EVAL.estimate].float()
        start_pos, _ = pose_errors(estimate, truth)
        print(
            "| setting | val median m / ° | mean m | within 5 cm, 5° | within 10 cm, 10° "
            "| worse than the teacher | ms per query |\n|---|---|---|---|---|---|---|"
        )
        for setting in settings:
            refiner = self.build_refiner(pl_module.scene_model, **(self.steps | parse(setting)))
            arguments = (outputs[EVAL.image], outputs[EVAL.intrinsics], estimate)
            refiner(*(a[:2] for a in arguments), outputs[EVAL.scene_estimate][:2])  # compile
            start = time.perf_counter()
            result = refiner(*arguments, outputs[EVAL.scene_estimate])
            ms = 1000 * (time.perf_counter() - start) / len(estimate)
            gated = callback.gate(result, estimate, 0.0)
            pos, rot = pose_errors(gated.poses.float(), truth)
            s = summarise_errors(pos, rot, outputs[EVAL.scene], pl_module.scene_names)
            print(
                f"| {setting} | {s['pos_median_m']:.4f} / {s['rot_median_deg']:.2f} "
                f"| {s['pos_mean_m']:.3f} | {100 * s['within_5cm_5deg']:.1f} % "
                f"| {100 * s['within_10cm_10deg']:.1f} % "
                f"| {100 * (pos > start_pos).float().mean():.1f} % | {ms:.1f} |",
                flush=True,
            )

    return refine


def main() -> int:
    if len(sys.argv) < 3:
        print(__doc__)
        return 2
    checkpoint, settings = Path(sys.argv[1]), sys.argv[2:]
    callback.RenderCompareCallback.refine = sweep(settings)
    from pae.evaluate import main as evaluate

    with tempfile.TemporaryDirectory() as folder:
        sys.argv = [
            "pae-eval",
            f"scene_model_ckpt={checkpoint}",
            "render_compare.oracle=false",
            f"hydra.run.dir={folder}",
        ]
        evaluate()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
