"""Run outputs: atomic metrics.json, the results table, and one-line errors for entry points."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from pae.core.atomic import check_writable_file, write_text_atomic
from pae.core.error_reporting import ERROR_FILE, first_line
from pae.report.method_rows import (
    ORACLE_SUFFIX,
    TEST_STORE_SUFFIX,
    marked,
    starts_from_truth,
    table_methods,
)
from pae.report.seed_stats import seed_report
from pae.report.sweep_jobs import MULTIRUN_FILE, sweep_jobs

REFERENCE_METHODS = (
    "teacher",
    "student",
    "student_gt",
    "mean_pose",
    "guess_initial",
    "guess_refined",
    "rpr_reference",
)
"""Table methods that do not refine the teacher's estimate: the teacher and its student, the
baselines, the random-guess check and the RPR's retrieved reference."""
STEP_METHODS = {
    "teacher": ("teacher",),
    "student": ("student", "refined"),
    "rpr": ("vrpr",),
    "rpr_image": ("rpr_image",),
    "scene_model": ("render_compare",),
}
"""The methods a step of pae-train is judged by (iapr: its last iteration; decoder: PSNR)."""


def honest_refinements(metrics: Mapping[str, float], split: str = "test") -> list[str]:
    """Methods that refine the teacher's estimate without the split's labels or the true
    scene (no ``*_test_store`` audit, no ``*_oracle`` bound), in table order."""
    return [
        m
        for m in table_methods(metrics, split)
        if m not in REFERENCE_METHODS and not m.endswith((TEST_STORE_SUFFIX, ORACLE_SUFFIX))
    ]


def best_refinement(metrics: Mapping[str, float], split: str = "test") -> str | None:
    """The honest refinement with the lowest median position error among those below the
    teacher's, if any: chosen on the validation split where every candidate has a ``val/``
    figure (then reported on ``split``), else on ``split`` itself. None where no refinement
    beats the teacher there: refining would not be chosen."""
    methods = honest_refinements(metrics, split)
    chooser = "val" if all(f"val/{m}/pos_median_m" in metrics for m in methods) else split
    teacher = metrics.get(f"{chooser}/teacher/pos_median_m", float("inf"))
    better = [m for m in methods if metrics[f"{chooser}/{m}/pos_median_m"] < teacher]
    return min(better, key=lambda m: metrics[f"{chooser}/{m}/pos_median_m"], default=None)


def _pos_rot(metrics: Mapping[str, float], split: str, method: str) -> str:
    pos, rot = (
        metrics[f"{split}/{method}/pos_median_m"],
        metrics[f"{split}/{method}/rot_median_deg"],
    )
    return f"{method} {pos:.3f} m / {rot:.2f}°"


def step_figures(step: str, metrics: Mapping[str, float], split: str = "test") -> str:
    """The figures a step is judged by, e.g. ``teacher 0.386 m / 7.04°`` (median position /
    orientation error over the split); empty when it has none yet."""
    methods = [m for m in STEP_METHODS.get(step, ()) if f"{split}/{m}/rot_median_deg" in metrics]
    if step == "iapr":
        iterations = [m for m in table_methods(metrics, split) if m.startswith("iapr_")]
        methods = sorted(iterations, key=lambda m: int(m.split("_")[1]))[-1:]
    parts = [_pos_rot(metrics, split, m) for m in methods]
    psnr = metrics.get(f"{split}/decoder/psnr_db")
    if step == "decoder" and psnr is not None:
        baseline = metrics.get(f"{split}/decoder/psnr_mean_image_db", float("nan"))
        parts.append(f"decoder PSNR {psnr:.1f} dB (mean train image {baseline:.1f} dB)")
    return ", ".join(parts)


