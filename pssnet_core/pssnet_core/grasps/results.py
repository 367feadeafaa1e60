"""What grasp planning returns: candidates in grid coordinates, ranked grasps in the camera frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pssnet_core.grasps.config import GraspError

KIND_NAMES = ("top", "side", "tilted")


@dataclass
class GraspCandidates:
    """Grasps in grid coordinates (voxel units, z up), before or after scoring.

    Attributes:
        origins: (K, 3) point between the fingertips.
        rotations: (K, 3, 3) columns are the gripper x, y (closing) and z (approach) axes in the grid frame.
        widths: (K,) opening needed, voxels.
        kinds: (K,) int8 index into :data:`KIND_NAMES` ("top", "side", "tilted").
    """

    origins: np.ndarray
    rotations: np.ndarray
    widths: np.ndarray
    kinds: np.ndarray

    def __len__(self) -> int:
        return len(self.origins)

    def subset(self, index: np.ndarray) -> GraspCandidates:
        return GraspCandidates(self.origins[index], self.rotations[index], self.widths[index], self.kinds[index])

    @classmethod
    def empty(cls) -> GraspCandidates:
        return cls(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0, np.int8))

    @classmethod
    def concatenate(cls, parts: list[GraspCandidates]) -> GraspCandidates:
        return cls(*(np.concatenate([getattr(c, f) for c in parts]) for f in ("origins", "rotations", "widths",
                                                                              "kinds")))


@dataclass
class GraspSet:
    """Grasps ranked best first, scored against every completion. Camera-frame fields use metres.

    Attributes:
        poses: (K, 4, 4) camera-frame poses (origin between the fingertips, z approach, y closing axis).
        widths: (K,) opening needed (metres).
        scores: (K,) in [0, 1]: fraction of the completions the grasp holds for.
        holds: (K, S) whether grasp k holds for completion s.
        secondary: (K,) tie-break term in [0, 1] (see the package docstring).
        kinds: (K,) "top", "side" or "tilted".
        grid: the same grasps in grid coordinates.
        support_z: height of the support plane in grid coordinates (voxels).
        voxel_size: voxel edge (metres).
        weight_shares: (K,) over the completions the grasp holds for (weighted as the score), the mean share of the
            object's weight its pads hold by friction (``GraspChecks.resistance``); 0 where it holds for none. In the
            grasp trials it told the grasps that lift from those that slip: on the true shape, rated >= 0.9, 105 of
            107 lifted the hidden-handle mug, below 0.7, 22 of 35 (``results/grasp_trials/oracle_slips/``).
        grip: (K,) the expected grip over the completions (``GraspConfig.rank_by``; see the package docstring), or
            None when not computed.
    """

    poses: np.ndarray
    widths: np.ndarray
    scores: np.ndarray
    holds: np.ndarray
    secondary: np.ndarray
    kinds: np.ndarray
    grid: GraspCandidates
    support_z: float
    voxel_size: float
    weight_shares: np.ndarray
    grip: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.scores)

    def subset(self, index: np.ndarray | slice) -> GraspSet:
        """The grasps at ``index`` (keeps their order)."""
        index = np.arange(len(self))[index]
        return GraspSet(self.poses[index], self.widths[index], self.scores[index], self.holds[index],
                        self.secondary[index], self.kinds[index], self.grid.subset(index), self.support_z,
                        self.voxel_size, self.weight_shares[index], None if self.grip is None else self.grip[index])

    def top(self, k: int, min_score: float = 0.0) -> GraspSet:
        """The best ``k`` grasps whose score is at least ``min_score``."""
        if k < 0:
            raise GraspError(f"k must be >= 0, got {k}")
        keep = np.flatnonzero(self.scores >= min_score)[:k]
        return self.subset(keep)

    def confident_choice(self, min_score: float = 0.9) -> int | None:
        """The risk-averse choice: among the grasps that hold for at least ``min_score`` of the completions'
        weight, the one that grips most firmly (largest secondary term); None when no grasp is that sure, i.e.
        the completions disagree about every grasp (look again from elsewhere, or accept the risk that
        ``scores[0]`` states)."""
        if not 0.0 < min_score <= 1.0:
            raise GraspError(f"min_score must be in (0, 1], got {min_score}")
        sure = np.flatnonzero(self.scores >= min_score - 1e-6)
        return int(sure[np.argmax(self.secondary[sure])]) if len(sure) else None


@dataclass
class SingleCompletionChoice:
    """The grasp one completion alone would choose, and how it fares against all completions.

    Attributes:
        index: the completion that chose.
        grasp: that grasp (a GraspSet of length 0 or 1) scored against *all* completions.
        score_alone: its score against completion ``index`` alone (1.0 when a grasp was found).
        score_all: its score against all completions (0.0 when none was found).
    """

    index: int
    grasp: GraspSet
    score_alone: float
    score_all: float


def matrix_to_position_quaternion(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4x4 rigid transform -> ((3,) position, (4,) unit quaternion x, y, z, w) as geometry_msgs/Pose wants.

    Raises:
        GraspError: not a finite 4x4 matrix with a rotation block.
    """
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise GraspError(f"pose must be a finite 4x4 matrix, got shape {matrix.shape}")
    r = matrix[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise GraspError("pose rotation block is not a proper rotation")
    return matrix[:3, 3].copy(), Rotation.from_matrix(r).as_quat()
