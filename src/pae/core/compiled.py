"""numba's compiled loops, cached where a cache can be written and keyed on pae's sources.

``jit(**options)`` is ``numba.njit(**options)`` with pae's own on-disk cache instead of
``cache=True``. The cache folder is the first writable one of ``NUMBA_CACHE_DIR``, the
``__pycache__`` beside the module (numba's default) and the user cache folder
(``$XDG_CACHE_HOME/pae/numba`` or ``~/.cache/pae/numba``); where none can be written (a read-only
install and a read-only ``HOME``) the loops compile in each process without a cache, and a
warning says so once. A cached loop is stamped with a digest of every source file of its
top-level package, not only its own file: a compiled function inlines the compiled helpers it
calls and the constants it reads from other modules, so a change to any of them compiles
it anew instead of running the old code.

The helpers several compiled loops share live here too (``insert_sorted``, ``copy_into``,
``run_in_parts``, the ``FASTMATH`` flags): the weight regressor's fit (``pae.refine.fused``)
and the pose index's search (``pae.refine.index``).
"""

from __future__ import annotations

import functools
import hashlib
import os
import tempfile
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, ClassVar, Literal

import numba
import numpy as np
import torch
from numba.core.caching import CompileResultCacheImpl, FunctionCache, _CacheLocator

Engine = Literal["auto", "numba", "torch"]
ENGINES: tuple[str, ...] = ("auto", "numba", "torch")
"""pae's one engine vocabulary for every kernel with a compiled loop beside its tensor
reference: ``numba`` the compiled loop (CPU tensors; an error where it cannot run), ``torch``
the tensor operations (any device), ``auto`` the compiled loop where it can run."""


class CompileCacheWarning(UserWarning):
    """numba's compiled loops cannot be cached (said once per process)."""


_SAID: set[str] = set()


def _say_once(message: str, key: str | None = None) -> None:
    """Warn with ``message`` once per process (per ``key`` when given, else per message)."""
    if (key or message) not in _SAID:
        _SAID.add(key or message)
        warnings.warn(message, CompileCacheWarning, stacklevel=3)


@functools.cache
def package_digest(package_dir: str) -> str:
    """SHA-256 over the path and bytes of every ``*.py`` below ``package_dir`` (sorted)."""
    digest = hashlib.sha256()
    root = Path(package_dir)
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()


def _user_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "pae"


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def candidate_folders(source_file: str) -> list[Path]:
    """Where the compiled code of functions in ``source_file`` may be cached, in order."""
    source_dir = os.path.dirname(os.path.abspath(source_file))
    # one sub-folder per source folder, as numba names them: installs in several places
    # (virtual environments, checkouts) do not overwrite each other's entries
    subpath = _CacheLocator.get_suitable_cache_subpath(source_file)
    folders = []
    if numba.config.CACHE_DIR:
        folders.append(Path(numba.config.CACHE_DIR) / subpath)
    folders.append(Path(source_dir) / "__pycache__")
    folders.append(_user_cache_dir() / "numba" / subpath)
    return folders


@functools.cache
def cache_folder(source_file: str) -> Path | None:
    """The first writable folder of ``candidate_folders`` (None, said once, if there is none)."""
    folders = candidate_folders(source_file)
    for folder in folders:
        if _writable(folder):
            return folder
    _say_once(
        "pae: numba's compiled loops are not cached: none of "
        f"{', '.join(str(f) for f in folders)} can be written (NUMBA_CACHE_DIR, the package "
        "folder, the user cache folder); they compile again in every process (seconds). "
        "Set NUMBA_CACHE_DIR to a writable folder to keep them",
        key="not cached",
    )
    return None


def _top_package_dir(func: Callable[..., Any]) -> str:
    """The folder of the top-level package that defines ``func`` (its own folder for a
    module outside any package)."""
    module_file = Path(func.__code__.co_filename).resolve()
    top = func.__module__.split(".")[0]
    for parent in module_file.parents:
        if parent.name == top and (parent / "__init__.py").is_file():
            return str(parent)
    return str(module_file.parent)