def headline_metrics(metrics: Mapping[str, float], split: str = "test") -> dict[str, float]:
    """A run's final figures without the per-scene ones, headline first: the teacher, the
    student, the best honest refinement (as ``{split}/best_refinement/...``), the test-store
    audit (``refined_test_store``), each as overall median position and orientation error;
    then the other methods' medians in table order, then every other figure (decoder,
    diagnostics, timings). Means and the within-threshold shares stay in metrics.json."""
    ordered: dict[str, float] = {}

    def add(method: str | None, name: str | None = None) -> None:
        for figure in ("pos_median_m", "rot_median_deg"):
            key = f"{split}/{method}/{figure}"
            if method is not None and key in metrics:
                ordered.setdefault(f"{split}/{name or method}/{figure}", metrics[key])

    add("teacher")
    add("student")
    add(best_refinement(metrics, split), "best_refinement")
    add("refined_test_store")
    for method in table_methods(metrics, split):
        add(method)
    per_scene = {
        key for key in metrics if key.split("/")[0] in ("val", "test") and key.count("/") == 3
    }
    means = ("/pos_mean_m", "/rot_mean_deg", "/within_5cm_5deg", "/within_10cm_10deg")
    for key, value in metrics.items():
        if key not in per_scene and not key.endswith(means) and isinstance(value, int | float):
            ordered.setdefault(key, float(value))
    return ordered


def format_results_table(metrics: Mapping[str, float], split: str = "test") -> str:
    """Paper-style table: median position / orientation error per method, overall and per scene.

    Rows of methods that retrieve among the evaluated split's own poses carry a ``*`` and a
    footnote: they read the test labels. Footnotes also say which train scenes the split
    lacks and, with allow_other_data=true, how many checkpoints were trained on other data.
    The geometry diagnostics follow the table.
    """
    methods = table_methods(metrics, split)
    scenes = sorted(
        {
            key.split("/")[2]
            for key in metrics
            if key.startswith(f"{split}/") and key.count("/") == 3
        }
    )
    columns = ["overall", *scenes]
    width = max([15, *(len(marked(m)) + 1 for m in methods)])
    header = f"{'method':<{width}}" + "".join(f"{c:>18}" for c in columns)
    lines = [f"median position [m] / orientation [deg] on the {split} split", header]
    lines.append("-" * len(header))
    for method in methods:
        cells = []
        for column in columns:
            prefix = f"{split}/{method}/" if column == "overall" else f"{split}/{method}/{column}/"
            pos, rot = metrics.get(prefix + "pos_median_m"), metrics.get(prefix + "rot_median_deg")
            cells.append("-" if pos is None else f"{pos:.3f} / {rot:.2f}")
        lines.append(f"{marked(method):<{width}}" + "".join(f"{c:>18}" for c in cells))
    if any(m.endswith(TEST_STORE_SUFFIX) for m in methods):
        lines.append(
            f"* uses {split} labels: retrieves among the {split} split's own poses (as the "
            "authors' public scripts do) or by the true pose: an audit, not a result"
        )
    if any(m.endswith(ORACLE_SUFFIX) for m in methods):
        lines.append(
            "† renders the true scene (the synthetic benchmark's own renderer): a bound, "
            "not a method"
        )
    if any(starts_from_truth(m) for m in methods):
        lines.append(
            "‡ starts from the true pose, a check, not a method: student_gt encodes it with "
            "the PAE; guess_* add Gaussian noise to its position only, so their orientation "
            "is the true one (0.00° unless refine.orientation averages it)"
        )
    missing = metrics.get(f"{split}/missing_scenes")
    if missing:
        lines.append(
            f"overall averages the scenes shown: {missing:g} train scene(s) have no {split} rows"
        )
    other_data = metrics.get("data/other_data_checkpoints")
    if other_data is not None:
        lines.append(
            f"allow_other_data=true: {other_data:g} checkpoint(s) read were trained on other "
            "data than these figures'"
            if other_data
            else "allow_other_data=true: every checkpoint read was trained on this data"
        )
    accuracy = metrics.get(f"{split}/teacher/scene_accuracy")
    if accuracy is not None:
        decided = metrics.get(f"{split}/render_compare/scene_accuracy")
        lines.append(
            f"teacher scene accuracy: {100 * accuracy:.1f} %"
            + ("" if decided is None else f"; after render_compare: {100 * decided:.1f} %")
        )
    diagnostics = f"{split}/diagnostics/"
    distances = {
        key.removeprefix(diagnostics).removesuffix("_m"): value
        for key, value in metrics.items()
        if key.startswith(diagnostics) and key.endswith("_m")
    }
    if distances:
        lines.append(
            "median distance to the nearest train position [m]: "
            + ", ".join(f"{name} {value:.3f}" for name, value in distances.items())
        )
    ratio = metrics.get(f"{diagnostics}gt_to_train_per_error")
    if ratio is not None:
        lines.append(
            f"{split}-camera distance to the train poses / teacher median error: {ratio:.2f} "
            "(Cambridge and 7-Scenes: 0.37-1.07, median about 0.7)"
        )
    return "\n".join(lines)


