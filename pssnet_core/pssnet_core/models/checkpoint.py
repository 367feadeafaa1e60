"""Checkpoints that rebuild their model on their own: config dict + weights (+ optional training state).

File layout (a ``torch.save`` dict, loaded with ``weights_only=True``)::

    format: "pssnet-checkpoint", version: 1
    config: ModelConfig.to_dict()          -> the registry rebuilds the model from it alone
    state_dict: weights (float32, or float16 for a compact export)
    storage_dtype: "float32" | "float16"
    inference_only: bool                   -> training-only modules (GAN discriminators) and state were dropped
    extra: dict                            -> free-form (training state, optimiser states, metrics)
    integrity: dict                        -> SHA-256 of the stored weights, their ranges and the self-test
                                              record (pssnet_core.models.integrity); written on every save

Every load refuses non-finite weights and, when the record is there, weights outside their recorded ranges, a
digest that differs and a canonical completion that no longer matches its fingerprint. A load for serving
(``for_serving``: the node, ``pssnet bag``, the demo) also requires the record (checkpoints saved before it
existed are re-exported with ``pssnet export-model``) and refuses a model whose canonical completion empties or
fills the grid (a randomly initialised one does).
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from pssnet_core.models.base import CompletionModel
from pssnet_core.models.config import ConfigError, ModelConfig, config_from_dict
from pssnet_core.models.integrity import (
    LIMITS,
    IntegrityError,
    SelfTestLimits,
    SelfTestResult,
    check_weights,
    make_record,
    self_test,
)
from pssnet_core.models.registry import build_model

FORMAT = "pssnet-checkpoint"
VERSION = 1
#: what a load not for serving checks of the self-test: only that the completion matches the record (a test's
#: or an early training run's model may fill or empty the grid and still be what was saved)
RECORD_ONLY = SelfTestLimits(min_fraction=0.0, max_fraction=1.0)


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable, or not a PSSNet-ROS checkpoint."""


def save_checkpoint(path: str | Path, model: CompletionModel, config: ModelConfig | None = None,
                    extra: dict[str, Any] | None = None, *, half: bool = False,
                    inference_only: bool = False, deflate: bool = False) -> Path:
    """Writes a checkpoint atomically (temporary file, then rename).

    Args:
        path: destination file.
        model: the model whose weights are saved.
        config: its config (default: ``model.config``).
        extra: free-form dict of tensors/numbers/strings (e.g. training state).
        half: store floating-point weights as float16 (half the size; loaded back as float32).
        inference_only: drop the training-only modules (``model.training_only_prefixes``: GAN discriminators);
            such a checkpoint samples but cannot resume training.
        deflate: compress the archive's members (see :func:`_deflate_archive`).

    Returns:
        The path written.
    """
    config = config or model.config
    state: dict[str, torch.Tensor] = {}
    for name, tensor in model.state_dict().items():
        if inference_only and name.startswith(model.training_only_prefixes):
            continue
        tensor = tensor.detach().to("cpu").contiguous()
        if half and tensor.is_floating_point():
            tensor = tensor.to(torch.float16)
        state[name] = tensor.clone()
    # The self-test is recorded from the weights as they will be loaded (fp16-rounded for a compact export).
    record = make_record(state, _model_from_state(config, state, inference_only, path)[0])
    payload = {"format": FORMAT, "version": VERSION, "config": config.to_dict(), "state_dict": state,
               "storage_dtype": "float16" if half else "float32", "inference_only": bool(inference_only),
               "extra": extra or {}, "integrity": record}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    torch.save(payload, tmp)
    if deflate:
        _deflate_archive(tmp)
    os.replace(tmp, path)
    return path


def _deflate_archive(path: Path) -> None:
    """Re-packs the zip archive ``torch.save`` wrote with its members deflated, in place.

    ``torch.save`` stores members uncompressed (so that they can be memory-mapped); ``torch.load`` reads deflated
    ones too. fp16 weights shrink by ~8 %: what keeps the shipped model, flow included, within the 15 MB a
    committed checkpoint may take. No checkpoint here is memory-mapped.
    """
    packed = path.with_name(path.name + ".deflated")
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(packed, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as out:
        for member in source.infolist():
            out.writestr(member.filename, source.read(member.filename))
    os.replace(packed, path)


def read_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The raw checkpoint dict, validated; raises :class:`CheckpointError` with the reason."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint file at {path}; train one with `pssnet train --model pssnet "
                              f"--data DIR --out DIR` (it writes best.pt and last.pt)")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:  # torch raises many types (pickle, zip, runtime) for a bad file
        reason = " ".join(str(error).split())  # one line: the node prints it as its exit message
        raise CheckpointError(f"{path} is not a readable checkpoint (corrupt or truncated?): "
                              f"{type(error).__name__}: {reason}") from error
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a PSSNet-ROS checkpoint (no '{FORMAT}' format tag)")
    if int(payload.get("version", -1)) > VERSION:
        raise CheckpointError(f"{path} has checkpoint version {payload.get('version')}, newer than this "
                              f"code understands ({VERSION})")
    for key in ("config", "state_dict"):
        if not isinstance(payload.get(key), dict):
            raise CheckpointError(f"{path} lacks its '{key}' entry")
    record = payload.get("integrity")
    if record is not None and not isinstance(record, dict):
        raise CheckpointError(f"{path} has a malformed integrity record")
    try:
        check_weights(payload["state_dict"], record)
    except IntegrityError as error:
        raise CheckpointError(f"{path} is corrupt: {error}") from error
    return payload


