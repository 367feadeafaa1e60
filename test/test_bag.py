"""``pssnet bag``: recorded depth/mask/camera_info in (MCAP and sqlite3), the node's outputs out, read back."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader
from sensor_msgs.msg import Image, PointCloud2
from std_msgs.msg import Header, String
from test_node_helpers import node_checkpoint

from pssnet_core.grasps import GripperConfig
from pssnet_core.pipeline import CompletionPipeline, PipelineConfig
from pssnet_ros.bag import (
    SENSOR_QOS,
    BagError,
    BagSummary,
    BagToolConfig,
    BagWriter,
    make_typestore,
    node_parameters,
    process_bag,
    read_params_file,
)
from pssnet_ros.bag_cli import register
from pssnet_ros.completion_io import OUTPUT_TOPICS, output_messages, stamp_ns
from pssnet_ros.conversions import pointcloud2_to_numpy
from pssnet_testing.demo import write_demo_bag
from pssnet_testing.synthetic_camera import FRAME_ID, SceneOptions, render_scene, view_messages

T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 200_000_000  # the synthetic camera's 5 Hz
GOOD_SETS = 4
SAMPLES = 4
INPUTS = ("/depth", "/mask", "/camera_info")


def header_at(t_ns: int) -> Header:
    return Header(stamp=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id=FRAME_ID)


@pytest.fixture(scope="module")
def view():
    return render_scene(SceneOptions())


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    return node_checkpoint(tmp_path_factory.mktemp("model"))[0]


@pytest.fixture(scope="module")
def parameters(view, checkpoint) -> dict:
    return node_parameters({"model_path": str(checkpoint), "num_samples": SAMPLES, "threads": 1,
                            "up_vector": [float(v) for v in view.up]})


def record(path: Path, view, storage: str, depth_encoding: str) -> list[int]:
    """What a recording of the synthetic camera holds, plus what real bags hold too: a set whose mask has an
    encoding the node refuses, a camera_info with no partners, a corrupt depth message, an unrelated topic.
    Returns the stamps of the good sets."""
    stamps = [T0_NS + i * PERIOD_NS for i in range(GOOD_SETS)]
    with BagWriter(path, storage) as writer:
        for stamp in stamps:
            for topic, message in zip(INPUTS, view_messages(view, depth_encoding, header_at(stamp)), strict=True):
                writer.write(topic, message, stamp + 3_000_000, SENSOR_QOS)  # received 3 ms after capture
            writer.write("/chatter", String(data="hello"), stamp + 4_000_000)
        bad = stamps[-1] + PERIOD_NS
        depth, _, info = view_messages(view, depth_encoding, header_at(bad))
        colour = Image(header=header_at(bad), height=2, width=2, encoding="bgr8", step=6, data=bytes(12))
        for topic, message in zip(INPUTS, (depth, colour, info), strict=True):
            writer.write(topic, message, bad + 3_000_000, SENSOR_QOS)
        lonely = bad + 10 * PERIOD_NS
        writer.write("/camera_info", view_messages(view, depth_encoding, header_at(lonely))[2], lonely, SENSOR_QOS)
        writer.write_raw("/depth", "sensor_msgs/msg/Image", b"\x00\x01\x00\x00 not an image", lonely + 1)
    return stamps


def read_back(path: Path) -> dict[str, list[tuple[int, object, bytes]]]:
    """Topic -> [(log time, message as the bag's own definitions decode it, raw CDR)] (rosbags, not rclpy)."""
    typestore = make_typestore()
    topics: dict[str, list] = {}
    with Reader(path) as reader:
        for connection, log_ns, data in reader.messages():
            try:
                decoded = typestore.deserialize_cdr(data, connection.msgtype)
            except Exception:  # the corrupt depth message is copied as it was recorded
                decoded = None
            topics.setdefault(connection.topic, []).append((log_ns, decoded, bytes(data)))
    return topics


#: recording -> (storage, depth encoding); tests that need one storage only use the MCAP one
RECORDINGS = {"mcap": ("mcap", "32FC1"), "sqlite3": ("sqlite3", "16UC1")}


@pytest.fixture(scope="module")
def recordings(tmp_path_factory, view) -> dict[str, tuple[Path, list[int]]]:
    """Name -> (bag directory, stamps of its good sets)."""
    found = {}
    for name, (storage, encoding) in RECORDINGS.items():
        path = tmp_path_factory.mktemp(name) / "recorded"
        found[name] = path, record(path, view, storage, encoding)
    return found


@pytest.fixture(scope="module")
def runs(recordings, parameters) -> dict[str, tuple[Path, BagSummary, list[int]]]:
    """Name -> (output bag, summary, stamps of the good sets): the tool run once on each recording."""
    done = {}
    for name, (path, stamps) in recordings.items():
        out = path.parent / "completed"
        summary = process_bag(BagToolConfig(input=path, output=out, storage=RECORDINGS[name][0],
                                            parameters=parameters, progress=False))
        done[name] = out, summary, stamps
    return done


def header_of(message):
    """A recorded message's header (a MarkerArray has none: its first marker's, the DELETEALL)."""
    return message.markers[0].header if hasattr(message, "markers") else message.header


@pytest.mark.parametrize("name", list(RECORDINGS))
def test_output_holds_the_inputs_and_the_node_outputs_with_input_stamps_and_frames(runs, name):
    out, summary, stamps = runs[name]
    topics = read_back(out)
    assert set(topics) == {*INPUTS, "/chatter", *OUTPUT_TOPICS.values()}
    assert [len(topics[t]) for t in INPUTS] == [GOOD_SETS + 2, GOOD_SETS + 1, GOOD_SETS + 2]  # copied as recorded
    assert len(topics["/chatter"]) == GOOD_SETS
    for topic in OUTPUT_TOPICS.values():
        entries = topics[topic]
        assert len(entries) == GOOD_SETS
        assert [stamp_ns(header_of(m)) for _, m, _ in entries] == stamps
        assert {header_of(m).frame_id for _, m, _ in entries} == {FRAME_ID}
        assert [log for log, _, _ in entries] == [s + 3_000_000 for s in stamps]  # when the set was complete
    cloud = topics["/pssnet/completions"][0][1]
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "sample"] and cloud.width > 0
    candidates = topics["/pssnet/grasp_candidates"][0][1]
    assert len(candidates.poses) == len(candidates.scores) == len(candidates.widths) > 0
    assert summary.sets_synchronised == GOOD_SETS + 1 and summary.sets_completed == GOOD_SETS
    assert summary.written["/pssnet/grasps"] == GOOD_SETS


@pytest.mark.parametrize("name", list(RECORDINGS))
def test_unsynchronised_and_malformed_input_are_counted_as_failures(runs, name):
    _, summary, _ = runs[name]
    assert sum(summary.sets_failed.values()) == 1
    assert "mask has encoding 'bgr8'" in next(iter(summary.sets_failed))
    assert summary.messages_unsynchronised == 1
    assert list(summary.messages_malformed.values()) == [1]
    assert next(iter(summary.messages_malformed)).startswith("/depth: ")
    assert summary.failures == 3
    report = summary.report()
    assert "completed: 4" in report and "failed set x1: mask has encoding 'bgr8'" in report
    assert "unsynchronised messages: 1" in report and "malformed message x1: /depth" in report


def test_every_second_set_halves_the_work_and_a_single_mcap_file_reads_back(recordings, parameters):
    path, stamps = recordings["mcap"]
    out = path.parent / "every2.mcap"
    summary = process_bag(BagToolConfig(input=path, output=out, every=2, parameters=parameters, progress=False))
    assert summary.sets_synchronised == GOOD_SETS + 1
    assert summary.sets_skipped == 2 and summary.sets_completed + sum(summary.sets_failed.values()) == 3
    topics = read_back(out)
    assert [stamp_ns(m.header) for _, m, _ in topics["/pssnet/completions"]] == stamps[::2]
    # A bag that already holds outputs (a recording of the live node, or this tool's) gets fresh ones instead.
    again = process_bag(BagToolConfig(input=out, output=path.parent / "again", parameters=parameters,
                                      progress=False))
    assert again.topics_not_copied == sorted(OUTPUT_TOPICS.values()) and again.sets_completed == GOOD_SETS
    assert again.written["/pssnet/completions"] == GOOD_SETS


def test_completions_equal_the_pipeline_called_directly_with_the_node_seed(runs, view, checkpoint):
    out, _, _ = runs["mcap"]  # 32FC1 depth: the same images as the direct call (16UC1 is rounded to mm)
    # The node completes every set with its `seed` parameter (default 0): each request is seeded the same way.
    pipeline = CompletionPipeline.from_checkpoint(
        checkpoint, PipelineConfig(num_samples=SAMPLES, up_vector=tuple(float(v) for v in view.up), seed=0), threads=1)
    result = pipeline.run(view.depth, view.mask, view.intrinsics)
    points, index = result.merged()
    topics = read_back(out)
    for (_, _, raw), (_, _, known) in zip(topics["/pssnet/completions"], topics["/pssnet/known_occupied"],
                                          strict=True):
        cloud = deserialize_message(raw, PointCloud2)
        got, sample = pointcloud2_to_numpy(cloud)
        np.testing.assert_array_equal(got, points)
        np.testing.assert_array_equal(sample, index)
        np.testing.assert_array_equal(pointcloud2_to_numpy(deserialize_message(known, PointCloud2))[0],
                                      result.known_occupied)
        # field for field what the node publishes for this result and header (CDR padding bytes are not
        # zeroed by the serialiser, so raw bytes are compared only through the messages they decode to)
        assert cloud == output_messages(result, cloud.header, GripperConfig()).completions
    grasps = topics["/pssnet/grasp_candidates"][0][1]
    np.testing.assert_allclose(grasps.scores, result.grasps.scores, rtol=1e-6)


def test_output_type_hashes_are_those_rosidl_generates(runs):
    out, _, _ = runs["sqlite3"]
    with Reader(out) as reader:
        digests = {c.msgtype: c.digest for c in reader.connections}
    typestore = make_typestore()
    for msgtype in ("sensor_msgs/msg/PointCloud2", "geometry_msgs/msg/PoseArray",
                    "pssnet_interfaces/msg/GraspCandidates"):
        package, _, name = msgtype.split("/")
        generated = Path(sys.prefix) / "share" / package / "msg" / f"{name}.json"
        if generated.is_file():  # rosidl's own description of the type, as the node's publisher announces it
            hashes = {h["type_name"]: h["hash_string"] for h in json.loads(generated.read_text())["type_hashes"]}
            assert typestore.hash_rihs01(msgtype) == hashes[msgtype]
        if digests[msgtype]:  # a bag directory records it in metadata.yaml
            assert digests[msgtype] == typestore.hash_rihs01(msgtype)


def run_cli(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="pssnet")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(list(argv))
    return args.func(args)


def test_cli_with_params_file_topics_and_errors(recordings, parameters, view, tmp_path, capsys):
    path, _ = recordings["mcap"]
    params = tmp_path / "params.yaml"
    up = ", ".join(repr(float(v)) for v in view.up)
    params.write_text(f"/**:\n  ros__parameters:\n    num_samples: 2\n    up_vector: [{up}]\n"
                      f"pssnet:\n  ros__parameters:\n    threads: 1\n    model_path: {parameters['model_path']}\n")
    assert read_params_file(params)["threads"] == 1
    out = tmp_path / "out"
    args = ("bag", str(path), "--out", str(out), "--params-file", str(params), "-p", "continuous_grasps:=false",
            "--no-progress")
    assert run_cli(*args) == 0
    printed = capsys.readouterr().out
    assert "sets synchronised: 5, completed: 4" in printed and f"wrote {out}" in printed
    topics = read_back(out)
    assert len(topics["/pssnet/grasps"]) == GOOD_SETS and not topics["/pssnet/grasps"][0][1].poses  # grasps off
    assert set(pointcloud2_to_numpy(deserialize_message(topics["/pssnet/completions"][0][2], PointCloud2))[1]) \
        == {0, 1}  # num_samples 2 from the file
    assert run_cli(*args) == 2  # the output exists
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert run_cli(*args, "--overwrite", "--depth-topic", "camera/depth") == 2
    assert "depth topic /camera/depth is not in the bag" in capsys.readouterr().err
    assert run_cli(*args, "--overwrite", "-p", "sync_tolerance:=-1.0") == 2
    assert "sync_tolerance" in capsys.readouterr().err
    assert run_cli("bag", str(tmp_path / "missing"), "--out", str(tmp_path / "x"), "--no-progress") == 2
    (tmp_path / "folder").mkdir()
    (tmp_path / "folder" / "keep.txt").write_text("not a bag")
    with pytest.raises(BagError, match="not a rosbag2 directory"):
        BagWriter(tmp_path / "folder", overwrite=True)


def test_demo_bag_records_the_exchange(tmp_path, view, parameters):
    from pssnet_interfaces.srv import SampleCompletions

    from pssnet_ros.completion_io import complete_messages, fill_response, load_pipeline

    header = header_at(T0_NS)
    depth, mask, info = view_messages(view, "32FC1", header)
    result, header = complete_messages(load_pipeline(parameters), depth, mask, info, 0.001, 0, True)
    response = fill_response(SampleCompletions.Response(), result, header)  # the service's response to these images
    path = write_demo_bag(tmp_path / "demo.mcap", view, response)
    assert path.is_file() and write_demo_bag(path, view, response) == path  # a second demo run replaces it
    topics = read_back(path)
    assert set(topics) == {*INPUTS, *OUTPUT_TOPICS.values()} and {len(v) for v in topics.values()} == {1}
    # The merged cloud is what the node would have published on /pssnet/completions for this set.
    assert deserialize_message(topics["/pssnet/completions"][0][2], PointCloud2) == \
        output_messages(result, header, GripperConfig()).completions
    assert deserialize_message(topics["/depth"][0][2], Image) == depth


def test_pssnet_help_does_not_import_rclpy():
    code = ("import sys; from pssnet_core.cli import build_parser; "
            "build_parser().parse_args(['bag', 'in', '--out', 'out', '--every', '2']); "
            "bad = [m for m in ('rclpy', 'rosbags') if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
