"""Print the MS-Transformer teacher's settings sweep (ms_val_sweep.sh) as a markdown table:
one row per setting, mean ± sd over its seeds (runs named ``<setting>_s<seed>``) of the scene
accuracy and median position error on the validation split (what the setting is chosen on)
and on the test split (reported, never chosen on), and the position median against the mean
pose's.

    python experiments/ablation_teacher/ms_val_table.py outputs/ms_sweep
"""

from __future__ import annotations

import json
import re
import statistics
import sys
from pathlib import Path


def spread(values: list[float], digits: int) -> str:
    """``mean ± sd`` of ``values`` (the mean alone for one value)."""
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    return f"{statistics.mean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"


def main(root: Path) -> None:
    settings: dict[str, list[dict[str, float]]] = {}
    for path in sorted(root.glob("*/metrics.json")):
        setting = re.sub(r"_s\d+$", "", path.parent.name)
        settings.setdefault(setting, []).append(json.loads(path.read_text()))
    print(
        "| setting | seeds | val scene acc. [%] | val position [m] | val / mean pose "
        "| test scene acc. [%] | test position [m] | test / mean pose |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for setting, runs in settings.items():
        cells = []
        for split in ("val", "test"):
            accuracy = [100 * m[f"{split}/teacher/scene_accuracy"] for m in runs]
            position = [m[f"{split}/teacher/pos_median_m"] for m in runs]
            ratio = [
                m[f"{split}/teacher/pos_median_m"] / m[f"{split}/mean_pose/pos_median_m"]
                for m in runs
            ]
            cells += [spread(accuracy, 1), spread(position, 3), spread(ratio, 2)]
        print(f"| {setting} | {len(runs)} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/ms_sweep"))
