"""Training: the loop, logs and the ``pssnet train`` command (checkpoints live in :mod:`pssnet_core.models`).

Importing this package needs only torch, numpy, scipy, matplotlib (lazily), tqdm and PyYAML.
"""

from pssnet_core.training.trainer import TrainConfig, Trainer, TrainingError, chamfer_mm, validate

__all__ = ["TrainConfig", "Trainer", "TrainingError", "chamfer_mm", "validate"]
