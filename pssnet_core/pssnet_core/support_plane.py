"""Up vector from the support plane the object stands on (RANSAC plane fit with open3d).

Used when the camera's tilt is not known in advance: the surface around and below the object gives the
direction against gravity. Candidate points are the valid readings in a window around the object's mask
(the mask itself excluded) that lie no higher than the object's lowest point plus a margin, measured along
a rough prior up vector; a table seen below and around a mug qualifies, a wall behind it does not.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
import open3d as o3d

from pssnet_core.geometry import CameraIntrinsics, ObservationError, masked_points, valid_depth


@dataclass(frozen=True)
class SupportPlaneConfig:
    """Parameters of the support-plane fit.

    Attributes:
        distance: RANSAC inlier distance (metres).
        window: the search window is the mask's bounding box grown by this factor of its size on each side.
        height_margin: candidates lie at most this far (metres) above the object's lowest observed point.
        max_tilt_deg: the fitted normal must lie within this angle of the prior up vector.
        min_inliers: fewer plane inliers than this is a failure.
        max_points: candidates are subsampled (evenly) to at most this many.
        iterations: RANSAC iterations.
        seed: RANSAC seed (open3d's global random generator), for reproducible fits.
    """

    distance: float = 0.005
    window: float = 1.0
    height_margin: float = 0.02
    max_tilt_deg: float = 45.0
    min_inliers: int = 200
    max_points: int = 20000
    iterations: int = 200
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.distance > 0 or not self.window > 0 or not self.height_margin >= 0:
            raise ValueError("distance and window must be positive, height_margin >= 0")
        if not 0 < self.max_tilt_deg <= 90 or self.min_inliers < 3 or self.iterations < 1 or self.max_points < 3:
            raise ValueError("max_tilt_deg in (0, 90], min_inliers >= 3, iterations >= 1, max_points >= 3")


@dataclass(frozen=True)
class SupportPlane:
    """A fitted support plane: ``up . p + offset = 0`` for points p on it (camera frame, metres).

    Attributes:
        up: (3,) unit normal pointing to the object's side (against gravity).
        offset: plane offset (metres).
        inliers: number of inlier points.
        tilt_deg: angle between ``up`` and the prior.
    """

    up: np.ndarray
    offset: float
    inliers: int
    tilt_deg: float


def fit_support_plane(depth: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics, prior_up: np.ndarray,
                      config: SupportPlaneConfig | None = None, min_depth: float = 0.1,
                      max_depth: float = 5.0) -> SupportPlane:
    """Fits the plane the masked object stands on.

    Args:
        depth: (H, W) float metres (0/NaN = no reading).
        mask: (H, W), non-zero = object.
        intrinsics: camera intrinsics.
        prior_up: rough up direction in the camera frame (selects the candidates and orients the normal).
        config: fit parameters (default: :class:`SupportPlaneConfig` defaults).
        min_depth: readings closer than this are ignored.
        max_depth: readings farther than this are ignored.

    Raises:
        ObservationError: too few candidate points or inliers, or a plane tilted beyond ``max_tilt_deg``.
    """
    config = config or SupportPlaneConfig()
    prior = np.asarray(prior_up, dtype=np.float64).reshape(3)
    norm = np.linalg.norm(prior)
    if not np.isfinite(norm) or norm < 1e-9:
        raise ObservationError(f"prior up vector must be finite and non-zero, got {prior.tolist()}")
    prior = prior / norm
    # Everything happens in the window around the mask, with intrinsics shifted to it: the same points as on the
    # whole image, without whole-image passes (9 -> ~3 ms a call; the node runs this on every input).
    object_pixels = np.asarray(mask) != 0
    rows, cols = np.flatnonzero(object_pixels.any(axis=1)), np.flatnonzero(object_pixels.any(axis=0))
    if not len(rows):
        raise ObservationError("mask is empty: no pixel marks the target object")
    h, w = depth.shape
    grow_v = int(np.ceil(config.window * (rows[-1] - rows[0] + 1)))
    grow_u = int(np.ceil(config.window * (cols[-1] - cols[0] + 1)))
    v0, v1 = max(0, rows[0] - grow_v), min(h, rows[-1] + grow_v + 1)
    u0, u1 = max(0, cols[0] - grow_u), min(w, cols[-1] + grow_u + 1)
    depth, object_pixels = depth[v0:v1, u0:u1], object_pixels[v0:v1, u0:u1]
    intrinsics = replace(intrinsics, width=u1 - u0, height=v1 - v0, cx=intrinsics.cx - u0, cy=intrinsics.cy - v0)
    object_points = masked_points(depth, object_pixels, intrinsics, min_depth, max_depth)
    lowest = float((object_points @ prior).min())
    # The mask's own border pixels mix object and background depths: keep a few pixels away from it.
    near_object = cv2.dilate(object_pixels.astype(np.uint8), np.ones((5, 5), np.uint8)) != 0
    usable = ~near_object & valid_depth(depth, min_depth, max_depth)
    v, u = np.nonzero(usable)
    candidates = intrinsics.backproject(u, v, depth[v, u])
    candidates = candidates[candidates @ prior <= lowest + config.height_margin]
    if len(candidates) < config.min_inliers:
        raise ObservationError(
            f"support plane estimation failed: only {len(candidates)} valid readings around and below the object "
            f"(need {config.min_inliers}); is the surface it stands on in view? Set up_vector instead")
    if len(candidates) > config.max_points:
        candidates = candidates[np.linspace(0, len(candidates) - 1, config.max_points).astype(np.int64)]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(candidates))
    o3d.utility.random.seed(int(config.seed))
    model, inliers = cloud.segment_plane(config.distance, 3, config.iterations)
    normal = np.asarray(model[:3], dtype=np.float64)
    scale = np.linalg.norm(normal)
    if len(inliers) < config.min_inliers or scale < 1e-12:
        raise ObservationError(f"support plane estimation failed: best plane has {len(inliers)} inliers "
                               f"(need {config.min_inliers})")
    normal, offset = normal / scale, float(model[3]) / scale
    if normal @ prior < 0:
        normal, offset = -normal, -offset
    tilt = float(np.degrees(np.arccos(np.clip(normal @ prior, -1.0, 1.0))))
    if tilt > config.max_tilt_deg:
        raise ObservationError(f"support plane estimation failed: the plane found is tilted {tilt:.0f} degrees "
                               f"from up_vector (max {config.max_tilt_deg:.0f}); set up_vector closer to the "
                               "true up direction")
    return SupportPlane(up=normal, offset=offset, inliers=len(inliers), tilt_deg=tilt)
