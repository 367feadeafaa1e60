"""Grippers drawn as outlines: line segments for any figure, and a matplotlib figure over the completions."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pssnet_core.geometry import GridPose
from pssnet_core.grasps.config import GraspConfig, GripperConfig
from pssnet_core.grasps.inputs import check_occupancy
from pssnet_core.grasps.results import GraspSet

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def gripper_lines(grasps: GraspSet, config: GraspConfig | None = None) -> np.ndarray:
    """(K, 4, 2, 3) camera-frame line segments drawing each gripper: two fingers, the palm bar, the stem."""
    return gripper_segments(grasps.poses, grasps.widths, (config or GraspConfig()).gripper)


def gripper_segments(poses: np.ndarray, widths: np.ndarray, gripper: GripperConfig) -> np.ndarray:
    """(K, 4, 2, 3) line segments of grippers at ``poses`` (K, 4, 4) opened to ``widths`` (K,), in the poses' frame.

    The segments: the two fingers (fingertip to palm), the palm bar between them, and a stem behind the palm
    as long as the palm is deep (at least 3 cm, so that the approach direction reads in a small figure).
    """
    poses, widths = np.asarray(poses, np.float64), np.asarray(widths, np.float64)
    lines = np.zeros((len(widths), 4, 2, 3))
    reach = gripper.finger_length
    for k in range(len(widths)):
        half = widths[k] / 2
        local = np.array([
            [[0, -half, 0], [0, -half, -reach]],
            [[0, half, 0], [0, half, -reach]],
            [[0, -half, -reach], [0, half, -reach]],
            [[0, 0, -reach], [0, 0, -reach - max(gripper.palm_depth, 0.03)]],
        ])
        lines[k] = local @ poses[k, :3, :3].T + poses[k, :3, 3]
    return lines


def plot_grasps(grasps: GraspSet, occupancy: np.ndarray, pose: GridPose, top_k: int = 5,
                config: GraspConfig | None = None, path: str | Path | None = None, max_completions: int = 6,
                observed: np.ndarray | None = None, title: str = "") -> Figure:
    """Draws the best grasps over the completions' voxel-centre clouds (camera-frame positions).

    Positions are the camera-frame points, drawn in gravity-aligned axes through the camera's origin (right,
    forward = the horizontal viewing direction, up), so the support plane is level. Two views: from the
    camera and from the side. Grasps are drawn as gripper outlines (fingers, palm, stem), coloured by rank
    (best = thick dark green) and labelled with rank and score.

    Args:
        grasps: ranked grasps.
        occupancy: (S, N, N, N) completions (at most ``max_completions`` are drawn, one colour each).
        pose: their grid pose.
        top_k: grasps drawn.
        config: the gripper used (finger length for the drawing).
        path: if given, the figure is also written there as a PNG.
        max_completions: completions drawn.
        observed: (M, 3) observed points (camera frame) drawn in black, or None.
        title: figure title.

    Returns:
        The matplotlib Figure (close it with ``matplotlib.pyplot.close(fig)`` when done).
    """
    import matplotlib.pyplot as plt

    occupancy = check_occupancy(occupancy, pose)
    shown = grasps.top(top_k)
    lines = gripper_lines(shown, config)
    fig = plt.figure(figsize=(13, 6.5))
    cmap = plt.get_cmap("tab10")
    rank_colours = plt.get_cmap("RdYlGn_r")(np.linspace(0.0, 0.85, max(len(shown), 1)))
    axes_rows = pose.rotation  # columns: forward (grid x), left (grid y), up (grid z) in the camera frame

    def view(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        g = np.asarray(p) @ axes_rows
        return -g[..., 1], g[..., 0], g[..., 2]  # right, forward, up

    clouds = [pose.occupied_centres(occupancy[s]) for s in range(min(max_completions, occupancy.shape[0]))]
    for panel, (elev, azim) in enumerate(((25.0, -65.0), (15.0, 5.0))):
        ax = fig.add_subplot(1, 2, panel + 1, projection="3d")
        for s, c in enumerate(clouds):
            if len(c) > 2000:
                c = c[np.linspace(0, len(c) - 1, 2000).astype(int)]
            ax.scatter(*view(c), s=3, alpha=0.25, color=cmap(s % 10),
                       label=f"completion {s}" if panel == 0 else None)
        if observed is not None and len(observed):
            o = np.asarray(observed)[:: max(1, len(observed) // 1000)]
            ax.scatter(*view(o), s=1, color="k", alpha=0.35, label="observed" if panel == 0 else None)
        for k in range(len(shown) - 1, -1, -1):  # best drawn last, on top
            for seg in lines[k]:
                ax.plot(*view(seg), color=rank_colours[k], linewidth=3.5 if k == 0 else 1.8)
            ax.text(*view(shown.poses[k, :3, 3]), f"#{k + 1} {shown.scores[k]:.2f}", color=rank_colours[k],
                    fontsize=8)
        everything = np.concatenate([pose.occupied_centres(occupancy.any(axis=0)), lines.reshape(-1, 3)])
        if len(everything):
            v = np.stack(view(everything), axis=1)
            centre, radius = (v.min(axis=0) + v.max(axis=0)) / 2, float(np.ptp(v, axis=0).max()) / 2 + 0.01
            ax.set_xlim(centre[0] - radius, centre[0] + radius)
            ax.set_ylim(centre[1] - radius, centre[1] + radius)
            ax.set_zlim(centre[2] - radius, centre[2] + radius)
        ax.set_xlabel("right of camera (m)")
        ax.set_ylabel("ahead of camera, horizontal (m)")
        ax.set_zlabel("up from camera (m)")
        ax.view_init(elev=elev, azim=azim)
        if panel == 0:
            ax.legend(loc="upper left", fontsize=7, markerscale=3)
    summary = ", ".join(f"#{k + 1} {shown.kinds[k]} {shown.scores[k]:.2f} w={shown.widths[k] * 100:.1f}cm"
                        for k in range(len(shown)))
    fig.suptitle((title + "\n" if title else "") + (summary or "no grasps"), fontsize=9)
    fig.tight_layout()
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
    return fig
