"""colcon builds both packages (pssnet_interfaces and pssnet_ros) as in a ROS 2 workspace, and the installed
completion_node starts.

"Starts" means: with the workspace's setup.bash sourced, install/pssnet_ros/lib/pssnet_ros/completion_node
(the file `ros2 run pssnet_ros completion_node` executes) imports this package from the install space (not
from the source tree), loads a model, declares its parameters, prints its ready line with the service name,
and exits 0 on SIGINT; with a missing model it exits 2 with a one-line error.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from test_node_helpers import domain_for, tiny_checkpoint

from pssnet_ros.processes import RosProcess, ros_env

pytestmark = pytest.mark.ros
ROOT = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent
DOMAIN = domain_for(4)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    base = tmp_path_factory.mktemp("colcon")
    env = ros_env(DOMAIN)
    venv = VENV_BIN.parent
    env.update(PATH=f"{VENV_BIN}{os.pathsep}{env.get('PATH', '')}", VIRTUAL_ENV=str(venv),
               CMAKE_PREFIX_PATH=str(venv), AMENT_PREFIX_PATH=str(venv))
    command = [str(VENV_BIN / "colcon"), "--log-base", str(base / "log"), "build",
               "--base-paths", str(ROOT), str(ROOT / "msg_schemas"),
               "--build-base", str(base / "build"), "--install-base", str(base / "install"),
               "--cmake-args", "-G", "Ninja", f"-DPython3_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=OFF"]
    result = subprocess.run(command, env=env, cwd=base, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"colcon build failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}"
    assert "Summary: 2 packages finished" in result.stdout, result.stdout[-2000:]
    return base / "install"


def sourced(install: Path, command: str) -> list[str]:
    return ["bash", "-c", f"source {shlex.quote(str(install / 'setup.bash'))} && {command}"]


def test_install_has_the_node_executable_where_ros2_run_looks(workspace):
    node = workspace / "pssnet_ros" / "lib" / "pssnet_ros" / "completion_node"
    assert node.is_file() and os.access(node, os.X_OK)
    assert (workspace / "pssnet_ros" / "share" / "pssnet_ros" / "package.xml").is_file()
    assert (workspace / "pssnet_ros" / "share" / "pssnet_ros" / "LICENSE").is_file()
    assert (workspace / "pssnet_ros" / "share" / "pssnet_ros" / "config" / "completion_node.yaml").is_file()
    assert (workspace / "pssnet_ros" / "share" / "ament_index" / "resource_index" / "packages" / "pssnet_ros").is_file()
    assert (workspace / "pssnet_interfaces" / "share" / "pssnet_interfaces" / "srv" / "SampleCompletions.srv").is_file()
    script = ("import pssnet_ros, pssnet_core, pssnet_interfaces.srv as s; print(pssnet_ros.__file__); "
              "print(pssnet_core.__file__); print(s.__file__)")
    where = subprocess.run(sourced(workspace, f"{shlex.quote(sys.executable)} -c {shlex.quote(script)}"),
                           env=ros_env(DOMAIN), cwd=workspace.parent, capture_output=True, text=True, timeout=120)
    assert where.returncode == 0, where.stderr
    assert all(line.startswith(str(workspace)) for line in where.stdout.split()), where.stdout


def test_installed_node_starts_and_stops_cleanly(workspace, tmp_path):
    node = workspace / "pssnet_ros" / "lib" / "pssnet_ros" / "completion_node"
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt")
    params = workspace / "pssnet_ros" / "share" / "pssnet_ros" / "config" / "completion_node.yaml"
    process = RosProcess(sourced(workspace, f"exec {node} --ros-args --params-file {params} "
                                            f"-p model_path:={checkpoint}"), ros_env(DOMAIN), name="installed node",
                         cwd=workspace.parent)
    try:
        process.wait_for(r"ready: serving /pssnet/sample_completions", timeout=120)
    finally:
        code = process.stop()
    assert code == 0, process.output[-3000:]
    failing = RosProcess(sourced(workspace, f"exec {node} --ros-args -p model_path:={tmp_path / 'missing.pt'}"),
                         ros_env(DOMAIN), name="installed node, missing model", cwd=workspace.parent)
    assert failing.proc.wait(timeout=120) == 2
    failing.stop()
    assert "[completion_node] error: cannot load the completion model: no checkpoint file at" in failing.output
    assert "Traceback" not in failing.output
