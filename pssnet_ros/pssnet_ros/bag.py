"""``pssnet bag IN --out OUT``: the completion node run over a recorded rosbag2, written to a new bag.

Reads a rosbag2 (MCAP or sqlite3: a bag directory, or one ``.mcap`` / ``.db3`` file), synchronises depth,
mask and camera_info by stamp with the node's own :class:`~pssnet_ros.sync.StampSynchronizer` and its
``sync_tolerance``, completes every synchronised set (or every k-th) with the node's pipeline and parameters,
and writes every input message plus ``/pssnet/completions``, ``/pssnet/known_occupied``, ``/pssnet/grasps``
and ``/pssnet/grasp_candidates``, each with the input's header, to OUT.

Bag I/O is the pure-Python ``rosbags`` library (rosbag2_py has no wheel). Messages cross it as raw CDR made
and read by ``rclpy.serialization``, the serialiser the node's publishers use, so the outputs are the node's
own messages field for field; the definitions and type hashes in the bag come from rosbags' Jazzy type store
(equal to rosidl's), with ``pssnet_interfaces/msg/GraspCandidates`` registered from its ``.msg`` file.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.interfaces import Connection, Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore
from sensor_msgs.msg import CameraInfo, Image
from tqdm import tqdm

from pssnet_core.pipeline import CompletionPipeline
from pssnet_ros.completion_io import (
    OUTPUT_TOPICS,
    STREAMS,
    SYNC_QUEUE_SIZE,
    complete_messages,
    load_pipeline,
    output_messages,
    stamp_ns,
)
from pssnet_ros.params import check_values, defaults
from pssnet_ros.sync import StampSynchronizer

GRASP_CANDIDATES_TYPE = "pssnet_interfaces/msg/GraspCandidates"
#: message type each input stream must have
STREAM_TYPES: dict[str, type] = {"depth": Image, "mask": Image, "camera_info": CameraInfo}

_NO_TIME = QosTime(0, 0)  # rmw's "default" (infinite) deadline, lifespan and lease
#: what the node's publishers offer (OUTPUT_QOS): ros2 bag play republishes with it
RELIABLE_QOS = Qos(QosHistory.KEEP_LAST, 2, QosReliability.RELIABLE, QosDurability.VOLATILE, _NO_TIME, _NO_TIME,
                   QosLiveliness.AUTOMATIC, _NO_TIME, False)
#: what a camera driver (and the synthetic camera) offers: rclpy's qos_profile_sensor_data
SENSOR_QOS = Qos(QosHistory.KEEP_LAST, 5, QosReliability.BEST_EFFORT, QosDurability.VOLATILE, _NO_TIME, _NO_TIME,
                 QosLiveliness.AUTOMATIC, _NO_TIME, False)


class BagError(RuntimeError):
    """The bag cannot be read or written as asked (missing topic, wrong type, output exists); says why."""


def ros_type_name(message: Any) -> str:
    """rclpy message (or class) -> its ROS type name, e.g. ``sensor_msgs/msg/Image``."""
    cls = message if isinstance(message, type) else type(message)
    return f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}"


def interface_definition(name: str = "GraspCandidates") -> str:
    """The .msg text of one pssnet_interfaces message: from the installed package share (a sourced ROS
    workspace or this venv), else from this source tree's pssnet_interfaces/."""
    shares = []
    try:
        from ament_index_python.packages import get_package_share_directory

        shares.append(Path(get_package_share_directory("pssnet_interfaces")))
    except (ImportError, LookupError, OSError):  # not sourced: AMENT_PREFIX_PATH unset or without the package
        pass
    source = Path(__file__).resolve().parents[2] / "pssnet_interfaces"  # pssnet_ros/pssnet_ros/bag.py -> the root
    shares += [Path(sys.prefix) / "share" / "pssnet_interfaces", source]
    for share in shares:
        path = share / "msg" / f"{name}.msg"
        if path.is_file():
            return path.read_text()
    raise BagError(f"cannot find {name}.msg of pssnet_interfaces in {', '.join(str(s) for s in shares)}")


