"""Checks that a checkpoint's weights are the ones that were saved and that the model still completes shapes.

``torch.load`` checks the archive's structure, not the numbers inside it: flipped bits, zeroed or random pages
and NaN weights load without a word and are then served. Every checkpoint therefore carries an integrity
record (``payload["integrity"]``), written by :func:`make_record` when it is saved (``pssnet train``,
``pssnet export-model``, ``pssnet fit-box-head`` all save through ``save_checkpoint``):

- ``digest``: SHA-256 over every stored tensor (name, dtype, shape, bytes);
- ``ranges``: each floating-point tensor's smallest and largest value;
- ``self_test``: a canonical observation (a cylinder on a table seen from 0.6 m, packed bits), the model's
  deterministic completion of it (the fingerprint, packed bits) and that completion's occupied fraction.

At load, :func:`check_weights` refuses any non-finite tensor, a tensor outside its recorded range and a digest
that differs; :func:`self_test` decodes the canonical observation again and refuses a completion that empties
or fills the grid, or that differs from the fingerprint. At run time :func:`check_samples` refuses samples
that are empty or fill the grid. Every refusal is an :class:`IntegrityError` with a one-line reason.

torch and numpy only (the geometry module for the canonical scene), no ROS.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

RECORD_VERSION = 1


class IntegrityError(ValueError):
    """Weights or a model's output fail an integrity check; the message says which and by how much."""


@dataclass(frozen=True)
class SelfTestLimits:
    """What the start-up self-test and the run-time check accept.

    Attributes:
        min_fraction: a canonical completion occupying a smaller share of the grid empties it. The canonical
            cylinder is 6.3 % of the grid and the shipped model's completion of it 4.7 %.
        max_fraction: a canonical completion occupying a larger share fills it: it is no completion of a 6.3 %
            cylinder. A randomly initialised PSSNet's canonical completion occupies 0 % or 100 % of the grid (15
            seeds of 16) or 87.5 % (1 of 16).
        min_iou: the canonical completion must overlap the recorded fingerprint at least this much (the same
            weights on another CPU kind or thread count flip only voxels whose probability is within rounding of
            0.5; the corruptions the digest catches first change far more).
        max_sample_fraction: at run time, a sample occupying a larger share of its grid fills it (looser than
            ``max_fraction``: a real object may be large; the grid is placed around it and no object fills 90 %).
    """

    min_fraction: float = 0.001
    max_fraction: float = 0.5
    min_iou: float = 0.9
    max_sample_fraction: float = 0.9


LIMITS = SelfTestLimits()


# ------------------------------------------------------------------------------------------------- weights
def _tensor_bytes(tensor: torch.Tensor) -> bytes:
    flat = tensor.detach().to("cpu").contiguous().reshape(-1)
    return flat.view(torch.uint8).numpy().tobytes() if flat.numel() else b""


def weights_digest(state: Mapping[str, torch.Tensor]) -> str:
    """SHA-256 (hex) of a state dict as stored: every tensor's name, dtype, shape and bytes, in name order."""
    digest = hashlib.sha256()
    for name in sorted(state):
        tensor = state[name]
        digest.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        digest.update(_tensor_bytes(tensor))
    return digest.hexdigest()


def _extremes(tensor: torch.Tensor) -> tuple[float, float]:
    # One pass: NaN propagates into min and max and inf is one of them, so both are finite iff every value is.
    low, high = torch.aminmax(tensor.detach())
    return float(low), float(high)


def weight_ranges(state: Mapping[str, torch.Tensor]) -> dict[str, list[float]]:
    """Smallest and largest value of every non-empty floating-point tensor (as stored)."""
    return {name: list(_extremes(t)) for name, t in state.items() if t.is_floating_point() and t.numel()}


def check_weights(state: Mapping[str, torch.Tensor], record: Mapping[str, Any] | None) -> None:
    """Refuses non-finite weights always; with a record, weights outside their recorded range and a digest
    that differs (checked in that order: the first failure says the most about what happened).

    Raises:
        IntegrityError: one line naming the tensor (or the digest) and the values.
    """
    ranges = (record or {}).get("ranges") or {}
    for name, tensor in state.items():
        if not tensor.is_floating_point() or not tensor.numel():
            continue
        low, high = _extremes(tensor)
        if not (math.isfinite(low) and math.isfinite(high)):
            bad = int((~torch.isfinite(tensor)).sum())
            raise IntegrityError(f"weight {name} has {bad} NaN/inf value(s) of {tensor.numel()}")
        if name in ranges and (low < ranges[name][0] or high > ranges[name][1]):
            raise IntegrityError(f"weight {name} spans [{low:.4g}, {high:.4g}], outside the [{ranges[name][0]:.4g}, "
                                 f"{ranges[name][1]:.4g}] recorded when it was saved")
    if record is None:
        return
    actual = weights_digest(state)
    if actual != record.get("digest"):
        raise IntegrityError(f"weights differ from those saved: SHA-256 {actual[:16]}... but the checkpoint "
                             f"records {str(record.get('digest'))[:16]}...")


