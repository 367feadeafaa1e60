"""Training: the loop, checkpoints, logs and the ``pssnet train`` command.

Importing this package needs only torch, numpy, scipy, matplotlib (lazily), tqdm and PyYAML.
"""

from pssnet_core.training.checkpoint import (
    CheckpointError,
    export_checkpoint,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from pssnet_core.training.trainer import TrainConfig, Trainer, TrainingError, chamfer_mm, validate

__all__ = ["CheckpointError", "TrainConfig", "Trainer", "TrainingError", "chamfer_mm", "export_checkpoint",
           "load_checkpoint", "read_checkpoint", "save_checkpoint", "validate"]
