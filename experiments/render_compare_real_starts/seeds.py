"""Median position error per seed and their mean ± sd, for one scene run by run.py into one
folder per seed (``OUT_K/<scene>/real_starts_<APR>.json``), with and without a setting:

    python experiments/render_compare_real_starts/seeds.py ShopFacade \\
        --without outputs/rs128_shop_seeds/without_{0,1,2} \\
        --with outputs/render_compare_real_starts_px128_stage outputs/rs128_shop_seeds/with_{1,2}

A row per APR: each seed's median (cm), the mean ± sd over the seeds (sample sd), the
difference of the means and whether it exceeds the larger sd (the rule of the README's
"ShopFacade's draw-to-draw spread")."""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

APRS = ("DFNet", "PoseNet")


def medians_cm(folders: list[Path], scene: str, apr: str) -> list[float]:
    """The refined median position error (cm) of ``apr``'s starts in each folder."""
    return [
        100
        * json.loads((f / scene / f"real_starts_{apr}.json").read_text())["render_compare"][
            "pos_median_m"
        ]
        for f in folders
    ]


def spread(values: list[float]) -> tuple[float, float]:
    return statistics.mean(values), statistics.stdev(values) if len(values) > 1 else 0.0


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("--without", nargs="+", type=Path, required=True)
    parser.add_argument("--with", dest="with_", nargs="+", type=Path, required=True)
    args = parser.parse_args(argv)
    header = ["starts", "without, each seed", "with, each seed", "without", "with"]
    header += ["with − without", "beyond the larger sd"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for apr in APRS:
        without = medians_cm(args.without, args.scene, apr)
        with_ = medians_cm(args.with_, args.scene, apr)
        (m0, s0), (m1, s1) = spread(without), spread(with_)
        beyond = "yes" if abs(m1 - m0) > max(s0, s1) else "no"
        cells = [
            apr,
            ", ".join(f"{v:.1f}" for v in without),
            ", ".join(f"{v:.1f}" for v in with_),
            f"{m0:.2f} ± {s0:.2f}",
            f"{m1:.2f} ± {s1:.2f}",
            f"{m1 - m0:+.2f}",
            beyond,
        ]
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
