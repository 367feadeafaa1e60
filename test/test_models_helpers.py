"""Shared helpers for the model, training and inference tests: tiny configs and a tiny dataset.

(Named test_models_* so it belongs to the models area; it holds no tests itself.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from pssnet_core.data.store import DatasetError, finalize, write_shard
from pssnet_core.models import CompletionModel, build_model, default_config

TINY = {"channels": [4, 8, 8, 16], "latent_dim": 32}
TINY_PSSNET = {**TINY, "flow_hidden": 32, "flow_couplings": 4, "flow_pretrain_steps": 5,
               "flow_pretrain_batch": 8}
TINY_GAN = {"channels": [4, 8, 8, 16], "latent_dim": 32, "disc_channels": [4, 8]}
TINY_RECGAN = {"channels": [4, 8, 8, 16], "bottleneck_dim": 16, "disc_channels": [4, 8]}
TINY_BY_MODEL = {"pssnet": TINY_PSSNET, "vae": TINY, "vae_gan": TINY_GAN, "recgan": TINY_RECGAN}


class DatasetWriter:
    """Sequential writer: buffers samples and writes a shard every ``shard_size`` samples."""

    def __init__(self, root: str | Path, meta: dict[str, Any], shard_size: int = 256) -> None:
        if shard_size < 1:
            raise DatasetError(f"shard_size must be positive, got {shard_size}")
        self.root = Path(root)
        self.meta = dict(meta)
        self.shard_size = shard_size
        self._buffer: list[dict[str, Any]] = []
        self._next_shard = 0

    def add(self, sample: dict[str, Any]) -> None:
        """Adds one sample (arrays and JSON-serialisable values)."""
        self._buffer.append(sample)
        if len(self._buffer) >= self.shard_size:
            self._flush()

    def _flush(self) -> None:
        if self._buffer:
            write_shard(self.root, self._next_shard, self._buffer)
            self._next_shard += 1
            self._buffer = []

    def close(self) -> int:
        """Writes the last shard and the index; returns the number of samples."""
        self._flush()
        return finalize(self.root, self.meta)


def tiny_model(name: str = "pssnet", grid: int = 16, **overrides) -> CompletionModel:
    """A seeded tiny model of the registry name ``name`` (``overrides`` change its config)."""
    torch.manual_seed(0)
    return build_model(default_config(name, grid_size=grid, **{**TINY_BY_MODEL[name], **overrides}))


def cuboid_sample(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    """A random axis-aligned cuboid seen from -x: occupancy, its front face, free space in front, box."""
    lo = rng.integers(2, n // 2, size=3)
    hi = lo + rng.integers(3, n // 2 - 1, size=3)
    occ = np.zeros((n, n, n), dtype=bool)
    occ[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = True
    known_occ = np.zeros_like(occ)
    known_occ[lo[0], lo[1]:hi[1], lo[2]:hi[2]] = True
    known_free = np.zeros_like(occ)
    known_free[:lo[0], lo[1]:hi[1], lo[2]:hi[2]] = True
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])],
                       dtype=np.float32)
    return {"known_occupied": known_occ, "known_free": known_free, "occupancy": occ,
            "box": corners.reshape(-1)}


def make_dataset(path: Path, num: int = 24, grid: int = 16, seed: int = 0, shard_size: int = 10) -> Path:
    """Writes a tiny cuboid dataset with the project's DatasetWriter."""
    rng = np.random.default_rng(seed)
    writer = DatasetWriter(path, {"grid_size": grid, "voxel_size": 0.005, "family": "cuboids"},
                           shard_size=shard_size)
    for i in range(num):
        writer.add({**cuboid_sample(rng, grid), "object_id": f"cuboid{i}"})
    writer.close()
    return path


def export_as_before_stop_38(src: Path, dst: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An inference-only export of ``src`` as exports were written before they kept PSSNet's flow (the shipped
    model is one): the flow dropped like a discriminator."""
    from pssnet_core.models.checkpoint import export_checkpoint
    from pssnet_core.models.vae import PSSNet

    with monkeypatch.context() as patch:
        patch.setattr(PSSNet, "training_only_prefixes", ("flow.",))
        return export_checkpoint(src, dst)
