"""How many threads pae uses, and waiting threads that sleep instead of spinning.

The count (``decide_threads``): ``PAE_THREADS`` where it is set; else the cores this process
may run on (its CPU affinity, capped by its cgroup's CPU quota rounded up), capped by
``OMP_NUM_THREADS`` where that is set (joblib's workers get their share through it).
``configure_threads``, called once at the start of each command, gives torch's intra-op and
inter-op pools, numba's pool and OpenCV's that many threads, caps the data loaders' workers
at it (``loader_workers``) and returns the one line that says how it was decided.

Waiting (``prepare_environment``, run when pae is imported, before torch and numba are):
OpenMP threads that wait for work sleep (``OMP_WAIT_POLICY=PASSIVE``, ``KMP_BLOCKTIME=0``)
unless the environment sets the wait itself (``OMP_WAIT_POLICY``, ``GOMP_SPINCOUNT`` or
``KMP_BLOCKTIME``). Spinning threads hold every core while they wait for the slowest; with
another process on one of the cores each parallel region then waits for a thread that is not
running, and a run slows down many times over instead of by the share of the core it lost.
The OpenMP runtimes read these variables when they are loaded, and child processes (data
loader workers, launchers' jobs) inherit them.

Memory (also ``prepare_environment``): torch places its CPU tensors of 2 MB and more on
transparent huge pages (``THP_MEM_ALLOC_ENABLE=1``, read at torch's first allocation) unless
the environment sets the variable. Each such tensor is fresh memory from the kernel, paged in
on first touch: a 224 px batch of 64 through the small CNN took 330,000 page faults per
forward with 4-kB pages and ran 1.7 times as fast on huge pages
(``experiments/bench/huge_pages.py``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import sys
from collections.abc import Iterator, Mapping, MutableMapping
from pathlib import Path

from pae.core.errors import ConfigError

CGROUP_ROOT = Path("/sys/fs/cgroup")
"""Where the cgroup file systems are mounted (v2: one tree; v1: one per controller)."""
PROC_CGROUP = Path("/proc/self/cgroup")
"""This process's cgroups, one ``hierarchy:controllers:path`` line each."""
WAIT_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "KMP_BLOCKTIME")
"""The environment variables that say how OpenMP threads wait (any one set: pae sets none)."""
SLEEPING_WAIT = {"OMP_WAIT_POLICY": "PASSIVE", "KMP_BLOCKTIME": "0"}
"""What pae sets where the environment says nothing about waiting: waiting threads sleep
(GNU OpenMP: no spinning at all under PASSIVE; Intel OpenMP: no block time)."""
HUGE_PAGES = {"THP_MEM_ALLOC_ENABLE": "1"}
"""What pae sets where the environment does not: torch's large CPU tensors on transparent
huge pages (module docstring; where the kernel's THP mode is ``never`` it changes nothing)."""


@dataclasses.dataclass(frozen=True)
class ThreadBudget:
    """threads: what pae uses; the inputs of that decision: affinity (CPUs this process may
    run on), cgroup_cores (its cgroup's CPU quota in cores, None without one),
    omp_num_threads and pae_threads (the variables, None where unset)."""

    threads: int
    affinity: int
    cgroup_cores: float | None
    omp_num_threads: int | None
    pae_threads: int | None

    def summary(self, environ: Mapping[str, str] | None = None) -> str:
        """One line: the thread count and why, and how waiting threads wait, e.g. ``threads:
        2 (affinity 2, cgroup none, OMP_NUM_THREADS unset, PAE_THREADS unset); waiting
        threads sleep (OMP_WAIT_POLICY=PASSIVE)``."""
        cgroup = "none" if self.cgroup_cores is None else f"{self.cgroup_cores:g} cores"
        inputs = ", ".join(
            (
                f"affinity {self.affinity}",
                f"cgroup {cgroup}",
                f"OMP_NUM_THREADS {_or_unset(self.omp_num_threads)}",
                f"PAE_THREADS {_or_unset(self.pae_threads)}",
            )
        )
        return f"threads: {self.threads} ({inputs}); {wait_policy(environ)}"


def _or_unset(value: int | None) -> str:
    return "unset" if value is None else str(value)


def wait_policy(environ: Mapping[str, str] | None = None) -> str:
    """How OpenMP threads wait, in words, from the environment's wait variables."""
    environ = os.environ if environ is None else environ
    settings = [f"{name}={environ[name]}" for name in WAIT_VARIABLES if name in environ]
    if settings == [f"{name}={value}" for name, value in SLEEPING_WAIT.items()]:
        return "waiting threads sleep (OMP_WAIT_POLICY=PASSIVE)"
    if not settings:
        return "waiting threads spin first (OpenMP's default)"
    return f"waiting threads as the environment says ({', '.join(settings)})"


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity mask; all CPUs where there is none)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def _cgroup_dirs(mount: Path, path: str) -> Iterator[Path]:
    """``mount``/``path`` and each folder above it up to ``mount`` (from the deepest one that
    exists: inside a container the path may name a folder that is not mounted)."""
    folder = mount / path.strip("/")
    while folder != mount and not folder.is_dir():
        folder = folder.parent
    while True:
        yield folder
        if folder == mount:
            return
        folder = folder.parent


def _read_quota(folder: Path) -> float | None:
    """The CPU quota in cores set in ``folder`` (v2 ``cpu.max``; v1 ``cpu.cfs_quota_us`` over
    ``cpu.cfs_period_us``), None where it sets none or cannot be read."""
    try:
        if (folder / "cpu.max").is_file():
            quota, period = (folder / "cpu.max").read_text().split()[:2]
        else:
            quota = (folder / "cpu.cfs_quota_us").read_text().strip()
            period = (folder / "cpu.cfs_period_us").read_text().strip()
        if quota == "max" or int(quota) <= 0 or int(period) <= 0:
            return None
        return int(quota) / int(period)
    except (OSError, ValueError):
        return None


