"""Node parameters: descriptors with ranges, validation rules with reasons, YAML defaults, rclpy enforcement."""

from __future__ import annotations

import array
import re
from pathlib import Path

import pytest
import yaml
from rcl_interfaces.msg import ParameterType

from pssnet_core.pipeline import PipelineConfig
from pssnet_ros.params import (
    CONFIGURE_ONLY,
    PARAMETERS,
    SPECS,
    check_values,
    config_default,
    default_yaml,
    defaults,
    from_ros,
    markdown_table,
    pipeline_config,
)

CONFIG = Path(__file__).resolve().parents[1] / "pssnet_ros" / "config" / "completion_node.yaml"


def test_yaml_lists_every_parameter_with_its_default():
    values = yaml.safe_load(CONFIG.read_text())["/**"]["ros__parameters"]
    assert values == defaults()
    assert CONFIG.read_text() == default_yaml(), "regenerate config/completion_node.yaml from params.default_yaml()"
    for spec in PARAMETERS:  # doubles must stay doubles in YAML, or rclpy rejects the type
        if spec.ros_type == ParameterType.PARAMETER_DOUBLE:
            assert isinstance(values[spec.name], float), spec.name


def test_defaults_are_valid_and_build_the_pipeline_config():
    assert check_values(defaults()) is None
    config = pipeline_config(defaults())
    assert isinstance(config, PipelineConfig) and config.num_samples == 20 and config.up_vector == (0.0, -1.0, 0.0)


def test_descriptors_carry_type_range_and_when_they_may_change():
    d = SPECS["num_samples"].descriptor()
    assert d.type == ParameterType.PARAMETER_INTEGER and d.description
    assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (1, 1000)
    d = SPECS["sync_tolerance"].descriptor()
    assert d.type == ParameterType.PARAMETER_DOUBLE and d.floating_point_range[0].to_value == 10.0
    for name in ("autostart", "model_path", "device", "threads", "precision"):
        assert name in CONFIGURE_ONLY and "set before configure" in SPECS[name].descriptor().additional_constraints
    assert "num_samples" not in CONFIGURE_ONLY
    assert "one of: cpu, cuda" in SPECS["device"].descriptor().additional_constraints
    assert SPECS["up_vector"].descriptor().type == ParameterType.PARAMETER_DOUBLE_ARRAY
    for spec in PARAMETERS:
        assert spec.description, spec.name
        if spec.ros_type in (ParameterType.PARAMETER_INTEGER, ParameterType.PARAMETER_DOUBLE):
            assert spec.low is not None and spec.low <= spec.default <= spec.high, spec.name


@pytest.mark.parametrize("changes, reason", [
    ({"num_samples": 200}, r"num_samples must be in \[1, max_num_samples=100\], got 200"),
    ({"num_samples": 0}, r"num_samples must be in \[1, 1000\], got 0"),
    ({"min_depth": 2.0, "max_depth": 1.0}, r"need 0 <= min_depth < max_depth, got 2.0 and 1.0"),
    ({"device": "tpu"}, "device must be one of cpu, cuda, got 'tpu'"),
    ({"up_vector": [0.0, 0.0, 0.0]}, "up_vector must be 3 finite numbers, not all zero"),
    ({"up_vector": [0.0, 1.0]}, "up_vector must be 3 finite numbers"),
    ({"up_vector": [0.0, float("nan"), 1.0]}, "up_vector must be 3 finite numbers"),
    ({"up_vector": [1e200, 1e200, 0.0]}, r"up_vector must be 3 finite numbers of length 1e-06 to 1e\+06"),
    ({"up_vector": [1e-200, 0.0, 0.0]}, r"up_vector must be 3 finite numbers of length 1e-06 to 1e\+06"),
    ({"min_valid_fraction": 1.5}, r"min_valid_fraction must be in \[0.0, 1.0\], got 1.5"),
    ({"max_rate_hz": float("inf")}, "max_rate_hz must be finite"),
    ({"sync_tolerance": -0.1}, r"sync_tolerance must be in \[0.0, 10.0\], got -0.1"),
    ({"continuous": 1}, "continuous must be a bool, got 1"),
    ({"seed": 1.5}, "seed must be an int, got 1.5"),
    ({"nonsense": 1}, "unknown parameter 'nonsense'"),
    ({"grasp_clearance": 0.05}, r"clearance must be in \[0, max_opening/2\) m, got 0.05"),
    ({"grasp_top_yaws": 0, "grasp_side_yaws": 0}, "no approach direction"),
    ({"grasp_tilted_pitches": "45"}, r"grasp_tilted_pitches must be a list of finite numbers, got '45'"),
    ({"grasp_tilted_pitches": [95.0]}, r"tilted_pitches must be degrees in \(0, 90\)"),
    ({"grasp_side_rolls": [0.0, float("inf")]}, "grasp_side_rolls must be finite numbers"),
    ({"grasp_shallow_depths": [0.06]}, r"shallow_depths must be in \(0, finger_length=0.05\)"),
    ({"grasp_rank_by": "luck"}, "grasp_rank_by must be one of expected_grip, fraction, got 'luck'"),
    ({"grasp_holds_axial_load": 1}, "grasp_holds_axial_load must be a bool"),
    ({"grasp_friction": 3.0}, r"grasp_friction must be in \[0.05, 2.0\], got 3.0"),
    ({"grasp_dense_below": 1.5}, r"grasp_dense_below must be in \[0.0, 1.0\], got 1.5"),
    ({"grasp_dense_tilted_pitches": [0.0]}, r"tilted_pitches must be degrees in \(0, 90\)"),
])
def test_invalid_values_are_rejected_with_a_reason(changes, reason):
    values = {**defaults(), **changes}
    result = check_values(values)
    assert result is not None
    assert re.search(reason, result), result


