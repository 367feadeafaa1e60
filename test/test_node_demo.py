"""The README's first command (python -m pssnet_ros.demo) runs end to end and exits 0 on its own."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from test_node_helpers import domain_for, node_checkpoint

from pssnet_ros.processes import ros_env

pytestmark = pytest.mark.ros


def test_demo_writes_the_figure_prints_the_summary_and_exits_0(tmp_path):
    checkpoint, trained = node_checkpoint(tmp_path)
    model = [] if trained else ["--model", str(checkpoint)]  # the shipped model, as the README runs it
    out = tmp_path / "demo"
    result = subprocess.run([sys.executable, "-m", "pssnet_ros.demo", "--out", str(out), "--samples", "6",
                             "--calls", "2", "--domain-id", str(domain_for(5)), *model],
                            env=ros_env(domain_for(5)), cwd=tmp_path, capture_output=True, text=True, timeout=300)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-4000:]
    png = out / "completions.png"
    assert png.is_file() and png.stat().st_size > 20_000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert re.search(r"samples: 6; voxel \d+\.\d+ mm; observed voxels: \d+; points per sample: min \d+", output)
    assert re.search(r"service latency \(request -> response, \d+ calls\): median \d+ ms", output)
    assert "all processes stopped cleanly" in output and "stale shared memory" not in output
    assert "Traceback" not in output