# --------------------------------------------------------------------------------------- canonical scene
@dataclass(frozen=True)
class CanonicalScene:
    """The self-test's view: a closed cylinder (a mug body) standing on a table, seen by a camera pitched down.

    Rendered analytically (ray casting, no mesh code), so it is cheap and depends on nothing that changes
    with the data generators; the resulting network input is stored in the record anyway.
    """

    radius: float = 0.04
    height: float = 0.10
    distance: float = 0.6
    tilt_deg: float = 30.0
    width: int = 160
    image_height: int = 120
    focal: float = 131.25  # a 525-px VGA depth camera at a quarter of its resolution: ~1 pixel per 32^3 voxel

    def for_grid(self, grid_size: int) -> CanonicalScene:
        """The scene with the image scaled so that a voxel of an N^3 grid keeps about one pixel."""
        scale = max(1.0, grid_size / 32)
        return replace(self, width=round(self.width * scale), image_height=round(self.image_height * scale),
                       focal=self.focal * scale)


def canonical_view(scene: CanonicalScene) -> tuple[np.ndarray, np.ndarray, Any, np.ndarray]:
    """(depth (H, W) metres, mask, intrinsics, up in the optical frame) of the canonical scene."""
    from pssnet_core.geometry import CameraIntrinsics

    tilt = math.radians(scene.tilt_deg)
    # World: z up, table z = 0, cylinder axis at (d, 0). Optical frame: x right, y down, z forward.
    forward = np.array([math.cos(tilt), 0.0, -math.sin(tilt)])
    right = np.array([0.0, -1.0, 0.0])
    down = np.cross(forward, right)
    centre = np.array([0.0, 0.0, scene.distance * math.sin(tilt)])
    axis_xy = np.array([scene.distance * math.cos(tilt), 0.0])
    intrinsics = CameraIntrinsics(scene.width, scene.image_height, scene.focal, scene.focal,
                                  (scene.width - 1) / 2, (scene.image_height - 1) / 2)
    v, u = np.mgrid[0:scene.image_height, 0:scene.width].astype(np.float64)
    rays = ((u - intrinsics.cx) / scene.focal)[..., None] * right + ((v - intrinsics.cy) / scene.focal)[..., None] \
        * down + forward  # (H, W, 3); depth along the optical axis is the ray parameter t
    with np.errstate(divide="ignore", invalid="ignore"):
        t_table = np.where(rays[..., 2] < 0, -centre[2] / rays[..., 2], np.inf)
        # side: |(c + t r)_xy - axis|^2 = radius^2, hits below the rim
        oc = centre[:2] - axis_xy
        a = (rays[..., :2] ** 2).sum(-1)
        b = 2 * (rays[..., :2] @ oc)
        c = oc @ oc - scene.radius ** 2
        t_side = (-b - np.sqrt(b * b - 4 * a * c)) / (2 * a)
        z_side = centre[2] + t_side * rays[..., 2]
        t_side = np.where(np.isfinite(t_side) & (t_side > 0) & (z_side >= 0) & (z_side <= scene.height), t_side,
                          np.inf)
        t_top = (scene.height - centre[2]) / rays[..., 2]
        top_xy = centre[:2] + t_top[..., None] * rays[..., :2]
        t_top = np.where((t_top > 0) & (((top_xy - axis_xy) ** 2).sum(-1) <= scene.radius ** 2), t_top, np.inf)
    t_object = np.minimum(t_side, t_top)
    mask = np.isfinite(t_object)
    depth = np.where(mask, t_object, t_table)
    depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    up = np.array([right[2], down[2], forward[2]])
    return depth, mask, intrinsics, up


