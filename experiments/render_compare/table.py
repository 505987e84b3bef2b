"""Print a markdown table of render-and-compare runs: one row per run directory (a run, or
every job of a sweep), named by its command-line overrides, with the teacher's and each
render-and-compare method's median position / orientation error on the test split, the
change in median position against the teacher, and the honest search's ms per query.

    python experiments/render_compare/table.py outputs/multirun/eval/<date> [more dirs]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

METHODS = ("teacher", "render_compare", "render_compare_oracle")


def runs(root: Path) -> list[Path]:
    """Every folder under ``root`` (itself included) that holds a metrics.json."""
    return sorted({path.parent for path in root.glob("**/metrics.json")})


def name(run: Path) -> str:
    overrides = run / ".hydra" / "overrides.yaml"
    if not overrides.is_file():
        return run.name
    lines = [line.removeprefix("- ").strip() for line in overrides.read_text().splitlines()]
    kept = [line for line in lines if line and not line.startswith(("hydra.", "scene_model_ckpt"))]
    return " ".join(kept) or "(defaults)"


def row(run: Path) -> str:
    metrics = json.loads((run / "metrics.json").read_text())
    teacher = metrics.get("test/teacher/pos_median_m")
    cells = []
    for method in METHODS:
        pos = metrics.get(f"test/{method}/pos_median_m")
        rot = metrics.get(f"test/{method}/rot_median_deg")
        if pos is None:
            cells.append("-")
            continue
        change = "" if method == "teacher" or not teacher else f" ({pos / teacher - 1:+.1%})"
        cells.append(f"{pos:.3f} / {rot:.2f}{change}")
    ms = metrics.get("bench/render_compare/ms_per_query")
    quality = metrics.get("test/scene_model/psnr_db")
    extra = [f"{ms:.1f}" if ms else "-", f"{quality:.1f}" if quality else "-"]
    return f"| {name(run)} | " + " | ".join(cells + extra) + " |"


def main(argv: list[str]) -> int:
    header = ["run", *METHODS, "ms/query", "PSNR at test poses [dB]"]
    print("| " + " | ".join(header) + " |")
    print("|---" * len(header) + "|")
    for root in argv:
        for run in runs(Path(root)):
            print(row(run))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