def cgroup_cpu_limit(root: Path | None = None, proc_cgroup: Path | None = None) -> float | None:
    """This process's CPU quota in cores: the tightest of its cgroup's and those above it
    (cgroup v2 ``cpu.max``, v1 ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``; the mounts under
    ``root``, default CGROUP_ROOT, the process's cgroups in ``proc_cgroup``, default
    PROC_CGROUP); None without one, or where the files cannot be read."""
    root = root or CGROUP_ROOT
    proc_cgroup = proc_cgroup or PROC_CGROUP
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return None
    quotas = []
    for line in lines:
        _, controllers, path = line.split(":", 2)
        if controllers == "":
            mounts = [root]
        elif "cpu" in controllers.split(","):
            mounts = [root / name for name in ("cpu", "cpu,cpuacct", "cpuacct,cpu")]
        else:
            continue
        for mount in mounts:
            if mount.is_dir():
                quotas += [q for f in _cgroup_dirs(mount, path) if (q := _read_quota(f))]
    return min(quotas) if quotas else None


def _positive_count(environ: Mapping[str, str], name: str) -> int | None:
    """``environ[name]`` as a thread count: its first comma-separated entry (OpenMP's nested
    lists); None where unset, empty or not a positive whole number."""
    text = environ.get(name, "").split(",")[0].strip()
    return int(text) if text.isdigit() and int(text) > 0 else None


def decide_threads(environ: Mapping[str, str] | None = None) -> ThreadBudget:
    """The threads pae uses (module docstring) and the inputs of the decision; a
    ``PAE_THREADS`` that is not a whole number of at least 1 is a ConfigError."""
    environ = os.environ if environ is None else environ
    pae_threads = _positive_count(environ, "PAE_THREADS")
    if environ.get("PAE_THREADS", "").strip() and pae_threads is None:
        raise ConfigError(
            f"PAE_THREADS={environ['PAE_THREADS']!r}: expected a whole number of threads, "
            "at least 1"
        )
    affinity = usable_cpus()
    cgroup = cgroup_cpu_limit()
    cores = affinity if cgroup is None else min(affinity, max(1, math.ceil(cgroup)))
    omp = _positive_count(environ, "OMP_NUM_THREADS")
    threads = pae_threads or min(cores, omp or cores)
    return ThreadBudget(threads, affinity, cgroup, omp, pae_threads)


def prepare_environment(environ: MutableMapping[str, str] | None = None) -> None:
    """Before torch and numba are imported: waiting threads sleep (``SLEEPING_WAIT``) unless
    the environment sets a wait variable; torch's large tensors on huge pages
    (``HUGE_PAGES``) unless it sets that variable; numba's pool as large as OpenMP's
    (``NUMBA_NUM_THREADS`` from ``PAE_THREADS``, else ``OMP_NUM_THREADS``, where unset): a
    larger numba pool keeps a thread on a core torch needs."""
    environ = os.environ if environ is None else environ
    if not any(name in environ for name in WAIT_VARIABLES):
        environ.update(SLEEPING_WAIT)
    for name, value in HUGE_PAGES.items():
        environ.setdefault(name, value)
    threads = _positive_count(environ, "PAE_THREADS") or _positive_count(environ, "OMP_NUM_THREADS")
    if threads is not None and "NUMBA_NUM_THREADS" not in environ:
        environ["NUMBA_NUM_THREADS"] = str(threads)


_CONFIGURED: ThreadBudget | None = None


def current_budget() -> ThreadBudget:
    """The budget ``configure_threads`` set, else the one decided now."""
    return _CONFIGURED or decide_threads()


def loader_workers(requested: int) -> int:
    """A data loader's worker processes: ``requested``, at most the threads pae uses."""
    return min(requested, current_budget().threads)


def _configure_torch(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)
    with contextlib.suppress(RuntimeError):  # allowed before the first inter-op work only
        torch.set_num_interop_threads(threads)


def _configure_numba(threads: int, environ: Mapping[str, str]) -> None:
    """numba's pool: ``threads`` (at most the pool it started with); where torch runs on
    OpenMP and the environment picks no layer, numba's OpenMP layer first."""
    import numba
    from numba.np.ufunc import parallel

    chosen = {"NUMBA_THREADING_LAYER", "NUMBA_THREADING_LAYER_PRIORITY"} & environ.keys()
    if not chosen and not parallel._is_initialized and "torch" in sys.modules:
        import torch

        if "OpenMP" in torch.__config__.parallel_info():
            numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


def configure_threads(load_libraries: bool = True) -> ThreadBudget:
    """Decide the threads (``decide_threads``) and give them to torch, numba and OpenCV;
    with ``load_libraries`` false, those not yet imported are left to read the count from
    the environment when they are (``OMP_NUM_THREADS``, ``MKL_NUM_THREADS``,
    ``NUMBA_NUM_THREADS``, where unset): for commands that may never import them. Returns
    the budget; its ``summary()`` is the line to log."""
    global _CONFIGURED
    budget = decide_threads()
    prepare_environment()
    loaded = set(sys.modules) if not load_libraries else {"torch", "numba", "cv2"}
    if "torch" in loaded:
        _configure_torch(budget.threads)
    else:
        for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(name, str(budget.threads))
    if "numba" in loaded:
        _configure_numba(budget.threads, os.environ)
    else:
        os.environ.setdefault("NUMBA_NUM_THREADS", str(budget.threads))
    if "cv2" in loaded:
        import cv2

        cv2.setNumThreads(budget.threads)
    _CONFIGURED = budget
    return budget
