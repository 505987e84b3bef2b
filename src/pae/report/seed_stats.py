"""Seed statistics for `pae-report`: the jobs of a sweep that differ only by `seed` grouped
into variants, mean ± sd (n) per variant, and paired differences between variants on the
seeds they share, with a 95 % t interval (marked when it excludes zero)."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from omegaconf import OmegaConf

from pae.report.method_rows import TEST_STORE_SUFFIX, table_methods

Metrics = dict[str, float]
Variants = dict[str, dict[int, Metrics]]
"""variant name -> seed -> that job's metrics."""

T_975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228)
"""Two-sided 95 % quantiles of Student's t for 1..10 degrees of freedom."""
FIGURES = (("pos_median_m", "position [m]", 3), ("rot_median_deg", "orientation [deg]", 2))
"""(metric key, what it is, decimals) of the tables."""
HIDDEN_OVERRIDES = ("hydra.", "trainer.", "+trainer.", "seed=")
"""Overrides that do not make a variant (launcher and trainer settings, the seed)."""


def t_quantile_975(df: int) -> float:
    """The 97.5 % quantile of Student's t with `df` >= 1 degrees of freedom (the half-width
    factor of a 95 % interval): tabulated to 10, then its Cornish-Fisher expansion (error
    below 1e-3)."""
    if df < 1:
        raise ValueError(f"degrees of freedom must be >= 1, got {df}")
    if df <= len(T_975):
        return T_975[df - 1]
    z = 1.959964
    return (
        z
        + (z**3 + z) / (4 * df)
        + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * df**2)
        + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * df**3)
    )


@dataclass(frozen=True)
class Spread:
    """Mean, sample standard deviation (n − 1; 0 for one value) and count of some values."""

    mean: float
    sd: float
    n: int

    @classmethod
    def of(cls, values: Sequence[float]) -> Spread:
        n = len(values)
        if n == 0:
            raise ValueError("no values")
        mean = sum(values) / n
        var = sum((v - mean) ** 2 for v in values) / (n - 1) if n > 1 else 0.0
        return cls(mean, math.sqrt(var), n)

    def format(self, decimals: int) -> str:
        return f"{self.mean:.{decimals}f} ± {self.sd:.{decimals}f} ({self.n})"


@dataclass(frozen=True)
class PairedDifference:
    """Mean of per-seed differences (variant − baseline) with its 95 % t interval; n pairs.
    With one pair the interval is unknown (nan)."""

    mean: float
    low: float
    high: float
    n: int

    @classmethod
    def of(cls, variant: Sequence[float], baseline: Sequence[float]) -> PairedDifference:
        spread = Spread.of([a - b for a, b in zip(variant, baseline, strict=True)])
        if spread.n < 2:
            return cls(spread.mean, math.nan, math.nan, spread.n)
        half = t_quantile_975(spread.n - 1) * spread.sd / math.sqrt(spread.n)
        return cls(spread.mean, spread.mean - half, spread.mean + half, spread.n)

    @property
    def excludes_zero(self) -> bool:
        return self.low > 0 or self.high < 0

    def format(self, decimals: int) -> str:
        if self.n < 2:
            return f"{self.mean:+.{decimals}f} (1)"
        mark = " ≠0" if self.excludes_zero else ""
        interval = f"[{self.low:+.{decimals}f}, {self.high:+.{decimals}f}]"
        return f"{self.mean:+.{decimals}f} {interval} ({self.n}){mark}"


def _overrides(run_dir: Path) -> list[str]:
    path = run_dir / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return []
    return [str(o) for o in OmegaConf.to_container(OmegaConf.load(path), resolve=False)]


def _seed(run_dir: Path, overrides: list[str]) -> int | None:
    """The job's seed: from its resolved config (`.hydra/config.yaml`), else its overrides."""
    config = run_dir / ".hydra" / "config.yaml"
    if config.is_file():
        seed = OmegaConf.load(config).get("seed")
        if isinstance(seed, int):
            return seed
    given = [o.removeprefix("seed=") for o in overrides if o.startswith("seed=")]
    return int(given[0]) if given and given[0].isdigit() else None


def seed_variants(root: str | Path) -> Variants:
    """The finished jobs below `root` (readable metrics.json) grouped by their overrides other
    than the seed (and launcher or trainer settings; in any order), then by seed. Variants are
    named by the overrides in which they differ (all of them when there is one variant)."""
    keyed: dict[tuple[str, ...], dict[int, Metrics]] = {}
    for path in sorted(Path(root).rglob("metrics.json")):
        run_dir = path.parent
        try:
            metrics = json.loads(path.read_text())
        except (OSError, ValueError):
            continue  # pae-report's job table lists it as failed
        overrides = _overrides(run_dir)
        seed = _seed(run_dir, overrides)
        if seed is None or not isinstance(metrics, dict):
            continue
        key = tuple(sorted(o for o in overrides if not o.startswith(HIDDEN_OVERRIDES)))
        jobs = keyed.setdefault(key, {})
        if seed in jobs:
            raise ValueError(f"{run_dir}: a second job of '{' '.join(key)}' with seed={seed}")
        jobs[seed] = metrics
    shared = set.intersection(*(set(k) for k in keyed)) if len(keyed) > 1 else set()
    return {
        " ".join(o for o in key if o not in shared) or "(defaults)": jobs
        for key, jobs in keyed.items()
    }


