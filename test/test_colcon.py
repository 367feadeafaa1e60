"""The repository in a ROS 2 workspace: a copy in ws/src builds with a plain `colcon build` (all four packages:
pssnet_interfaces, pssnet_core, pssnet_ros, pssnet_testing), the installed completion_node starts, and `colcon test`
runs a package's tests from the install.

"Starts" means: with the workspace's setup.bash sourced, install/pssnet_ros/lib/pssnet_ros/completion_node
(the file `ros2 run pssnet_ros completion_node` executes) imports the packages from the install space (not
from the source tree), loads a model, declares its parameters, prints its ready line with the service name,
and exits 0 on SIGINT; with a missing model it exits 2 with a one-line error.

`colcon test` of every package runs the whole suite a second time (`make colcon-test`); here it runs one
package's launch-file tests, which is enough to show that colcon finds the tests through the package's
pytest.ini and runs them against the install. Which test file belongs to which package is checked without
colcon, below.
"""

from __future__ import annotations

import configparser
import os
import re
import shlex
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from test_node_helpers import domain_for, tiny_checkpoint

from pssnet_testing.processes import RosProcess, ros_env

pytestmark = pytest.mark.ros
ROOT = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent
PACKAGES = ("pssnet_interfaces", "pssnet_core", "pssnet_ros", "pssnet_testing")
PYTHON_PACKAGES = PACKAGES[1:]
DOMAIN = domain_for(4)


def source_files() -> list[str]:
    """What a clone of this checkout holds: the files git tracks or would track (working-tree versions)."""
    listed = subprocess.run(["git", "-C", str(ROOT), "ls-files", "--cached", "--others", "--exclude-standard"],
                            capture_output=True, text=True)
    if listed.returncode != 0:  # not a git checkout: the packages and the tests
        return [str(p.relative_to(ROOT)) for d in (*PACKAGES, "test") for p in (ROOT / d).rglob("*") if p.is_file()]
    return [f for f in listed.stdout.splitlines() if (ROOT / f).is_file()]


