"""Print the per-scene table of `run.py`'s runs: test-split medians (position m /
orientation deg) of the teacher, render-and-compare (with its ratio to the teacher's
position error) and the oracle bound, the shares within (0.10 m, 10 deg), the share of
refinements the gate accepted, the scene model's quality at the test poses, its fit time and
the refiner's ms per query; then each dataset's mean over its scenes that
reached the refinement.

    python experiments/render_compare_geometry/table.py outputs/render_compare_geometry

With a second folder (the `pae-eval` runs of the same scene models with other refiner
settings, one ``<scene>/metrics.json`` each), the refinement figures of the scenes it holds
come from it (their names marked ``*``), the others' from their training runs, and the fit
seconds always from the first.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from run import DATASETS

HEADER = (
    "| scene | teacher | render_compare | ratio | oracle † | within 10 cm, 10° (teacher → rc) "
    "| accepted | PSNR / ZNCC | fit s | ms/query |\n|---|---|---|---|---|---|---|---|---|---|"
)


def figures(metrics: dict[str, float]) -> dict[str, float]:
    get = metrics.get
    return {
        "t_pos": get("test/teacher/pos_median_m"),
        "t_rot": get("test/teacher/rot_median_deg"),
        "r_pos": get("test/render_compare/pos_median_m"),
        "r_rot": get("test/render_compare/rot_median_deg"),
        "o_pos": get("test/render_compare_oracle/pos_median_m"),
        "o_rot": get("test/render_compare_oracle/rot_median_deg"),
        "t_in": get("test/teacher/within_10cm_10deg"),
        "r_in": get("test/render_compare/within_10cm_10deg"),
        "accepted": get("test/render_compare/accepted_share"),
        "psnr": get("test/scene_model/psnr_db"),
        "zncc": get("test/scene_model/zncc"),
        "fit": get("bench/scene_model/fit_s"),
        "ms": get("bench/render_compare/ms_per_query"),
    }


def line(name: str, f: dict[str, float]) -> str:
    def pair(pos: float | None, rot: float | None) -> str:
        return "-" if pos is None else f"{pos:.3f} / {rot:.2f}"

    ratio = f["r_pos"] / f["t_pos"] if f["r_pos"] is not None and f["t_pos"] else None
    cells = [
        pair(f["t_pos"], f["t_rot"]),
        pair(f["r_pos"], f["r_rot"]),
        "-" if ratio is None else f"{ratio:.2f}×",
        pair(f["o_pos"], f["o_rot"]),
        "-" if f["r_in"] is None else f"{f['t_in']:.0%} → {f['r_in']:.0%}",
        "-" if f["accepted"] is None else f"{f['accepted']:.0%}",
        "-" if f["psnr"] is None else f"{f['psnr']:.1f} dB / {f['zncc']:.2f}",
        "-" if f["fit"] is None else f"{f['fit']:.0f}",
        "-" if f["ms"] is None else f"{f['ms']:.1f}",
    ]
    return f"| {name} | " + " | ".join(cells) + " |"


def mean(rows: list[dict[str, float]]) -> dict[str, float]:
    keys = rows[0].keys()
    return {
        k: sum(r[k] for r in rows) / len(rows) if all(r[k] is not None for r in rows) else None
        for k in keys
    }


def main(argv: list[str]) -> int:
    root = Path(argv[0] if argv else "outputs/render_compare_geometry")
    evaluated = Path(argv[1]) if len(argv) > 1 else root
    print(HEADER)
    for dataset, scenes in DATASETS.items():
        rows = []
        for scene in scenes:
            path, fitted = evaluated / scene / "metrics.json", root / scene / "metrics.json"
            if not fitted.is_file():
                continue
            again = evaluated != root and path.is_file()
            row = figures(json.loads((path if again else fitted).read_text()))
            row["fit"] = figures(json.loads(fitted.read_text()))["fit"]
            print(line(f"{scene} *" if again else scene, row))
            if row["r_pos"] is not None:  # a run that has not reached its refinement yet
                rows.append(row)
        if rows:
            print(line(f"**{dataset} mean ({len(rows)} scenes)**", mean(rows)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