def _methods(variants: Variants, split: str) -> list[str]:
    merged = {key: 0.0 for jobs in variants.values() for m in jobs.values() for key in m}
    return table_methods(merged, split)


def _label(method: str) -> str:
    return f"{method} *" if method.endswith(TEST_STORE_SUFFIX) else method


def seed_table(variants: Variants, split: str = "test") -> str:
    """Markdown tables, position then orientation: one row per variant, one column per
    method, cells mean ± sd (n) of the per-seed medians."""
    methods = _methods(variants, split)
    lines: list[str] = []
    for figure, what, decimals in FIGURES:
        lines += [
            f"median {what} over seeds, {split} split: mean ± sd (n seeds)",
            "",
            "| variant | seeds | " + " | ".join(_label(m) for m in methods) + " |",
            "|---|---|" + "---:|" * len(methods),
        ]
        for name, jobs in variants.items():
            cells = []
            for method in methods:
                found = [m.get(f"{split}/{method}/{figure}") for m in jobs.values()]
                values = [float(v) for v in found if v is not None]
                cells.append(Spread.of(values).format(decimals) if values else "-")
            seeds = ",".join(str(s) for s in sorted(jobs))
            lines.append(f"| {name} | {seeds} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines).rstrip()


def _values(jobs: Mapping[int, Metrics], seeds: list[int], key: str) -> list[float] | None:
    values = [jobs[s].get(key) for s in seeds]
    return None if any(v is None for v in values) else [float(v) for v in values]


def paired_table(variants: Variants, baseline: str | None = None, split: str = "test") -> str:
    """Markdown tables, position then orientation: per method, each variant's paired
    difference to `baseline` (default: the first variant) over the seeds both have, mean
    [95 % t interval] (n pairs), marked ≠0 when the interval excludes zero."""
    if len(variants) < 2:
        raise ValueError(f"--compare needs two variants; found {list(variants) or 'none'}")
    baseline = baseline if baseline is not None else next(iter(variants))
    if baseline not in variants:
        raise ValueError(f"no variant {baseline!r}; the variants are {list(variants)}")
    others = [name for name in variants if name != baseline]
    methods = _methods(variants, split)
    lines: list[str] = []
    for figure, what, decimals in FIGURES:
        lines += [
            f"paired difference in median {what} against {baseline}, {split} split: "
            "mean [95 % t interval] (n seeds); ≠0: the interval excludes zero",
            "",
            "| method | " + " | ".join(f"{name} − baseline" for name in others) + " |",
            "|---|" + "---:|" * len(others),
        ]
        for method in methods:
            key = f"{split}/{method}/{figure}"
            cells = []
            for name in others:
                seeds = sorted(set(variants[name]) & set(variants[baseline]))
                a = _values(variants[name], seeds, key)
                b = _values(variants[baseline], seeds, key)
                cells.append("-" if not seeds or a is None or b is None else _cell(a, b, decimals))
            lines.append(f"| {_label(method)} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines).rstrip()


def _cell(variant: list[float], baseline: list[float], decimals: int) -> str:
    return PairedDifference.of(variant, baseline).format(decimals)


def has_seed_groups(variants: Variants) -> bool:
    """Whether some variant ran with more than one seed."""
    return any(len(jobs) > 1 for jobs in variants.values())


def merge_sweeps(roots: Sequence[Path], names: Sequence[str]) -> Variants:
    """Variants of several sweep directories, each a single variant over seeds, named
    `names` (one per directory)."""
    if len(names) != len(roots):
        raise ValueError(f"--names gives {len(names)} names for {len(roots)} sweeps")
    merged: Variants = {}
    for root, name in zip(roots, names, strict=True):
        found = seed_variants(root)
        if len(found) != 1:
            raise ValueError(
                f"{root}: holds {len(found)} variants ({', '.join(found)}); compare them with "
                f"pae-report {root} --compare"
            )
        merged[name] = next(iter(found.values()))
    return merged


def seed_report(
    directory: Path | None, compare: Sequence[Path] | None, names: Sequence[str], **options: str
) -> str | None:
    """pae-report's seed outputs (None: not a seed report): `DIR --compare` pairs the variants
    of one sweep against `baseline`; `--compare SWEEP SWEEP ...` pairs sweeps of one variant
    each (the first is the baseline); `DIR` alone gives mean ± sd when some variant has
    several seeds."""
    split = options.get("split", "test")
    if directory is not None and compare is not None:
        return paired_table(seed_variants(directory), options.get("baseline"), split)
    if directory is not None:
        variants = seed_variants(directory)
        return seed_table(variants, split) if has_seed_groups(variants) else None
    sweeps = [seed_variants(root) for root in compare or ()]
    if not sweeps or not all(has_seed_groups(found) for found in sweeps):
        return None
    return paired_table(merge_sweeps(list(compare or ()), names), None, split)