def _overrides(run_dir: Path) -> list[str] | None:
    """A run directory's command-line overrides (.hydra/overrides.yaml), if it has them."""
    overrides_file = run_dir / ".hydra" / "overrides.yaml"
    if not overrides_file.is_file():
        return None
    try:
        return [str(o) for o in OmegaConf.to_container(OmegaConf.load(overrides_file))]
    except Exception:  # a damaged file: the job is named by its folder
        return None


def _shown(overrides: list[str]) -> str:
    """A job's name: its overrides without the execution settings and checkpoint paths."""
    shown = [o for o in overrides if not o.startswith(("hydra.", "+trainer.", "trainer."))]
    shown = [o for o in shown if not o.startswith(("teacher_ckpt=", "student_ckpt=", "pae_ckpt="))]
    return " ".join(shown) or "(defaults)"


def _job_name(run_dir: Path, root: Path) -> str:
    overrides = _overrides(run_dir)
    if overrides is None:
        return str(run_dir.relative_to(root)) or "."
    return _shown(overrides)


def _job_dirs(root: Path) -> list[Path]:
    """Run directories below `root`: those with a metrics.json, an error.txt or a .hydra/."""
    found = {p.parent for name in ("metrics.json", ERROR_FILE) for p in root.rglob(name)}
    found |= {p.parent.parent for p in root.rglob(".hydra/overrides.yaml")}
    return sorted(found, key=_natural)


def _natural(path: Path) -> list[tuple[int, str]]:
    """Sort key that puts job 2 before job 10."""
    return [(int(part), "") if part.isdigit() else (-1, part) for part in path.parts]


def _missing_jobs(root: Path, run_dirs: list[Path]) -> list[tuple[Path, str]]:
    """(where, report line) for each job of a sweep below `root` (its multirun.yaml) that left
    no run directory: it never started, or was stopped before Hydra set it up."""
    started = {tuple(o) for o in map(_overrides, run_dirs) if o is not None}
    missing = []
    for multirun in sorted(root.rglob(MULTIRUN_FILE)):
        for job in sweep_jobs(multirun.parent) or []:
            if job.run_dir in run_dirs or (job.run_dir is None and tuple(job.overrides) in started):
                continue
            where = job.run_dir or multirun.parent / f"job {job.number}"
            state = f"never started (job {job.number}, no {where})"
            if where.is_dir():
                state = f"stopped as it started: no .hydra/, no metrics.json ({where})"
            missing.append((where, f"- {_shown(job.overrides)}: {state}"))
    return missing


def _read_metrics(path: Path) -> tuple[dict[str, float] | None, str | None]:
    """metrics.json -> (metrics, None), or (None, why it cannot be used)."""
    if not path.is_file():
        return None, None
    non_finite: list[str] = []
    try:
        metrics = json.loads(path.read_text(), parse_constant=non_finite.append)
    except (OSError, ValueError) as err:
        return None, f"{path}: unreadable metrics.json ({first_line(err)})"
    if not isinstance(metrics, dict):
        return None, f"{path}: metrics.json does not hold a JSON object"
    if non_finite:
        return None, (
            f"{path}: metrics.json holds non-finite figures ({', '.join(sorted(set(non_finite)))})"
            ": a run that diverged, not a result"
        )
    return metrics, None


