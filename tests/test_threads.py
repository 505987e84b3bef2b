"""pae.core.threads: the thread count from affinity, the cgroup quota and the environment,
and the wait policy set before the OpenMP runtimes load (the decision, not its speed)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from pae.core import threads
from pae.core.errors import ConfigError
from pae.core.threads import (
    HUGE_PAGES,
    cgroup_cpu_limit,
    decide_threads,
    loader_workers,
    prepare_environment,
    wait_policy,
)


@pytest.fixture
def machine(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    """A machine of 8 usable CPUs without a cgroup quota; returns a function that sets one."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    proc = tmp_path / "proc_cgroup"
    proc.write_text("0::/\n")
    root = tmp_path / "cgroup"
    root.mkdir()
    monkeypatch.setattr(threads, "CGROUP_ROOT", root)
    monkeypatch.setattr(threads, "PROC_CGROUP", proc)

    def set_quota(text: str) -> None:
        (root / "cpu.max").write_text(text)

    return set_quota


def test_the_affinity_decides_without_quota_or_variables(machine) -> None:
    budget = decide_threads({})
    assert (budget.threads, budget.affinity, budget.cgroup_cores) == (8, 8, None)
    assert budget.summary({}).startswith(
        "threads: 8 (affinity 8, cgroup none, OMP_NUM_THREADS unset, PAE_THREADS unset)"
    )


def test_a_cgroup_quota_caps_the_threads_rounded_up(machine) -> None:
    machine("250000 100000\n")
    budget = decide_threads({})
    assert (budget.threads, budget.cgroup_cores) == (3, 2.5)
    assert "cgroup 2.5 cores" in budget.summary({})
    machine("max 100000\n")
    assert decide_threads({}).threads == 8
    machine("50000 100000\n")
    assert decide_threads({}).threads == 1


def test_omp_num_threads_caps_and_pae_threads_overrides(machine) -> None:
    machine("400000 100000\n")
    assert decide_threads({"OMP_NUM_THREADS": "2"}).threads == 2
    assert decide_threads({"OMP_NUM_THREADS": "16"}).threads == 4
    assert decide_threads({"OMP_NUM_THREADS": "3,1"}).threads == 3  # OpenMP's nested list
    assert decide_threads({"OMP_NUM_THREADS": "many"}).omp_num_threads is None
    budget = decide_threads({"OMP_NUM_THREADS": "2", "PAE_THREADS": "6"})
    assert (budget.threads, budget.pae_threads, budget.omp_num_threads) == (6, 6, 2)
    assert "OMP_NUM_THREADS 2, PAE_THREADS 6" in budget.summary({})


@pytest.mark.parametrize("value", ["0", "two", "-1", "1.5"])
def test_a_pae_threads_that_is_not_a_count_is_one_line_naming_it(machine, value: str) -> None:
    with pytest.raises(ConfigError, match=r"^PAE_THREADS=.*at least 1$"):
        decide_threads({"PAE_THREADS": value})


def test_cgroup_v2_takes_the_tightest_quota_of_the_process_cgroup_and_those_above(
    tmp_path: Path,
) -> None:
    proc = tmp_path / "proc_cgroup"
    proc.write_text("0::/jobs/job7\n")
    (tmp_path / "jobs" / "job7").mkdir(parents=True)
    (tmp_path / "jobs" / "job7" / "cpu.max").write_text("max 100000\n")
    (tmp_path / "jobs" / "cpu.max").write_text("150000 100000\n")
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert cgroup_cpu_limit(tmp_path, proc) == 1.5
    proc.write_text("0::/not/mounted/here\n")  # a container's view: the root's files
    assert cgroup_cpu_limit(tmp_path, proc) is None


def test_cgroup_v1_reads_the_cfs_quota_and_period(tmp_path: Path) -> None:
    proc = tmp_path / "proc_cgroup"
    proc.write_text("4:memory:/box\n2:cpu,cpuacct:/box\n1:name=systemd:/\n")
    box = tmp_path / "cpu,cpuacct" / "box"
    box.mkdir(parents=True)
    (box / "cpu.cfs_quota_us").write_text("200000\n")
    (box / "cpu.cfs_period_us").write_text("100000\n")
    (tmp_path / "cpu,cpuacct" / "cpu.cfs_quota_us").write_text("-1\n")
    (tmp_path / "cpu,cpuacct" / "cpu.cfs_period_us").write_text("100000\n")
    assert cgroup_cpu_limit(tmp_path, proc) == 2.0
    (box / "cpu.cfs_quota_us").write_text("-1\n")
    assert cgroup_cpu_limit(tmp_path, proc) is None
    assert cgroup_cpu_limit(tmp_path, tmp_path / "absent") is None


def test_waiting_threads_sleep_unless_the_environment_says_how_they_wait() -> None:
    environ: dict[str, str] = {}
    prepare_environment(environ)
    assert environ == {"OMP_WAIT_POLICY": "PASSIVE", "KMP_BLOCKTIME": "0", **HUGE_PAGES}
    assert wait_policy(environ) == "waiting threads sleep (OMP_WAIT_POLICY=PASSIVE)"
    for chosen in ({"OMP_WAIT_POLICY": "ACTIVE"}, {"GOMP_SPINCOUNT": "300000"}):
        environ = {**chosen, "THP_MEM_ALLOC_ENABLE": "0"}
        prepare_environment(environ)
        assert environ == {**chosen, "THP_MEM_ALLOC_ENABLE": "0"}
        assert "as the environment says" in wait_policy(environ)


def test_numba_pool_follows_pae_threads_then_omp_num_threads() -> None:
    environ = {"OMP_NUM_THREADS": "1", "PAE_THREADS": "3"}
    prepare_environment(environ)
    assert environ["NUMBA_NUM_THREADS"] == "3"
    environ = {"OMP_NUM_THREADS": "1"}
    prepare_environment(environ)
    assert environ["NUMBA_NUM_THREADS"] == "1"
    environ = {"OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "2"}
    prepare_environment(environ)
    assert environ["NUMBA_NUM_THREADS"] == "2"


def test_loaders_get_no_more_workers_than_threads(machine, monkeypatch) -> None:
    monkeypatch.setattr(threads, "_CONFIGURED", None)
    monkeypatch.setenv("PAE_THREADS", "2")
    assert (loader_workers(4), loader_workers(1), loader_workers(0)) == (2, 1, 0)


def test_a_command_configures_torch_and_numba_and_says_so_first() -> None:
    """In a fresh process (the libraries read the wait policy when they load): PAE_THREADS=1
    gives torch and numba one thread each, waiting threads sleep, and the line says why."""
    code = (
        "import pae, torch, numba;"
        "from pae.core.threads import configure_threads;"
        "line = configure_threads().summary();"
        "import os; print(line, torch.get_num_threads(), numba.get_num_threads(),"
        " os.environ['OMP_WAIT_POLICY'])"
    )
    environ = {k: v for k, v in os.environ.items() if k not in threads.WAIT_VARIABLES}
    environ["PAE_THREADS"] = "1"
    printed = subprocess.run(
        [sys.executable, "-c", code], env=environ, capture_output=True, text=True, check=True
    ).stdout
    assert "threads: 1 (" in printed and "PAE_THREADS 1)" in printed
    assert printed.strip().endswith("1 1 PASSIVE")
