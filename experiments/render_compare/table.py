"""Print a markdown table of render-and-compare runs: one row per run directory (a run, or
every job of a sweep), named by its command-line overrides, with the median position /
orientation error of the teacher and of render-and-compare on the validation split (held-out
train sequences: what settings are chosen on) and on the test split, the change in median
position against the teacher, the test split's oracle bound, the honest search's ms per
query, the scene model's PSNR at the test poses, the share of test refinements the gate
accepted and the share of test queries within (0.10 m, 10 deg) after render-and-compare.

    python experiments/render_compare/table.py outputs/multirun/eval/<date> [more dirs]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

COLUMNS = (
    ("val", "teacher"),
    ("val", "render_compare"),
    ("test", "teacher"),
    ("test", "render_compare"),
    ("test", "render_compare_oracle"),
)


def runs(root: Path) -> list[Path]:
    """Every folder under ``root`` (itself included) that holds a metrics.json."""
    return sorted({path.parent for path in root.glob("**/metrics.json")})


def name(run: Path) -> str:
    """The run's command-line overrides (checkpoints, Hydra paths and the oracle switch left
    out)."""
    overrides = run / ".hydra" / "overrides.yaml"
    if not overrides.is_file():
        return run.name
    lines = [line.removeprefix("- ").strip() for line in overrides.read_text().splitlines()]
    skipped = ("hydra.", "scene_model_ckpt", "teacher_ckpt", "render_compare.oracle")
    kept = [line for line in lines if line and not line.startswith(skipped)]
    return " ".join(kept) or "(defaults)"


def cell(metrics: dict[str, float], split: str, method: str) -> str:
    pos = metrics.get(f"{split}/{method}/pos_median_m")
    rot = metrics.get(f"{split}/{method}/rot_median_deg")
    if pos is None:
        return "-"
    teacher = metrics.get(f"{split}/teacher/pos_median_m")
    change = "" if method == "teacher" or not teacher else f" ({pos / teacher - 1:+.1%})"
    return f"{pos:.3f} / {rot:.2f}{change}"


def row(run: Path) -> str:
    metrics = json.loads((run / "metrics.json").read_text())
    cells = [cell(metrics, split, method) for split, method in COLUMNS]
    ms = metrics.get("bench/render_compare/ms_per_query")
    quality = metrics.get("test/scene_model/psnr_db")
    accepted = metrics.get("test/render_compare/accepted_share")
    within = metrics.get("test/render_compare/within_10cm_10deg")
    cells += [
        f"{ms:.1f}" if ms else "-",
        f"{quality:.1f}" if quality else "-",
        "-" if accepted is None else f"{accepted:.0%}",
        "-" if within is None else f"{within:.0%}",
    ]
    return f"| {name(run)} | " + " | ".join(cells) + " |"


def main(argv: list[str]) -> int:
    header = ["run", *(f"{split} {method}" for split, method in COLUMNS)]
    header += ["ms/query", "PSNR at test poses [dB]", "test accepted", "test within 10 cm, 10°"]
    print("| " + " | ".join(header) + " |")
    print("|---" * len(header) + "|")
    for root in argv:
        for run in runs(Path(root)):
            print(row(run))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
