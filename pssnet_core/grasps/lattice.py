"""The bit kernel: S completions packed into one bit word per voxel, and gripper boxes as lattice points.

Each lattice point of a gripper part costs one gather and a bitwise OR whatever S, which is what makes
scoring every candidate against every completion cheap.
"""

from __future__ import annotations

import math

import numpy as np

from pssnet_core.grasps.config import VoxelDims


class PackedGrids:
    """S occupancy grids packed into one little-endian bit word per voxel (bit s = completion s).

    The grid is padded by one empty voxel on every side; lattice points are clipped into the padded grid,
    so every point outside the grid reads as empty.
    """

    def __init__(self, occupancy: np.ndarray) -> None:
        s, n = occupancy.shape[0], occupancy.shape[1]
        self.num = s
        self.size = n
        self.padded = n + 2
        nbytes = (s + 7) // 8
        packed = np.packbits(np.moveaxis(occupancy, 0, -1), axis=-1, bitorder="little")  # (n, n, n, nbytes)
        if nbytes <= 8:
            width = next(b for b in (1, 2, 4, 8) if b >= nbytes)
            self.words = 1
        else:
            width = 8 * ((nbytes + 7) // 8)
            self.words = width // 8
        self.nbytes = width
        data = np.zeros((self.padded,) * 3 + (width,), dtype=np.uint8)
        data[1:-1, 1:-1, 1:-1, :nbytes] = packed
        dtype = np.dtype(f"<u{min(width, 8)}")
        flat = data.reshape(-1, width).view(dtype)  # (P^3, words)
        self.data = flat[:, 0].copy() if self.words == 1 else flat.copy()

    def occupied_in_any(self) -> np.ndarray:
        """(P^3,) bool over the flat padded grid: the voxel is occupied in at least one completion."""
        return self.data != 0 if self.words == 1 else (self.data != 0).any(axis=1)

    def gather(self, index: np.ndarray) -> np.ndarray:
        """Words at flat padded-grid indices: shape (...) or (..., words)."""
        return self.data[index]

    def reduce_or(self, words: np.ndarray, axis: int | tuple[int, ...]) -> np.ndarray:
        return np.bitwise_or.reduce(words, axis=axis)

    def bit_at(self, words: np.ndarray, slice_index: np.ndarray) -> np.ndarray:
        """Bit s of ``words[k, :, slice_index[k, s], :]`` for every completion s.

        Args:
            words: (K, nx, ny, nz) or (K, nx, ny, nz, W) words.
            slice_index: (K, S) index along axis 2 per completion.

        Returns:
            (K, S, nx, nz) bool.
        """
        k = words.shape[0]
        s = np.arange(self.num)
        picked = words[np.arange(k)[:, None], :, slice_index]  # (K, S, nx, nz[, W])
        if self.words > 1:
            picked = np.take_along_axis(picked, (s // 64)[None, :, None, None, None], axis=-1)[..., 0]
            shift = (s % 64).astype(np.uint64)
        else:
            shift = s.astype(picked.dtype)
        return ((picked >> shift[None, :, None, None]) & 1).astype(bool)

    def unpack(self, words: np.ndarray) -> np.ndarray:
        """Words (...) or (..., words) -> (..., S) bool."""
        words = np.ascontiguousarray(words)
        if self.words == 1:
            words = words[..., None]
        raw = words.view(np.uint8)
        return np.unpackbits(raw, axis=-1, bitorder="little")[..., :self.num].astype(bool)


def _lattice(n: int) -> np.ndarray:
    """n evenly spaced values in [-1, 1] (both ends included); [0] when n == 1."""
    return np.zeros(1, np.float32) if n <= 1 else np.linspace(-1.0, 1.0, n, dtype=np.float32)


def lattice_count(extent: float, step: float) -> int:
    """Points covering ``extent`` (both ends) with spacing at most ``step``."""
    return int(math.ceil(extent / step - 1e-6)) + 1 if extent > 0 else 1


def box_lattice_index(bits: PackedGrids, origins: np.ndarray, rotations: np.ndarray, centre: np.ndarray,
                      half: np.ndarray, counts: tuple[int, int, int]) -> np.ndarray:
    """Flat padded-grid indices of a box's lattice points (per candidate centre/half extents, gripper frame).

    Args:
        bits: the packed grids (for the padded size).
        origins: (K, 3) gripper origins (grid).
        rotations: (K, 3, 3) gripper axes as columns (grid).
        centre: (K, 3) or (3,) box centre in the gripper frame.
        half: (K, 3) or (3,) half extents in the gripper frame.
        counts: lattice points along the gripper x, y, z.

    Returns:
        (K, nx, ny, nz) int32 indices; points outside the grid map to an empty padding voxel.
    """
    k = len(origins)
    centre = np.broadcast_to(np.asarray(centre, np.float32), (k, 3))
    half = np.broadcast_to(np.asarray(half, np.float32), (k, 3))
    rot = rotations.astype(np.float32)
    # +1: the padding layer, so that floor == truncation for every point inside the padded grid.
    base = origins.astype(np.float32) + np.float32(1.0)
    local = [centre[:, a, None] + _lattice(counts[a])[None, :] * half[:, a, None] for a in range(3)]  # (K, n_a)
    p = bits.padded
    hi = np.float32(p - 1)
    index = np.zeros((k, *counts), dtype=np.int32)
    coord = np.empty((k, *counts), dtype=np.float32)
    for c, stride in enumerate((p * p, p, 1)):
        tx = local[0] * rot[:, c, 0, None]
        ty = local[1] * rot[:, c, 1, None]
        tz = local[2] * rot[:, c, 2, None] + base[:, c, None]
        np.add(tx[:, :, None, None], ty[:, None, :, None], out=coord)
        coord += tz[:, None, None, :]
        np.clip(coord, np.float32(0.0), hi, out=coord)
        index += coord.astype(np.int32) * np.int32(stride)
    return index


def lowest_point(origins: np.ndarray, rotations: np.ndarray, widths: np.ndarray, dims: VoxelDims) -> np.ndarray:
    """(K,) lowest grid z reached by any gripper part (fingers at ``widths``, palm), analytically."""
    k = len(origins)
    fl, fw, ft = dims.finger_length, dims.finger_width, dims.finger_thickness
    centres, halves = [], []
    for sign in (-1.0, 1.0):
        centres.append(np.stack([np.zeros(k), sign * (widths / 2 + ft / 2), np.full(k, -fl / 2)], axis=1))
        halves.append(np.broadcast_to([fw / 2, ft / 2, fl / 2], (k, 3)))
    centres.append(np.broadcast_to([0.0, 0.0, -fl - dims.palm_depth / 2], (k, 3)))
    halves.append(np.broadcast_to([fw / 2, dims.max_opening / 2 + ft, dims.palm_depth / 2], (k, 3)))
    zrow = rotations[:, 2, :]  # (K, 3): grid z of each gripper axis
    lows = [np.einsum("kj,kj->k", zrow, c) - np.einsum("kj,kj->k", np.abs(zrow), h)
            for c, h in zip(centres, halves, strict=True)]
    return origins[:, 2] + np.min(np.stack(lows, axis=1), axis=1)