def sweep_report(root: str | Path, split: str = "test") -> tuple[str, int]:
    """(the table of ``sweep_table``, the number of jobs it lists as failed or missing)."""
    root = Path(root)
    jobs = []
    failed = []
    run_dirs = _job_dirs(root)
    for run_dir in run_dirs:
        name = _job_name(run_dir, root)
        metrics, problem = _read_metrics(run_dir / "metrics.json")
        error_file = run_dir / ERROR_FILE
        if error_file.is_file():
            problem = f"{error_file.read_text().strip()} ({error_file})"
        elif metrics is None and problem is None:
            problem = (
                f"no metrics.json: unfinished, or stopped without a recorded error ({run_dir})"
            )
        if metrics is not None:
            jobs.append((name, metrics))
        if problem is not None:
            failed.append((run_dir, f"- {name}: {problem}"))
    failed = sorted(failed + _missing_jobs(root, run_dirs), key=lambda entry: _natural(entry[0]))
    if not jobs and not failed:
        raise FileNotFoundError(f"{root}: no metrics.json below this directory")
    methods = table_methods({key: 0.0 for _, job in jobs for key in job}, split)
    lines = ["| job | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    if not jobs:
        lines = [f"{root}: no finished job"]
    for name, metrics in jobs:
        cells = []
        for method in methods:
            pos = metrics.get(f"{split}/{method}/pos_median_m")
            rot = metrics.get(f"{split}/{method}/rot_median_deg")
            cells.append("-" if pos is None else f"{pos:.3f} / {rot:.2f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if failed:
        plural = "s" if len(failed) > 1 else ""
        lines += ["", f"{len(failed)} failed job{plural}:", *(f for _, f in failed)]
    return "\n".join(lines), len(failed)


def sweep_table(root: str | Path, split: str = "test") -> str:
    """Markdown table of every metrics.json under `root` (a run or a multirun directory):
    one row per job, named by its command-line overrides; cells are median position [m] /
    orientation [deg] per method. Below it, every failed job with its error (error.txt, an
    unreadable or non-finite metrics.json, or no metrics.json at all), and every job of a
    sweep's multirun.yaml that never started."""
    return sweep_report(root, split)[0]


CHANGE_AGAINST = {"guess_refined": "guess_initial", "guess_refined_test_store": "guess_initial"}
"""Methods whose change is measured against another than the teacher."""
WITHOUT_CHANGE = ("teacher", "student_gt", "guess_initial", "mean_pose")
"""Methods shown without a change: the baselines, and student_gt (no image involved)."""


def compare_table(runs: Sequence[Path], names: Sequence[str], split: str = "test") -> str:
    """Markdown table with one column per run (its ``metrics.json``) and one row per method:
    median position [m] / orientation [deg] and the position's change against the run's
    teacher (refined guesses: against the initial guess); ``*_test_store`` rows are marked as
    audits, and the geometry diagnostics close it."""
    if len(names) != len(runs):
        raise ValueError(f"--names gives {len(names)} names for {len(runs)} runs")
    columns = []
    for run in runs:
        metrics, problem = _read_metrics(Path(run) / "metrics.json")
        if metrics is None:
            raise ValueError(problem or f"{run}: no metrics.json")
        columns.append(metrics)
    merged = {key: 0.0 for metrics in columns for key in metrics}
    methods = [m for m in table_methods(merged, split) if m != "mean_pose"]
    lines = ["| method | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for method in methods:
        cells = []
        for metrics in columns:
            pos = metrics.get(f"{split}/{method}/pos_median_m")
            rot = metrics.get(f"{split}/{method}/rot_median_deg")
            baseline = metrics.get(f"{split}/{CHANGE_AGAINST.get(method, 'teacher')}/pos_median_m")
            if pos is None:
                cells.append("-")
                continue
            change = (
                "" if not baseline or method in WITHOUT_CHANGE else f" ({pos / baseline - 1:+.1%})"
            )
            cells.append(f"{pos:.3f} / {rot:.2f}{change}")
        label = marked(method)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    for key, label in (
        ("gt_to_train_m", "test camera → nearest train camera [m]"),
        ("gt_to_train_per_error", "the same ÷ teacher's median error"),
        ("estimate_to_train_m", "teacher estimate → nearest train camera [m]"),
    ):
        values = [metrics.get(f"{split}/diagnostics/{key}") for metrics in columns]
        cells = ["-" if v is None else f"{v:.2f}" for v in values]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append(
        f"\n\\* reads the {split} labels: retrieves among the {split} split's own poses (as the "
        "authors' public scripts do) or by the true pose: an audit, not a result."
    )
    return "\n".join(lines)


class SweepReport(Callback):
    """Hydra callback: at the end of a sweep, print its `pae-report` table and write it to
    `<sweep dir>/report.md` (failed jobs listed below the table, then mean ± sd over seeds
    when jobs differ only by seed)."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        try:
            table = sweep_table(sweep_dir)
            seeds = seed_report(sweep_dir, None, [])
        except (FileNotFoundError, ValueError) as err:
            print(f"pae-report: {err}", file=sys.stderr)
            return
        if seeds is not None:
            table += "\n\n" + seeds
        write_text_atomic(sweep_dir / "report.md", table + "\n")
        print(table)
        print(f"report: {sweep_dir / 'report.md'}")


def main(argv: list[str] | None = None) -> int:
    """`pae-report DIR`: the results of a run or a sweep as a markdown table (and, for jobs
    that differ only by seed, mean ± sd per variant); `pae-report DIR --compare`: paired
    differences between the sweep's variants over their seeds; `pae-report --compare RUN
    [RUN ...] --names A,B,...`: methods × runs (runs that are seed sweeps: paired); `--out
    FILE` also writes what is printed to FILE, whole or not at all. Exit status 1 when a job
    failed or is missing."""
    parser = argparse.ArgumentParser(prog="pae-report", description=sweep_table.__doc__)
    parser.add_argument("directory", type=Path, nargs="?")
    parser.add_argument("--split", default="test", choices=("test", "val"))
    parser.add_argument(
        "--compare",
        type=Path,
        nargs="*",
        metavar="RUN",
        help="run directories as columns; with DIR and no RUN: the sweep's variants, paired",
    )
    parser.add_argument("--names", help="comma-separated column names for --compare")
    parser.add_argument("--baseline", help="DIR --compare: the variant to compare against")
    parser.add_argument(
        "--out", type=Path, metavar="FILE", help="also write the report to FILE (markdown)"
    )
    args = parser.parse_args(argv)
    if (args.directory is None) == (not args.compare):  # DIR [--compare] or --compare RUN...
        parser.error("give DIR, DIR --compare, or --compare RUN [RUN ...]")
    try:
        if args.out is not None:
            check_writable_file(args.out, "--out")
        names = args.names.split(",") if args.names else [p.name for p in args.compare or ()]
        seeds = seed_report(
            args.directory, args.compare, names, split=args.split, baseline=args.baseline
        )
        parts = []
        if args.compare and seeds is None:
            parts.append(compare_table(args.compare, names, args.split))
        problems = 0
        if args.directory is not None and args.compare is None:
            table, problems = sweep_report(args.directory, args.split)
            parts.append(table)
        if seeds is not None:
            parts.append(("\n" if args.compare is None else "") + seeds)
        report = "\n".join(parts)
        print(report)
        if args.out is not None:
            write_text_atomic(args.out, report + "\n")
        if problems:
            return 1
    except (OSError, ValueError) as err:
        print(f"pae-report: error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