def make_typestore() -> Typestore:
    """Jazzy's standard types plus pssnet_interfaces/msg/GraspCandidates (hashes equal rosidl's)."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    typestore.register(get_types_from_msg(interface_definition(), GRASP_CANDIDATES_TYPE))
    return typestore


class BagWriter:
    """Writes a new rosbag2 from rclpy messages or raw CDR; a context manager.

    ``path`` ending in ``.mcap`` gives one self-contained MCAP file (what Foxglove opens and ``ros2 bag``
    reads); any other path a rosbag2 directory with ``storage`` mcap or sqlite3 and its metadata.yaml.
    """

    def __init__(self, path: Path, storage: str = "mcap", overwrite: bool = False) -> None:
        self.path = Path(path)
        self.single_file = self.path.suffix == ".mcap"
        if self.single_file:
            storage = "mcap"
        if storage not in ("mcap", "sqlite3"):
            raise BagError(f"storage must be mcap or sqlite3, got {storage!r}")
        if self.path.exists() or self.path.is_symlink():
            if not overwrite:
                raise BagError(f"{self.path} exists; pass --overwrite to replace it")
            _remove_bag(self.path)
        # rosbags writes a directory; a single .mcap is moved out of it on close.
        self._directory = self.path.with_name(self.path.name + ".partial") if self.single_file else self.path
        if self._directory.exists():
            _remove_bag(self._directory)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.typestore = make_typestore()
        self._writer = Writer(self._directory, version=Writer.VERSION_LATEST,
                              storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
        self._connections: dict[tuple[str, str], Connection] = {}
        self.counts: Counter[str] = Counter()

    def __enter__(self) -> BagWriter:
        self._writer.open()
        return self

    def __exit__(self, exc_type: object, exc: object, traceback: object) -> None:
        if exc_type is not None:
            self._writer.abort()
            shutil.rmtree(self._directory, ignore_errors=True)
            return
        self._writer.close()
        if self.single_file:
            (self._directory / f"{self._directory.name}.mcap").replace(self.path)
            shutil.rmtree(self._directory)

    def _connection(self, topic: str, msgtype: str, qos: Sequence[Qos], msgdef: str = "",
                    digest: str = "") -> Connection:
        key = (topic, msgtype)
        if key not in self._connections:
            if msgdef and digest:  # a copied topic keeps the definition it was recorded with
                self._connections[key] = self._writer.add_connection(topic, msgtype, msgdef=msgdef, rihs01=digest,
                                                                     offered_qos_profiles=qos)
            else:
                self._connections[key] = self._writer.add_connection(topic, msgtype, typestore=self.typestore,
                                                                     offered_qos_profiles=qos)
        return self._connections[key]

    def write(self, topic: str, message: Any, log_ns: int, qos: Qos = RELIABLE_QOS) -> None:
        """Writes one rclpy message, serialised exactly as a publisher would send it."""
        self.write_raw(topic, ros_type_name(message), serialize_message(message), log_ns, [qos])

    def write_raw(self, topic: str, msgtype: str, data: bytes, log_ns: int, qos: Sequence[Qos] = (),
                  msgdef: str = "", digest: str = "") -> None:
        """Writes serialised CDR as it is (definition and hash from the type store unless both are given)."""
        self._writer.write(self._connection(topic, msgtype, qos, msgdef, digest), int(log_ns), data)
        self.counts[topic] += 1

    def copy(self, connection: Connection, data: bytes, log_ns: int) -> None:
        """Copies one message read from another bag, with its recorded definition, hash and QoS."""
        digest = connection.digest if connection.digest.startswith("RIHS01_") else ""
        self.write_raw(connection.topic, connection.msgtype, data, log_ns,
                       list(getattr(connection.ext, "offered_qos_profiles", [])), connection.msgdef.data, digest)


def _remove_bag(path: Path) -> None:
    """Removes an earlier output, refusing anything that does not look like a bag (never a random folder)."""
    if path.is_dir() and not path.is_symlink():
        if not (path / "metadata.yaml").is_file() and not any(path.glob("*.mcap")) and not any(path.glob("*.db3")):
            raise BagError(f"{path} exists and is not a rosbag2 directory; not removing it")
        shutil.rmtree(path)
    elif path.suffix in (".mcap", ".db3") or path.is_symlink():
        path.unlink()
    else:
        raise BagError(f"{path} exists and is not a bag file; not removing it")


# ----------------------------------------------------------------------------------------- parameters
def read_params_file(path: Path, node_name: str = "pssnet") -> dict[str, Any]:
    """The node's parameters from a ROS parameter file (``/**`` first, then sections naming the node)."""
    try:
        document = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as error:
        raise BagError(f"cannot read parameter file {path}: {error}") from None
    if not isinstance(document, dict):
        raise BagError(f"parameter file {path} is not a mapping of node names")
    values: dict[str, Any] = {}
    wildcards = ("/**", "**")
    sections = sorted((k for k in document if k in wildcards or str(k).rstrip("/").split("/")[-1] == node_name),
                      key=lambda k: k not in wildcards)  # wildcard sections first: the node's own override them
    for key in sections:
        section = document[key]
        if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
            values.update(section["ros__parameters"])
    if not sections or not values:
        raise BagError(f"parameter file {path} has no ros__parameters for /** or {node_name}")
    return values


