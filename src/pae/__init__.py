"""pae: Camera Pose Auto-Encoders on PyTorch Lightning and Hydra."""

from pathlib import Path

from pae.core.threads import prepare_environment

__version__ = "0.1.0"

prepare_environment()  # before torch and numba are imported: pae.core.threads


def _config_dir() -> Path:
    """The Hydra configs: inside the package when pae is installed from a wheel (pae/conf),
    else conf/ at the top of the checkout (source tree and editable installs)."""
    packaged = Path(__file__).resolve().parent / "conf"
    if packaged.is_dir():
        return packaged
    return Path(__file__).resolve().parents[2] / "conf"


CONFIG_DIR = str(_config_dir())
"""The folder of train.yaml and eval.yaml (the config groups below it)."""