def test_markdown_table_has_every_parameter():
    table = markdown_table()
    for spec in PARAMETERS:
        assert f"| `{spec.name}` |" in table


@pytest.fixture(scope="module")
def param_node():
    """A bare node in this process with the parameters declared (no DDS traffic needed)."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=101, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("param_test", context=context)
    for spec in PARAMETERS:
        default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
        node.declare_parameter(spec.name, default, spec.descriptor())
    yield node
    node.destroy_node()
    context.try_shutdown()


def test_rclpy_enforces_descriptor_ranges_and_types(param_node):
    from rclpy.parameter import Parameter

    results = param_node.set_parameters([
        Parameter("num_samples", value=5000), Parameter("sync_tolerance", value="fast"),
        Parameter("num_samples", value=30)])
    assert not results[0].successful and "out of range" in results[0].reason
    assert not results[1].successful and "type" in results[1].reason.lower()
    assert results[2].successful and param_node.get_parameter("num_samples").value == 30


def test_every_pipeline_parameter_names_a_config_field_with_its_default():
    fields = [spec.field for spec in PARAMETERS if spec.field]
    assert len(fields) == len(set(fields)) == 49
    for spec in PARAMETERS:
        if spec.field:
            assert spec.default == config_default(spec.field), spec.name
    # Each field-backed value reaches its field: change every one at once and read them back from the config.
    values = defaults()
    changed = {"num_samples": 7, "max_num_samples": 50, "box_temperature": 1.5, "seed": -1, "voxel_size": 0.004,
               "front_margin": 2.0, "bottom_margin": 0.5, "up_vector": [0.0, 0.0, 1.0], "estimate_up": True,
               "support_plane_distance": 0.002, "support_plane_max_tilt_deg": 30.0, "min_depth": 0.2,
               "max_depth": 3.0, "min_mask_pixels": 10, "min_valid_points": 5, "min_valid_fraction": 0.5,
               "grasp_max_opening": 0.1,
               "grasp_finger_length": 0.06, "grasp_finger_width": 0.015, "grasp_finger_thickness": 0.012,
               "grasp_palm_depth": 0.03, "grasp_min_object_width": 0.004, "grasp_clearance": 0.004,
               "grasp_max_candidates": 300, "grasp_top_yaws": 4, "grasp_side_yaws": 6, "grasp_top_k": 3,
               "grasp_min_score": 0.25, "sampler": "posterior", "check_delta": 0.02, "proposals_per_sample": 5,
               "refine_steps": 2, "up_check_deg": 10.0, "grasp_side_rolls": [0.0, 45.0, 90.0],
               "grasp_tilted_pitches": [30.0, 60.0],
               "grasp_shallow_depths": [], "grasp_thin_anchor_bias": 2.0, "grasp_rank_by": "fraction",
               "grasp_grip_force": 40.0, "grasp_holds_axial_load": True, "grasp_friction": 0.8,
               "grasp_object_density": 400.0, "grasp_observed_points_check": False,
               "grasp_surface_at_voxel_centres": False, "grasp_dense_below": 0.5,
               "grasp_dense_max_candidates": 900, "grasp_dense_side_yaws": 36, "grasp_dense_tilted_pitches": [30.0],
               "grasp_dense_shallow_depths": [0.02]}
    assert set(changed) == {s.name for s in PARAMETERS if s.field}
    config = pipeline_config({**values, **changed})
    for name, value in changed.items():
        got = config_value(config, SPECS[name].field)
        assert got == (tuple(value) if isinstance(value, list) else value), name


def config_value(config, path: str):
    for part in path.split("."):
        config = getattr(config, part)
    return config


def test_an_empty_list_in_a_parameter_file_turns_an_option_off(tmp_path):
    """rcl reads ``[]`` in a parameter file as unset (an empty list has no element type): the node takes it as
    empty for a list parameter, and still refuses an unset ``up_vector``."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    grasp_tilted_pitches: []\n")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=102, signal_handler_options=SignalHandlerOptions.NO,
               args=["--ros-args", "--params-file", str(params)])
    try:
        node = rclpy.create_node("empty_list_test", context=context)
        spec = SPECS["grasp_tilted_pitches"]
        raw = node.declare_parameter(spec.name, list(spec.default), spec.descriptor()).value
        node.destroy_node()
    finally:
        context.try_shutdown()
    assert raw is None  # what rcl makes of it
    values = {**defaults(), spec.name: from_ros(spec.name, raw)}
    assert values[spec.name] == [] and check_values(values) is None
    assert pipeline_config(values).grasps.tilted_pitches == ()
    assert from_ros("up_vector", None) is None and "up_vector must be a list of 3 numbers" in check_values(
        {**defaults(), "up_vector": None})
    assert from_ros("grasp_side_rolls", array.array("d", [0.0, 90.0])) == [0.0, 90.0]  # as rclpy gives arrays
