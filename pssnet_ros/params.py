"""The completion node's parameters: one table of specs, their ROS descriptors, and the validation rules.

Ranges live in the descriptors (rclpy rejects out-of-range values itself, with a reason); rules that span
several parameters or are not ranges (choices, vector length, num_samples <= max_num_samples, min_depth <
max_depth, voxel size vs. the model) are checked by :func:`check_values`, which the node's set-parameters
callback calls. Nothing is silently clamped. The model parameters (model_path, device, threads) and
autostart take effect on the lifecycle ``configure`` and can change only while the node is unconfigured
(:data:`CONFIGURE_ONLY`); the others can change at any time. Defaults here equal config/completion_node.yaml
(a test checks that).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType

from pssnet_core.grasps import GraspConfig, GripperConfig
from pssnet_core.pipeline import PipelineConfig

INT32_MAX = 2**31 - 1


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter.

    Attributes:
        name: parameter name.
        default: default value (its Python type sets the ROS type; a tuple of floats is a double array).
        description: what it does, with its unit.
        low: inclusive lower bound (numbers only).
        high: inclusive upper bound (numbers only).
        configure_only: read on the lifecycle configure; changes are refused while the node is configured.
        choices: allowed values (strings only).
        constraints: extra rule in words (shown in the descriptor's additional_constraints).
    """

    name: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    configure_only: bool = False
    choices: tuple[str, ...] = ()
    constraints: str = ""

    @property
    def ros_type(self) -> int:
        if isinstance(self.default, bool):
            return ParameterType.PARAMETER_BOOL
        if isinstance(self.default, int):
            return ParameterType.PARAMETER_INTEGER
        if isinstance(self.default, float):
            return ParameterType.PARAMETER_DOUBLE
        if isinstance(self.default, str):
            return ParameterType.PARAMETER_STRING
        return ParameterType.PARAMETER_DOUBLE_ARRAY

    @property
    def type_name(self) -> str:
        return {ParameterType.PARAMETER_BOOL: "bool", ParameterType.PARAMETER_INTEGER: "int",
                ParameterType.PARAMETER_DOUBLE: "double", ParameterType.PARAMETER_STRING: "string",
                ParameterType.PARAMETER_DOUBLE_ARRAY: "double[]"}[self.ros_type]

    def descriptor(self) -> ParameterDescriptor:
        """The ROS parameter descriptor (type, description, range)."""
        constraints = self.constraints
        if self.choices:
            constraints = (f"one of: {', '.join(self.choices)}" + (f"; {constraints}" if constraints else ""))
        if self.configure_only:
            constraints = "set before configure" + (f"; {constraints}" if constraints else "")
        descriptor = ParameterDescriptor(name=self.name, type=self.ros_type, description=self.description,
                                         additional_constraints=constraints)
        if self.ros_type == ParameterType.PARAMETER_INTEGER and self.low is not None:
            descriptor.integer_range = [IntegerRange(from_value=int(self.low), to_value=int(self.high), step=0)]
        elif self.ros_type == ParameterType.PARAMETER_DOUBLE and self.low is not None:
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(self.low),
                                                                  to_value=float(self.high), step=0.0)]
        return descriptor

    def range_text(self) -> str:
        if self.choices:
            return " / ".join(self.choices)
        if self.low is not None:
            return f"[{_fmt(self.low)}, {_fmt(self.high)}]"
        return self.constraints


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, tuple):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    if isinstance(value, str):
        return f'"{value}"'
    return str(value).lower() if isinstance(value, bool) else str(value)


_GRIPPER = GripperConfig()
_GRASPS = GraspConfig()
_PIPELINE = PipelineConfig()

PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("autostart", True, "configure and activate at start-up (the plain node); false = wait for a "
              "lifecycle manager", configure_only=True),
    ParamSpec("model_path", "", "checkpoint file of the completion model; empty = the shipped default 32^3 PSSNet",
              configure_only=True),
    ParamSpec("device", "cpu", "torch device of the model", configure_only=True, choices=("cpu", "cuda")),
    ParamSpec("threads", 0, "torch CPU threads; 0 = torch's default (all cores)", 0, 256, configure_only=True),
    ParamSpec("num_samples", 20, "completions per call when the request says 0 (and in continuous mode)", 1, 1000,
              constraints="<= max_num_samples"),
    ParamSpec("max_num_samples", 100, "requests asking for more samples are rejected", 1, 1000),
    ParamSpec("box_temperature", 0.0, "factor on the posterior sigma of PSSNet's box latent (wider = more diverse "
              "hidden sides); 0 = the value calibrated with the model", 0.0, 10.0,
              constraints="0 or 1 for models without a box part"),
    ParamSpec("seed", 0, "latent-noise seed: the same input gives the same completions; -1 = a fresh seed per "
              "call", -1, INT32_MAX),
    ParamSpec("voxel_size", 0.0, "grid voxel size in metres; 0 = the model's training voxel size", 0.0, 0.1,
              constraints="must equal the model's when its checkpoint records one"),
    ParamSpec("front_margin", 1.0, "grid placement: voxels in front of the nearest observed point", 0.0, 16.0,
              constraints="< grid size / 2"),
    ParamSpec("bottom_margin", 1.0, "grid placement: voxels below the lowest observed point", 0.0, 16.0,
              constraints="< grid size / 2"),
    ParamSpec("up_vector", (0.0, -1.0, 0.0), "up (against gravity) in the camera optical frame; [0, -1, 0] for a "
              "level camera", constraints="3 finite numbers, not all zero"),
    ParamSpec("estimate_up", False, "estimate up from the support plane around the object (RANSAC); up_vector "
              "is then the prior that orients it"),
    ParamSpec("support_plane_distance", 0.005, "support-plane RANSAC inlier distance, metres", 0.0005, 0.05),
    ParamSpec("support_plane_max_tilt_deg", 45.0, "largest angle between the fitted plane normal and up_vector",
              1.0, 90.0),
    ParamSpec("depth_scale", 0.001, "metres per unit of 16UC1 depth images (0.001 = millimetres)", 1e-6, 1.0),
    ParamSpec("min_depth", 0.1, "readings closer than this are ignored, metres", 0.0, 50.0,
              constraints="< max_depth"),
    ParamSpec("max_depth", 5.0, "readings farther than this are ignored, metres", 0.01, 100.0),
    ParamSpec("min_mask_pixels", 50, "masks with fewer pixels are rejected", 1, 10_000_000),
    ParamSpec("min_valid_points", 20, "fewer masked pixels with valid depth are rejected", 1, 10_000_000),
    ParamSpec("sync_tolerance", 0.01, "largest stamp difference of a synchronised depth/mask/camera_info set, "
              "seconds", 0.0, 10.0),
    ParamSpec("max_input_age", 1.0, "sets older than this (node clock minus stamp) are stale: dropped in "
              "continuous mode, refused by the service; seconds, 0 = no limit", 0.0, 3600.0),
    ParamSpec("continuous", False, "complete every newest synchronised set (at most max_rate_hz) and publish; "
              "false = serve the service only"),
    ParamSpec("max_rate_hz", 2.0, "continuous mode: largest completion rate, Hz", 0.01, 100.0),
    ParamSpec("continuous_grasps", True, "continuous mode: also compute and publish grasps"),
    ParamSpec("grasp_max_opening", _GRIPPER.max_opening, "gripper: largest distance between the finger pads, "
              "metres", 0.005, 0.5),
    ParamSpec("grasp_finger_length", _GRIPPER.finger_length, "gripper: finger length from palm to fingertips, "
              "metres", 0.001, 0.5),
    ParamSpec("grasp_finger_width", _GRIPPER.finger_width, "gripper: finger extent across the closing plane, "
              "metres", 0.001, 0.5),
    ParamSpec("grasp_finger_thickness", _GRIPPER.finger_thickness, "gripper: finger extent along the closing "
              "axis, metres", 0.001, 0.5),
    ParamSpec("grasp_palm_depth", _GRIPPER.palm_depth, "gripper: palm thickness behind the fingers, metres",
              0.001, 0.5),
    ParamSpec("grasp_min_object_width", _GRIPPER.min_object_width, "less object than this between the fingers "
              "is not held, metres", 0.0, 0.5, constraints="< grasp_max_opening"),
    ParamSpec("grasp_clearance", _GRASPS.clearance, "free space between each finger pad and the widest "
              "completion, metres", 0.0, 0.25, constraints="< grasp_max_opening / 2"),
    ParamSpec("grasp_max_candidates", _GRASPS.max_candidates, "candidate grasps scored against every completion",
              1, 100_000),
    ParamSpec("grasp_top_yaws", _GRASPS.top_yaws, "closing-axis angles of top-down grasps (0 = no top grasps)",
              0, 180),
    ParamSpec("grasp_side_yaws", _GRASPS.side_yaws, "horizontal approach directions of side grasps (0 = no side "
              "grasps)", 0, 360, constraints="grasp_top_yaws or grasp_side_yaws > 0"),
    ParamSpec("grasp_top_k", _PIPELINE.grasp_top_k, "grasps returned, best first", 1, 1000),
    ParamSpec("grasp_min_score", _PIPELINE.grasp_min_score, "grasps holding for a smaller fraction of the "
              "completions are not returned", 0.0, 1.0),
)

