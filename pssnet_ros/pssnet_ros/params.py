"""The completion node's parameters: one table of specs, from which everything else is derived.

Each :class:`ParamSpec` names the :class:`~pssnet_core.pipeline.PipelineConfig` field it sets (a dotted path,
e.g. ``grasps.gripper.max_opening``), or none for the node's own settings (model, topics, continuous mode).
A spec that sets a field takes its default from that field's default, and :func:`pipeline_config` builds the
config from the specs alone: adding a pipeline parameter is one line here. Ranges live in the descriptors
(rclpy rejects out-of-range values itself, with a reason); :func:`check_values` applies the same per-value
rules to a plain dict (a YAML file checked without a node) and leaves the rules that span several values to
the configs' own checks (``PipelineConfig``, ``GraspConfig``, ``GripperConfig``). Nothing is silently
clamped. The model parameters (model_path, device, threads, precision) and autostart take effect on the lifecycle
``configure`` and can change only while the node is unconfigured (:data:`CONFIGURE_ONLY`); the others can
change at any time. Defaults here equal config/completion_node.yaml (a test checks that).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType

from pssnet_core.grasps import GraspConfig, GripperConfig
from pssnet_core.pipeline import UP_VECTOR_LENGTH, PipelineConfig

INT32_MAX = 2**31 - 1
_DEFAULT_PIPELINE = PipelineConfig()


def config_default(path: str) -> Any:
    """The default of a (dotted) PipelineConfig field, e.g. ``grasps.gripper.max_opening``."""
    value: Any = _DEFAULT_PIPELINE
    for part in path.split("."):
        value = getattr(value, part)
    return value


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter.

    Attributes:
        name: parameter name.
        description: what it does, with its unit.
        low: inclusive lower bound (numbers only).
        high: inclusive upper bound (numbers only).
        field: the PipelineConfig field it sets (dotted path), or "" for a setting of the node itself.
        default: default value (its Python type sets the ROS type; a tuple of floats is a double array);
            None = the default of ``field``.
        configure_only: read on the lifecycle configure; changes are refused while the node is configured.
        choices: allowed values (strings only).
        constraints: extra rule in words (shown in the descriptor's additional_constraints).
        length: arrays only: the exact number of values (None = any number, none included).
        nonzero: arrays only: not every value may be zero (a direction).
    """

    name: str
    description: str
    low: float | None = None
    high: float | None = None
    field: str = ""
    default: Any = None
    configure_only: bool = False
    choices: tuple[str, ...] = ()
    constraints: str = ""
    length: int | None = None
    nonzero: bool = False

    def __post_init__(self) -> None:
        if self.default is None:
            if not self.field:
                raise ValueError(f"parameter {self.name} needs a default or a config field")
            object.__setattr__(self, "default", config_default(self.field))

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
            return f"[{literal(self.low)}, {literal(self.high)}]"
        return self.constraints


