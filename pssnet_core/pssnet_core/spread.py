"""Picking items that spread out: evenly spaced indices, and occupancy grids by greedy farthest-point selection on
packed bits, with one of two distances: Jaccard (1 - IoU), or what each grid has beyond a margin around the other.

:func:`evenly_spaced` is the one picker of evenly spaced subsets (views a command scores, completions re-checked,
samples drawn). The farthest-point selection serves the two places that pick a few grids differing most: the
checked sampler (which samples to return, and the share of the accepted proposals each stands for) and the figures
(which samples to draw). numpy only, so that figure code does not pull in torch.
"""

from __future__ import annotations

import numpy as np

_M1, _M2, _M4 = np.uint64(0x5555555555555555), np.uint64(0x3333333333333333), np.uint64(0x0F0F0F0F0F0F0F0F)
_ONES = np.uint64(0x0101010101010101)


def row_bit_counts_portable(words: np.ndarray) -> np.ndarray:
    """Set bits of each row of (G, W) uint64 words, as (G,) int64, with shifts and masks that every numpy version
    has (the usual parallel popcount: 2-, 4-, then 8-bit sums, added up by one wrapping multiply)."""
    x = np.asarray(words, dtype=np.uint64)
    x = x - ((x >> np.uint64(1)) & _M1)
    x = (x & _M2) + ((x >> np.uint64(2)) & _M2)
    x = (x + (x >> np.uint64(4))) & _M4
    return ((x * _ONES) >> np.uint64(56)).sum(axis=1, dtype=np.int64)


def row_bit_counts(words: np.ndarray) -> np.ndarray:
    """Set bits of each row of (G, W) uint64 words, as (G,) int64: ``np.bitwise_count`` where numpy has it (2.0
    and newer), else :func:`row_bit_counts_portable` (numpy 1.26, as on Ubuntu 24.04: ~1 ms for 200 grids of
    32^3, about 3x longer)."""
    if hasattr(np, "bitwise_count"):
        return np.bitwise_count(words).sum(axis=1, dtype=np.int64)
    return row_bit_counts_portable(words)


def evenly_spaced(count: int, limit: int | None) -> list[int]:
    """Indices of ``limit`` items spread evenly over ``count``, ascending (all when ``limit`` is None or ``>= count``).

    The same ``count`` and ``limit`` always give the same indices, so that the subsets of different commands
    (``--max-observations``, ``--max-views``) coincide.

    Raises:
        ValueError: ``limit`` < 1 (and smaller than ``count``).
    """
    if limit is None or limit >= count:
        return list(range(count))
    if limit < 1:
        raise ValueError(f"an evenly spaced subset needs at least 1 item, got {limit}")
    return sorted(set(np.linspace(0, count - 1, limit).round().astype(int).tolist()))


class BitRows:
    """Occupancy grids as rows of packed bits (64-bit words), with their voxel counts.

    Why packed: a grid against 200 others at 32^3 is a few thousand popcounts (numpy's ``bitwise_count``), well
    under a millisecond, where torch bool reductions over the same grids took ~200 ms.
    """

    def __init__(self, words: np.ndarray) -> None:
        self.words = words
        self.sizes = row_bit_counts(words)

    @classmethod
    def pack(cls, occupancy: np.ndarray) -> BitRows:
        """(G, ...) bool grids (any grid shape, the same for all) -> their bit rows."""
        bits = np.packbits(np.asarray(occupancy, bool).reshape(len(occupancy), -1), axis=1)
        return cls(np.ascontiguousarray(np.pad(bits, ((0, 0), (0, (-bits.shape[1]) % 8)))).view(np.uint64))

    def __len__(self) -> int:
        return self.words.shape[0]

    def subset(self, rows: np.ndarray) -> BitRows:
        """The grids ``rows``, without packing them again."""
        return BitRows(self.words[rows])

    def count_within(self, mask: np.ndarray) -> np.ndarray:
        """Occupied voxels of each grid inside ``mask`` (one grid's shape, or flat)."""
        return row_bit_counts(self.words & BitRows.pack(mask[None]).words[0])

    def jaccard_to(self, index: int) -> np.ndarray:
        """1 - IoU of every grid to grid ``index`` (two empty grids: distance 0)."""
        inter = row_bit_counts(self.words & self.words[index])
        union = self.sizes + self.sizes[index] - inter
        return np.where(union > 0, 1.0 - inter / np.maximum(union, 1), 0.0)

    def distance_to(self, index: int) -> np.ndarray:
        """The selection's distance of every grid to grid ``index``: Jaccard."""
        return self.jaccard_to(index)