SPECS: dict[str, ParamSpec] = {spec.name: spec for spec in PARAMETERS}
CONFIGURE_ONLY: frozenset[str] = frozenset(spec.name for spec in PARAMETERS if spec.configure_only)


def defaults() -> dict[str, Any]:
    """Name -> default value (arrays as lists)."""
    return {s.name: list(s.default) if isinstance(s.default, tuple) else s.default for s in PARAMETERS}


def check_values(values: dict[str, Any]) -> str | None:
    """The reason ``values`` (a complete name -> value dict) is invalid, or None when it is valid.

    Checks types, ranges and choices of each value (as rclpy does, so that the same rules hold for a YAML
    file checked without a node) and the rules that span parameters.
    """
    for name, value in values.items():
        spec = SPECS.get(name)
        if spec is None:
            return f"unknown parameter {name!r}"
        reason = _check_one(spec, value)
        if reason:
            return reason
    if values["num_samples"] > values["max_num_samples"]:
        return (f"num_samples ({values['num_samples']}) must not exceed max_num_samples "
                f"({values['max_num_samples']})")
    if values["min_depth"] >= values["max_depth"]:
        return f"min_depth ({values['min_depth']}) must be smaller than max_depth ({values['max_depth']})"
    try:  # the grasp options' own rules (clearance vs opening, at least one approach direction, ...)
        pipeline_config(values)
    except ValueError as error:
        return str(error)
    return None


def _check_one(spec: ParamSpec, value: Any) -> str | None:
    name = spec.name
    if spec.ros_type == ParameterType.PARAMETER_DOUBLE_ARRAY:
        try:
            vector = [float(v) for v in value]
        except (TypeError, ValueError):
            return f"{name} must be a list of 3 numbers, got {value!r}"
        if len(vector) != 3 or not all(math.isfinite(v) for v in vector) or not any(vector):
            return f"{name} must be 3 finite numbers, not all zero, got {list(value)}"
        return None
    expected = {ParameterType.PARAMETER_BOOL: (bool,), ParameterType.PARAMETER_INTEGER: (int,),
                ParameterType.PARAMETER_DOUBLE: (float, int), ParameterType.PARAMETER_STRING: (str,)}[spec.ros_type]
    if not isinstance(value, expected) or (spec.ros_type != ParameterType.PARAMETER_BOOL and isinstance(value, bool)):
        article = "an" if spec.type_name == "int" else "a"
        return f"{name} must be {article} {spec.type_name}, got {value!r}"
    if spec.choices and value not in spec.choices:
        return f"{name} must be one of {', '.join(spec.choices)}, got {value!r}"
    if spec.low is not None:
        if isinstance(value, float) and not math.isfinite(value):
            return f"{name} must be finite, got {value}"
        if not spec.low <= value <= spec.high:
            return f"{name} must be in [{_fmt(spec.low)}, {_fmt(spec.high)}], got {value}"
    return None


