"""pae: Camera Pose Auto-Encoders on PyTorch Lightning and Hydra."""

from pathlib import Path

__version__ = "0.1.0"

CONFIG_DIR = str(Path(__file__).resolve().parents[2] / "conf")
"""The Hydra configs at the top of the repository (pae runs from a clone: `pip install -e .`)."""
