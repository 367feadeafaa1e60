"""Starting and stopping ROS 2 processes from Python (no ros2cli/launch here): the demo, tests and benchmark.

- :func:`ros_env`: the environment of a child process: its own ROS_DOMAIN_ID, discovery on localhost, the
  shipped Fast DDS profile, and the ROS wheels' bootstrap guard cleared (a child must redo the wheels'
  library-path set-up itself, which matters when it runs another interpreter).
- :func:`free_domain_id`: a ROS_DOMAIN_ID that no DDS participant on this machine uses right now and no
  process has claimed; :func:`claim_domain_id` also claims it for the rest of this process's life, so that
  concurrent test runs, demos and benchmarks on one machine never share a domain.
- :class:`RosProcess`: a child process whose output is collected in the background; ``wait_for`` a log
  line, ``stop`` with SIGINT (then SIGTERM/SIGKILL only if it hangs), and the Fast DDS shared-memory
  segments it created, to check that none are left behind (:func:`stale_shm_files`);
  :func:`spinning_node_script`: the source of a small child node spun until SIGINT.
- :func:`rss_mb`, :func:`resident_mib_by_kind`, :func:`cpu_seconds`: a live process's memory and CPU time.

Fast DDS shared memory: every participant creates its own segments (``fastrtps_<id>``) and listens on port
segments (``fastrtps_port<n>``), some of which (ports 7000, 7001, ...) every participant on the machine
shares, whatever its domain. The owner of a segment or the listener of a port holds an exclusive flock on
its ``<name>_el`` file. A file left by another process (e.g. one killed with -9) may be opened and even taken
over by ours, so a process is blamed only for segments it owned that did not exist before it started.
The node removes the files of dead processes when it starts (:func:`pssnet_ros.shm.clean_stale_shm`).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Mapping, MutableMapping, Sequence
from pathlib import Path
from typing import BinaryIO

import pssnet_ros
from pssnet_ros.shm import SHM_DIR, locked_inodes, mapped_inodes

BOOTSTRAP_GUARD = "_ROS_WHEELS_BOOTSTRAP_COMPLETE"
SHM_PREFIX = "fastrtps_"
LOCK_SUFFIX = "_el"  # Fast DDS: the owner of segment X holds a flock on X_el
#: RTPS well-known ports (UDP): domain d uses [PORT_BASE + DOMAIN_GAIN * d, ... + DOMAIN_GAIN)
PORT_BASE, DOMAIN_GAIN = 7400, 250


#: With it rmw_fastrtps reads the history memory policy (and publication mode, data sharing) from the profile: the
#: shipped profile frees a service request's payload once taken instead of keeping the buffer at the largest
#: request's size (set only together with the shipped profile; another profile may not restate rmw's defaults).
USE_QOS_FROM_XML = "RMW_FASTRTPS_USE_QOS_FROM_XML"


def fastdds_profile() -> Path | None:
    """The shipped Fast DDS profile of the pssnet_ros package: its config/ in the source tree (beside the
    package's modules), or share/pssnet_ros/config of an install."""
    source = Path(pssnet_ros.__file__).resolve().parents[1] / "config" / "fastdds_profile.xml"
    if source.is_file():
        return source
    try:
        from ament_index_python.packages import get_package_share_directory

        installed = Path(get_package_share_directory("pssnet_ros")) / "config" / "fastdds_profile.xml"
        return installed if installed.is_file() else None
    except Exception:  # no ament index (package not installed through colcon)
        return None


def _set_fastdds_defaults(env: MutableMapping[str, str]) -> None:
    """Discovery on localhost and the shipped Fast DDS profile, unless ``env`` says otherwise; the profile's
    history memory policies read (USE_QOS_FROM_XML) only when the profile in use is the shipped one."""
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    profile = fastdds_profile()
    if profile is None:
        return
    env.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(profile))
    try:
        shipped = Path(env["FASTRTPS_DEFAULT_PROFILES_FILE"]).resolve() == profile.resolve()
    except OSError:
        shipped = False
    if shipped:
        env.setdefault(USE_QOS_FROM_XML, "1")


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
    _set_fastdds_defaults(env)
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
    env.update(extra or {})
    return env


def configure_this_process(domain_id: int) -> None:
    """Sets the discovery range and Fast DDS profile for ROS contexts created later in *this* process."""
    _set_fastdds_defaults(os.environ)
    os.environ["ROS_DOMAIN_ID"] = str(domain_id)


def udp_ports_in_use() -> set[int]:
    """Local UDP ports bound on this machine (IPv4 and IPv6)."""
    ports: set[int] = set()
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            ports.add(int(line.split()[1].rsplit(":", 1)[1], 16))
    return ports


