"""completion_node: samples diverse plausible completions of a segmented object and ranks grasps across them.

Interface (node name ``pssnet``; relative names are remappable):

- subscribes ``depth`` (sensor_msgs/Image 32FC1 m | 16UC1), ``mask`` (mono8 | 8UC1), ``camera_info``;
  synchronised by stamp within ``sync_tolerance``; best-effort QoS, so reliable and sensor-data publishers
  both connect.
- serves ``~/sample_completions`` (pssnet_interfaces/srv/SampleCompletions) -> /pssnet/sample_completions,
  and ``~/get_stats`` (std_srvs/Trigger: counters as JSON, see :meth:`CompletionNode.stats`).
- publishes in continuous mode ``~/completions`` (PointCloud2 x, y, z + ``sample``), ``~/known_occupied``,
  ``~/grasps`` (PoseArray, best first), ``~/grasp_candidates`` (pssnet_interfaces/msg/GraspCandidates).

All outputs carry the input's header. The node only converts messages; the work is done by
:class:`pssnet_core.pipeline.CompletionPipeline`.
"""

from __future__ import annotations

import json
import sys
import threading
import time
import traceback
from collections.abc import Sequence
from typing import Any

import rclpy
from geometry_msgs.msg import PoseArray
from pssnet_interfaces.msg import GraspCandidates
from pssnet_interfaces.srv import SampleCompletions
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from pssnet_core.pipeline import CompletionPipeline, PipelineResult
from pssnet_ros import conversions
from pssnet_ros.newest_slot import NewestSlot
from pssnet_ros.params import PARAMETERS, check_values, markdown_table, pipeline_config
from pssnet_ros.processes import clean_stale_shm
from pssnet_ros.spinning import spin_until_shutdown
from pssnet_ros.sync import StampSynchronizer, SyncedSet

NODE_NAME = "pssnet"
STREAMS = ("depth", "mask", "camera_info")
WARN_THROTTLE_S = 2.0

#: Best effort + volatile matches both best-effort (sensor data) and reliable publishers.
INPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.VOLATILE)
#: Reliable publishers match reliable and best-effort subscribers alike.
OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: Requests wait in DDS while the node answers one at a time; the default services QoS keeps only the last 10,
#: so with more waiting clients the oldest requests were dropped unanswered (16 clients: 41 of 755 lost,
#: RELIABILITY.md). 64 waiting 640x480 requests hold about 100 MB at most.
SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=64, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)


class StartupError(RuntimeError):
    """The node cannot start (bad parameters, missing or corrupt model); the message says why."""


class InputError(ValueError):
    """A request or a topic set cannot be used (no data yet, stale, unsynchronised stamps)."""


