"""Starting and stopping ROS 2 processes from Python (no ros2cli/launch here): the demo, tests and benchmark.

- :func:`ros_env`: the environment of a child process: its own ROS_DOMAIN_ID, discovery on localhost, the
  shipped Fast DDS profile, and the ROS wheels' bootstrap guard cleared (a child must redo the wheels'
  library-path set-up itself, which matters when it runs another interpreter).
- :class:`RosProcess`: a child process whose output is collected in the background; ``wait_for`` a log
  line, ``stop`` with SIGINT (then SIGTERM/SIGKILL only if it hangs), and the Fast DDS shared-memory
  files it had mapped, to check that none are left behind.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

BOOTSTRAP_GUARD = "_ROS_WHEELS_BOOTSTRAP_COMPLETE"
SHM_DIR = Path("/dev/shm")
_SHM_RE = re.compile(r"(/dev/shm/(?:sem\.)?fastrtps_\S+)")


def fastdds_profile() -> Path | None:
    """The shipped Fast DDS profile: config/ of the source tree, or share/pssnet_ros/config of an install."""
    source = Path(__file__).resolve().parents[1] / "config" / "fastdds_profile.xml"
    if source.is_file():
        return source
    try:
        from ament_index_python.packages import get_package_share_directory

        installed = Path(get_package_share_directory("pssnet_ros")) / "config" / "fastdds_profile.xml"
        return installed if installed.is_file() else None
    except Exception:  # no ament index (package not installed through colcon)
        return None


def ros_env(domain_id: int, extra: Mapping[str, str] | None = None, base: Mapping[str, str] | None = None
            ) -> dict[str, str]:
    """Environment for a ROS 2 child process.

    Args:
        domain_id: ROS_DOMAIN_ID (0-101 on Linux): one per test module / demo run avoids cross-talk.
        extra: variables to set on top.
        base: starting environment (default: this process's).
    """
    if not 0 <= domain_id <= 101:
        raise ValueError(f"ROS_DOMAIN_ID must be in [0, 101], got {domain_id}")
    env = dict(os.environ if base is None else base)
    env.pop(BOOTSTRAP_GUARD, None)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    profile = fastdds_profile()
    if profile is not None:
        env.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(profile))
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
    env.update(extra or {})
    return env


def configure_this_process(domain_id: int) -> None:
    """Sets the discovery range and Fast DDS profile for ROS contexts created later in *this* process."""
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    profile = fastdds_profile()
    if profile is not None:
        os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(profile))
    os.environ["ROS_DOMAIN_ID"] = str(domain_id)


def mapped_shm_files(pid: int) -> set[str]:
    """Fast DDS shared-memory files a live process has mapped (empty once it exited)."""
    try:
        text = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return set()
    return set(_SHM_RE.findall(text))


def stale_shm_files(files: set[str]) -> set[str]:
    """Those of ``files`` that still exist and that no live process maps any more."""
    existing = {f for f in files if Path(f).exists()}
    if not existing:
        return set()
    in_use: set[str] = set()
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            in_use |= mapped_shm_files(int(proc.name))
    return existing - in_use


class RosProcess:
    """A child process with collected output (stdout and stderr merged)."""

    def __init__(self, argv: Sequence[str], env: Mapping[str, str], name: str = "process",
                 cwd: str | os.PathLike | None = None, echo: bool = False) -> None:
        self.name = name
        self.argv = list(argv)
        self._lines: list[str] = []
        self._cond = threading.Condition()
        self._echo = echo
        self.shm_files: set[str] = set()
        self.proc = subprocess.Popen(self.argv, env=dict(env), cwd=cwd, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, bufsize=1)
        self._reader = threading.Thread(target=self._read, name=f"{name}-reader", daemon=True)
        self._reader.start()

    @classmethod
    def python_module(cls, module: str, args: Sequence[str], env: Mapping[str, str], name: str | None = None,
                      python: str | None = None, **kwargs) -> RosProcess:
        """Runs ``python -m module args`` (default interpreter: this one)."""
        return cls([python or sys.executable, "-m", module, *args], env, name=name or module, **kwargs)

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._cond:
                self._lines.append(line.rstrip("\n"))
                self._cond.notify_all()
            if self._echo:
                print(f"[{self.name}] {line}", end="", file=sys.stderr)
        with self._cond:
            self._cond.notify_all()

    @property
    def output(self) -> str:
        with self._cond:
            return "\n".join(self._lines)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def running(self) -> bool:
        return self.proc.poll() is None

    def wait_for(self, pattern: str, timeout: float = 60.0) -> re.Match[str]:
        """Waits for an output line matching ``pattern``; raises TimeoutError or RuntimeError (process exited)."""
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout
        seen = 0
        with self._cond:
            while True:
                for line in self._lines[seen:]:
                    match = regex.search(line)
                    if match:
                        self.shm_files |= mapped_shm_files(self.pid)
                        return match
                seen = len(self._lines)
                if self.proc.poll() is not None and not self._reader.is_alive():
                    raise RuntimeError(f"{self.name} exited with code {self.proc.returncode} before printing "
                                       f"{pattern!r}; output:\n{self.output[-4000:]}")
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"{self.name} did not print {pattern!r} within {timeout} s; output:\n"
                                       f"{self.output[-4000:]}")
                self._cond.wait(timeout=min(remaining, 0.5))

    def stop(self, timeout: float = 20.0) -> int:
        """SIGINT, wait; SIGTERM then SIGKILL only when it does not exit. Returns the exit code."""
        if self.proc.poll() is None:
            self.shm_files |= mapped_shm_files(self.pid)
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.terminate()
                try:
                    self.proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
        self._reader.join(timeout=5)
        return self.proc.returncode

    def __enter__(self) -> RosProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