def literal(value: Any) -> str:
    """A value as it is written in the YAML parameter file (floats keep their decimal point: ROS types are
    strict), used for the file, the table and messages alike."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, tuple | list):
        return "[" + ", ".join(literal(v) for v in value) + "]"
    if isinstance(value, str):
        return f'"{value}"'
    return str(value)


PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("autostart", "configure and activate at start-up (the plain node); false = wait for a "
              "lifecycle manager", default=True, configure_only=True),
    ParamSpec("model_path", "checkpoint file of the completion model; empty = the shipped default 32^3 PSSNet",
              default="", configure_only=True),
    ParamSpec("device", "torch device of the model", default="cpu", configure_only=True, choices=("cpu", "cuda")),
    ParamSpec("threads", "torch CPU threads; 0 = torch's default (all cores)", 0, 256, default=0,
              configure_only=True),
    ParamSpec("precision", "network precision: auto = bf16 where the CPU (AVX512-BF16/AMX) or GPU runs it natively, "
              "else fp32", default="auto", configure_only=True, choices=("auto", "fp32", "bf16")),
    ParamSpec("num_samples", "completions per call when the request says 0 (and in continuous mode)", 1, 1000,
              field="num_samples", constraints="<= max_num_samples"),
    ParamSpec("max_num_samples", "requests asking for more samples are rejected", 1, 1000, field="max_num_samples"),
    ParamSpec("box_temperature", "factor on the posterior sigma of PSSNet's box latent (wider = more diverse "
              "hidden sides); 0 = the value calibrated with the model", 0.0, 10.0, field="box_temperature",
              constraints="0 or 1 for models without a box part"),
    ParamSpec("sampler", "posterior = the model's samples as drawn; checked = many proposals, those the view "
              "rules out rejected, the rest spread over what the view allows and weighted", field="sampler",
              choices=("posterior", "checked"), constraints="checked needs a latent-variable model"),
    ParamSpec("check_delta", "checked sampler: depth tolerance of its plausibility check, metres", 0.001, 0.2,
              field="check_delta"),
    ParamSpec("proposals_per_sample", "checked sampler: proposals decoded per requested sample", 1, 100,
              field="proposals_per_sample"),
    ParamSpec("refine_steps", "checked sampler: gradient steps that move its nearest misses towards the view "
              "(0 = none, cheaper: each step costs about three decodes of 20 latents, of 60 where fewer proposals "
              "than the requested samples pass the check)", 0, 100,
              field="refine_steps"),
    ParamSpec("seed", "latent-noise seed: the same input gives the same completions; -1 = a fresh seed per "
              "call", -1, INT32_MAX, field="seed"),
    ParamSpec("voxel_size", "grid voxel size in metres; 0 = the model's training voxel size", 0.0, 0.1,
              field="voxel_size", constraints="must equal the model's when its checkpoint records one"),
    ParamSpec("front_margin", "grid placement: voxels in front of the nearest observed point", 0.0, 16.0,
              field="front_margin", constraints="< grid size / 2"),
    ParamSpec("bottom_margin", "grid placement: voxels below the lowest observed point", 0.0, 16.0,
              field="bottom_margin", constraints="< grid size / 2"),
    ParamSpec("up_vector", "up (against gravity) in the camera optical frame; [0, -1, 0] for a level camera",
              field="up_vector", length=3, nonzero=True,
              constraints=f"3 finite numbers, length {UP_VECTOR_LENGTH[0]:g} to {UP_VECTOR_LENGTH[1]:g}"),
    ParamSpec("estimate_up", "estimate up from the support plane around the object (RANSAC); up_vector is then "
              "the prior that orients it", field="estimate_up"),
    ParamSpec("up_check_deg", "with estimate_up false: warn when the support plane around the object is tilted "
              "more than this from up_vector, degrees; 0 = no check", 0.0, 90.0, field="up_check_deg"),
    ParamSpec("support_plane_distance", "support-plane RANSAC inlier distance, metres", 0.0005, 0.05,
              field="support_plane_distance"),
    ParamSpec("support_plane_max_tilt_deg", "largest angle between the fitted plane normal and up_vector",
              1.0, 90.0, field="support_plane_max_tilt_deg"),
    ParamSpec("depth_scale", "metres per unit of 16UC1 depth images (0.001 = millimetres)", 1e-6, 1.0,
              default=0.001),
    ParamSpec("min_depth", "readings closer than this are ignored, metres", 0.0, 50.0, field="min_depth",
              constraints="< max_depth"),
    ParamSpec("max_depth", "readings farther than this are ignored, metres", 0.01, 100.0, field="max_depth"),
    ParamSpec("min_mask_pixels", "masks with fewer pixels are rejected", 1, 10_000_000, field="min_mask_pixels"),
    ParamSpec("min_valid_points", "fewer masked pixels with valid depth are rejected", 1, 10_000_000,
              field="min_valid_points"),
    ParamSpec("min_valid_fraction", "a smaller share of the masked pixels with valid depth is rejected", 0.0, 1.0,
              field="min_valid_fraction"),
    ParamSpec("sync_tolerance", "largest stamp difference of a synchronised depth/mask/camera_info set, seconds",
              0.0, 10.0, default=0.01),
    ParamSpec("max_input_age", "sets older than this (node clock minus stamp) are stale: dropped in continuous "
              "mode, refused by the service; seconds, 0 = no limit", 0.0, 3600.0, default=1.0),
    ParamSpec("continuous", "complete every newest synchronised set (at most max_rate_hz) and publish; false = "
              "serve the service only", default=False),
    ParamSpec("max_rate_hz", "continuous mode: largest completion rate, Hz", 0.01, 100.0, default=2.0),
    ParamSpec("continuous_grasps", "continuous mode: also compute and publish grasps", default=True),
    ParamSpec("publish_service_results", "also publish each service (and action) result on the output topics "
              "(RViz shows what a planner asked for)", default=False),
    ParamSpec("grasp_max_opening", "gripper: largest distance between the finger pads, metres", 0.005, 0.5,
              field="grasps.gripper.max_opening"),
    ParamSpec("grasp_finger_length", "gripper: finger length from palm to fingertips, metres", 0.001, 0.5,
              field="grasps.gripper.finger_length"),
    ParamSpec("grasp_finger_width", "gripper: finger extent across the closing plane, metres", 0.001, 0.5,
              field="grasps.gripper.finger_width"),
    ParamSpec("grasp_finger_thickness", "gripper: finger extent along the closing axis, metres", 0.001, 0.5,
              field="grasps.gripper.finger_thickness"),
    ParamSpec("grasp_palm_depth", "gripper: palm thickness behind the fingers, metres", 0.001, 0.5,
              field="grasps.gripper.palm_depth"),
    ParamSpec("grasp_min_object_width", "less object than this between the fingers is not held, metres", 0.0, 0.5,
              field="grasps.gripper.min_object_width", constraints="< grasp_max_opening"),
    ParamSpec("grasp_clearance", "free space between each finger pad and the widest completion, metres", 0.0,
              0.25, field="grasps.clearance", constraints="< grasp_max_opening / 2"),
    ParamSpec("grasp_surface_at_voxel_centres", "the clearance is measured from the completions' outermost voxels' "
              "centres, where the surface passes (a voxel is occupied wherever the surface crosses it), not from "
              "their outer faces; no finger enters an occupied voxel either way",
              field="grasps.surface_at_voxel_centres"),
    ParamSpec("grasp_max_candidates", "candidate grasps scored against every completion", 1, 100_000,
              field="grasps.max_candidates"),
    ParamSpec("grasp_top_yaws", "closing-axis angles of top-down grasps (0 = no top grasps)", 0, 180,
              field="grasps.top_yaws"),
    ParamSpec("grasp_side_yaws", "horizontal approach directions of side grasps (0 = no side grasps)", 0, 360,
              field="grasps.side_yaws", constraints="grasp_top_yaws or grasp_side_yaws > 0"),
    ParamSpec("grasp_side_rolls", "closing-axis angles of side and tilted grasps about the approach, degrees: 0 = "
              "horizontal, 90 = vertical", field="grasps.side_rolls", constraints="finite degrees"),
    ParamSpec("grasp_tilted_pitches", "approaches pitched this far below the horizontal at every side yaw, degrees "
              "(they reach a handle under a shelf); [] = none", field="grasps.tilted_pitches",
              constraints="each in (0, 90)"),
    ParamSpec("grasp_shallow_depths", "besides the deepest grasp, grasps whose fingertips go only this far past the "
              "first contact, metres (a handle pinch clear of the body); [] = deepest only",
              field="grasps.shallow_depths", constraints="each in (0, grasp_finger_length)"),
    ParamSpec("grasp_thin_anchor_bias", "candidates are anchored on thin parts (handles) more often: draw "
              "probability ~ local density ^ -bias; 0 = uniform", 0.0, 4.0, field="grasps.thin_anchor_bias"),
    ParamSpec("grasp_dense_below", "when the best grasp found holds less than this share of the object's weight "
              "(or none holds), search again with the grasp_dense_* options and rank both searches' grasps "
              "together; 0 = never", 0.0, 1.0, field="grasps.dense_below"),
    ParamSpec("grasp_dense_max_candidates", "the denser search: candidate grasps", 1, 100_000,
              field="grasps.dense_max_candidates"),
    ParamSpec("grasp_dense_side_yaws", "the denser search: horizontal approach directions", 0, 360,
              field="grasps.dense_side_yaws"),
    ParamSpec("grasp_dense_tilted_pitches", "the denser search: tilted approaches' pitches below the horizontal, "
              "degrees", field="grasps.dense_tilted_pitches", constraints="each in (0, 90)"),
    ParamSpec("grasp_dense_shallow_depths", "the denser search: shallow grasps' fingertip depths past the first "
              "contact, metres", field="grasps.dense_shallow_depths", constraints="each in (0, grasp_finger_length)"),
    ParamSpec("grasp_rank_by", "expected_grip = by the weighted share of completions each grasp holds firmly "
              "(pad contact x weight held); fraction = by the share of completions it holds", field="grasps.rank_by",
              choices=("expected_grip", "fraction")),
    ParamSpec("grasp_grip_force", "gripper: force each finger presses with, newtons (for the weight check)", 0.1,
              1000.0, field="grasps.gripper.grip_force"),
    ParamSpec("grasp_holds_axial_load", "gripper: the fingers hold a load along the closing axis (a stiff, "
              "non-backdrivable drive); false = force-controlled fingers that follow it",
              field="grasps.gripper.holds_axial_load"),
    ParamSpec("grasp_observed_points_check", "no grasp with an observed point (at the camera's resolution) inside a "
              "finger or the palm; the completions' voxels alone can leave a finger room where the camera saw "
              "surface", field="grasps.observed_points_check"),
    ParamSpec("grasp_friction", "friction coefficient between finger pads and object (for the weight check)", 0.05,
              2.0, field="grasps.friction"),
    ParamSpec("grasp_object_density", "density assumed for every completion when the weight check turns volume "
              "into weight, kg/m^3", 10.0, 25000.0, field="grasps.object_density"),
    ParamSpec("grasp_top_k", "grasps returned, best first", 1, 1000, field="grasp_top_k"),
    ParamSpec("grasp_min_score", "grasps holding for a smaller fraction of the completions are not returned",
              0.0, 1.0, field="grasp_min_score"),
)

SPECS: dict[str, ParamSpec] = {spec.name: spec for spec in PARAMETERS}
CONFIGURE_ONLY: frozenset[str] = frozenset(spec.name for spec in PARAMETERS if spec.configure_only)


def defaults() -> dict[str, Any]:
    """Name -> default value (arrays as lists)."""
    return {s.name: list(s.default) if isinstance(s.default, tuple) else s.default for s in PARAMETERS}


def from_ros(name: str, value: Any) -> Any:
    """A value as rclpy hands it over, in the form :func:`check_values` takes: arrays as lists of floats (rclpy
    gives ``array.array``), and an unset variable-length array as empty (rcl reads ``[]`` in a parameter file as
    unset: it cannot tell the element type of an empty list)."""
    spec = SPECS.get(name)
    if spec is None or spec.ros_type != ParameterType.PARAMETER_DOUBLE_ARRAY:
        return value
    if value is None:
        return [] if spec.length is None else None
    try:
        return [float(v) for v in value]
    except (TypeError, ValueError):
        return value  # check_values says what is wrong with it


def check_values(values: dict[str, Any]) -> str | None:
    """The reason ``values`` (a complete name -> value dict) is invalid, or None when it is valid.

    Checks the type, range and choices of each value (as rclpy does, so that the same rules hold for a YAML
    file checked without a node), then builds the pipeline config, whose own checks cover the rules that span
    values (num_samples <= max_num_samples, min_depth < max_depth, the gripper's clearances, ...).
    """
    for name, value in values.items():
        spec = SPECS.get(name)
        if spec is None:
            return f"unknown parameter {name!r}"
        reason = _check_one(spec, value)
        if reason:
            return reason
    try:
        pipeline_config(values)
    except ValueError as error:
        return str(error)
    return None


def _check_one(spec: ParamSpec, value: Any) -> str | None:
    name = spec.name
    if spec.ros_type == ParameterType.PARAMETER_DOUBLE_ARRAY:
        count = "" if spec.length is None else f"{spec.length} "
        try:
            if isinstance(value, str | bytes):
                raise TypeError
            vector = [float(v) for v in value]
        except (TypeError, ValueError):
            return f"{name} must be a list of {count or 'finite '}numbers, got {value!r}"
        if (spec.length is not None and len(vector) != spec.length) or not all(math.isfinite(v) for v in vector) \
                or (spec.nonzero and not any(vector)):
            return f"{name} must be {count}finite numbers{', not all zero' if spec.nonzero else ''}, got {list(value)}"
        return None  # the values' own ranges (a direction's length, a pitch's) are the pipeline config's checks
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
            return f"{name} must be in {spec.range_text()}, got {value}"
    return None


def _as_field_type(value: Any, default: Any) -> Any:
    """A parameter value in the type of the config field it sets (ROS doubles may arrive as ints, arrays as lists)."""
    if isinstance(default, tuple):
        return tuple(float(v) for v in value)
    return type(default)(value)


def pipeline_config(values: dict[str, Any]) -> PipelineConfig:
    """The pipeline configuration for a complete set of parameter values, built from the specs' fields.

    Raises:
        ValueError: the configs refuse the values (the message says which rule).
    """
    nested: dict[str, Any] = {}
    for spec in PARAMETERS:
        if spec.field:
            *parents, leaf = spec.field.split(".")
            level = nested
            for parent in parents:
                level = level.setdefault(parent, {})
            level[leaf] = _as_field_type(values[spec.name], spec.default)
    grasps = nested.pop("grasps", {})
    gripper = GripperConfig(**grasps.pop("gripper", {}))
    # Fields no parameter sets keep their defaults (e.g. the grasp seed, replaced by each call's seed).
    return dataclasses.replace(_DEFAULT_PIPELINE, grasps=dataclasses.replace(GraspConfig(), gripper=gripper, **grasps),
                               **nested)


def markdown_table() -> str:
    """The parameter table (Markdown), for the README and ``completion_node --help``."""
    lines = ["| parameter | type | default | range | description |", "|---|---|---|---|---|"]
    for spec in PARAMETERS:
        description = spec.description + (" (set before configure)" if spec.configure_only else "")
        lines.append(f"| `{spec.name}` | {spec.type_name} | `{literal(spec.default)}` | {spec.range_text()} | "
                     f"{description} |")
    return "\n".join(lines)


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
        lines.append(f"    {spec.name}: {literal(spec.default)}")
    lines += ["    # QoS of the inputs and outputs, read at start-up (history, depth, reliability), by resolved topic",
              "    # name; by default the inputs are best effort (sensor-data and reliable publishers both connect)",
              "    # and the outputs reliable.",
              "    # qos_overrides:",
              "    #   /camera/depth/image_rect:",
              "    #     subscription:",
              "    #       reliability: reliable",
              "    #       depth: 5"]
    return "\n".join(lines) + "\n"