def parse_param(text: str) -> tuple[str, Any]:
    """``NAME:=VALUE`` (as after ``--ros-args -p``) -> (name, value); the value is read as YAML, as rcl does."""
    name, sep, value = text.partition(":=")
    if not sep or not name:
        raise BagError(f"parameter {text!r} must be NAME:=VALUE")
    try:
        return name.strip(), yaml.safe_load(value)
    except yaml.YAMLError as error:
        raise BagError(f"parameter {name}: cannot read value {value!r}: {error}") from None


def node_parameters(overrides: dict[str, Any]) -> dict[str, Any]:
    """The node's defaults with ``overrides`` applied, checked by the node's own rules."""
    values = defaults()
    values.update(overrides)
    reason = check_values(values)
    if reason:
        raise BagError(f"invalid parameters: {reason}")
    return values


# --------------------------------------------------------------------------------------------- the tool
@dataclass(frozen=True)
class BagToolConfig:
    """What ``pssnet bag`` does.

    Attributes:
        input: rosbag2 directory, or one .mcap / .db3 file.
        output: output bag (a directory, or a .mcap file).
        topics: stream (depth, mask, camera_info) -> topic name in the bag.
        every: complete every k-th synchronised set (1 = all).
        storage: mcap or sqlite3 (for a directory output).
        overwrite: replace an existing output bag.
        parameters: the node's parameters (complete and checked, see :func:`node_parameters`).
        progress: show a tqdm progress bar.
    """

    input: Path
    output: Path
    topics: dict[str, str] = field(default_factory=lambda: {s: f"/{s}" for s in STREAMS})
    every: int = 1
    storage: str = "mcap"
    overwrite: bool = False
    parameters: dict[str, Any] = field(default_factory=defaults)
    progress: bool = True

    def __post_init__(self) -> None:
        if self.every < 1:
            raise BagError(f"--every must be >= 1, got {self.every}")
        if set(self.topics) != set(STREAMS):
            raise BagError(f"topics must name {', '.join(STREAMS)}, got {sorted(self.topics)}")
        outputs = set(OUTPUT_TOPICS.values())
        if any(t in outputs for t in self.topics.values()):
            raise BagError("an input topic cannot be one of the outputs " + ", ".join(sorted(outputs)))