class _PackageLocator(_CacheLocator):
    """Cache files of one function in ``cache_folder``, fresh while its package is unchanged."""

    def __init__(self, py_func: Callable[..., Any], py_file: str) -> None:
        self._lineno = py_func.__code__.co_firstlineno
        self._folder = cache_folder(py_file)
        self._package_dir = _top_package_dir(py_func)

    def get_cache_path(self) -> str:
        return str(self._folder)

    def get_source_stamp(self) -> str:
        return package_digest(self._package_dir)

    def get_disambiguator(self) -> str:
        return str(self._lineno)

    @classmethod
    def from_function(cls, py_func: Callable[..., Any], py_file: str) -> _PackageLocator | None:
        return cls(py_func, py_file) if cache_folder(py_file) is not None else None


class _PackageCacheImpl(CompileResultCacheImpl):
    _locator_classes: ClassVar[list[type]] = [_PackageLocator]


class _PackageCache(FunctionCache):
    """numba's function cache with ``_PackageLocator``; a failed write (the disk filled up,
    the folder became read-only) is said once and the compiled code is used uncached."""

    _impl_class = _PackageCacheImpl

    def save_overload(self, sig: Any, data: Any) -> None:
        try:
            super().save_overload(sig, data)
        except OSError as err:
            _say_once(
                f"pae: numba's compiled loops could not be cached in {self._cache_path}: {err}"
            )


def jit(**options: Any) -> Callable[[Callable[..., Any]], Any]:
    """``numba.njit(**options)`` cached as the module docstring says (no ``cache`` option)."""

    def compile_lazily(func: Callable[..., Any]) -> Any:
        dispatcher = numba.njit(**options)(func)
        if cache_folder(func.__code__.co_filename) is not None:
            dispatcher._cache = _PackageCache(func)  # what numba's cache=True sets, relocated
        return dispatcher

    return compile_lazily


# Helpers the compiled loops share (the weight regressor's fit, the pose index's search).

FASTMATH = {"reassoc", "contract"}
"""Reassociated sums (vectorised reductions) and fused multiply-adds; no other liberties, so
NaN and infinity keep their meaning. ``error_model="numpy"``: a division by zero gives inf or
NaN as in numpy and torch instead of raising, which also lets divisions vectorise."""


@jit(nogil=True)
def insert_sorted(values: np.ndarray, labels: np.ndarray, value: float, label: int) -> None:
    """Insert ``value`` (with ``label``) into the ascending ``values`` [m] (and ``labels``
    [m]), dropping the last entry; the caller has checked that value < values[-1]."""
    slot = values.shape[0] - 1
    while slot > 0 and values[slot - 1] > value:
        values[slot] = values[slot - 1]
        labels[slot] = labels[slot - 1]
        slot -= 1
    values[slot] = value
    labels[slot] = label


@jit(nogil=True, inline="always")
def copy_into(source: np.ndarray, target: np.ndarray) -> None:
    """target[i] = source[i] for the length of ``source`` (1-D); a plain loop, which numba
    compiles to a vectorised copy (slice assignment takes a slower general path)."""
    for i in range(np.uint64(source.shape[0])):
        target[i] = source[i]


def run_in_parts(run: Callable[[slice], None], rows: int, min_rows: int) -> None:
    """Call ``run`` on consecutive row ranges of ``min_rows`` rows covering ``rows`` rows,
    on ``torch.get_num_threads()`` threads at once, each taking the next range when it is
    done (queries differ in cost): for compiled functions that release the GIL."""
    parts = [slice(lo, min(lo + min_rows, rows)) for lo in range(0, rows, min_rows)]
    threads = max(1, min(torch.get_num_threads(), len(parts)))
    if threads == 1:
        run(slice(0, rows))
        return
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(run, parts))
