"""Where to look next: the camera pose whose depth image would best tell the samples apart.

The samples of one view all agree with it (the checked sampler made sure); where they differ is what the view
could not see. A second camera that would see those differences resolves the ambiguity a grasp planner meets,
so :func:`rank_views` scores candidate camera poses by how likely the depth image from each is to tell two
samples (drawn by their weights) apart: the samples' depth images are rendered from each candidate, with the
known surroundings (``occluders``) in front of whatever they hide, and two samples count as told apart when
their depths differ by more than ``delta`` on at least ``min_pixels`` pixels (Alg. 1's observation model, the
same test that made them all agree with the first view).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from pssnet_core.geometry import CameraIntrinsics, GridPose

#: A ring of places to look from round an object, (azimuth, elevation) in degrees (azimuth 180: the side of a camera
#: at the default orbit, ``data.scenes.orbit_camera``): every 45 degrees round, 15 and 45 degrees up. The trials'
#: robot, the demo and the benchmark look from these.
RING_PLACES: tuple[tuple[float, float], ...] = tuple((float(a), float(e)) for e in (15, 45) for a in range(0, 360, 45))


@dataclass(frozen=True)
class NextViewConfig:
    """How candidate views are scored.

    Attributes:
        delta: depths further apart than this tell two samples apart (metres; the checked sampler's default).
        min_pixels: two samples count as told apart when they differ on at least this many pixels of the
            rendered image (at ``scale``): a few stray voxels are not a difference a depth camera resolves.
        scale: the samples are rendered at this fraction of the camera's resolution (cheap, and still finer than
            the voxels at the working distances).
    """

    delta: float = 0.01
    min_pixels: int = 12
    scale: float = 0.25

    def __post_init__(self) -> None:
        if not self.delta > 0 or self.min_pixels < 1 or not 0.0 < self.scale <= 1.0:
            raise ValueError(f"need delta > 0, min_pixels >= 1 and scale in (0, 1], got {self.delta}, "
                             f"{self.min_pixels} and {self.scale}")


def scaled_intrinsics(intrinsics: CameraIntrinsics, scale: float) -> CameraIntrinsics:
    """The same camera at ``scale`` times the resolution (pixel centres kept)."""
    width, height = max(1, round(intrinsics.width * scale)), max(1, round(intrinsics.height * scale))
    sx, sy = width / intrinsics.width, height / intrinsics.height
    return CameraIntrinsics(fx=intrinsics.fx * sx, fy=intrinsics.fy * sy, cx=(intrinsics.cx + 0.5) * sx - 0.5,
                            cy=(intrinsics.cy + 0.5) * sy - 0.5, width=width, height=height)


def render_sample_depths(occupancy: np.ndarray, pose: GridPose, camera_from_first: np.ndarray,
                         intrinsics: CameraIntrinsics) -> np.ndarray:
    """(n, H, W) depth images (inf: nothing) of ``n`` occupancy grids seen from another camera.

    Each occupied voxel is splatted as a square of its projected size at its nearest depth, the nearest voxel
    winning per pixel: open3d's ray casting would need a mesh per sample, and a z-buffer of voxel centres is
    what this comparison needs at a quarter of the camera's resolution.

    Args:
        occupancy: (n, N, N, N) bool samples in the grid at ``pose`` (first camera's frame).
        camera_from_first: (4, 4) the candidate camera <- first camera.
        intrinsics: the candidate camera's intrinsics (already scaled).
    """
    occupancy = np.asarray(occupancy, dtype=bool)
    return _render(*_voxel_centres(occupancy, pose), len(occupancy), pose.voxel_size, camera_from_first, intrinsics)


def _voxel_centres(occupancy: np.ndarray, pose: GridPose) -> tuple[np.ndarray, np.ndarray]:
    """All samples' occupied voxel centres (first camera's frame) and each one's sample index."""
    centres = pose.occupied_centres_per_grid(occupancy)
    return (np.concatenate([np.zeros((0, 3)), *centres]).astype(np.float64),
            np.repeat(np.arange(len(centres)), [len(c) for c in centres]))