#: Claim files of ROS domains (``<id>.lock``), one flock each, shared by every process on the machine.
DOMAIN_CLAIMS_DIR = Path(tempfile.gettempdir()) / "pssnet_ros_domains"
#: The domains this process has claimed, with their open, flock-ed claim files. Process-wide on purpose: a claim
#: lasts exactly as long as the process, and the kernel drops the flock when it ends, even on kill -9.
_CLAIMS: dict[int, BinaryIO] = {}


def _claim_path(domain: int) -> Path:
    return DOMAIN_CLAIMS_DIR / f"{domain}.lock"


def _claimed(domain: int) -> bool:
    """Whether this or another live process holds the claim of ``domain``."""
    if domain in _CLAIMS:
        return True
    try:
        fd = os.open(_claim_path(domain), os.O_RDONLY)
    except OSError:  # no claim file: never claimed
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return False
    except BlockingIOError:
        return True
    finally:
        os.close(fd)


def _candidates(preferred: int, low: int, high: int) -> list[int]:
    """Domains in [low, high] from ``preferred`` on, without those whose RTPS ports somebody has bound."""
    busy = udp_ports_in_use()
    count = high - low + 1
    order = [low + (preferred - low + i) % count for i in range(count)]
    return [d for d in order
            if not any(PORT_BASE + DOMAIN_GAIN * d <= port < PORT_BASE + DOMAIN_GAIN * (d + 1) for port in busy)]


def free_domain_id(preferred: int, low: int = 10, high: int = 99) -> int:
    """A ROS_DOMAIN_ID in [low, high] whose RTPS ports nobody has bound and that no process has claimed,
    starting the search at ``preferred``.

    Another DDS user on the same domain (a concurrent test run, a robot stack) would talk to our nodes.
    """
    for domain in _candidates(preferred, low, high):
        if not _claimed(domain):
            return domain
    raise RuntimeError(f"every ROS domain in [{low}, {high}] is in use on this machine")


def claim_domain_id(preferred: int | None = None, low: int = 10, high: int = 99) -> int:
    """:func:`free_domain_id`, claimed for the rest of this process's life: no other process's
    :func:`free_domain_id` or :func:`claim_domain_id` returns it meanwhile, nor this process's again. The search
    starts at ``preferred``, by default at a domain derived from this process's id (so that concurrent runs
    start apart).

    Why a claim and not the ports alone: a test session picks the domains of all its modules when it collects
    them, minutes before their nodes bind any port, and a second session on the machine saw those domains as
    free (two nodes answered one test's calls: node-test loop and CI run side by side).
    """
    if preferred is None:
        preferred = low + os.getpid() % (high - low + 1)
    DOMAIN_CLAIMS_DIR.mkdir(exist_ok=True)
    with contextlib.suppress(OSError):  # the first creator opens the folder to every user of the machine
        DOMAIN_CLAIMS_DIR.chmod(0o1777)
    for domain in _candidates(preferred, low, high):
        if domain in _CLAIMS:
            continue
        path = _claim_path(domain)
        handle = open(path, "ab")  # noqa: SIM115 -- held open until the process ends: that is the claim
        with contextlib.suppress(OSError):
            path.chmod(0o666)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            continue
        _CLAIMS[domain] = handle
        return domain
    raise RuntimeError(f"every ROS domain in [{low}, {high}] is in use or claimed on this machine")


def shm_files() -> dict[str, int]:
    """Fast DDS files in /dev/shm: path -> inode."""
    files: dict[str, int] = {}
    try:
        entries = list(os.scandir(SHM_DIR))
    except OSError:
        return files
    for entry in entries:
        if entry.name.startswith(SHM_PREFIX):
            try:
                files[entry.path] = entry.inode()
            except OSError:  # removed meanwhile
                continue
    return files


def owned_shm_files(pid: int) -> dict[str, int]:
    """Fast DDS segments and ports a live process owns (it holds the flock of their ``_el`` file): path -> inode."""
    locked = locked_inodes(pid)
    files = shm_files()
    owned = {}
    for path, inode in files.items():
        if inode in locked and path.endswith(LOCK_SUFFIX):
            segment = path[:-len(LOCK_SUFFIX)]
            if segment in files:
                owned[segment] = files[segment]
    return owned


def stale_shm_files(files: dict[str, int]) -> set[str]:
    """Those of ``files`` (path -> inode) that still exist as the same file and that no live process maps or
    locks any more: shared memory leaked by processes that are gone."""
    current = shm_files()
    existing = {path for path, inode in files.items() if current.get(path) == inode}
    if not existing:
        return set()
    in_use = mapped_inodes()
    locked = locked_inodes()
    lock_of = {path: current.get(path + LOCK_SUFFIX) for path in existing}
    return {path for path in existing if files[path] not in in_use and lock_of[path] not in locked}


