"""The README's first command (python -m pssnet_testing.demo) runs end to end and exits 0 on its own."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from pssnet_interfaces.msg import GraspCandidates
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader
from sensor_msgs.msg import PointCloud2
from test_node_helpers import domain_for, node_checkpoint

from pssnet_ros.bag import BagToolConfig, node_parameters, process_bag
from pssnet_testing.processes import ros_env
from pssnet_testing.synthetic_camera import SceneOptions, render_scene

pytestmark = pytest.mark.ros


def test_demo_writes_the_figure_prints_the_summary_and_exits_0(tmp_path):
    checkpoint, trained = node_checkpoint(tmp_path)
    model = [] if trained else ["--model", str(checkpoint)]  # the shipped model, as the README runs it
    out = tmp_path / "demo"
    domain = domain_for(5)
    result = subprocess.run([sys.executable, "-m", "pssnet_testing.demo", "--out", str(out), "--samples", "6",
                             "--calls", "2", "--domain-id", str(domain), *model],
                            env=ros_env(domain), cwd=tmp_path, capture_output=True, text=True, timeout=300)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-4000:]
    png = out / "completions.png"
    assert png.is_file() and png.stat().st_size > 20_000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert re.search(r"samples: 6; voxel \d+\.\d+ mm; observed voxels: \d+; points per sample: min \d+", output)
    assert re.search(r"service latency \(request -> response, \d+ calls\): median \d+ ms", output)
    # The second look: the node scored the 16 places and completed both views (more observed voxels).
    look = re.search(r"second look: of 16 places round the mug, the samples disagree most about the view from azimuth "
                     r"\d+, \d+ deg up \(probability ([\d.]+) that it tells two samples apart", output)
    added = re.search(r"with that view added: observed voxels (\d+) -> (\d+), top grasp's score", output)
    assert look and added, output[-3000:]
    assert int(added.group(2)) > int(added.group(1))
    assert "all processes stopped cleanly" in output and "stale shared memory" not in output
    assert "Traceback" not in output
    with Reader(out / "demo.mcap") as bag:  # what the camera sent and the node answered, one message each
        assert {c.topic: c.msgcount for c in bag.connections} == {
            "/depth": 1, "/mask": 1, "/camera_info": 1, "/pssnet/completions": 1, "/pssnet/known_occupied": 1,
            "/pssnet/grasps": 1, "/pssnet/grasp_candidates": 1, "/pssnet/grasp_markers": 1}
    # `pssnet bag` on that recording, with the demo node's parameters, reproduces the node's service answer.
    up = [float(v) for v in render_scene(SceneOptions()).up]
    again = tmp_path / "again.mcap"
    process_bag(BagToolConfig(input=out / "demo.mcap", output=again, progress=False, parameters=node_parameters(
        {"model_path": "" if trained else str(checkpoint), "num_samples": 6, "up_vector": up})))
    node, tool = last_messages(out / "demo.mcap"), last_messages(again)
    for topic, cls in (("/pssnet/completions", PointCloud2), ("/pssnet/grasp_candidates", GraspCandidates)):
        assert deserialize_message(node[topic], cls) == deserialize_message(tool[topic], cls), topic


def last_messages(path: Path) -> dict[str, bytes]:
    """Topic -> raw CDR of its last message in a bag."""
    with Reader(path) as bag:
        return {connection.topic: bytes(data) for connection, _, data in bag.messages()}
