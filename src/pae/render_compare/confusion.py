"""Scene confusion tables of multi-scene teachers and of render-and-compare's scene decision:
how many queries of each true scene each method assigned to each scene."""

from __future__ import annotations

import torch
from torch import Tensor

from pae.core.shapes import check_shape


def scene_confusion(assigned: Tensor, truth: Tensor, scenes: int) -> Tensor:
    """Counts [S, S] (int64) of queries by true scene (row) and assigned scene (column), from
    the assigned [N] and true scene ids [N] in ``range(scenes)``."""
    n = check_shape(assigned, "assigned", "N")["N"]
    check_shape(truth, "truth", f"{n}")
    ids = torch.cat([assigned, truth])
    if n and (int(ids.min()) < 0 or int(ids.max()) >= scenes):
        raise ValueError(f"scene ids must lie in [0, {scenes}), got {ids.min()}..{ids.max()}")
    flat = truth.long().cpu() * scenes + assigned.long().cpu()
    return torch.bincount(flat, minlength=scenes * scenes).view(scenes, scenes)


def confusion_figures(prefix: str, table: Tensor, names: list[str]) -> dict[str, Tensor]:
    """The counts of a confusion ``table`` [S, S] as flat figures
    ``{prefix}/scene_confusion/{true scene}/{assigned scene}``."""
    return {
        f"{prefix}/scene_confusion/{true}/{assigned}": table[i, j].float()
        for i, true in enumerate(names)
        for j, assigned in enumerate(names)
    }


def confusion_markdown(tables: dict[str, Tensor], names: list[str]) -> str:
    """Markdown of confusion tables [S, S] by method: one table per method, rows the true
    scenes, columns the assigned ones, and each method's scene accuracy."""
    lines = []
    for method, table in tables.items():
        accuracy = 100 * float(table.diagonal().sum()) / max(1, int(table.sum()))
        lines += [f"**{method}** (scene accuracy {accuracy:.1f} %)", ""]
        lines += ["| true \\ assigned | " + " | ".join(names) + " |"]
        lines += ["|---" * (len(names) + 1) + "|"]
        for i, name in enumerate(names):
            lines.append(f"| {name} | " + " | ".join(str(int(v)) for v in table[i]) + " |")
        lines.append("")
    return "\n".join(lines)
