"""Start-up failures of completion_node: a clear one-line error and a non-zero exit, never a traceback wall."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from test_integrity import bench
from test_node_helpers import domain_for, tiny_checkpoint

from pssnet_core.inference import DEFAULT_CHECKPOINT
from pssnet_testing.processes import RosProcess, configure_this_process, ros_env, ros_param_args

pytestmark = pytest.mark.ros
DOMAIN = domain_for(3)


def test_startup_errors_are_one_clean_line_and_exit_2(tmp_path):
    """Separate processes, as users start the node: bad model files and a bad parameter."""
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"\x80\x02 definitely not a zip archive" * 100)
    flipped = Path(shutil.copyfile(DEFAULT_CHECKPOINT, tmp_path / "flipped.pt"))
    bench.edit_bytes(flipped, np.random.default_rng(0), "flip")
    untrained = Path(shutil.copyfile(DEFAULT_CHECKPOINT, tmp_path / "untrained.pt"))
    bench.edit_state(untrained, bench.random_init(DEFAULT_CHECKPOINT), np.random.default_rng(0), True)
    cases = {
        "bit-flipped model": (ros_param_args(model_path=flipped),
                              r"\[completion_node\] error: cannot load the completion model: \S+flipped\.pt (is "
                              r"corrupt: (weights differ|weight \S+ (has|spans))|is not a readable checkpoint "
                              r"\(corrupt or truncated\?\))"),  # the shipped archive is deflated: a flip may break it
        "untrained model": (ros_param_args(model_path=untrained),
                            r"\[completion_node\] error: cannot load the completion model: \S+untrained\.pt: "
                            r"self-test failed: the model (empties|fills) the grid"),
        "missing model": (ros_param_args(model_path=tmp_path / "nope.pt"),
                          r"\[completion_node\] error: cannot load the completion model: no checkpoint file at "
                          r"\S+nope\.pt"),
        "corrupt model": (ros_param_args(model_path=corrupt),
                          r"\[completion_node\] error: cannot load the completion model: "
                          r"\S+corrupt\.pt is not a readable checkpoint \(corrupt or truncated\?\)"),
        "out of range": (ros_param_args(model_path=tmp_path / "nope.pt", num_samples=5000),
                         r"\[completion_node\] error: invalid parameter num_samples: .*out of range. Min: 1, Max: "
                         r"1000, value: 5000"),
        "bad ROS arguments": (["--ros-args", "-p", "model_path:="],
                              r"\[completion_node\] error: invalid ROS arguments: .*Couldn't parse parameter "
                              r"override rule: '-p model_path:='"),
    }
    env = ros_env(DOMAIN)
    procs = {name: (RosProcess.python_module("pssnet_ros.completion_node", args, env, name=name), pattern)
             for name, (args, pattern) in cases.items()}
    for name, (proc, pattern) in procs.items():
        code = proc.proc.wait(timeout=120)
        proc.stop()
        out = proc.output
        assert code == 2, f"{name}: exit code {code}\n{out}"
        assert re.search(pattern, out), f"{name}: {out}"
        assert "Traceback" not in out, f"{name}: {out}"
        assert sum(line.startswith("[completion_node] error: ") for line in out.splitlines()) == 1, f"{name}: {out}"


@pytest.fixture(scope="module")
def context():
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    configure_this_process(DOMAIN)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN, signal_handler_options=SignalHandlerOptions.NO)
    yield ctx
    ctx.try_shutdown()


def test_invalid_parameters_stop_startup_with_the_reason(tmp_path, context):
    """The same start-up path in this process (faster): every kind of invalid parameter value."""
    from rclpy.parameter import Parameter

    from pssnet_ros.completion_node import CompletionNode, StartupError

    good = str(tiny_checkpoint(tmp_path / "tiny.pt"))
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    cases = [
        ({"model_path": str(foreign)}, r"^cannot load the completion model: \S+foreign\.pt is not a PSSNet-ROS "
                                       r"checkpoint"),
        ({"sync_tolerance": "fast"}, r"^invalid parameter sync_tolerance: .*expecting type 'DOUBLE'"),
        ({"num_samples": 200}, r"^invalid parameters: num_samples must be in \[1, max_num_samples=100\], got 200$"),
        ({"device": "tpu"}, r"^invalid parameters: device must be one of cpu, cuda, got 'tpu'$"),
        ({"up_vector": [0.0, 0.0, 0.0]}, r"^invalid parameters: up_vector must be 3 finite numbers, not all zero"),
        ({"min_depth": 3.0, "max_depth": 2.0},
         r"^invalid parameters: need 0 <= min_depth < max_depth, got 3.0 and 2.0$"),
        ({"front_margin": 16.0}, r"^invalid parameters for this model: grid margins must be in \[0, size/2\) voxels$"),
    ]
    for changes, pattern in cases:
        overrides = [Parameter("model_path", value=good)] + [Parameter(k, value=v) for k, v in changes.items()]
        with pytest.raises(StartupError) as info:
            CompletionNode(context=context, parameter_overrides=overrides)
        assert re.search(pattern, str(info.value)), str(info.value)
    node = CompletionNode(context=context, parameter_overrides=[Parameter("model_path", value=good)])
    assert node.pipeline.grid_size == 32
    node.destroy_node()


def test_help_prints_the_interface_and_parameters():
    proc = RosProcess.python_module("pssnet_ros.completion_node", ["--help"], ros_env(DOMAIN), name="help")
    assert proc.proc.wait(timeout=60) == 0
    proc.stop()
    assert "usage: completion_node" in proc.output and "/pssnet/sample_completions" in proc.output
    assert "| `num_samples` | int | `20` | [1, 1000] |" in proc.output
