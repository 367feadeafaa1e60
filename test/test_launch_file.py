"""pssnet_ros/launch/completion.launch.py as far as this machine can check it: `launch` and `launch_ros` have no
wheels.

The file runs against recording stand-ins for launch / launch_ros (each action and substitution keeps its
arguments), so the test sees exactly what `ros2 launch` would be given: the executable and node name, the
parameter file, the remappings and the launch arguments, and checks them against the node's own interface.
"""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import pytest
import yaml

from pssnet_ros.completion_io import STREAMS
from pssnet_ros.params import SPECS, check_values

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "pssnet_ros"
LAUNCH_FILE = PACKAGE / "launch" / "completion.launch.py"


class Recorded:
    """Stands in for any launch class: remembers its positional and keyword arguments."""

    def __init__(self, *args, **kwargs) -> None:
        self.args, self.kwargs = args, kwargs


def stand_in_modules() -> dict[str, types.ModuleType]:
    names = {"launch": ["LaunchDescription"], "launch.actions": ["DeclareLaunchArgument"],
             "launch.conditions": ["IfCondition"],
             "launch.substitutions": ["LaunchConfiguration", "PathJoinSubstitution", "PythonExpression"],
             "launch_ros.actions": ["Node"], "launch_ros.parameter_descriptions": ["ParameterValue"],
             "launch_ros.substitutions": ["FindPackageShare"], "launch_ros": []}
    modules = {}
    for module, classes in names.items():
        modules[module] = types.ModuleType(module)
        for name in classes:
            setattr(modules[module], name, type(name, (Recorded,), {}))
    return modules


@pytest.fixture
def description(monkeypatch):
    for name, module in stand_in_modules().items():
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location("completion_launch", LAUNCH_FILE)
    launch_file = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(launch_file)
    return launch_file.generate_launch_description()


def perform(substitution, arguments: dict[str, str]) -> str:
    """What ``ros2 launch`` makes of a recorded substitution, given the launch arguments' values."""
    if isinstance(substitution, str):
        return substitution
    if isinstance(substitution, list):
        return "".join(perform(s, arguments) for s in substitution)
    kind = type(substitution).__name__
    if kind == "LaunchConfiguration":
        return arguments[substitution.args[0]]
    if kind == "PythonExpression":
        return str(eval(perform(substitution.args[0], arguments)))  # launch evaluates it so, too
    raise TypeError(kind)


def nodes_of(entities, package: str) -> list[dict]:
    return [e.kwargs for e in entities if type(e).__name__ == "Node" and e.kwargs["package"] == package]


def launch_arguments(entities, **given: str) -> dict[str, str]:
    defaults = {e.args[0]: e.kwargs["default_value"] for e in entities if type(e).__name__ == "DeclareLaunchArgument"}
    return {**defaults, **given}


def test_the_node_its_parameters_and_remappings(description):
    entities = description.args[0]
    nodes = [e for e in entities if type(e).__name__ == "Node" and e.kwargs["package"] == "pssnet_ros"]
    assert len(nodes) == 1
    node = nodes[0].kwargs
    assert node["package"] == "pssnet_ros" and node["name"] == "pssnet"
    assert f"{node['executable']} = pssnet_ros.completion_node:main" in (PACKAGE / "setup.py").read_text()
    # Every input the node subscribes to is remapped by a launch argument of the same name, and nothing else.
    given = {"depth": "/cam/depth/image_rect_raw", "mask": "/seg/mask", "camera_info": "/cam/depth/camera_info"}
    remapped = {source: perform(target, launch_arguments(entities, **given)) for source, target in node["remappings"]}
    assert remapped == given
    arguments = {e.args[0]: e.kwargs for e in entities if type(e).__name__ == "DeclareLaunchArgument"}
    assert set(arguments) == {"namespace", "params_file", "autostart", "rviz", "compressed_depth", *STREAMS}
    assert all(arguments[s]["default_value"] == s for s in STREAMS)  # defaults: the node's own names
    assert node["namespace"].args[0] == "namespace"
    # The parameter file: the installed config/completion_node.yaml, then autostart from its argument as a bool.
    params_file, overrides = node["parameters"]
    assert params_file.args[0] == "params_file"
    share = arguments["params_file"]["default_value"].args[0]
    assert share[0].args[0] == "pssnet_ros" and share[1:] == ["config", "completion_node.yaml"]
    assert set(overrides) == {"autostart"} and "autostart" in SPECS
    assert overrides["autostart"].args[0].args[0] == "autostart" and overrides["autostart"].kwargs["value_type"] is bool
    assert arguments["autostart"]["default_value"] == "true"


def test_the_parameter_file_it_installs_is_valid_for_the_node():
    values = yaml.safe_load((PACKAGE / "config" / "completion_node.yaml").read_text())["/**"]["ros__parameters"]
    assert check_values(values) is None
    setup = (PACKAGE / "setup.py").read_text()
    assert '(f"share/{PACKAGE}/launch", glob("launch/*.launch.py"))' in setup
    assert '(f"share/{PACKAGE}/config", glob("config/*"))' in setup


def test_rviz_starts_on_request_with_the_installed_config_that_draws_the_node_outputs(description):
    from pssnet_ros.completion_io import OUTPUT_TOPICS

    entities = description.args[0]
    arguments = {e.args[0]: e.kwargs for e in entities if type(e).__name__ == "DeclareLaunchArgument"}
    assert arguments["rviz"]["default_value"] == "false"
    (rviz,) = [e.kwargs for e in entities if type(e).__name__ == "Node" and e.kwargs["package"] == "rviz2"]
    assert rviz["condition"].args[0].args[0] == "rviz" and rviz["arguments"][0] == "-d"
    config = rviz["arguments"][1].args[0]
    assert config[0].args[0] == "pssnet_ros" and config[1:] == ["config", "pssnet.rviz"]
    view = yaml.safe_load((PACKAGE / "config" / "pssnet.rviz").read_text())["Visualization Manager"]
    topics = {d["Topic"]["Value"]: d["Class"] for d in view["Displays"] if "Topic" in d}
    assert topics == {OUTPUT_TOPICS["completions"]: "rviz_default_plugins/PointCloud2",
                      OUTPUT_TOPICS["known_occupied"]: "rviz_default_plugins/PointCloud2",
                      OUTPUT_TOPICS["grasp_markers"]: "rviz_default_plugins/MarkerArray"}
    assert view["Global Options"]["Fixed Frame"] == "camera_depth_optical_frame"  # what the outputs carry


def test_compressed_depth_is_decompressed_on_request_and_fed_to_the_node(description):
    entities = description.args[0]
    (node,) = nodes_of(entities, "pssnet_ros")
    (republish,) = nodes_of(entities, "image_transport")
    assert republish["executable"] == "republish" and republish["condition"].args[0].args[0] == "compressed_depth"
    assert republish["parameters"] == [{"in_transport": "compressedDepth", "out_transport": "raw"}]
    arguments = launch_arguments(entities, depth="/cam/depth/image_rect_raw")
    assert arguments["compressed_depth"] == "false"
    for flag in ("true", "True", "false"):
        arguments["compressed_depth"] = flag
        node_depth = perform(dict(node["remappings"])["depth"], arguments)
        remaps = {source: perform(target, arguments) for source, target in republish["remappings"]}
        assert remaps["in/compressedDepth"] == "/cam/depth/image_rect_raw/compressedDepth"
        compressed = flag.lower() == "true"
        assert node_depth == (remaps["out"] if compressed else "/cam/depth/image_rect_raw")
