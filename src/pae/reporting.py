"""Run outputs: atomic metrics.json, the results table, and one-line errors for entry points."""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

from hydra.errors import HydraException, InstantiationException
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from pae.checkpoints import CheckpointError
from pae.data.labels import LabelError
from pae.data.transforms import ImageError
from pae.models.backbones import BackboneError

METHOD_ORDER = (
    "teacher",
    "student",
    "student_gt",
    "refined",
    "vrpr",
    "guess_initial",
    "guess_refined",
    "mean_pose",
)


class ConfigError(ValueError):
    """A configuration value that cannot work; the message names the key."""


USER_ERRORS = (
    ConfigError,
    LabelError,
    ImageError,
    CheckpointError,
    BackboneError,
    OmegaConfBaseException,
    HydraException,
)


def write_json_atomic(path: str | Path, payload: Mapping[str, object]) -> None:
    """Write JSON to a temporary file beside `path`, then rename it over `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as handle:
            json.dump(dict(payload), handle, indent=2, sort_keys=True)
            handle.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def format_results_table(metrics: Mapping[str, float], split: str = "test") -> str:
    """Paper-style table: median position / orientation error per method, overall and per scene."""
    methods = [m for m in METHOD_ORDER if f"{split}/{m}/pos_median_m" in metrics]
    scenes = sorted(
        {
            key.split("/")[2]
            for key in metrics
            if key.startswith(f"{split}/") and key.count("/") == 3
        }
    )
    columns = ["overall", *scenes]
    header = f"{'method':<15}" + "".join(f"{c:>18}" for c in columns)
    lines = [f"median position [m] / orientation [deg] on the {split} split", header]
    lines.append("-" * len(header))
    for method in methods:
        cells = []
        for column in columns:
            prefix = f"{split}/{method}/" if column == "overall" else f"{split}/{method}/{column}/"
            pos, rot = metrics.get(prefix + "pos_median_m"), metrics.get(prefix + "rot_median_deg")
            cells.append("-" if pos is None else f"{pos:.3f} / {rot:.2f}")
        lines.append(f"{method:<15}" + "".join(f"{c:>18}" for c in cells))
    accuracy = metrics.get(f"{split}/teacher/scene_accuracy")
    if accuracy is not None:
        lines.append(f"teacher scene accuracy: {100 * accuracy:.1f} %")
    diagnostics = {
        key.rsplit("/", 1)[1]: value
        for key, value in metrics.items()
        if key.startswith(f"{split}/diagnostics/")
    }
    if diagnostics:
        lines.append(
            "median distance to the nearest train position [m]: "
            + ", ".join(
                f"{name.removesuffix('_m')} {value:.3f}" for name, value in diagnostics.items()
            )
        )
    return "\n".join(lines)


def _first_line(err: BaseException) -> str:
    """The user-facing line of an error: the root of a Hydra instantiation error, and the
    original message (not the worker traceback) of an error raised in a DataLoader worker."""
    cause = err
    while isinstance(cause, InstantiationException) and cause.__cause__ is not None:
        cause = cause.__cause__
    lines = [line.strip() for line in str(cause).strip().splitlines() if line.strip()]
    if lines and lines[0].startswith("Caught ") and "Traceback" in str(cause):
        lines = [lines[-1].split(": ", 1)[-1]]
    return " ".join(" ".join(lines).split()) or type(cause).__name__


@contextmanager
def reporting_errors(program: str) -> Iterator[None]:
    """Turn user errors (bad labels, images, checkpoints, config) into one line and exit 1."""
    try:
        yield
    except InstantiationException as err:
        print(f"{program}: error: {_first_line(err)}", file=sys.stderr)
        raise SystemExit(1) from None
    except USER_ERRORS as err:
        print(f"{program}: error: {_first_line(err)}", file=sys.stderr)
        raise SystemExit(1) from None


def _job_name(run_dir: Path, root: Path) -> str:
    overrides_file = run_dir / ".hydra" / "overrides.yaml"
    if not overrides_file.is_file():
        return str(run_dir.relative_to(root)) or "."
    overrides = [str(o) for o in OmegaConf.load(overrides_file)]
    shown = [o for o in overrides if not o.startswith(("hydra.", "+trainer.", "trainer."))]
    shown = [o for o in shown if not o.startswith(("teacher_ckpt=", "pae_ckpt="))]
    return " ".join(shown) or "(defaults)"


def sweep_table(root: str | Path, split: str = "test") -> str:
    """Markdown table of every metrics.json under `root` (a run or a multirun directory):
    one row per job, named by its command-line overrides; cells are median position [m] /
    orientation [deg] per method."""
    root = Path(root)
    jobs = []
    for path in sorted(root.rglob("metrics.json")):
        metrics = json.loads(path.read_text())
        jobs.append((_job_name(path.parent, root), metrics))
    if not jobs:
        raise FileNotFoundError(f"{root}: no metrics.json below this directory")
    methods = [
        m for m in METHOD_ORDER if any(f"{split}/{m}/pos_median_m" in job for _, job in jobs)
    ]
    lines = [
        "| job | " + " | ".join(methods) + " |",
        "|---|" + "---|" * len(methods),
    ]
    for name, metrics in jobs:
        cells = []
        for method in methods:
            pos = metrics.get(f"{split}/{method}/pos_median_m")
            rot = metrics.get(f"{split}/{method}/rot_median_deg")
            cells.append("-" if pos is None else f"{pos:.3f} / {rot:.2f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """`pae-report DIR`: the results of a run or a sweep as a markdown table."""
    parser = argparse.ArgumentParser(prog="pae-report", description=sweep_table.__doc__)
    parser.add_argument("directory", type=Path)
    parser.add_argument("--split", default="test", choices=("test", "val"))
    args = parser.parse_args(argv)
    try:
        print(sweep_table(args.directory, args.split))
    except (OSError, ValueError) as err:
        print(f"pae-report: error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
