"""The bit kernel: S completions packed into one bit word per voxel, and gripper boxes as lattice points.

Each lattice point of a gripper part costs one gather and a bitwise OR whatever S, which is what makes
scoring every candidate against every completion cheap.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from pssnet_core.grasps.config import VoxelDims

# Lattice points per block of candidates (by timing): candidates are the innermost, contiguous axis, so a block
# must hold enough of them for long vector loops, yet its temporaries (a few MB) should stay in cache.
_BLOCK_POINTS = 1 << 17


#: Gaussian smoothing (voxels) of a completion before its gradient is read as surface normals: enough to turn a
#: voxel staircase into the slope it approximates, small against a handle's section (1-2 voxels at 32^3).
NORMAL_SMOOTHING = 1.0


class PackedGrids:
    """S occupancy grids packed into bit words: bit ``s % 64`` of word ``s // 64`` is completion s.

    ``data`` is (W, P^3), the flat padded grid of each word (W = 1 up to 64 completions, with the narrowest
    unsigned type that holds S bits). The grid is padded by one empty voxel on every side; lattice points are
    clipped into the padded grid, so every point outside the grid reads as empty.
    """

    def __init__(self, occupancy: np.ndarray) -> None:
        s, n = occupancy.shape[0], occupancy.shape[1]
        self.num = s
        self.size = n
        self.padded = n + 2
        words = (s + 63) // 64
        dtype = np.dtype(f"<u{next(b for b in (1, 2, 4, 8) if 8 * b >= s) if words == 1 else 8}")
        data = np.zeros((words, self.padded, self.padded, self.padded), dtype)
        inner = data[:, 1:-1, 1:-1, 1:-1]
        bit = np.empty((n, n, n), dtype)
        for i in range(s):  # one shift and OR per completion: contiguous passes (packbits across S is strided)
            np.left_shift(occupancy[i], i % 64, out=bit, dtype=dtype)
            inner[i // 64] |= bit
        self.data = data.reshape(words, -1)
        self._occupancy = occupancy  # a reference, for mass_centres (computed only when asked)

    @functools.cached_property
    def mass_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(S, 3) centroid of each completion's voxel centres (grid coordinates; zeros for an empty one) and its
        (S,) voxel count: a completion's centre of mass at uniform density."""
        occupancy = self._occupancy
        counts = occupancy.reshape(self.num, -1).sum(axis=1)
        centres = np.arange(self.size) + 0.5
        sums = np.stack([occupancy.sum(axis=tuple(a for a in (1, 2, 3) if a != axis)) @ centres
                         for axis in (1, 2, 3)], axis=1)
        return sums / np.maximum(counts, 1)[:, None], counts

    @functools.cached_property
    def inward_normals(self) -> np.ndarray:
        """(S, N, N, N, 3) float32: the gradient of each completion's occupancy smoothed by a Gaussian of
        :data:`NORMAL_SMOOTHING` voxels, which points into the object across its surface (an unnormalised inward
        normal; zero far from any surface)."""
        from scipy.ndimage import gaussian_filter

        smooth = gaussian_filter(self._occupancy.astype(np.float32), (0.0, *(NORMAL_SMOOTHING,) * 3), mode="constant")
        return np.stack(np.gradient(smooth, axis=(1, 2, 3)), axis=-1)

    @functools.cached_property
    def solid_cores(self) -> PackedGrids:
        """Each completion eroded by one voxel in every direction (a 3x3x3 cube): the voxels that lie inside a part at
        least 3 voxels thick every way, packed alike. A wall, handle or rim one or two voxels thick has none."""
        from scipy.ndimage import binary_erosion

        cube = np.ones((1, 3, 3, 3), dtype=bool)  # no erosion across completions
        return PackedGrids(binary_erosion(self._occupancy, cube))

    def unpack(self, words: np.ndarray) -> np.ndarray:
        """Words (W, ...) -> (..., S) bool."""
        raw = np.ascontiguousarray(np.moveaxis(words, 0, -1)).view(np.uint8)
        return np.unpackbits(raw, axis=-1, bitorder="little")[..., :self.num].view(bool)

    def count(self, words: np.ndarray) -> np.ndarray:
        """Words (W, C, ...) -> (..., S): in how many of the C words bit s is set."""
        raw = np.ascontiguousarray(np.moveaxis(words, 0, -1)).view(np.uint8)
        flags = np.unpackbits(raw, axis=-1, bitorder="little")  # contiguous: a fast sum over C
        return np.add.reduce(flags, axis=0, dtype=np.min_scalar_type(words.shape[1]))[..., :self.num].astype(np.intp)

    def pack(self, flags: np.ndarray) -> np.ndarray:
        """(..., S) bool -> words (W, ...), the inverse of :meth:`unpack`."""
        raw = np.packbits(flags, axis=-1, bitorder="little")
        raw = np.pad(raw, [(0, 0)] * (raw.ndim - 1) + [(0, len(self.data) * self.data.itemsize - raw.shape[-1])])
        return np.moveaxis(np.ascontiguousarray(raw).view(self.data.dtype), -1, 0)


