"""pae: Camera Pose Auto-Encoders on PyTorch Lightning and Hydra."""

import os
from pathlib import Path

__version__ = "0.1.0"


def _config_dir() -> Path:
    """The Hydra configs: inside the package when pae is installed from a wheel (pae/conf),
    else conf/ at the top of the checkout (source tree and editable installs)."""
    packaged = Path(__file__).resolve().parent / "conf"
    if packaged.is_dir():
        return packaged
    return Path(__file__).resolve().parents[2] / "conf"


CONFIG_DIR = str(_config_dir())
"""The folder of train.yaml and eval.yaml (the config groups below it)."""


def sleeping_openmp_threads() -> None:
    """OpenMP threads that wait for work sleep instead of spinning (OMP_WAIT_POLICY=PASSIVE,
    unless the environment sets it), for this process and those it starts. Torch starts one
    thread per core; on cores shared with other work a spinning thread holds a core that a
    descheduled peer needs, and a small model's steps then take about 10x as long. Call
    before torch is imported: OpenMP reads it once, when it loads."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
