"""Starting and stopping ROS 2 processes from Python (no ros2cli/launch here): the demo, tests and benchmark.

- :func:`ros_env`: the environment of a child process: its own ROS_DOMAIN_ID, discovery on localhost, the
  shipped Fast DDS profile, and the ROS wheels' bootstrap guard cleared (a child must redo the wheels'
  library-path set-up itself, which matters when it runs another interpreter).
- :func:`free_domain_id`: a ROS_DOMAIN_ID that no DDS participant on this machine uses right now and no
  process has claimed; :func:`claim_domain_id` also claims it for the rest of this process's life, so that
  concurrent test runs, demos and benchmarks on one machine never share a domain.
- :class:`RosProcess`: a child process whose output is collected in the background; ``wait_for`` a log
  line, ``stop`` with SIGINT (then SIGTERM/SIGKILL only if it hangs), and the Fast DDS shared-memory
  segments it created, to check that none are left behind (:func:`stale_shm_files`).

Fast DDS shared memory: every participant creates its own segments (``fastrtps_<id>``) and listens on port
segments (``fastrtps_port<n>``), some of which (ports 7000, 7001, ...) every participant on the machine
shares, whatever its domain. The owner of a segment or the listener of a port holds an exclusive flock on
its ``<name>_el`` file. A file left by another process (e.g. one killed with -9) may be opened and even taken
over by ours, so a process is blamed only for segments it owned that did not exist before it started.
:func:`clean_stale_shm` removes the segments and ports of dead processes (the node calls it when it starts).
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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

BOOTSTRAP_GUARD = "_ROS_WHEELS_BOOTSTRAP_COMPLETE"
SHM_DIR = Path("/dev/shm")
SHM_PREFIX = "fastrtps_"
LOCK_SUFFIX = "_el"  # Fast DDS: the owner of segment X holds a flock on X_el
#: RTPS well-known ports (UDP): domain d uses [PORT_BASE + DOMAIN_GAIN * d, ... + DOMAIN_GAIN)
PORT_BASE, DOMAIN_GAIN = 7400, 250


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


def _locked_inodes(pid: int | None = None) -> set[int]:
    """Inodes of /dev/shm files flock-ed by ``pid`` (None: by any live process), from /proc/locks."""
    inodes: set[int] = set()
    try:
        st_dev = os.stat(SHM_DIR).st_dev
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return inodes
    shm_device = f"{os.major(st_dev):02x}:{os.minor(st_dev):02x}"  # as /proc/locks writes it
    for line in lines:
        fields = line.split()
        if "->" in fields:  # a waiter blocked on the lock above, not a holder
            continue
        try:
            holder, (major, minor, inode) = int(fields[4]), fields[5].split(":")
        except (IndexError, ValueError):
            continue
        if f"{major}:{minor}" == shm_device and (pid is None or holder == pid):
            inodes.add(int(inode))
    return inodes


def owned_shm_files(pid: int) -> dict[str, int]:
    """Fast DDS segments and ports a live process owns (it holds the flock of their ``_el`` file): path -> inode."""
    locked = _locked_inodes(pid)
    files = shm_files()
    owned = {}
    for path, inode in files.items():
        if inode in locked and path.endswith(LOCK_SUFFIX):
            segment = path[:-len(LOCK_SUFFIX)]
            if segment in files:
                owned[segment] = files[segment]
    return owned


def _mapped_inodes() -> set[int]:
    """Inodes of /dev/shm files that any live process maps."""
    inodes: set[int] = set()
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            text = (proc / "maps").read_text()
        except OSError:  # exited meanwhile, or not ours to read
            continue
        for line in text.splitlines():
            fields = line.split(maxsplit=5)
            if len(fields) == 6 and fields[5].startswith("/dev/shm/"):
                inodes.add(int(fields[4]))
    return inodes


def stale_shm_files(files: dict[str, int]) -> set[str]:
    """Those of ``files`` (path -> inode) that still exist as the same file and that no live process maps or
    locks any more: shared memory leaked by processes that are gone."""
    current = shm_files()
    existing = {path for path, inode in files.items() if current.get(path) == inode}
    if not existing:
        return set()
    in_use = _mapped_inodes()
    locked = _locked_inodes()
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
# Stale Fast DDS shared memory: what a process killed with -9 (or that crashed) leaves in /dev/shm.

#: Participant segments (one per participant, ``segment_size`` each: 32 MiB with the shipped profile) and
#: ports (~50 kB each) of Fast DDS 2.x (``fastrtps_``, ROS 2 Jazzy) and 3.x (``fastdds_``).
_SEGMENT_NAME = re.compile(r"^(fastrtps|fastdds)_[0-9a-f]{16}$")
_PORT_NAME = re.compile(r"^(fastrtps|fastdds)_port\d+$")
#: Fast DDS' lock files: the owner of a segment, or the listener of a port, holds a flock on one of them.
_LOCK_SUFFIXES = ("_el", "_sl")
#: Files younger than this are never removed: a participant creates a segment an instant before it locks it,
#: and tests elsewhere on the machine may still be inspecting what a participant they killed just left.
SHM_GRACE_S = 10.0


@dataclass
class ShmCleanup:
    """What :func:`clean_stale_shm` did.

    Attributes:
        removed: paths removed (segments, ports and their lock files).
        freed_bytes: memory those files held (allocated blocks, not their apparent size).
        kept: segments and ports left alone: a live process locks or maps them, they are newer than the grace
            period, or this user may not remove them.
    """

    removed: list[str] = field(default_factory=list)
    freed_bytes: int = 0
    kept: int = 0


class _PortMutex:
    """Fast DDS' named mutex of a port (a POSIX semaphore, /dev/shm/sem.<port>_mutex, 1 = free), taken without
    waiting, so that a port is never removed while a starting participant is opening it."""

    def __init__(self, port_name: str) -> None:
        import ctypes
        import ctypes.util

        self._libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        self._libc.sem_open.restype = ctypes.c_void_p
        self._libc.sem_open.argtypes = [ctypes.c_char_p, ctypes.c_int]
        for name in ("sem_trywait", "sem_post", "sem_close"):
            getattr(self._libc, name).argtypes = [ctypes.c_void_p]
        # oflag 0: open only; a port without a mutex file has no opener to race with (NULL: no such semaphore).
        self._sem = self._libc.sem_open(f"/{port_name}_mutex".encode(), 0)
        self.held = False

    def __enter__(self) -> bool:
        """True when the mutex is ours now (or does not exist); False when someone else holds it."""
        if not self._sem:
            return True
        self.held = self._libc.sem_trywait(self._sem) == 0
        return self.held

    def __exit__(self, *exc: object) -> None:
        if self._sem:
            if self.held:
                self._libc.sem_post(self._sem)
            self._libc.sem_close(self._sem)


def _lock_files(path: Path) -> list[Path]:
    return [lock for lock in (path.with_name(path.name + suffix) for suffix in _LOCK_SUFFIXES) if lock.exists()]


def _stat_or_none(path: Path) -> os.stat_result | None:
    try:
        return os.stat(path)
    except OSError:
        return None


def clean_stale_shm(grace_s: float = SHM_GRACE_S) -> ShmCleanup:
    """Removes the Fast DDS segments and ports in /dev/shm whose owner is dead.

    A file is stale when no live process holds a flock on its Fast DDS lock files (/proc/locks: the kernel
    drops a dead process's flocks; a port opened only for writing has none), no live process maps it
    (/proc/*/maps), and it and its lock files are older than ``grace_s``. Another live participant's files are
    never touched, whatever its user or domain. Ports are removed under their named mutex, as Fast DDS opens
    them; the 32-byte mutex itself (``sem.<port>_mutex``) stays: Fast DDS reuses it, and removing it could let
    two openers race. Files this user may not remove are left (counted as kept). The manual equivalent, with
    no DDS process running, is ``fastdds shm clean`` (Fast DDS' own tool, in the venv's bin/).
    """
    result = ShmCleanup()
    try:
        names = {entry.name for entry in os.scandir(SHM_DIR)}
    except OSError:
        return result
    now = time.time()
    locked = _locked_inodes()
    candidates: list[tuple[Path, bool]] = []  # (segment or port, is a port)
    for name in sorted(names):
        is_port = bool(_PORT_NAME.match(name))
        if not is_port and not _SEGMENT_NAME.match(name):
            continue
        locks = _lock_files(SHM_DIR / name)
        stats = [_stat_or_none(path) for path in [SHM_DIR / name, *locks]]
        if (None in stats or any(s.st_ino in locked for s in stats[1:])
                or now - max(s.st_mtime for s in stats) < grace_s):
            result.kept += 1
            continue
        candidates.append((SHM_DIR / name, is_port))
    if not candidates:
        return result  # the common case: nothing to check against every process's maps
    mapped = _mapped_inodes()
    for path, is_port in candidates:
        if _in_use(path, mapped, locked):
            result.kept += 1
            continue
        with _PortMutex(path.name) if is_port else contextlib.nullcontext(True) as ours:
            # A participant may have opened the port since the first look: look again, with its mutex ours.
            if not ours or (is_port and _in_use(path, _mapped_inodes(), _locked_inodes())):
                result.kept += 1
            elif not _remove_all([path, *_lock_files(path)], result):
                result.kept += 1
    return result


def _in_use(path: Path, mapped: set[int], locked: set[int]) -> bool:
    """A live process maps ``path`` or locks one of its lock files (or it changed meanwhile: left alone)."""
    stats = [_stat_or_none(p) for p in [path, *_lock_files(path)]]
    return None in stats or stats[0].st_ino in mapped or any(s.st_ino in locked for s in stats[1:])


def _remove_all(paths: list[Path], result: ShmCleanup) -> bool:
    """Unlinks ``paths``, adding them to ``result``; False when one may not be removed (another user's)."""
    for path in paths:
        stat = _stat_or_none(path)
        try:
            path.unlink()
        except FileNotFoundError:  # removed meanwhile (by Fast DDS or another cleaner)
            continue
        except OSError:
            return False
        result.removed.append(str(path))
        result.freed_bytes += stat.st_blocks * 512 if stat is not None else 0
    return True


# ------------------------------------------------------------------------------------------------------------
# For benchmarks: node arguments, a process's memory, the CPU.

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


def cpu_kind() -> str:
    """The CPU's model name (lscpu's "Model name", from /proc/cpuinfo) and whether it has AVX512-BF16 / AMX."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return "unknown CPU"
    fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    flags = set(fields.get("flags", "").split())
    kind = f"{fields.get('model name', 'unknown CPU')}, avx512_bf16 {'present' if 'avx512_bf16' in flags else 'absent'}"
    return kind + (", amx_bf16 present" if "amx_bf16" in flags else "")