def colcon_env() -> dict[str, str]:
    """This venv's ROS (the PyPI wheels) as the underlay, as `make colcon` sets it up."""
    env = ros_env(DOMAIN)
    venv = VENV_BIN.parent
    env.update(PATH=f"{VENV_BIN}{os.pathsep}{env.get('PATH', '')}", VIRTUAL_ENV=str(venv),
               CMAKE_PREFIX_PATH=str(venv), AMENT_PREFIX_PATH=str(venv))
    return env


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """ws/src/pssnet_ros_repo holds a copy of the repository; `colcon build` runs in ws/ with no arguments
    beyond the generator and the venv's Python."""
    ws = tmp_path_factory.mktemp("ws")
    src = ws / "src" / "pssnet_ros_repo"
    for name in source_files():
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, src / name)
    command = [str(VENV_BIN / "colcon"), "build", "--cmake-args", "-G", "Ninja",
               f"-DPython3_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=OFF"]
    result = subprocess.run(command, env=colcon_env(), cwd=ws, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"colcon build failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}"
    assert f"Summary: {len(PACKAGES)} packages finished" in result.stdout, result.stdout[-2000:]
    return ws


def sourced(install: Path, command: str) -> list[str]:
    return ["bash", "-c", f"source {shlex.quote(str(install / 'setup.bash'))} && {command}"]


def test_install_has_the_node_executable_where_ros2_run_looks(workspace):
    install = workspace / "install"
    node = install / "pssnet_ros" / "lib" / "pssnet_ros" / "completion_node"
    assert node.is_file() and os.access(node, os.X_OK)
    assert (install / "pssnet_core" / "lib" / "pssnet_core" / "pssnet").is_file()
    for package in PYTHON_PACKAGES:
        assert (install / package / "share" / package / "package.xml").is_file()
        assert (install / package / "share" / package / "LICENSE").is_file()
        assert (install / package / "share" / "ament_index" / "resource_index" / "packages" / package).is_file()
    assert (install / "pssnet_ros" / "share" / "pssnet_ros" / "config" / "completion_node.yaml").is_file()
    assert (install / "pssnet_ros" / "share" / "pssnet_ros" / "launch" / "completion.launch.py").is_file()
    assert (install / "pssnet_interfaces" / "share" / "pssnet_interfaces" / "srv" / "SampleCompletions.srv").is_file()
    script = ("import pssnet_ros.completion_node, pssnet_core.inference as i, pssnet_testing.processes as t, "
              "pssnet_interfaces.srv as s; print(pssnet_ros.completion_node.__file__); print(i.__file__); "
              "print(t.__file__); print(s.__file__); print(i.DEFAULT_CHECKPOINT.is_file())")
    where = subprocess.run(sourced(install, f"{shlex.quote(sys.executable)} -c {shlex.quote(script)}"),
                           env=ros_env(DOMAIN), cwd=workspace, capture_output=True, text=True, timeout=120)
    assert where.returncode == 0, where.stderr
    *paths, checkpoint = where.stdout.split()
    assert len(paths) == 4 and all(line.startswith(str(install)) for line in paths), where.stdout
    assert checkpoint == "True", "the shipped checkpoint is installed with pssnet_core"


def test_installed_node_starts_and_stops_cleanly(workspace, tmp_path):
    install = workspace / "install"
    node = install / "pssnet_ros" / "lib" / "pssnet_ros" / "completion_node"
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt")
    params = install / "pssnet_ros" / "share" / "pssnet_ros" / "config" / "completion_node.yaml"
    process = RosProcess(sourced(install, f"exec {node} --ros-args --params-file {params} "
                                          f"-p model_path:={checkpoint}"), ros_env(DOMAIN), name="installed node",
                         cwd=workspace)
    try:
        process.wait_for(r"ready: serving /pssnet/sample_completions", timeout=120)
    finally:
        code = process.stop()
    assert code == 0, process.output[-3000:]
    failing = RosProcess(sourced(install, f"exec {node} --ros-args -p model_path:={tmp_path / 'missing.pt'}"),
                         ros_env(DOMAIN), name="installed node, missing model", cwd=workspace)
    assert failing.proc.wait(timeout=120) == 2
    failing.stop()
    assert "[completion_node] error: cannot load the completion model: no checkpoint file at" in failing.output
    assert "Traceback" not in failing.output


def test_colcon_test_runs_a_packages_tests_from_the_install(workspace):
    """`colcon test` finds pssnet_ros's tests through its pytest.ini (../test/...), runs them with the install's
    packages, and `colcon test-result` counts them: here only the launch-file tests (-k), to stay short."""
    command = [str(VENV_BIN / "colcon"), "test", "--packages-select", "pssnet_ros", "--pytest-args", "-k",
               "test_launch_file"]
    result = subprocess.run(sourced(workspace / "install", shlex.join(command)), env=colcon_env(), cwd=workspace,
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"colcon test failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}"
    summary = subprocess.run([str(VENV_BIN / "colcon"), "test-result", "--test-result-base", "build/pssnet_ros"],
                             env=colcon_env(), cwd=workspace, capture_output=True, text=True, timeout=60)
    assert summary.returncode == 0, summary.stdout + summary.stderr  # non-zero: a failure or an error
    counts = summary.stdout.strip().splitlines()[-1]  # "Summary: N tests, 0 errors, 0 failures, 0 skipped"
    expected = re.findall(r"^def (test_\w+)", (ROOT / "test" / "test_launch_file.py").read_text(), re.MULTILINE)
    assert f"Summary: {len(expected)} tests, 0 errors, 0 failures" in counts, summary.stdout
    junit = ET.parse(workspace / "build" / "pssnet_ros" / "pytest.xml").getroot()
    assert sorted(case.get("name") for case in junit.iter("testcase")) == sorted(expected)


# ------------------------------------------------------------------------ which tests each package runs
def package_ini(package: str) -> configparser.SectionProxy:
    ini = configparser.ConfigParser()
    ini.read(ROOT / package / "pytest.ini")
    return ini["pytest"]


def test_every_test_file_belongs_to_exactly_one_package():
    """`colcon test` runs each package's pytest.ini; together they are the whole of test/, each file once."""
    owners: dict[str, list[str]] = {}
    for package in PYTHON_PACKAGES:
        for pattern in package_ini(package)["testpaths"].split():
            assert pattern.startswith("../test/test_"), pattern
            for path in (ROOT / package).glob(pattern):
                owners.setdefault(path.name, []).append(package)
    every = {path.name for path in (ROOT / "test").glob("test_*.py")}
    assert set(owners) == every, f"in no package's pytest.ini: {sorted(every - set(owners))}"
    assert not {name: p for name, p in owners.items() if len(p) > 1}, "a test file in two packages"


def test_the_packages_run_their_tests_as_make_test_does():
    """Same options as the root pytest.ini (markers, deselection, timeout): only testpaths differ."""
    root = configparser.ConfigParser()
    root.read(ROOT / "pytest.ini")
    expected = {k: v for k, v in root["pytest"].items() if k != "testpaths"}
    for package in PYTHON_PACKAGES:
        assert {k: v for k, v in package_ini(package).items() if k != "testpaths"} == expected, package