def _lattice(n: int) -> np.ndarray:
    """n evenly spaced values in [-1, 1] (both ends included); [0] when n == 1."""
    return np.zeros(1, np.float32) if n <= 1 else np.linspace(-1.0, 1.0, n, dtype=np.float32)


def lattice_count(extent: float, step: float) -> int:
    """Points covering ``extent`` (both ends) with spacing at most ``step``."""
    return int(math.ceil(extent / step - 1e-6)) + 1 if extent > 0 else 1


def _box_terms(rotations: np.ndarray, centre: np.ndarray, half: np.ndarray,
               counts: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The origin-free float32 terms of every lattice point's grid coordinates.

    Padded-grid axis c of point (i, j, l) of box k at ``origin`` is ``xy[c, i, j, k] + (z[c, l, k] + base_c)``
    with ``xy = x_i r_c0 + y_j r_c1``, ``z = z_l r_c2`` and ``base = origin + 1`` (the padding layer, so that
    floor == truncation inside the padded grid): always summed in this order, in float32, so that a point falls
    in the same voxel whichever way the lattice is traversed.

    Returns:
        xy (3, nx, ny, K) and z (3, nz, K).
    """
    k = len(rotations)
    centre = np.broadcast_to(np.asarray(centre, np.float32), (k, 3))
    half = np.broadcast_to(np.asarray(half, np.float32), (k, 3))
    rot = rotations.astype(np.float32)
    local = [centre[:, a, None] + _lattice(counts[a])[None, :] * half[:, a, None] for a in range(3)]  # (K, n_a)
    xy = np.empty((3, counts[0], counts[1], k), np.float32)
    z = np.empty((3, counts[2], k), np.float32)
    for c in range(3):
        np.add((local[0] * rot[:, c, 0, None]).T[:, None, :], (local[1] * rot[:, c, 1, None]).T[None, :, :],
               out=xy[c])
        z[c] = (local[2] * rot[:, c, 2, None]).T
    return xy, z


def box_or(table: np.ndarray, padded: int, origins: np.ndarray, rotations: np.ndarray, centre: np.ndarray,
           half: np.ndarray, counts: tuple[int, int, int], keep: tuple[int, ...]) -> np.ndarray:
    """OR of ``table`` over each box's lattice points (gripper frame), over the lattice axes not in ``keep``.

    Args:
        table: (W, P^3) words (or bool) over the flat padded grid, e.g. :attr:`PackedGrids.data`.
        padded: P, the padded grid size.
        origins: (K, 3) gripper origins (grid).
        rotations: (K, 3, 3) gripper axes as columns (grid).
        centre: (K, 3) or (3,) box centre in the gripper frame.
        half: (K, 3) or (3,) half extents in the gripper frame.
        counts: lattice points along the gripper x, y, z.
        keep: lattice axes (0 = x, 1 = y, 2 = z) not reduced, in the order they have in the result.

    Returns:
        (W, *(counts[a] for a in keep), K) words; points outside the grid read as empty.
    """
    k = len(origins)
    xy, z = _box_terms(rotations, centre, half, counts)
    z += (origins.astype(np.float32) + np.float32(1.0)).T[:, None, :]
    reduced = tuple(a for a in range(3) if a not in keep)
    order = (0, *(1 + a for a in reduced + keep), 4)  # (component, lattice axes: reduced first, candidates)
    xy = xy[:, :, :, None, :].transpose(order)
    z = z[:, None, None, :, :].transpose(order)
    out = np.empty((len(table), *(counts[a] for a in keep), k), table.dtype)
    hi = np.float32(padded - 1)
    block = max(1, _BLOCK_POINTS // math.prod(counts))
    for start in range(0, k, block):
        part = slice(start, start + block)
        coord = np.add(xy[..., part], z[..., part])  # (3, *lattice, b)
        np.clip(coord, np.float32(0.0), hi, out=coord)
        voxel = coord.astype(np.int32)  # truncation == floor: clipped to >= 0
        index = voxel[0] * np.int32(padded * padded)
        index += voxel[1] * np.int32(padded)
        index += voxel[2]
        for w, words in enumerate(table):
            picked = words.take(index)
            if reduced:
                picked = np.bitwise_or.reduce(picked.reshape(-1, *picked.shape[len(reduced):]), axis=0)
            out[w, ..., part] = picked
    return out


def voxel_box_rows(grid: np.ndarray, voxels: np.ndarray, rotations: np.ndarray, orientation: np.ndarray,
                   centre: np.ndarray, half: np.ndarray, counts: tuple[int, int, int]) -> np.ndarray:
    """``box_or(..., keep=(2,))`` of a bool grid for boxes whose origins are voxel centres, exactly.

    A box at the centre of voxel v reads voxel ``v + offset(rotation, point)`` at each lattice point, unless the
    point lies within float32 rounding of a voxel face: so offsets are computed once per orientation and a point
    costs one add and one gather. Points that close to a face (a few per orientation) are placed box by box
    with the float32 sums of :func:`box_or`.

    Args:
        grid: (N, N, N) bool.
        voxels: (K, 3) int voxel of each origin (the origin is ``voxels + 0.5``).
        rotations: (O, 3, 3) the distinct orientations.
        orientation: (K,) index into ``rotations`` of each box.
        centre, half, counts: the box, as :func:`box_or` (the same for every box).

    Returns:
        (counts[2], K) bool: the box's x-y layer at each lattice z meets the grid.
    """
    n, k, o_count = grid.shape[0], len(voxels), len(rotations)
    xy, z = _box_terms(rotations, centre, half, counts)
    # Rows of lattice points: (3, O, nz, nx * ny), the layout of the gathers below.
    xy = np.broadcast_to(xy.transpose(0, 3, 1, 2)[:, :, None], (3, o_count, counts[2], counts[0], counts[1]))
    xy = xy.reshape(3, o_count, counts[2], -1)
    z = np.broadcast_to(z.transpose(0, 2, 1)[..., None], xy.shape)
    # Exact padded coordinate minus the voxel index (+1 padding, +0.5 voxel centre); float64 holds the sum.
    d = xy.astype(np.float64) + z + 1.5
    step = np.floor(d)
    # The float32 sums round twice, each by at most half an ulp of the largest magnitude they reach.
    largest = n + 2.0 + float(np.abs(xy).max() + np.abs(z).max())
    tolerance = 2.0 ** (math.ceil(math.log2(largest)) - 21)  # four of those ulps
    near = (np.minimum(d - step, step + 1.0 - d) <= tolerance).any(axis=0)  # (O, nz, nx * ny)
    # Voxels of a copy of the grid with a margin no point leaves (empty, as the padding reads); +1: a point
    # near a face may fall one voxel either side of its offset.
    offset = step.astype(np.int64) - 1
    margin = int(max(-offset.min(), offset.max(), 0)) + 1
    size = n + 2 * margin
    table = np.zeros((size,) * 3, bool)
    table[margin:margin + n, margin:margin + n, margin:margin + n] = grid
    table = table.ravel()
    strides = np.array([size * size, size, 1])
    flat = np.einsum("c,c...->...", strides, offset).astype(np.int32)  # (O, nz, nx * ny)
    start = ((voxels + margin) @ strides).astype(np.int32)
    base = (voxels + 0.5).astype(np.float32) + np.float32(1.0)  # as box_or's origin + padding
    out = np.empty((counts[2], k), bool)
    for o in range(o_count):
        boxes = np.flatnonzero(orientation == o)
        index = start[boxes, None, None] + flat[o]  # (b, nz, nx * ny)
        rows, points = np.nonzero(near[o])
        if len(rows):
            coord = xy[:, o, rows, points][:, None] + (z[:, o, rows, points][:, None] + base[boxes].T[..., None])
            index[:, rows, points] = np.einsum("c,cbp->bp", strides, np.floor(coord).astype(np.int64) - 1 + margin)
        out[:, boxes] = table.take(index).any(axis=2).T
    return out


def gripper_part_boxes(widths: np.ndarray, dims: VoxelDims) -> tuple[np.ndarray, np.ndarray]:
    """The gripper's parts as boxes in its own frame (voxels): (K, 3, 3) centres and (K, 3, 3) half extents of
    the finger at -y, the finger at +y (open to ``widths``) and the palm, in that order."""
    k = len(widths)
    fl, fw, ft = dims.finger_length, dims.finger_width, dims.finger_thickness
    centres = np.zeros((k, 3, 3))
    centres[:, 0, 1], centres[:, 1, 1] = -(widths / 2 + ft / 2), widths / 2 + ft / 2
    centres[:, :2, 2] = -fl / 2
    centres[:, 2, 2] = -fl - dims.palm_depth / 2
    halves = np.empty((k, 3, 3))
    halves[:, :2] = [fw / 2, ft / 2, fl / 2]
    halves[:, 2] = [fw / 2, dims.max_opening / 2 + ft, dims.palm_depth / 2]
    return centres, halves


def lowest_point(origins: np.ndarray, rotations: np.ndarray, widths: np.ndarray, dims: VoxelDims) -> np.ndarray:
    """(K,) lowest grid z reached by any gripper part (fingers at ``widths``, palm), analytically."""
    centres, halves = gripper_part_boxes(widths, dims)
    zrow = rotations[:, 2, :]  # (K, 3): grid z of each gripper axis
    lows = np.einsum("kj,kpj->kp", zrow, centres) - np.einsum("kj,kpj->kp", np.abs(zrow), halves)
    return origins[:, 2] + lows.min(axis=1)