class RosProcess:
    """A child process with collected output (stdout and stderr merged)."""

    def __init__(self, argv: Sequence[str], env: Mapping[str, str], name: str = "process",
                 cwd: str | os.PathLike | None = None, echo: bool = False) -> None:
        self.name = name
        self.argv = list(argv)
        self._lines: list[str] = []
        self._cond = threading.Condition()
        self._echo = echo
        # Fast DDS files that existed before this process started cannot be ones it created.
        self._shm_before = set(shm_files().values())
        self.shm_files: dict[str, int] = {}  # path -> inode of the segments it created and owned
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

    def lines(self, start: int = 0) -> list[str]:
        """Output lines from index ``start`` on (``len(lines())`` marks a point to read from later)."""
        with self._cond:
            return self._lines[start:]

    @property
    def pid(self) -> int:
        return self.proc.pid

    def record_shm_files(self) -> None:
        """Adds the Fast DDS segments this (live) process owns now and created itself to :attr:`shm_files`."""
        for path, inode in owned_shm_files(self.pid).items():
            if inode not in self._shm_before:
                self.shm_files[path] = inode

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
                        self.record_shm_files()
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
            self.record_shm_files()
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


# ------------------------------------------------------------------------------------------------------------
# For tests and benchmarks: node arguments, a process's memory and CPU time, the machine's CPU time.

def ros_param_args(**params: bool | int | float | str | Sequence[float]) -> list[str]:
    """``--ros-args -p name:=value ...`` with values typed as ROS parameters need (doubles keep a decimal
    point, booleans are lower case, sequences are double arrays)."""
    args = ["--ros-args"]
    for name, value in params.items():
        if hasattr(value, "tolist"):  # numpy arrays and scalars: as the Python values they hold
            value = value.tolist()
        if isinstance(value, bool):
            text = str(value).lower()
        elif isinstance(value, str | os.PathLike):
            text = os.fspath(value)
        elif isinstance(value, Sequence):
            text = "[" + ",".join(repr(float(v)) for v in value) + "]"
        else:
            text = repr(value)
        args += ["-p", f"{name}:={text}"]
    return args


def rss_mb(pid: int) -> float:
    """Resident memory of a live process (VmRSS of /proc/PID/status), MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise ValueError(f"no VmRSS for process {pid}")


def resident_mib_by_kind(pid: int) -> dict[str, float]:
    """Resident MiB of a live process by kind of mapping (/proc/PID/smaps): "heap and anonymous" (glibc heaps and
    anonymous memory), "dds shared memory" (/dev/shm: Fast DDS segments) and "files" (libraries, other files)."""
    totals = {"heap and anonymous": 0, "dds shared memory": 0, "files": 0}
    kind = "files"
    for line in Path(f"/proc/{pid}/smaps").read_text().splitlines():
        head = line.split()
        if re.match(r"^[0-9a-f]+-[0-9a-f]+ ", line):
            path = head[5] if len(head) > 5 else ""
            kind = ("dds shared memory" if path.startswith("/dev/shm") else
                    "heap and anonymous" if path in ("", "[heap]") or path.startswith("[anon") else "files")
        elif head and head[0] == "Rss:":
            totals[kind] += int(head[1])
    return {k: v / 1024 for k, v in totals.items()}


def spinning_node_script(node_name: str, setup: str, ready: str) -> str:
    """Python source of a child ROS process: one node ``node`` named ``node_name``, set up by the lines ``setup``
    (their imports included), spun until SIGINT; it prints ``ready`` just before spinning."""
    return f"""
import rclpy
from rclpy.executors import SingleThreadedExecutor
from pssnet_ros.spinning import shutdown_once, spin_until_shutdown
rclpy.init()
node = rclpy.create_node({node_name!r})
{setup}
executor = SingleThreadedExecutor()
executor.add_node(node)
print({ready!r}, flush=True)
try:
    spin_until_shutdown(executor)
except KeyboardInterrupt:
    pass
node.destroy_node()
shutdown_once()
"""


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a live process so far (/proc/PID/stat), seconds."""
    stat = Path(f"/proc/{pid}/stat").read_text()
    fields = stat[stat.rindex(")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime: fields 14, 15 of stat


def machine_cpu() -> tuple[float, float]:
    """(busy, total) CPU time of the whole machine so far, all cores, seconds (/proc/stat): over an interval,
    busy minus a process's own CPU time is what the other processes took."""
    ticks = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    total = sum(ticks)
    return (total - ticks[3] - ticks[4]) / os.sysconf("SC_CLK_TCK"), total / os.sysconf("SC_CLK_TCK")  # idle, iowait