@dataclass
class BagSummary:
    """Counts of one run.

    Attributes:
        messages_read: messages in the input bag (all topics).
        sets_synchronised: depth/mask/camera_info sets matched within sync_tolerance.
        sets_completed: sets completed and written.
        sets_skipped: sets left out by ``every``.
        sets_failed: reason -> sets the node would have dropped (bad encoding, calibration, empty mask, ...).
        messages_unsynchronised: input-stream messages that joined no set (no partner within the tolerance).
        messages_malformed: reason -> input-stream messages that could not be deserialised.
        topics_not_copied: input topics left out (outputs of an earlier run: this run writes its own).
        written: topic -> messages written.
        seconds: wall time of the run.
        completion_seconds: time inside the pipeline (conversion to output messages excluded).
    """

    messages_read: int = 0
    sets_synchronised: int = 0
    sets_completed: int = 0
    sets_skipped: int = 0
    sets_failed: Counter[str] = field(default_factory=Counter)
    messages_unsynchronised: int = 0
    messages_malformed: Counter[str] = field(default_factory=Counter)
    topics_not_copied: list[str] = field(default_factory=list)
    written: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    completion_seconds: float = 0.0

    @property
    def failures(self) -> int:
        """Sets that failed plus input messages that could not be used."""
        return sum(self.sets_failed.values()) + sum(self.messages_malformed.values()) + self.messages_unsynchronised

    def report(self) -> str:
        """The summary printed at the end of a run."""
        rate = self.sets_completed / self.completion_seconds if self.completion_seconds else 0.0
        failed = sum(self.sets_failed.values())
        lines = [f"messages read: {self.messages_read}; sets synchronised: {self.sets_synchronised}, completed: "
                 f"{self.sets_completed}, skipped (--every): {self.sets_skipped}, failed: {failed}",
                 f"time: {self.seconds:.1f} s in all, {self.completion_seconds:.1f} s completing "
                 f"({rate:.2f} sets/s)"]
        for reason, count in self.sets_failed.most_common():
            lines.append(f"  failed set x{count}: {reason}")
        for reason, count in self.messages_malformed.most_common():
            lines.append(f"  malformed message x{count}: {reason}")
        if self.messages_unsynchronised:
            lines.append(f"  unsynchronised messages: {self.messages_unsynchronised} (no partner within "
                         "sync_tolerance)")
        if self.topics_not_copied:
            lines.append(f"  not copied (this run writes its own): {', '.join(self.topics_not_copied)}")
        lines.append("written: " + ", ".join(f"{t} {n}" for t, n in self.written.items()))
        return "\n".join(lines)


def _input_connections(reader: Reader, topics: dict[str, str]) -> None:
    """Checks that every input stream is in the bag with the type the node subscribes with."""
    available = {c.topic: c.msgtype for c in reader.connections}
    listing = ", ".join(f"{t} ({m})" for t, m in sorted(available.items())) or "none"
    for stream, topic in topics.items():
        expected = ros_type_name(STREAM_TYPES[stream])
        if topic not in available:
            raise BagError(f"{stream} topic {topic} is not in the bag (set --{stream.replace('_', '-')}-topic); "
                           f"its topics: {listing}")
        if available[topic] != expected:
            raise BagError(f"{stream} topic {topic} has type {available[topic]}; the node subscribes {expected}")