def stamp_ns(header: Header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


class CompletionNode(Node):
    """The thin ROS layer over :class:`CompletionPipeline` (see the module docstring for the interface)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        try:
            self._values = self._declare()
            self.pipeline = self._load_pipeline()
        except StartupError:
            self.destroy_node()
            raise
        # Guards the counters, the latest set and the slot's put/done, so that stats() is one consistent snapshot.
        self._lock = threading.Lock()
        self._counters = {"sets_synchronised": 0, "sets_processed": 0, "sets_dropped_stale": 0,
                          "sets_dropped_invalid": 0, "service_calls": 0, "service_failures": 0}
        self._latest: SyncedSet | None = None  # newest synchronised set (the service's default input)
        # Continuous mode: the worker completes the newest pending set at most max_rate_hz; a newer set replaces
        # an unprocessed one (one slot: bounded memory, no queue).
        self._slot: NewestSlot[SyncedSet] = NewestSlot(self._values["max_rate_hz"],
                                                       paused=not self._values["continuous"])
        self._sync = StampSynchronizer(STREAMS, self._values["sync_tolerance"], queue_size=10)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        topics = MutuallyExclusiveCallbackGroup()
        self.create_subscription(Image, "depth", lambda m: self._on_input("depth", m), INPUT_QOS,
                                 callback_group=topics)
        self.create_subscription(Image, "mask", lambda m: self._on_input("mask", m), INPUT_QOS,
                                 callback_group=topics)
        self.create_subscription(CameraInfo, "camera_info", lambda m: self._on_input("camera_info", m), INPUT_QOS,
                                 callback_group=topics)
        # Inference has its own group so that topic callbacks keep flowing while a request runs.
        self.create_service(SampleCompletions, "~/sample_completions", self._on_sample_completions,
                            qos_profile=SERVICE_QOS, callback_group=MutuallyExclusiveCallbackGroup())
        self.create_service(Trigger, "~/get_stats", self._on_get_stats, callback_group=topics)
        self._pub_completions = self.create_publisher(PointCloud2, "~/completions", OUTPUT_QOS)
        self._pub_known = self.create_publisher(PointCloud2, "~/known_occupied", OUTPUT_QOS)
        self._pub_grasps = self.create_publisher(PoseArray, "~/grasps", OUTPUT_QOS)
        self._pub_candidates = self.create_publisher(GraspCandidates, "~/grasp_candidates", OUTPUT_QOS)

        self._worker = threading.Thread(target=self._continuous_loop, name="pssnet_continuous", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------------------------------ set-up
    def _declare(self) -> dict[str, Any]:
        values: dict[str, Any] = {}
        for spec in PARAMETERS:
            default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
            try:
                values[spec.name] = self.declare_parameter(spec.name, default, spec.descriptor()).value
            except (InvalidParameterValueException, InvalidParameterTypeException) as error:
                raise StartupError(f"invalid parameter {spec.name}: {error}") from None
        values["up_vector"] = [float(v) for v in values["up_vector"]]
        reason = check_values(values)
        if reason:
            raise StartupError(f"invalid parameters: {reason}")
        return values

    def _load_pipeline(self) -> CompletionPipeline:
        from pssnet_core.models.checkpoint import CheckpointError  # imports torch

        values = self._values
        try:
            config = pipeline_config(values)
        except ValueError as error:
            raise StartupError(f"invalid parameters: {error}") from None
        try:
            pipeline = CompletionPipeline.from_checkpoint(values["model_path"] or None, None, device=values["device"],
                                                          threads=values["threads"] or None)
        except CheckpointError as error:
            raise StartupError(f"cannot load the completion model: {error}") from None
        except ValueError as error:  # e.g. device cuda without CUDA
            raise StartupError(f"cannot load the completion model: {error}") from None
        try:
            pipeline.config = config
        except ValueError as error:
            raise StartupError(f"invalid parameters for this model: {error}") from None
        completer = pipeline.completer
        self.get_logger().info(
            f"model {completer.model_name} {completer.grid_size}^3 from {completer.info.get('path')} on "
            f"{values['device']} ({completer.precision}); voxel {pipeline.grid_config().voxel_size * 1000:.2f} mm")
        return pipeline

    # -------------------------------------------------------------------------------------- parameters
    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
        values = dict(self._values)
        for param in params:
            values[param.name] = param.value
        reason = check_values(values)
        if reason is None:
            try:
                self.pipeline.check_config(pipeline_config(values))
            except ValueError as error:
                reason = str(error)
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _apply_parameters(self, params: list[Parameter]) -> None:
        for param in params:
            self._values[param.name] = param.value
        self.pipeline.config = pipeline_config(self._values)
        if any(p.name == "sync_tolerance" for p in params):
            self._sync.tolerance_s = self._values["sync_tolerance"]
        self._slot.max_rate_hz = self._values["max_rate_hz"]
        self._slot.paused = not self._values["continuous"]

    # ------------------------------------------------------------------------------------------ topics
    def _count(self, key: str, n: int = 1) -> int:
        with self._lock:
            self._counters[key] += n
            return self._counters[key]

    def _on_input(self, stream: str, msg: Image | CameraInfo) -> None:
        synced = self._sync.add(stream, stamp_ns(msg.header), msg)
        if synced is None:
            return
        with self._lock:
            self._counters["sets_synchronised"] += 1
            self._latest = synced
            if self._values["continuous"]:
                self._slot.put(synced)

    def _age_s(self, synced: SyncedSet) -> float:
        return (self.get_clock().now().nanoseconds - synced.stamp_ns) * 1e-9

    def _continuous_loop(self) -> None:
        while (synced := self._slot.take()) is not None:
            self._complete_topic_set(synced)

    def _finish(self, outcome: str) -> int:
        """Counts the outcome of the set in progress and frees the slot in one step (stats stay consistent)."""
        with self._lock:
            self._counters[outcome] += 1
            self._slot.done()
            return self._counters[outcome]

    def _complete_topic_set(self, synced: SyncedSet) -> None:
        max_age = self._values["max_input_age"]
        age = self._age_s(synced)
        if max_age > 0 and age > max_age:
            count = self._finish("sets_dropped_stale")
            self.get_logger().warning(f"dropped a stale input set ({count} so far): {age:.2f} s old, "
                                      f"max_input_age {max_age} s", throttle_duration_sec=WARN_THROTTLE_S)
            return
        try:
            result, header = self._run(synced.messages["depth"], synced.messages["mask"],
                                       synced.messages["camera_info"], 0, self._values["continuous_grasps"])
            self._publish(result, header)
        except ValueError as error:
            count = self._finish("sets_dropped_invalid")
            self.get_logger().warning(f"dropped an input set ({count} so far): {error}",
                                      throttle_duration_sec=WARN_THROTTLE_S)
            return
        except Exception as error:  # never let one bad set kill the worker
            count = self._finish("sets_dropped_invalid")
            self.get_logger().error(f"completion failed ({count} dropped so far): {type(error).__name__}: {error}\n"
                                    f"{traceback.format_exc()}", throttle_duration_sec=WARN_THROTTLE_S)
            return
        self._finish("sets_processed")

    def _publish(self, result: PipelineResult, header: Header) -> None:
        points, index = result.merged()
        self._pub_completions.publish(conversions.points_to_pointcloud2(points, header, index))
        self._pub_known.publish(conversions.points_to_pointcloud2(result.known_occupied, header))
        poses, scores, widths = self._grasp_fields(result)
        self._pub_grasps.publish(PoseArray(header=header, poses=poses))
        self._pub_candidates.publish(GraspCandidates(header=header, poses=poses, scores=scores, widths=widths))

    @staticmethod
    def _grasp_fields(result: PipelineResult) -> tuple[list, list[float], list[float]]:
        grasps = result.grasps
        if grasps is None or len(grasps.scores) == 0:
            return [], [], []
        poses = [conversions.matrix_to_pose(m) for m in grasps.poses]
        return poses, [float(s) for s in grasps.scores], [float(w) for w in grasps.widths]

    # ----------------------------------------------------------------------------------------- service
    def _run(self, depth_msg: Image, mask_msg: Image, info_msg: CameraInfo, num_samples: int,
             compute_grasps: bool) -> tuple[PipelineResult, Header]:
        depth = conversions.depth_to_metres(depth_msg, self._values["depth_scale"])
        mask = conversions.mask_to_numpy(mask_msg)
        intrinsics = conversions.camera_info_to_intrinsics(info_msg)
        return self.pipeline.run(depth, mask, intrinsics, num_samples, compute_grasps), depth_msg.header

    def _request_input(self, request: SampleCompletions.Request) -> tuple[Image, Image, CameraInfo]:
        if request.depth.height == 0:
            with self._lock:
                synced = self._latest
            if synced is None:
                names = ", ".join(self.resolve_topic_name(s) for s in STREAMS)
                raise InputError(f"request has no depth image and no synchronised set has arrived on {names} "
                                 f"yet (sync_tolerance {self._values['sync_tolerance']} s)")
            max_age = self._values["max_input_age"]
            age = self._age_s(synced)
            if max_age > 0 and age > max_age:
                raise InputError(f"the latest synchronised input is stale: {age:.2f} s old, "
                                 f"max_input_age {max_age} s")
            return synced.messages["depth"], synced.messages["mask"], synced.messages["camera_info"]
        tolerance = self._values["sync_tolerance"]
        depth_stamp = stamp_ns(request.depth.header)
        for name, header in (("mask", request.mask.header), ("camera_info", request.camera_info.header)):
            other = stamp_ns(header)
            # An unset stamp (0) means the caller does not claim a time for that part: nothing to compare.
            if other and depth_stamp and abs(other - depth_stamp) > tolerance * 1e9:
                raise InputError(f"unsynchronised request: depth stamp {depth_stamp * 1e-9:.6f} s and {name} stamp "
                                 f"{other * 1e-9:.6f} s differ by {abs(other - depth_stamp) * 1e-9:.6f} s "
                                 f"(sync_tolerance {tolerance} s)")
        return request.depth, request.mask, request.camera_info

    def _on_sample_completions(self, request: SampleCompletions.Request,
                               response: SampleCompletions.Response) -> SampleCompletions.Response:
        self._count("service_calls")
        t0 = time.perf_counter()
        try:
            depth_msg, mask_msg, info_msg = self._request_input(request)
            response.header = depth_msg.header
            result, header = self._run(depth_msg, mask_msg, info_msg, int(request.num_samples),
                                       bool(request.compute_grasps))
        except ValueError as error:
            count = self._count("service_failures")
            response.success, response.message = False, str(error)
            self.get_logger().warning(f"sample_completions refused ({count} so far): {error}",
                                      throttle_duration_sec=WARN_THROTTLE_S)
            return response
        except Exception as error:  # an answer even for a bug: the caller must not hang
            self._count("service_failures")
            response.success, response.message = False, f"internal error: {type(error).__name__}: {error}"
            self.get_logger().error(f"sample_completions failed: {traceback.format_exc()}")
            return response
        response.header = header
        response.voxel_size = float(result.voxel_size)
        response.known_occupied = conversions.points_to_pointcloud2(result.known_occupied, header)
        response.completions = [conversions.points_to_pointcloud2(c, header) for c in result.completions]
        poses, scores, widths = self._grasp_fields(result)
        response.grasps = PoseArray(header=header, poses=poses)
        response.grasp_scores, response.grasp_widths = scores, widths
        response.success = True
        points = sum(len(c) for c in result.completions)
        response.message = (f"{result.num_samples} samples, {points} voxels, {len(poses)} grasps, seed "
                            f"{result.seed}, {(time.perf_counter() - t0) * 1000:.0f} ms")
        return response

    def _on_get_stats(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        del request
        stats = self.stats()
        response.success, response.message = True, json.dumps(stats, sort_keys=True)
        return response

    def stats(self) -> dict[str, int]:
        """Counters, one consistent snapshot.

        ``sets_synchronised`` (all synchronised sets), ``sets_processed`` (completed and published in continuous
        mode), ``sets_dropped_superseded`` / ``_stale`` / ``_invalid``, ``sets_pending`` and ``sets_in_progress``
        (0 or 1 each), ``service_calls``, ``service_failures``, ``messages_received``, ``messages_unmatched``,
        and ``latest_set_stamp_ns`` (stamp of the newest synchronised set, 0 before the first). While continuous
        mode is on, every synchronised set is accounted for: synchronised = processed + superseded + stale +
        invalid + pending + in_progress.
        """
        with self._lock:
            stats = dict(self._counters)
            slot = self._slot.stats()
            stats.update(sets_dropped_superseded=slot.superseded, sets_pending=slot.pending,
                         sets_in_progress=slot.in_progress,
                         latest_set_stamp_ns=self._latest.stamp_ns if self._latest is not None else 0)
        sync = self._sync.stats
        stats.update(messages_received=sync.received, messages_unmatched=sync.dropped_unmatched)
        return stats

    def destroy_node(self) -> None:
        if hasattr(self, "_worker"):
            self._slot.close()
            if self._worker.is_alive() and self._worker is not threading.current_thread():
                self._worker.join(timeout=10.0)
        super().destroy_node()


def usage() -> str:
    return ("usage: completion_node [--help] [--ros-args -p NAME:=VALUE ... --params-file FILE -r FROM:=TO]\n\n"
            "PSSNet completion node: diverse plausible shape completions of a segmented object from one depth\n"
            "image, and parallel-jaw grasps ranked across them.\n\n"
            "Node name: pssnet. Subscribes: depth, mask, camera_info (remappable). Serves:\n"
            "/pssnet/sample_completions (pssnet_interfaces/srv/SampleCompletions), /pssnet/get_stats.\n"
            "Publishes (continuous mode): /pssnet/completions, /pssnet/known_occupied, /pssnet/grasps,\n"
            "/pssnet/grasp_candidates.\n\nParameters:\n" + markdown_table() + "\n")


def main(args: Sequence[str] | None = None) -> int:
    """Entry point (console script and ``ros2 run pssnet_ros completion_node``); returns the exit code."""
    argv = list(sys.argv if args is None else args)
    try:
        plain_args = remove_ros_args(argv)[1:]
    except RuntimeError as error:  # rclpy's RCLInvalidROSArgsError: a malformed --ros-args section
        print(f"[completion_node] error: invalid ROS arguments: {error}", file=sys.stderr)
        return 2
    if any(a in ("-h", "--help") for a in plain_args):
        print(usage())
        return 0
    # A predecessor killed with -9 leaves its Fast DDS shared memory (32 MiB per participant): remove what
    # belongs to dead processes only, before this process's own participant exists.
    shm = clean_stale_shm()
    rclpy.init(args=argv)
    node: CompletionNode | None = None
    code = 0
    try:
        node = CompletionNode()
        executor = MultiThreadedExecutor(num_threads=4)
        executor.add_node(node)
        if shm.removed:
            node.get_logger().info(f"removed {len(shm.removed)} stale Fast DDS shared-memory files of dead "
                                   f"processes ({shm.freed_bytes / 2**20:.1f} MiB): {' '.join(shm.removed)}")
        node.get_logger().info(f"ready: serving {node.resolve_service_name('~/sample_completions')}, continuous "
                               f"{'on' if node.get_parameter('continuous').value else 'off'}")
        spin_until_shutdown(executor)
    except StartupError as error:
        print(f"[completion_node] error: {error}", file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
