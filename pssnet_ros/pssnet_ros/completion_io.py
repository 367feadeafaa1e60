"""What the completion node makes of messages, without a node: input messages -> pipeline -> output messages.

The node, ``pssnet bag`` and the demo's recording all go through these functions, so that a completion
computed offline from a bag is, field for field, what the node would have published for the same set.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import Point, Pose, PoseArray
from pssnet_interfaces.msg import GraspCandidates
from pssnet_interfaces.srv import SampleCompletions
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from pssnet_core.geometry import CameraIntrinsics
from pssnet_core.grasps import GripperConfig, gripper_segments
from pssnet_core.pipeline import CompletionPipeline, MoreView, PipelineResult
from pssnet_ros import conversions
from pssnet_ros.params import pipeline_config

#: The node's input streams (relative topic names of its subscriptions) and its synchroniser's queue per stream.
STREAMS: tuple[str, ...] = ("depth", "mask", "camera_info")
SYNC_QUEUE_SIZE = 10

#: The node's publications (``~/name`` of the node ``pssnet``) as absolute topic names, in publishing order.
OUTPUT_TOPICS: dict[str, str] = {
    "completions": "/pssnet/completions",
    "known_occupied": "/pssnet/known_occupied",
    "grasps": "/pssnet/grasps",
    "grasp_candidates": "/pssnet/grasp_candidates",
    "grasp_markers": "/pssnet/grasp_markers",
}
#: Line width of the grasp markers' gripper outlines (metres).
MARKER_LINE_WIDTH = 0.003


@dataclass(frozen=True)
class OutputMessages:
    """The messages the node publishes for one completed set (field names are keys of OUTPUT_TOPICS).

    Attributes:
        completions: every sample's voxel centres, x, y, z float32 + ``sample`` uint32.
        known_occupied: the observed voxels' centres.
        grasps: grasp poses, best first.
        grasp_candidates: the same poses with their scores and widths.
        grasp_markers: the grasps drawn as gripper outlines for RViz (:func:`grasp_markers`).
    """

    completions: PointCloud2
    known_occupied: PointCloud2
    grasps: PoseArray
    grasp_candidates: GraspCandidates
    grasp_markers: MarkerArray

    def by_topic(self) -> dict[str, Any]:
        """Topic name -> message, in publishing order."""
        return {topic: getattr(self, name) for name, topic in OUTPUT_TOPICS.items()}


def stamp_ns(header: Header) -> int:
    """A header's stamp in nanoseconds (the synchroniser's time axis)."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def load_pipeline(values: dict[str, Any]) -> CompletionPipeline:
    """The node's pipeline for a complete, valid set of parameter values (``params.check_values`` passed).

    Raises:
        ValueError: the model cannot be loaded (missing or corrupt checkpoint, unavailable device), or the
            parameters do not fit it; the message says which.
    """
    try:
        config = pipeline_config(values)
    except ValueError as error:
        raise ValueError(f"invalid parameters: {error}") from None
    try:  # CheckpointError is a ValueError, and so is an unavailable device
        pipeline = CompletionPipeline.from_checkpoint(values["model_path"] or None, None, device=values["device"],
                                                      threads=values["threads"] or None,
                                                      precision=values["precision"])
    except ValueError as error:
        raise ValueError(f"cannot load the completion model: {error}") from None
    try:
        pipeline.config = config
    except ValueError as error:
        raise ValueError(f"invalid parameters for this model: {error}") from None
    return pipeline


@dataclass(frozen=True)
class MoreViewMessages:
    """A further look at the object, as a request carries it: images, camera_info and the camera's optical frame as
    a pose in the first depth image's frame."""

    depth: Image
    mask: Image
    camera_info: CameraInfo
    camera_pose: Pose


def more_views_of(request: Any) -> list[MoreViewMessages]:
    """The further looks of a ``SampleCompletions`` request or goal.

    Raises:
        ValueError: its four ``more_*`` arrays differ in length.
    """
    arrays = (request.more_depths, request.more_masks, request.more_camera_infos, request.more_camera_poses)
    if len({len(a) for a in arrays}) != 1:
        raise ValueError(f"more_depths, more_masks, more_camera_infos and more_camera_poses must be the same length, "
                         f"got {', '.join(str(len(a)) for a in arrays)}")
    return [MoreViewMessages(*parts) for parts in zip(*arrays, strict=True)]


def complete_messages(pipeline: CompletionPipeline, depth_msg: Image, mask_msg: Image, info_msg: CameraInfo,
                      depth_scale: float, num_samples: int, compute_grasps: bool,
                      should_stop: Callable[[str], bool] | None = None,
                      more_views: Sequence[MoreViewMessages] = (),
                      candidate_views: Sequence[Pose] = ()) -> tuple[PipelineResult, Header]:
    """Converts one depth/mask/camera_info set (and any further looks, and the candidate views to score) and
    completes it; returns the result and the header outputs carry.

    Raises:
        ValueError: a message cannot be converted or the pipeline refuses the input (the message says why).
        RunCancelled: ``should_stop`` (told the next step, see :meth:`CompletionPipeline.run`) returned True.
    """
    def images(depth: Image, mask: Image, info: CameraInfo) -> tuple[np.ndarray, np.ndarray, CameraIntrinsics]:
        return (conversions.depth_to_metres(depth, depth_scale), conversions.mask_to_numpy(mask),
                conversions.camera_info_to_intrinsics(info))

    depth, mask, intrinsics = images(depth_msg, mask_msg, info_msg)
    more = []
    for number, view in enumerate(more_views, start=2):
        try:
            more.append(MoreView(*images(view.depth, view.mask, view.camera_info),
                                 conversions.pose_to_matrix(view.camera_pose)))
        except ValueError as error:
            raise ValueError(f"view {number}: {error}") from error
    candidates = []
    for number, pose in enumerate(candidate_views):
        try:
            candidates.append(conversions.pose_to_matrix(pose))
        except ValueError as error:
            raise ValueError(f"candidate view {number}: {error}") from error
    result = pipeline.run(depth, mask, intrinsics, num_samples, compute_grasps, should_stop, more_views=more,
                          candidate_views=candidates)
    return result, depth_msg.header


