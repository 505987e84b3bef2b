"""Seed statistics of pae-report: mean ± sd per variant and paired 95 % intervals, on
numbers whose answers are known."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from pae.core.atomic import write_json_atomic
from pae.report.seed_stats import PairedDifference, Spread, seed_variants, t_quantile_975
from pae.report.tables import main


def _job(folder: Path, overrides: list[str], seed: int, teacher: float, student: float) -> None:
    """A finished sweep job: its overrides, resolved seed and metrics."""
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    (folder / ".hydra" / "config.yaml").write_text(f"seed: {seed}\n")
    metrics = {}
    for method, pos in (("teacher", teacher), ("student", student)):
        metrics[f"test/{method}/pos_median_m"] = pos
        metrics[f"test/{method}/rot_median_deg"] = 10 * pos
    write_json_atomic(folder / "metrics.json", metrics)


@pytest.fixture
def sweep(tmp_path: Path) -> Path:
    """pae.L=0,6 x seed=0,1,2: teacher 1, 2, 3 m (shared per seed); the L=6 student 0.9, 1.0,
    1.1 m above the teacher, the L=0 student 1, 2, 3 m above it."""
    job = 0
    for seed, teacher in enumerate((1.0, 2.0, 3.0)):
        for L, extra in (("0", (1.0, 2.0, 3.0)[seed]), ("6", (0.9, 1.0, 1.1)[seed])):
            overrides = [f"pae.L={L}", f"seed={seed}", "teacher_ckpt=t/${seed}.ckpt"]
            _job(tmp_path / str(job), overrides, seed, teacher, teacher + extra)
            job += 1
    return tmp_path


def test_spread_and_paired_interval_on_known_numbers() -> None:
    assert Spread.of([1.0, 2.0, 3.0]) == Spread(2.0, 1.0, 3)
    wide = PairedDifference.of([2.0, 4.0, 6.0], [1.0, 2.0, 3.0])  # differences 1, 2, 3
    assert wide.mean == 2.0 and wide.high - 2.0 == pytest.approx(4.303 / math.sqrt(3))
    assert not wide.excludes_zero
    narrow = PairedDifference.of([1.9, 3.0, 4.1], [1.0, 2.0, 3.0])  # 0.9, 1.0, 1.1
    assert (narrow.low, narrow.high) == pytest.approx((1 - 0.24843, 1 + 0.24843), abs=1e-5)
    assert narrow.excludes_zero and narrow.format(3) == "+1.000 [+0.752, +1.248] (3) ≠0"


def test_t_quantiles_match_scipy() -> None:
    stats = pytest.importorskip("scipy.stats")
    for df in range(1, 60):
        assert t_quantile_975(df) == pytest.approx(stats.t.ppf(0.975, df), abs=1e-3)


def test_jobs_that_differ_only_by_seed_form_one_variant(sweep: Path) -> None:
    variants = seed_variants(sweep)
    assert list(variants) == ["pae.L=0", "pae.L=6"]  # the shared checkpoint override is hidden
    assert sorted(variants["pae.L=6"]) == [0, 1, 2]


def test_report_prints_mean_sd_n_per_variant(sweep: Path, capsys: pytest.CaptureFixture) -> None:
    assert main([str(sweep)]) == 0
    out = capsys.readouterr().out
    # L=0 student: 2, 4, 6 m -> 4 ± 2; L=6: 1.9, 3.0, 4.1 -> 3 ± 1.1; teacher 2 ± 1
    assert "| pae.L=0 | 0,1,2 | 2.000 ± 1.000 (3) | 4.000 ± 2.000 (3) |" in out
    assert "| pae.L=6 | 0,1,2 | 2.000 ± 1.000 (3) | 3.000 ± 1.100 (3) |" in out
    assert "| pae.L=0 | 0,1,2 | 20.00 ± 10.00 (3) | 40.00 ± 20.00 (3) |" in out


def test_compare_gives_paired_intervals_and_marks_those_excluding_zero(
    sweep: Path, capsys: pytest.CaptureFixture
) -> None:
    assert main([str(sweep), "--compare", "--baseline", "pae.L=6"]) == 0
    out = capsys.readouterr().out
    # L=0 - L=6 student differences per seed: 0.1, 1.0, 1.9 m: mean 1.0, sd 0.9
    half = 4.303 * 0.9 / math.sqrt(3)
    assert f"| student | +1.000 [{1 - half:+.3f}, {1 + half:+.3f}] (3) |" in out
    assert "| teacher | +0.000 [+0.000, +0.000] (3) |" in out  # the same teacher per seed
    assert main([str(sweep), "--compare"]) == 0  # baseline: the first variant, L=0
    out = capsys.readouterr().out
    assert f"| student | -1.000 [{-1 - half:+.3f}, {-1 + half:+.3f}] (3) |" in out


def test_compare_pairs_two_sweeps_of_one_variant_each(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    for seed, (a, b) in enumerate(((1.0, 1.9), (2.0, 3.0), (3.0, 4.1))):
        _job(tmp_path / "a" / str(seed), [f"seed={seed}"], seed, a, a)
        _job(tmp_path / "b" / str(seed), [f"seed={seed}"], seed, a, b)
    assert main(["--compare", str(tmp_path / "a"), str(tmp_path / "b"), "--names", "x,y"]) == 0
    out = capsys.readouterr().out
    assert "| student | +1.000 [+0.752, +1.248] (3) ≠0 |" in out and "y − baseline" in out


def test_a_repeated_seed_is_an_error(sweep: Path, capsys: pytest.CaptureFixture) -> None:
    _job(sweep / "again", ["pae.L=0", "seed=1", "teacher_ckpt=t/${seed}.ckpt"], 1, 1.0, 1.0)
    assert main([str(sweep), "--compare"]) == 1
    assert "a second job of 'pae.L=0 teacher_ckpt=t/${seed}.ckpt' with seed=1" in (
        capsys.readouterr().err
    )


def test_the_sweep_objective_is_a_validation_figure() -> None:
    from pae.train import objective

    metrics = {"test/student/pos_median_m": 0.1, "val/student/pos_median_m": 0.3}
    assert objective(metrics) == 0.3
    assert objective({"test/teacher/pos_median_m": 0.1, "val/teacher/pos_median_m": 0.2}) == 0.2
    assert objective({"test/teacher/pos_median_m": 0.1}) is None


def test_a_finished_sweep_writes_its_seed_table_to_report_md(
    sweep: Path, capsys: pytest.CaptureFixture
) -> None:
    from omegaconf import OmegaConf

    from pae.report.tables import SweepReport

    SweepReport().on_multirun_end(OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep)}}}))
    report = (sweep / "report.md").read_text()
    assert "| pae.L=6 seed=2 |" in report  # the job table, then the variants over seeds
    assert "| pae.L=6 | 0,1,2 | 2.000 ± 1.000 (3) | 3.000 ± 1.100 (3) |" in report
    assert report.strip() in capsys.readouterr().out
