"""pae: Camera Pose Auto-Encoders on PyTorch Lightning and Hydra."""

__version__ = "0.1.0"