def _model_from_state(config: ModelConfig, state: dict[str, torch.Tensor], inference_only: bool,
                      path: str | Path) -> tuple[CompletionModel, list[str]]:
    """A CPU model in eval mode holding ``state`` as float32, as every load builds it, and the prefixes of the
    modules an inference-only export lacks (``training_only_prefixes``, ``export_optional_prefixes``)."""
    model = build_model(config)
    floats = {k: (v.float() if v.is_floating_point() else v) for k, v in state.items()}
    try:
        missing, unexpected = model.load_state_dict(floats, strict=False)
    except RuntimeError as error:  # shape mismatch
        reason = " ".join(str(error).split())
        raise CheckpointError(f"{path}: weights do not fit its config: {reason}") from error
    allowed = model.training_only_prefixes + model.export_optional_prefixes if inference_only else ()
    absent = sorted({prefix for prefix in allowed for k in missing if k.startswith(prefix)})
    missing = [k for k in missing if not k.startswith(allowed)] if allowed else list(missing)
    if missing or unexpected:
        raise CheckpointError(f"{path}: weights do not match the {config.model} model "
                              f"(missing {missing[:5]}, unexpected {list(unexpected)[:5]})")
    return model.eval(), absent


#: keys :func:`load_verified` adds to a checkpoint's ``extra`` about the file itself; a checkpoint saved from a loaded
#: one must not carry them over (the new file's own are written and read again).
LOAD_FACTS: tuple[str, ...] = ("inference_only", "storage_dtype", "missing_modules")


@dataclass(frozen=True)
class LoadedCheckpoint:
    """A loaded checkpoint: the model (eval mode, float32 weights), its config, ``extra`` (which also carries
    ``inference_only`` and ``storage_dtype``) and its self-test's result (None without an integrity record)."""

    model: CompletionModel
    config: ModelConfig
    extra: dict[str, Any]
    self_test: SelfTestResult | None


def load_verified(path: str | Path, map_location: str | torch.device = "cpu", *,
                  for_serving: bool = False) -> LoadedCheckpoint:
    """Rebuilds the model of a checkpoint after checking its weights, and runs its self-test.

    Args:
        path: the checkpoint file.
        map_location: device of the returned model (the checks run on the CPU).
        for_serving: also require the integrity record and refuse a model whose canonical completion empties
            or fills the grid (the node, ``pssnet bag``, the demo).

    Raises:
        CheckpointError: missing, corrupt, foreign or mismatching file, or a failed self-test; one line.
    """
    payload = read_checkpoint(path)
    try:
        config = config_from_dict(payload["config"])
    except ConfigError as error:
        raise CheckpointError(f"{path} has an invalid model config: {error}") from error
    inference_only = bool(payload.get("inference_only", False))
    model, absent = _model_from_state(config, payload["state_dict"], inference_only, path)
    record = payload.get("integrity")
    if record is None and for_serving:
        raise CheckpointError(f"{path} has no integrity record (SHA-256 and self-test; saved before checkpoints "
                              f"carried one): re-export it with `pssnet export-model {path} NEW.pt`")
    result = None
    if record is not None:
        try:
            result = self_test(model, record, LIMITS if for_serving else RECORD_ONLY)
        except IntegrityError as error:
            raise CheckpointError(f"{path}: {error}") from error
        except (KeyError, TypeError, ValueError, RuntimeError) as error:
            raise CheckpointError(f"{path} has a malformed self-test record: {type(error).__name__}: "
                                  f"{' '.join(str(error).split())}") from error
    model.to(map_location)
    extra = dict(payload.get("extra") or {})
    # What the load says of the file (LOAD_FACTS), beside what was saved.
    extra.setdefault("inference_only", inference_only)
    extra.setdefault("storage_dtype", payload.get("storage_dtype", "float32"))
    extra["missing_modules"] = absent  # what the file lacks, e.g. ["flow."] (freshly initialised in the model)
    return LoadedCheckpoint(model, config, extra, result)


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu"
                    ) -> tuple[CompletionModel, ModelConfig, dict[str, Any]]:
    """``(model, config, extra)`` of :func:`load_verified` (not for serving).

    Raises:
        CheckpointError: missing, corrupt, foreign or mismatching file, or a failed self-test.
    """
    loaded = load_verified(path, map_location)
    return loaded.model, loaded.config, loaded.extra


def export_checkpoint(src: str | Path, dst: str | Path, *, half: bool = True,
                      inference_only: bool = True, box_temperature: float | None = None) -> Path:
    """Compact copy of a checkpoint for shipping: fp16 weights, training-only modules and state dropped, the
    archive deflated.

    The training metadata in ``extra`` (metrics, data, duration) is kept; optimiser states are not.
    ``box_temperature`` records the temperature calibrated for this model (``extra["box_temperature"]``), the
    default of every :class:`pssnet_core.inference.Completer` that loads it.
    """
    from pssnet_core.models.base import ModelInputError, check_box_temperature

    model, config, extra = load_checkpoint(src)
    kept = {k: v for k, v in extra.items() if k not in ("optimizers", "rng", *LOAD_FACTS)}
    kept["exported_from"] = str(src)
    if box_temperature is not None:
        try:
            kept["box_temperature"] = check_box_temperature(box_temperature, model.has_box_latent)
        except ModelInputError as error:
            raise CheckpointError(str(error)) from error
    return save_checkpoint(dst, model, config, kept, half=half, inference_only=inference_only, deflate=True)