#: pixels of voxel squares expanded at once when rendering (bounds the memory of one step: ~40 bytes a pixel)
SPLAT_CHUNK = 1 << 21


def _render(points: np.ndarray, sample: np.ndarray, count: int, voxel_size: float, camera_from_first: np.ndarray,
            intrinsics: CameraIntrinsics) -> np.ndarray:
    """:func:`render_sample_depths` of voxel centres already gathered (once for every candidate of a ranking).

    Each voxel's square is clipped to the image before its pixels are listed, so the work is the pixels the
    squares cover in the image, whatever the camera: a camera a few centimetres from the samples (any valid pose a
    client may send) or with a narrow field of view projects each voxel over hundreds of pixels, and listing
    them over the square's whole extent took minutes.
    """
    h, w = intrinsics.height, intrinsics.width
    depth = np.full(count * h * w, np.inf)
    transform = np.asarray(camera_from_first, dtype=np.float64)
    here = points @ transform[:3, :3].T + transform[:3, 3]
    front = here[:, 2] > 1e-3
    here, sample = here[front], sample[front]
    if not len(here):
        return depth.reshape(count, h, w)
    z = here[:, 2]
    u = intrinsics.fx * here[:, 0] / z + intrinsics.cx
    v = intrinsics.fy * here[:, 1] / z + intrinsics.cy
    half_u = np.maximum(0.5 * voxel_size * intrinsics.fx / z, 0.5)
    half_v = np.maximum(0.5 * voxel_size * intrinsics.fy / z, 0.5)
    near = z - 0.5 * voxel_size
    # The pixels whose centres the voxel's projected square covers (at least the one under its centre), as a
    # range of columns and rows inside the image.
    u0, u1 = _covered_range(u, half_u, w)
    v0, v1 = _covered_range(v, half_v, h)
    width, height = u1 - u0 + 1, v1 - v0 + 1
    area = np.where((width > 0) & (height > 0), width * height, 0)
    inside = np.flatnonzero(area)
    # Split the voxels into runs of at most SPLAT_CHUNK covered pixels (a single voxel never covers more than the
    # image), list each run's pixels and keep the nearest voxel per pixel.
    ends = np.cumsum(area[inside])
    cuts = np.searchsorted(ends, np.arange(SPLAT_CHUNK, ends[-1] if len(ends) else 0, SPLAT_CHUNK), side="right")
    for run in np.split(inside, cuts):
        if not len(run):
            continue
        n = area[run]
        which = np.repeat(run, n)
        offset = np.arange(len(which)) - np.repeat(np.cumsum(n) - n, n)
        pu = u0[which] + offset % width[which]
        pv = v0[which] + offset // width[which]
        flat = sample[which] * (h * w) + pv * w + pu
        order = np.argsort(flat)
        flat, nearest = flat[order], near[which][order]
        starts = np.flatnonzero(np.r_[True, flat[1:] != flat[:-1]])
        flat = flat[starts]
        depth[flat] = np.minimum(depth[flat], np.minimum.reduceat(nearest, starts))
    return depth.reshape(count, h, w)


