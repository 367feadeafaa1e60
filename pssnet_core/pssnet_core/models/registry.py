"""One registry of completion models: name -> (model class, config class)."""

from __future__ import annotations

from typing import Any

from pssnet_core.models.base import CompletionModel
from pssnet_core.models.config import ConfigError, ModelConfig, config_class, config_from_dict
from pssnet_core.models.recgan import RecGAN
from pssnet_core.models.vae import VAE, VAEGAN, PSSNet

MODEL_CLASSES: dict[str, type[CompletionModel]] = {cls.name: cls for cls in (PSSNet, VAE, VAEGAN, RecGAN)}


def model_names() -> list[str]:
    """Registered model names."""
    return sorted(MODEL_CLASSES)


def get_model_class(name: str) -> type[CompletionModel]:
    """Model class registered under ``name`` (``pssnet``, ``vae``, ``vae_gan``, ``recgan``)."""
    try:
        return MODEL_CLASSES[name]
    except KeyError:
        raise ConfigError(f"unknown model {name!r}; known: {model_names()}") from None


def default_config(name: str, **overrides: Any) -> ModelConfig:
    """The default config of model ``name`` with ``overrides`` applied (e.g. ``grid_size=64``)."""
    return config_from_dict({"model": config_class(name).model, **overrides})


def build_model(config: ModelConfig | dict[str, Any]) -> CompletionModel:
    """Builds a freshly initialised model from a config (or its dict form)."""
    if isinstance(config, dict):
        config = config_from_dict(config)
    return get_model_class(config.model)(config)
