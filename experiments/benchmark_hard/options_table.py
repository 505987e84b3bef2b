"""Every option of the hard benchmark alone through the whole pipeline: `pae-train
experiment=demo_hard` (the same steps and refiner, its filters and gate chosen on each run's
val split) with every benchmark option off but the row's, and with all on; one table of the
runs' test figures from their metrics.json.

    python experiments/benchmark_hard/options_table.py [--rows ROW ...] [--seed 0]
        [--out outputs/benchmark_hard/options] [--teachers-from DIR] [--table-only]
        [-- OVERRIDE ...]

Runs each missing row into OUT/<row>_seed<seed> (about 9.5 minutes a row on 2 cores, its data
rendered on first use), skips the rows whose metrics.json holds the test figures, and prints
the markdown table: the teacher, render_compare and its oracle (the benchmark's own renderer,
a bound), each test median position / orientation and share within 5 cm / 5 deg, the share
of refinements the gate accepted, the scene model's PSNR at the test poses and the compared
images' filter val chose. ``--teachers-from DIR``: each row takes the teacher of its run in
DIR (an earlier table's ``--out``) and runs the scene-model step alone (its fit and the
refinement: about 4.5 minutes a row), for a change that leaves the teacher as it was.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

from pae.render_compare.queries import recorded_match
from pae.synthetic.settings import CaptureOptions, Nuisances, SurfaceOptions

OFF = {
    field.name: field.default
    for options in (Nuisances, SurfaceOptions, CaptureOptions)
    for field in dataclasses.fields(options)
}
"""Every benchmark option (``data.*`` key) off: the settings' defaults."""
ROWS = {
    "plain": ("plain_surface_share",),
    "repeated": ("repeated_surface_share",),
    "glossy": ("glossy_surface_share",),
    "pipeline": ("camera_pipeline",),
    "jpeg": ("jpeg_quality",),
    "resolution": ("render_scale",),
    "nuisances": tuple(field.name for field in dataclasses.fields(Nuisances)),
    "all": tuple(OFF),
}
"""Row -> the options it leaves at experiment=demo_hard's values (the rest are turned off)."""
METHODS = ("teacher", "render_compare", "render_compare_oracle")
FILTER_NAMES = {
    "highpass_sigma_px": "high-pass",
    "contrast_sigma_px": "contrast",
    "trim_sigma": "trim",
    "highlight_quantile": "clip",
}
"""The filter settings a run logs when val chose them, and their names in the table."""


def overrides(row: str) -> list[str]:
    """The ``data.*`` overrides of experiment=demo_hard that make ``row``'s benchmark."""
    return [f"data.{key}={value}" for key, value in OFF.items() if key not in ROWS[row]]


def cells(metrics: dict[str, float]) -> list[str]:
    """The row's table cells from a run's metrics.json."""
    out = []
    for method in METHODS:
        key = f"test/{method}"
        out.append(
            f"{metrics[key + '/pos_median_m']:.3f} m / {metrics[key + '/rot_median_deg']:.2f}° "
            f"({100 * metrics[key + '/within_5cm_5deg']:.0f} %)"
        )
    ratio = metrics["test/render_compare/pos_median_m"] / metrics["test/teacher/pos_median_m"]
    accepted = metrics["test/render_compare/accepted_share"]
    psnr = metrics.get("test/scene_model/psnr_db", float("nan"))
    stage = recorded_match(metrics, "test/render_compare")
    return [
        *out,
        f"{ratio:.3f}×",
        f"{100 * accepted:.0f} %",
        f"{psnr:.1f}",
        chosen_filter(metrics),
        stage.described() if stage is not None else "none",
    ]


def chosen_filter(metrics: dict[str, float]) -> str:
    """The compared images' filter val chose (the run's ``test/render_compare/<setting>``)."""
    parts = [
        f"{name} {metrics[f'test/render_compare/{key}']:g}"
        for key, name in FILTER_NAMES.items()
        if metrics.get(f"test/render_compare/{key}", 0)
    ]
    return " + ".join(parts) or "the refiner's own"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", nargs="+", choices=list(ROWS), default=list(ROWS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="outputs/benchmark_hard/options")
    parser.add_argument("--teachers-from", type=Path, help="reuse the teachers of these runs")
    parser.add_argument("--table-only", action="store_true", help="run nothing")
    parser.add_argument("extra", nargs="*", help="overrides given to every run (after --)")
    args = parser.parse_args()
    pae_train = str(Path(sys.executable).with_name("pae-train"))
    lines = [
        "| options on | teacher | render_compare | oracle † | ratio | accepted | PSNR (dB) "
        "| filter chosen on val | stage chosen on val |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in args.rows:
        run_dir = Path(args.out) / f"{row}_seed{args.seed}"
        metrics_path = run_dir / "metrics.json"
        done = metrics_path.exists() and "test/render_compare/pos_median_m" in json.loads(
            metrics_path.read_text()
        )
        if not done and not args.table_only:
            command = [
                pae_train,
                "experiment=demo_hard",
                f"seed={args.seed}",
                f"hydra.run.dir={run_dir}",
                *overrides(row),
                *args.extra,
            ]
            if args.teachers_from is not None:
                teacher = args.teachers_from / run_dir.name / "teacher/checkpoints/last.ckpt"
                command += ["stage.steps=[scene_model]", f"teacher_ckpt={teacher}"]
            print(" ".join(command[1:]), file=sys.stderr, flush=True)
            returncode = subprocess.run(command).returncode
            if returncode:
                sys.exit(
                    f"options_table: row {row} stopped (exit {returncode}); its run is "
                    f"{run_dir} (error.txt there): continue it with --rows {row} -- resume=true"
                )
            done = True
        if done:
            lines.append(f"| {row} | {' | '.join(cells(json.loads(metrics_path.read_text())))} |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