def _covered_range(centre: np.ndarray, half: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """First and last pixel index p (int64, clipped to [0, size - 1]; first > last: none) with |p - centre| <= half.

    The bounds from ceil/floor are moved by one where rounding put them on the wrong side of that test, so that
    a pixel is covered exactly when the test says so.
    """
    first = np.ceil(centre - half)
    first = np.where(np.abs(first - 1 - centre) <= half, first - 1, first)
    first = np.where(np.abs(first - centre) > half, first + 1, first)
    last = np.floor(centre + half)
    last = np.where(np.abs(last + 1 - centre) <= half, last + 1, last)
    last = np.where(np.abs(last - centre) > half, last - 1, last)
    first = np.clip(first, 0, size)  # clipped as floats: a far-off centre may not fit an int64
    last = np.clip(last, -1, size - 1)
    return first.astype(np.int64), last.astype(np.int64)


def separability(depths: np.ndarray, weights: np.ndarray, config: NextViewConfig,
                 occluder_depth: np.ndarray | None = None) -> float:
    """The probability that this view's depth image tells two samples apart, the two drawn by ``weights``.

    A pixel of one sample differs from another sample when its depth lies more than ``delta`` from the other's
    depths at that pixel and its 8 neighbours (or it sees the sample where the other sees nothing around it): a
    one-pixel tolerance, without which the voxels' staircase along every silhouette (a voxel more or less at the
    edge, in front of a far background) would tell every two samples apart, even from the first camera.

    Args:
        depths: (n, H, W) the samples' depth images from the candidate (:func:`render_sample_depths`).
        weights: (n,) the samples' weights (summing to 1).
        occluder_depth: (H, W) depth of what is known to stand in front (inf: nothing), or None.
    """
    depths = np.asarray(depths, dtype=np.float32)
    count = len(depths)
    if count < 2:
        return 0.0
    if occluder_depth is not None:
        depths = np.where(depths < np.asarray(occluder_depth, np.float32)[None], depths, np.inf)
    # Only pixels some sample sees can differ: the window around them (and its one-pixel rim for the tolerance).
    rows, cols = np.nonzero(np.isfinite(depths).any(axis=0))
    if not len(rows):
        return 0.0
    depths = depths[:, max(rows.min() - 1, 0):rows.max() + 2, max(cols.min() - 1, 0):cols.max() + 2]
    kernel = np.ones((3, 3), np.uint8)
    # Per sample, the nearest and farthest depth around each pixel (inf counts as farthest: nothing seen).
    nearest = np.stack([cv2.erode(d, kernel, borderType=cv2.BORDER_REPLICATE) for d in depths]).reshape(count, -1)
    farthest = np.stack([cv2.dilate(d, kernel, borderType=cv2.BORDER_REPLICATE) for d in depths]).reshape(count, -1)
    flat = depths.reshape(count, -1)
    seen = np.isfinite(flat)
    delta = np.float32(config.delta)
    told_apart = np.zeros((count, count), dtype=bool)
    with np.errstate(invalid="ignore"):  # inf - inf where neither sees anything: compares False
        for i in range(count):
            # Pixels where sample i sees something nearer than all of j's depths around it, or farther than all.
            nearer = seen[i] & (flat[i] < nearest - delta)
            farther = seen[i] & (flat[i] > farthest + delta)
            told_apart[i] = (nearer | farther).sum(axis=1) >= config.min_pixels
    told_apart |= told_apart.T
    np.fill_diagonal(told_apart, False)
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    return float(w @ told_apart @ w)


def rank_views(occupancy: np.ndarray, weights: np.ndarray, pose: GridPose, cameras_from_first: Sequence[np.ndarray],
               intrinsics: CameraIntrinsics, occluder_depths: Sequence[np.ndarray | None] | None = None,
               config: NextViewConfig | None = None) -> np.ndarray:
    """Each candidate camera's :func:`separability` of the samples (higher: a more telling look).

    Args:
        occupancy: (n, N, N, N) the samples; weights: (n,) their weights.
        pose: their grid's pose in the first camera's frame.
        cameras_from_first: the candidates, each (4, 4) candidate camera <- first camera.
        intrinsics: the candidates' camera (full resolution; rendered at ``config.scale``).
        occluder_depths: per candidate, the depth of the known surroundings at the scaled resolution
            (:func:`scaled_intrinsics`), or None.
    """
    config = config or NextViewConfig()
    small = scaled_intrinsics(intrinsics, config.scale)
    occluders = list(occluder_depths) if occluder_depths is not None else [None] * len(cameras_from_first)
    if len(occluders) != len(cameras_from_first):
        raise ValueError(f"{len(occluders)} occluder images for {len(cameras_from_first)} candidate cameras")
    occupancy = np.asarray(occupancy, dtype=bool)
    points, sample = _voxel_centres(occupancy, pose)
    return np.array([separability(_render(points, sample, len(occupancy), pose.voxel_size, camera, small), weights,
                                  config, occluder)
                     for camera, occluder in zip(cameras_from_first, occluders, strict=True)])