def _voxel_rows(occupancy: np.ndarray) -> np.ndarray:
    """(G, A, B, N) bool grids -> (G, A, B) unsigned ints, bit k of [g, i, j] = voxel (i, j, k) of grid g (N <= 64).

    One integer per row of voxels along the last axis, so that a dilation along it is a shift: the dilation below
    then touches N^2 integers per grid instead of N^3 bytes (~30x faster than shifted ORs on bools).
    """
    n = occupancy.shape[-1]
    if n > 64:
        raise ValueError(f"grids of at most 64 voxels a side, got {n}")
    width = next(w for w in (1, 2, 4, 8) if 8 * w >= n)
    packed = np.packbits(occupancy, axis=-1, bitorder="little")  # voxel k -> bit k % 8 of byte k // 8
    packed = np.pad(packed, ((0, 0), (0, 0), (0, 0), (0, width - packed.shape[-1])))
    # Little-endian integers: byte b holds bits 8b..8b+7, so bit k of the integer is voxel k.
    return np.ascontiguousarray(packed).view(f"<u{width}").reshape(occupancy.shape[:-1])


def _words(rows: np.ndarray) -> BitRows:
    """(G, A, B) row integers -> bit rows (one grid per row; the same voxel-to-bit map for every grid)."""
    raw = rows.reshape(len(rows), -1).view(np.uint8)
    return BitRows(np.ascontiguousarray(np.pad(raw, ((0, 0), (0, (-raw.shape[1]) % 8)))).view(np.uint64))


class MarginRows:
    """Occupancy grids compared by the voxels each has beyond ``radius`` voxels of the other.

    Why not Jaccard alone: two mugs whose bodies differ by a voxel all round are farther apart in Jaccard than two
    mugs whose handles sit 60 degrees apart (a body has ~10x a handle's voxels), so a selection on Jaccard spreads
    body sizes and leaves handles bunched. Voxels beyond a margin count only what one shape has where the other has
    nothing near: a handle elsewhere, a box reaching deeper. The distance is that count over both directions, plus
    the Jaccard distance (below 1) to order grids that nothing separates beyond the margin.
    """

    def __init__(self, grids: BitRows, beyond: BitRows) -> None:
        self.grids = grids
        self.beyond = beyond  # per grid: the voxels farther than the margin from it

    @classmethod
    def pack(cls, occupancy: np.ndarray, radius: int) -> MarginRows:
        """(G, A, B, N) bool grids (N <= 64) -> their bit rows and those of the space beyond ``radius`` voxels of
        each (a cube of ``2 * radius + 1`` voxels a side around every voxel)."""
        rows = _voxel_rows(np.asarray(occupancy, dtype=bool))
        n = rows.shape[-1]
        valid = rows.dtype.type((1 << n) - 1) if n < 8 * rows.itemsize else ~rows.dtype.type(0)
        grown = rows.copy()
        for shift in range(1, radius + 1):  # along the last axis: shifts within each row
            step = rows.dtype.type(shift)
            grown |= (rows << step) | (rows >> step)
        grown &= valid
        for axis in (1, 2):  # along the other two: shifted ORs of whole rows
            source, grown = grown, grown.copy()
            for shift in range(1, radius + 1):
                ahead, behind = [slice(None)] * 3, [slice(None)] * 3
                ahead[axis], behind[axis] = slice(shift, None), slice(None, -shift)
                grown[tuple(ahead)] |= source[tuple(behind)]
                grown[tuple(behind)] |= source[tuple(ahead)]
        return cls(_words(rows), _words(~grown & valid))

    def __len__(self) -> int:
        return len(self.grids)

    def subset(self, rows: np.ndarray) -> MarginRows:
        return MarginRows(self.grids.subset(rows), self.beyond.subset(rows))

    def distance_to(self, index: int) -> np.ndarray:
        """Voxels of every grid beyond the margin of grid ``index`` plus those of grid ``index`` beyond theirs, plus
        their Jaccard distance."""
        words = self.grids.words
        out = row_bit_counts(words & self.beyond.words[index]) + row_bit_counts(self.beyond.words & words[index])
        return out + self.grids.jaccard_to(index)


def farthest_point_selection(grids: BitRows | MarginRows, count: int, start: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Picks ``count`` grids that spread out (greedy farthest point on the grids' ``distance_to``, ties to the
    lowest index).

    Returns:
        The picked indices (``min(count, len(grids))`` of them at most, distinct: the selection stops when every
        remaining grid equals a picked one) and, for every grid, the position in the picked list of its nearest
        picked grid (its Voronoi cell).
    """
    picked = [int(start)]
    nearest = grids.distance_to(start)
    cell = np.zeros(len(grids), dtype=np.int64)
    for position in range(1, min(count, len(grids))):
        candidate = int(np.argmax(nearest))
        if nearest[candidate] <= 0.0:
            break  # every remaining grid equals a picked one
        picked.append(candidate)
        distance = grids.distance_to(candidate)
        closer = distance < nearest
        cell[closer] = position
        nearest = np.minimum(nearest, distance)
    return np.asarray(picked, dtype=np.int64), cell