def grasp_fields(result: PipelineResult) -> tuple[list[Pose], list[float], list[float], list[float]]:
    """Poses, scores, widths and weight shares of the result's grasps (empty lists when grasps were not computed)."""
    grasps = result.grasps
    if grasps is None or len(grasps.scores) == 0:
        return [], [], [], []
    poses = [conversions.matrix_to_pose(m) for m in grasps.poses]
    return (poses, [float(s) for s in grasps.scores], [float(w) for w in grasps.widths],
            [float(share) for share in grasps.weight_shares])


def score_colour(score: float) -> ColorRGBA:
    """Red (held by no completion) through yellow to green (held by every completion), mostly opaque."""
    score = min(max(float(score), 0.0), 1.0)
    return ColorRGBA(r=min(1.0, 2.0 * (1.0 - score)), g=min(1.0, 2.0 * score), b=0.0, a=0.9)


def grasp_markers(poses: list[Pose], scores: list[float], widths: list[float], header: Header,
                  gripper: GripperConfig) -> MarkerArray:
    """RViz markers of ranked grasps: a DELETEALL (the previous set's grippers go), then one LINE_LIST per grasp
    (``ns`` "grasps", ``id`` = rank): both fingers, the palm bar and a stem along the approach, as in the demo's
    figure, coloured by score (:func:`score_colour`)."""
    markers = [Marker(header=header, ns="grasps", action=Marker.DELETEALL)]
    matrices = np.array([conversions.pose_to_matrix(p) for p in poses]).reshape(-1, 4, 4)
    segments = gripper_segments(matrices, np.asarray(widths, np.float64), gripper)
    for rank, (lines, score) in enumerate(zip(segments, scores, strict=True)):  # lines: (4, 2, 3)
        marker = Marker(header=header, ns="grasps", id=rank, type=Marker.LINE_LIST, action=Marker.ADD,
                        color=score_colour(score))
        marker.pose.orientation.w = 1.0
        marker.scale.x = MARKER_LINE_WIDTH
        marker.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in lines.reshape(-1, 3)]
        markers.append(marker)
    return MarkerArray(markers=markers)


def output_messages(result: PipelineResult, header: Header, gripper: GripperConfig) -> OutputMessages:
    """The node's continuous-mode publications for one result, all carrying ``header``; ``gripper`` draws the
    grasp markers (the pipeline's ``config.grasps.gripper``)."""
    points, index = result.merged()
    poses, scores, widths, shares = grasp_fields(result)
    return OutputMessages(
        completions=conversions.points_to_pointcloud2(points, header, index),
        known_occupied=conversions.points_to_pointcloud2(result.known_occupied, header),
        grasps=PoseArray(header=header, poses=poses),
        grasp_candidates=GraspCandidates(header=header, poses=poses, scores=scores, widths=widths,
                                         weight_shares=shares),
        grasp_markers=grasp_markers(poses, scores, widths, header, gripper))


def fill_response(response: SampleCompletions.Response, result: PipelineResult,
                  header: Header) -> SampleCompletions.Response:
    """A successful service response for ``result``: one cloud per sample, the known-occupied cloud and the ranked
    grasps, all carrying ``header`` (``message`` is the caller's)."""
    response.header = header
    response.voxel_size = float(result.voxel_size)
    response.known_occupied = conversions.points_to_pointcloud2(result.known_occupied, header)
    response.completions = [conversions.points_to_pointcloud2(c, header) for c in result.completions]
    response.sample_weights = [float(w) for w in result.weights]
    poses, scores, widths, shares = grasp_fields(result)
    response.grasps = PoseArray(header=header, poses=poses)
    response.grasp_scores, response.grasp_widths, response.grasp_weight_shares = scores, widths, shares
    response.candidate_view_scores = [float(s) for s in result.view_scores]
    response.success = True
    return response


def outputs_from_response(response: SampleCompletions.Response, gripper: GripperConfig) -> OutputMessages:
    """The publications the node would have made for a successful service response (its samples merged into
    one cloud with a ``sample`` field), e.g. to record a service exchange next to topic output."""
    header = response.header
    clouds = [conversions.pointcloud2_to_numpy(c)[0] for c in response.completions]
    points = np.concatenate([np.zeros((0, 3)), *clouds]).astype(np.float32)
    index = np.concatenate([np.zeros(0, np.uint32), *(np.full(len(c), i, np.uint32) for i, c in enumerate(clouds))])
    poses = list(response.grasps.poses)
    return OutputMessages(
        completions=conversions.points_to_pointcloud2(points, header, index),
        known_occupied=response.known_occupied,
        grasps=PoseArray(header=header, poses=poses),
        grasp_candidates=GraspCandidates(header=header, poses=poses, scores=list(response.grasp_scores),
                                         widths=list(response.grasp_widths),
                                         weight_shares=list(response.grasp_weight_shares)),
        grasp_markers=grasp_markers(poses, list(response.grasp_scores), list(response.grasp_widths), header,
                                    gripper))
