"""Spinning an executor until its context shuts down, and shutting it down, without rclpy's shutdown races.

rclpy's signal handler shuts the context down from another thread on SIGINT/SIGTERM. Two races follow, each
of which turned a clean Ctrl-C into a traceback and exit code 1 now and then:

- an executor that is building its wait set at that moment raises rclpy's RCLError (a RuntimeError: "failed
  to initialize wait set: the given context is not valid") instead of ExternalShutdownException
  (ros2/rclpy#398, ros2/ros2cli#854): :func:`spin_until_shutdown`;
- ``rclpy.try_shutdown()`` checks that the context is valid, then shuts it down; when the signal handler's
  thread shuts it down in between, rcl raises "rcl_shutdown already called on the given context"
  (ros2/rclpy#1352, fixed upstream after the rclpy 7.1 this project runs): :func:`shutdown_once`.
"""

from __future__ import annotations

import rclpy
from rclpy.context import Context
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


def shutdown_once(context: Context | None = None) -> None:
    """``try_shutdown`` of ``context`` (default: rclpy's default context) that leaves quietly when another
    thread (rclpy's signal handler) has shut it down meanwhile.

    Raises:
        RuntimeError: a failure to shut down a context that is still valid.
    """
    try:
        rclpy.try_shutdown(context=context)
    except RuntimeError:
        # On this failure rclpy keeps the failed context as its default, so this is the context that failed.
        if (context if context is not None else rclpy.get_default_context()).ok():
            raise
