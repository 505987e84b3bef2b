"""pae: Camera Pose Auto-Encoders on PyTorch Lightning and Hydra."""

import os
from pathlib import Path

__version__ = "0.1.0"


def _numba_threads_follow_omp() -> None:
    """numba's thread pool as large as OpenMP's (``NUMBA_NUM_THREADS`` from
    ``OMP_NUM_THREADS`` when only the latter is set; read when numba is first imported, so
    before it). torch and numba's parallel loops share the OpenMP runtime, and a numba pool
    larger than torch's leaves a worker spinning on a core torch needs once numba has run:
    a teacher trained on novel views with ``OMP_NUM_THREADS=1`` ran 8x slower."""
    threads = os.environ.get("OMP_NUM_THREADS", "")
    if threads.isdigit() and int(threads) > 0 and "NUMBA_NUM_THREADS" not in os.environ:
        os.environ["NUMBA_NUM_THREADS"] = threads


_numba_threads_follow_omp()


def _config_dir() -> Path:
    """The Hydra configs: inside the package when pae is installed from a wheel (pae/conf),
    else conf/ at the top of the checkout (source tree and editable installs)."""
    packaged = Path(__file__).resolve().parent / "conf"
    if packaged.is_dir():
        return packaged
    return Path(__file__).resolve().parents[2] / "conf"


CONFIG_DIR = str(_config_dir())
"""The folder of train.yaml and eval.yaml (the config groups below it)."""
