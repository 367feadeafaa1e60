"""Node parameters: descriptors with ranges, validation rules with reasons, YAML defaults, rclpy enforcement."""

from __future__ import annotations

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
    assert len(fields) == len(set(fields)) == 32
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
               "up_check_deg": 10.0}
    assert set(changed) == {s.name for s in PARAMETERS if s.field}
    config = pipeline_config({**values, **changed})
    for name, value in changed.items():
        got = config_value(config, SPECS[name].field)
        assert got == (tuple(value) if isinstance(value, list) else value), name


def config_value(config, path: str):
    for part in path.split("."):
        config = getattr(config, part)
    return config
