"""A completion node under test: started on its own ROS domain, awaited until it serves, stopped cleanly.

    with NodeUnderTest(model_path=checkpoint, threads=1) as node:
        node.ros.call(...)        # a RosClient on the node's domain
        node.process.lines()      # the node's output
        node.restart()            # a fresh process, same domain and parameters

Readiness is the node's lifecycle state read over the graph (``get_state``), not a log line: "active" for the
plain node, "unconfigured" with ``autostart: false``. The tests, the benchmarks and the demo start the node
through this one class.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pssnet_testing.client import NODE, RosClient, wait_until
from pssnet_testing.processes import RosProcess, claim_domain_id, ros_env, ros_param_args

MODULE = "pssnet_ros.completion_node"


class NodeUnderTest:
    """One completion_node process at a time on one ROS domain, and a :class:`RosClient` on that domain.

    Args:
        domain: ROS_DOMAIN_ID (default: one claimed for this process, see :func:`claim_domain_id`).
        state: the lifecycle state that means "ready" (default: "active", or "unconfigured" when ``autostart``
            is False in ``params``).
        timeout: seconds the node may take to become ready.
        env: extra environment variables of the node process.
        client_name: node name of the client.
        echo: copy the node's output to this process's stderr.
        params: the node's parameters (``name=value``; see ``completion_node --help``).
    """

    def __init__(self, domain: int | None = None, *, state: str | None = None, timeout: float = 180.0,
                 env: Mapping[str, str] | None = None, client_name: str = "node_under_test_client",
                 echo: bool = False, **params: Any) -> None:
        self.domain = claim_domain_id() if domain is None else domain
        self.params = params
        self.state = state or ("unconfigured" if params.get("autostart") is False else "active")
        self.timeout = timeout
        self.echo = echo
        self._env = ros_env(self.domain, extra=env)
        self._client_name = client_name
        self._ros: RosClient | None = None
        self.process: RosProcess | None = None

    @property
    def ros(self) -> RosClient:
        """The client on the node's domain (created on first use, closed by :meth:`close`)."""
        if self._ros is None:
            self._ros = RosClient(self.domain, self._client_name)
        return self._ros

    def start(self) -> RosProcess:
        """Starts the node and waits until it is in :attr:`state`.

        Raises:
            RuntimeError: the process exited first (the message has its output).
            TimeoutError: not ready within :attr:`timeout` s.
        """
        process = RosProcess.python_module(MODULE, ros_param_args(**self.params), self._env, name="completion_node",
                                           echo=self.echo)
        self.process = process
        try:
            wait_until(lambda: self._in_state(process), self.timeout, f"completion_node {self.state}",
                       interval=0.1)
        except BaseException as error:
            process.stop()
            if isinstance(error, TimeoutError):
                raise TimeoutError(f"{error}; its output:\n{process.output[-4000:]}") from None
            raise
        process.record_shm_files()
        return process

    def _in_state(self, process: RosProcess) -> bool:
        if not process.running():
            raise RuntimeError(f"completion_node exited with code {process.proc.returncode} before it was "
                               f"{self.state}; its output:\n{process.output[-4000:]}")
        try:
            return self.ros.lifecycle_state(NODE, timeout=2.0) == self.state
        except TimeoutError:  # not discovered yet, or not spinning yet
            return False

    def restart(self) -> RosProcess:
        """Stops the current process (if it still runs) and starts a new one."""
        self.stop()
        return self.start()

    def stop(self) -> int | None:
        """Stops the node (SIGINT, harder only if it hangs); its exit code, None when none was started."""
        return None if self.process is None else self.process.stop()

    def close_client(self) -> None:
        """Closes the client (its DDS participant leaves the domain); the next use creates a new one."""
        if self._ros is not None:
            self._ros.close()
            self._ros = None

    def close(self) -> int | None:
        """Stops the node and closes the client; the node's exit code."""
        code = self.stop()
        self.close_client()
        return code

    def __enter__(self) -> NodeUnderTest:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
