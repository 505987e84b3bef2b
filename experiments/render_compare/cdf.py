"""Cumulative distributions of render-and-compare's errors, from the per-query files a run
writes (``queries_{split}_{method}.csv`` beside the scene-model step's TensorBoard events).

    python experiments/render_compare/cdf.py LABEL=FILE.csv [LABEL=FILE.csv ...] \
        --out experiments/render_compare/cdf_test.svg

Each file gives two curves: its start (the teacher; drawn once per distinct start) and its
final poses (refined where the gate accepted, else the start). Prints, per curve, the median
and mean position / orientation error, the share within (5 cm, 5°) and within (10 cm, 10°),
and the share of queries that end farther from the truth than the teacher (a wrong basin);
writes one SVG with the position and orientation CDFs on log axes.
"""

from __future__ import annotations

import argparse
import csv
import math
import statistics
from pathlib import Path

COLOURS = ("#000000", "#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")
PANEL_W, PANEL_H, MARGIN = 420, 300, 50


def read_queries(path: Path) -> dict[str, list[float]]:
    """start and final position (m) and orientation (deg) errors of every query of a file."""
    if not path.is_file():
        raise SystemExit(f"{path}: no such file (a run writes queries_{{split}}_{{method}}.csv)")
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    if not rows:
        raise SystemExit(f"{path}: no queries")
    final_pos, final_rot = [], []
    for row in rows:
        accepted = row["accepted"] == "1"
        final_pos.append(float(row["refined_pos_m" if accepted else "start_pos_m"]))
        final_rot.append(float(row["refined_rot_deg" if accepted else "start_rot_deg"]))
    return {
        "start_pos": [float(r["start_pos_m"]) for r in rows],
        "start_rot": [float(r["start_rot_deg"]) for r in rows],
        "pos": final_pos,
        "rot": final_rot,
    }


def summary(pos: list[float], rot: list[float], start: list[float]) -> str:
    n = len(pos)
    within5 = sum(p < 0.05 and r < 5 for p, r in zip(pos, rot, strict=True)) / n
    within10 = sum(p < 0.10 and r < 10 for p, r in zip(pos, rot, strict=True)) / n
    worse = sum(p > s for p, s in zip(pos, start, strict=True)) / n
    return (
        f"| {statistics.median(pos):.3f} / {statistics.median(rot):.2f} "
        f"| {statistics.mean(pos):.3f} / {statistics.mean(rot):.2f} "
        f"| {100 * within5:.1f} % | {100 * within10:.1f} % | {100 * worse:.1f} % |"
    )


def polyline(values: list[float], lo: float, hi: float, x0: float, colour: str) -> str:
    """The empirical CDF of values on a log x axis [lo, hi] inside the panel at x0."""
    ordered = sorted(min(max(v, lo), hi) for v in values)
    points = []
    for i, value in enumerate(ordered):
        x = x0 + MARGIN + (math.log10(value / lo) / math.log10(hi / lo)) * (PANEL_W - MARGIN)
        y = PANEL_H - MARGIN * 0.6 - (i + 1) / len(ordered) * (PANEL_H - MARGIN * 1.2)
        points.append(f"{x:.1f},{y:.1f}")
    return (
        f'<polyline fill="none" stroke="{colour}" stroke-width="1.5" points="{" ".join(points)}"/>'
    )


def axes(x0: float, lo: float, hi: float, label: str) -> list[str]:
    parts = []
    top, bottom = MARGIN * 0.6, PANEL_H - MARGIN * 0.6
    left, right = x0 + MARGIN, x0 + PANEL_W
    parts.append(
        f'<rect x="{left}" y="{top}" width="{right - left}" height="{bottom - top}" '
        'fill="none" stroke="#888"/>'
    )
    decade = 10 ** math.floor(math.log10(lo))
    while decade <= hi:
        if decade >= lo:
            x = left + math.log10(decade / lo) / math.log10(hi / lo) * (right - left)
            parts.append(
                f'<line x1="{x:.1f}" y1="{top}" x2="{x:.1f}" y2="{bottom}" stroke="#ddd"/>'
            )
            parts.append(
                f'<text x="{x:.1f}" y="{bottom + 14}" font-size="10" '
                f'text-anchor="middle">{decade:g}</text>'
            )
        decade *= 10
    for share in (0.25, 0.5, 0.75, 1.0):
        y = bottom - share * (bottom - top)
        parts.append(
            f'<text x="{left - 4}" y="{y + 3:.1f}" font-size="10" '
            f'text-anchor="end">{share:g}</text>'
        )
    parts.append(
        f'<text x="{(left + right) / 2}" y="{PANEL_H - 4}" font-size="11" '
        f'text-anchor="middle">{label}</text>'
    )
    return parts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("curves", nargs="+", metavar="LABEL=FILE.csv")
    parser.add_argument("--out", type=Path, required=True, help="the SVG to write")
    args = parser.parse_args(argv)
    curves: list[tuple[str, list[float], list[float], list[float]]] = []
    starts: dict[tuple[float, ...], str] = {}
    for item in args.curves:
        label, _, file = item.partition("=")
        queries = read_queries(Path(file))
        key = tuple(queries["start_pos"])
        if key not in starts:
            starts[key] = f"teacher ({label})" if starts else "teacher"
            start = queries["start_pos"], queries["start_rot"]
            curves.append((starts[key], *start, queries["start_pos"]))
        curves.append((label, queries["pos"], queries["rot"], queries["start_pos"]))
    print(
        "| curve | median m / ° | mean m / ° | within 5 cm, 5° | within 10 cm, 10° | worse "
        "than the teacher |"
    )
    print("|---|---|---|---|---|---|")
    for label, pos, rot, start in curves:
        print(f"| {label} {summary(pos, rot, start)}")
    width = 2 * PANEL_W + 20
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" '
        f'height="{PANEL_H + 20 * len(curves)}" font-family="sans-serif">'
    ]
    parts += axes(0, 0.01, 10.0, "position error [m]")
    parts += axes(PANEL_W + 20, 0.1, 180.0, "orientation error [deg]")
    for i, (label, pos, rot, _) in enumerate(curves):
        colour = COLOURS[i % len(COLOURS)]
        parts.append(polyline(pos, 0.01, 10.0, 0, colour))
        parts.append(polyline(rot, 0.1, 180.0, PANEL_W + 20, colour))
        y = PANEL_H + 14 + 20 * i
        parts.append(f'<text x="{MARGIN}" y="{y}" font-size="12" fill="{colour}">{label}</text>')
    parts.append("</svg>")
    args.out.write_text("\n".join(parts) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
