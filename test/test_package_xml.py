"""package.xml declares every ROS package the code imports (rosdep and colcon resolve from it, not from pip)."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Declared though not imported by name: what needs them.
INDIRECT = {"lifecycle_msgs": "rclpy.lifecycle (the managed node) imports it"}
IMPORT = re.compile(r"^\s*(?:from|import)\s+([A-Za-z_][A-Za-z0-9_]*)", re.MULTILINE)


def is_ros_package(module: str) -> bool:
    return module in ("rclpy", "launch", "launch_ros") or module.endswith(("_msgs", "_srvs", "_interfaces"))


def imported_ros_packages(files: list[Path]) -> set[str]:
    return {m for f in files for m in IMPORT.findall(f.read_text()) if is_ros_package(m)}


def dependencies(kind: str) -> set[str]:
    return {e.text for e in ET.parse(ROOT / "package.xml").getroot().iter(kind)}


def test_every_imported_ros_package_is_declared():
    runtime = imported_ros_packages(sorted((ROOT / "pssnet_ros").glob("*.py")) + sorted((ROOT / "launch").glob("*.py")))
    assert {"rclpy", "diagnostic_msgs", "std_srvs", "launch_ros", "pssnet_interfaces"} <= runtime  # the scan works
    exec_depends = dependencies("exec_depend")
    assert runtime - exec_depends == set(), "imported by the package but not an exec_depend"
    tests = imported_ros_packages(sorted((ROOT / "test").glob("*.py")))
    assert tests - exec_depends - dependencies("test_depend") == set(), "imported by the tests but not declared"


def test_core_imports_no_ros_package():
    core = imported_ros_packages(sorted((ROOT / "pssnet_core").rglob("*.py")))
    assert core == set(), f"pssnet_core must stay ROS-free, imports {core}"


def test_declared_ros_packages_are_imported_or_launch_tools():
    declared = {d for d in dependencies("exec_depend") if is_ros_package(d)}
    runtime = imported_ros_packages(sorted((ROOT / "pssnet_ros").glob("*.py")) + sorted((ROOT / "launch").glob("*.py")))
    assert declared - runtime - set(INDIRECT) == set(), "declared but never imported: stale dependency"
    assert "from rclpy.lifecycle import" in (ROOT / "pssnet_ros" / "completion_node.py").read_text()