def process_bag(config: BagToolConfig) -> BagSummary:
    """Runs the node's pipeline over every (or every k-th) synchronised set of ``config.input``.

    Raises:
        BagError: unreadable input, a missing input topic, an existing output, bad parameters or model.
    """
    t0 = time.perf_counter()
    values = config.parameters
    stream_of = {topic: stream for stream, topic in config.topics.items()}
    sync = StampSynchronizer(STREAMS, values["sync_tolerance"], queue_size=SYNC_QUEUE_SIZE)
    summary = BagSummary()
    try:
        reader = Reader(config.input)
        reader.open()
    except Exception as error:  # rosbags raises its own errors, OSError or sqlite/yaml errors: all mean unreadable
        raise BagError(f"cannot read {config.input}: {type(error).__name__}: {error}") from None
    try:
        _input_connections(reader, config.topics)  # before loading the model: a wrong topic name fails at once
        try:
            pipeline = load_pipeline(values)
        except ValueError as error:
            raise BagError(str(error)) from None
        outputs = set(OUTPUT_TOPICS.values())
        summary.topics_not_copied = sorted({c.topic for c in reader.connections if c.topic in outputs})
        with BagWriter(config.output, config.storage, config.overwrite) as writer, \
                tqdm(total=reader.message_count, unit="msg", desc="pssnet bag",
                     disable=not config.progress) as progress:
            for connection, log_ns, data in reader.messages():
                summary.messages_read += 1
                progress.update()
                if connection.topic not in outputs:
                    writer.copy(connection, data, log_ns)
                stream = stream_of.get(connection.topic)
                if stream is None:
                    continue
                try:
                    message = deserialize_message(bytes(data), STREAM_TYPES[stream])
                except Exception as error:  # rclpy raises its RMWError (not exported) for bad CDR
                    summary.messages_malformed[f"{connection.topic}: {error}"] += 1
                    continue
                synced = sync.add(stream, stamp_ns(message.header), message)
                if synced is None:
                    continue
                summary.sets_synchronised += 1
                if (summary.sets_synchronised - 1) % config.every:
                    summary.sets_skipped += 1
                    continue
                _complete(pipeline, values, synced.messages, writer, log_ns, summary)
                progress.set_postfix(completed=summary.sets_completed, failed=sum(summary.sets_failed.values()))
            summary.written = dict(writer.counts)
    finally:
        reader.close()
    summary.messages_unsynchronised = sync.stats.received - len(STREAMS) * sync.stats.matched
    summary.seconds = time.perf_counter() - t0
    return summary


def _complete(pipeline: CompletionPipeline, values: dict[str, Any], messages: dict[str, Any], writer: BagWriter,
              log_ns: int, summary: BagSummary) -> None:
    """Completes one set as the node's continuous mode does; its outputs are logged at the time the set's last
    message was recorded (when the node could have started on it), so playback keeps inputs and outputs in order."""
    t0 = time.perf_counter()
    try:
        result, header = complete_messages(pipeline, messages["depth"], messages["mask"], messages["camera_info"],
                                           values["depth_scale"], 0, values["continuous_grasps"])
    except ValueError as error:  # what the node drops with a warning
        summary.sets_failed[str(error)] += 1
        return
    except Exception as error:  # the node never dies of one bad set; neither does a long bag run
        summary.sets_failed[f"internal error: {type(error).__name__}: {error}"] += 1
        return
    summary.completion_seconds += time.perf_counter() - t0
    for topic, message in output_messages(result, header, pipeline.config.grasps.gripper).by_topic().items():
        writer.write(topic, message, log_ns)
    summary.sets_completed += 1


def run_command(args: argparse.Namespace) -> int:
    """``pssnet bag`` (arguments from :mod:`pssnet_ros.bag_cli`); returns the exit code."""
    try:
        overrides = read_params_file(args.params_file) if args.params_file else {}
        overrides.update(parse_param(p) for p in args.param)
        config = BagToolConfig(input=args.input, output=args.out, every=args.every, storage=args.storage,
                               overwrite=args.overwrite, parameters=node_parameters(overrides),
                               topics={"depth": _absolute(args.depth_topic), "mask": _absolute(args.mask_topic),
                                       "camera_info": _absolute(args.camera_info_topic)},
                               progress=not args.no_progress)
        summary = process_bag(config)
    except BagError as error:
        print(f"[pssnet bag] error: {error}", file=sys.stderr)
        return 2
    print(summary.report())
    print(f"wrote {config.output}")
    return 0 if summary.sets_completed else 1


def _absolute(topic: str) -> str:
    """Bags record absolute names; the node's relative ``depth`` is ``/depth`` in the root namespace."""
    return topic if topic.startswith("/") else f"/{topic}"