def canonical_input(grid_size: int) -> np.ndarray:
    """The canonical observation as the network sees it: (2, N, N, N) bool, known occupied and known free."""
    from pssnet_core.geometry import GridConfig, observe

    depth, mask, intrinsics, up = canonical_view(CanonicalScene().for_grid(grid_size))
    observation = observe(depth, mask, intrinsics, up, GridConfig.for_size(grid_size))
    return np.stack([observation.known_occupied, observation.known_free])


# ------------------------------------------------------------------------------------------------ self-test
def _pack(grid: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.packbits(grid.astype(bool).reshape(-1)))


def _unpack(packed: torch.Tensor, shape: tuple[int, ...]) -> np.ndarray:
    count = int(np.prod(shape))
    return np.unpackbits(packed.numpy(), count=count).astype(bool).reshape(shape)


def canonical_completion(model: torch.nn.Module, network_input: np.ndarray) -> np.ndarray:
    """The model's deterministic completion (posterior mean, fp32, its own device) of one input, (N, N, N) bool."""
    was_training = model.training
    model.eval()
    try:
        with torch.inference_mode():
            logits = model.reconstruct(torch.from_numpy(network_input.astype(np.float32))[None])
    finally:
        model.train(was_training)
    return (logits[0, 0].float() > 0).cpu().numpy()


def make_record(state: Mapping[str, torch.Tensor], model: torch.nn.Module) -> dict[str, Any]:
    """The integrity record of a state dict as stored; ``model`` must hold exactly those weights (as loaded)."""
    grid = int(model.grid_size)
    network_input = canonical_input(grid)
    completion = canonical_completion(model, network_input)
    return {"version": RECORD_VERSION, "digest": weights_digest(state), "ranges": weight_ranges(state),
            "self_test": {"grid_size": grid, "input": _pack(network_input), "fingerprint": _pack(completion),
                          "occupied_fraction": float(completion.mean())}}


@dataclass(frozen=True)
class SelfTestResult:
    """What the self-test measured: the canonical completion's occupied fraction (and the recorded one), its
    IoU with the fingerprint, and the time it took."""

    occupied_fraction: float
    recorded_fraction: float
    iou: float
    seconds: float


def self_test(model: torch.nn.Module, record: Mapping[str, Any], limits: SelfTestLimits = LIMITS) -> SelfTestResult:
    """Decodes the recorded canonical observation and compares the completion with the record.

    Raises:
        IntegrityError: the completion empties or fills the grid, or overlaps the fingerprint too little.
    """
    t0 = time.perf_counter()
    test = record["self_test"]
    grid = int(test["grid_size"])
    if grid != int(model.grid_size):
        raise IntegrityError(f"self-test recorded for a {grid}^3 grid, the model is {model.grid_size}^3")
    network_input = _unpack(test["input"], (2, grid, grid, grid))
    expected = _unpack(test["fingerprint"], (grid,) * 3)
    completion = canonical_completion(model, network_input)
    fraction = float(completion.mean())
    union = int((completion | expected).sum())
    iou = int((completion & expected).sum()) / union if union else 1.0
    result = SelfTestResult(fraction, float(test["occupied_fraction"]), iou, time.perf_counter() - t0)
    what = (f"its completion of the canonical view occupies {fraction:.1%} of the grid (recorded "
            f"{result.recorded_fraction:.1%})")
    if fraction < limits.min_fraction:
        raise IntegrityError(f"self-test failed: the model empties the grid: {what}")
    if fraction > limits.max_fraction:
        raise IntegrityError(f"self-test failed: the model fills the grid: {what}")
    if iou < limits.min_iou:
        raise IntegrityError(f"self-test failed: {what} and overlaps the recorded completion by IoU {iou:.3f} "
                             f"(need {limits.min_iou})")
    return result


def check_samples(occupancy: np.ndarray, limits: SelfTestLimits = LIMITS) -> None:
    """Refuses sampled completions (n, N, N, N) of which one is empty (no voxel at all: a small object may
    occupy less than ``min_fraction``) or fills the grid (``max_sample_fraction``).

    Raises:
        IntegrityError: which sample, and how many voxels it has.
    """
    counts = occupancy.reshape(len(occupancy), -1).sum(1)
    size = occupancy[0].size if len(occupancy) else 1
    for i, count in enumerate(counts):
        if count == 0 or count > limits.max_sample_fraction * size:
            what = "is empty" if count == 0 else f"fills the grid ({count / size:.0%} of its voxels occupied)"
            raise IntegrityError(f"the model's output is not a shape: sample {i} of {len(counts)} {what}; the "
                                 "model or its weights are broken")
