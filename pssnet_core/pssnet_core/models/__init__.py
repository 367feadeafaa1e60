"""Completion models (PSSNet and the paper's baselines), looked up by name from one registry.

Importing this package needs only torch, numpy and PyYAML (no open3d, trimesh or rclpy), so training and
inference run on machines without them.
"""

from pssnet_core.models.base import (
    PRECISIONS,
    CompletionModel,
    ModelInputError,
    StepContext,
    cpu_has_fast_bf16,
    resolve_precision,
)
from pssnet_core.models.checkpoint import (
    CheckpointError,
    export_checkpoint,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from pssnet_core.models.config import (
    ConfigError,
    ModelConfig,
    PSSNetConfig,
    RecGANConfig,
    VAEConfig,
    VAEGANConfig,
    config_from_dict,
)
from pssnet_core.models.registry import build_model, default_config, get_model_class, model_names

__all__ = [
    "PRECISIONS", "CheckpointError", "CompletionModel", "ConfigError", "ModelConfig", "ModelInputError", "PSSNetConfig",
    "RecGANConfig",
    "StepContext", "VAEConfig", "VAEGANConfig", "build_model", "config_from_dict",
    "cpu_has_fast_bf16", "default_config", "export_checkpoint", "get_model_class", "load_checkpoint",
    "model_names", "read_checkpoint", "resolve_precision", "save_checkpoint",
]