def pipeline_config(values: dict[str, Any]) -> PipelineConfig:
    """The pipeline configuration for a complete, valid set of parameter values."""
    return PipelineConfig(
        num_samples=int(values["num_samples"]), max_num_samples=int(values["max_num_samples"]),
        seed=int(values["seed"]), voxel_size=float(values["voxel_size"]),
        front_margin=float(values["front_margin"]), bottom_margin=float(values["bottom_margin"]),
        up_vector=tuple(float(v) for v in values["up_vector"]), estimate_up=bool(values["estimate_up"]),
        support_plane_distance=float(values["support_plane_distance"]),
        support_plane_max_tilt_deg=float(values["support_plane_max_tilt_deg"]),
        min_depth=float(values["min_depth"]), max_depth=float(values["max_depth"]),
        min_mask_pixels=int(values["min_mask_pixels"]), min_valid_points=int(values["min_valid_points"]),
        box_temperature=float(values["box_temperature"]),
        grasps=GraspConfig(
            gripper=GripperConfig(max_opening=float(values["grasp_max_opening"]),
                                  finger_length=float(values["grasp_finger_length"]),
                                  finger_width=float(values["grasp_finger_width"]),
                                  finger_thickness=float(values["grasp_finger_thickness"]),
                                  palm_depth=float(values["grasp_palm_depth"]),
                                  min_object_width=float(values["grasp_min_object_width"])),
            max_candidates=int(values["grasp_max_candidates"]), top_yaws=int(values["grasp_top_yaws"]),
            side_yaws=int(values["grasp_side_yaws"]), clearance=float(values["grasp_clearance"])),
        grasp_top_k=int(values["grasp_top_k"]), grasp_min_score=float(values["grasp_min_score"]),
    )


def markdown_table() -> str:
    """The parameter table (Markdown), for the README and ``completion_node --help``."""
    lines = ["| parameter | type | default | range | description |", "|---|---|---|---|---|"]
    for spec in PARAMETERS:
        description = spec.description + (" (set before configure)" if spec.configure_only else "")
        lines.append(f"| `{spec.name}` | {spec.type_name} | `{_yaml_value(spec.default)}` | {spec.range_text()} | "
                     f"{description} |")
    return "\n".join(lines)


def _yaml_value(value: Any) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return repr(value)  # keeps the decimal point: 1.0 stays a double for ROS
    if isinstance(value, tuple):
        return "[" + ", ".join(_yaml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return f'"{value}"'
    return str(value)


def default_yaml() -> str:
    """config/completion_node.yaml as generated from :data:`PARAMETERS` (defaults, ranges, descriptions)."""
    lines = ["# Parameters of the PSSNet completion node (node name: pssnet), with their defaults.",
             "# `completion_node --help` prints them as a table with types, ranges and descriptions.",
             "# Use: ros2 run pssnet_ros completion_node --ros-args --params-file config/completion_node.yaml",
             "# Doubles need a decimal point (1.0, not 1): ROS parameters are strictly typed.",
             "/**:", "  ros__parameters:"]
    for spec in PARAMETERS:
        notes = [n for n in (spec.range_text(), spec.constraints if spec.low is not None else "",
                             "set before configure" if spec.configure_only else "") if n]
        lines.append(f"    # {spec.description}" + (f" ({'; '.join(notes)})" if notes else ""))
        lines.append(f"    {spec.name}: {_yaml_value(spec.default)}")
    return "\n".join(lines) + "\n"
