"""Spinning an executor until its context shuts down, without rclpy's shutdown race.

rclpy's signal handler shuts the context down from another thread on SIGINT/SIGTERM. An executor that is
building its wait set at that moment raises rclpy's RCLError (a RuntimeError: "failed to initialize wait set:
the given context is not valid") instead of ExternalShutdownException: a known rclpy race (ros2/rclpy#398,
ros2/ros2cli#854) that turned a clean Ctrl-C into a traceback and exit code 1 now and then.
"""

from __future__ import annotations

from rclpy.executors import Executor, ExternalShutdownException


def spin_until_shutdown(executor: Executor) -> None:
    """``executor.spin()``; returns once the executor's context has been shut down (signal or rclpy.shutdown).

    Raises:
        RuntimeError: an error while the context is still valid (a real failure, not the shutdown race).
    """
    try:
        executor.spin()
    except ExternalShutdownException:
        pass
    except RuntimeError:
        if executor.context.ok():
            raise
