"""Print the MS-Transformer demo's scene figures per run as a markdown table: the teacher's
and render-and-compare's scene accuracy on val and test, the scene rule chosen on val, the
test medians and their ratio, and the test confusion tables (teacher and render_compare).

    python experiments/ms_scene_decision/seed_table.py outputs/ms_seed0 outputs/ms_seed1 ...
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

METHODS = ("teacher", "render_compare")


def confusion(metrics: dict[str, float], method: str) -> str:
    """The test confusion table of ``method`` as 'true>assigned: count' for the errors."""
    prefix = f"test/{method}/scene_confusion/"
    errors = [
        f"{key[len(prefix) :].replace('/', '→')} {int(value)}"
        for key, value in sorted(metrics.items())
        if key.startswith(prefix) and value and key.split("/")[-1] != key.split("/")[-2]
    ]
    return ", ".join(errors) or "none"


def accuracy(metrics: dict[str, float], split: str, method: str) -> float:
    """The share of ``method``'s queries of ``split`` assigned their true scene, from its
    confusion table (%)."""
    prefix = f"{split}/{method}/scene_confusion/"
    cells = {k[len(prefix) :]: v for k, v in metrics.items() if k.startswith(prefix)}
    right = sum(v for k, v in cells.items() if k.split("/")[0] == k.split("/")[1])
    return 100 * right / sum(cells.values())


def main(runs: list[Path]) -> None:
    print(
        "| run | teacher scene acc. val / test [%] | render_compare scene acc. val / test [%] "
        "| rule (floor, probe, prior, margin) | test teacher / render_compare [m] | ratio "
        "| test errors, teacher | test errors, render_compare |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for run in runs:
        m = json.loads((run / "metrics.json").read_text())
        acc = {
            method: " / ".join(f"{accuracy(m, split, method):.1f}" for split in ("val", "test"))
            for method in METHODS
        }
        rule = ", ".join(
            f"{m[f'test/render_compare/scene_{key}']:g}"
            for key in ("check_below", "probe_scale", "prior_weight", "move_margin")
        )
        teacher, refined = m["test/teacher/pos_median_m"], m["test/render_compare/pos_median_m"]
        print(
            f"| {run.name} | {acc['teacher']} | {acc['render_compare']} | {rule} "
            f"| {teacher:.3f} / {refined:.3f} | {refined / teacher:.3f} "
            f"| {confusion(m, 'teacher')} | {confusion(m, 'render_compare')} |"
        )


if __name__ == "__main__":
    main([Path(p) for p in sys.argv[1:]])
