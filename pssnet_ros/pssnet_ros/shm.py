"""Stale Fast DDS shared memory: what a participant killed with -9 (or that crashed) leaves in /dev/shm, and
:func:`clean_stale_shm`, which the node runs when it starts to remove the segments and ports of dead processes.

Fast DDS shared memory: every participant creates its own segments (``fastrtps_<id>``) and listens on port
segments (``fastrtps_port<n>``), some of which (ports 7000, 7001, ...) every participant on the machine
shares, whatever its domain. The owner of a segment or the listener of a port holds an exclusive flock on
its ``<name>_el`` file; :func:`locked_inodes` and :func:`mapped_inodes` tell which files live processes still
use (the test harness, ``pssnet_testing.processes``, uses them too, to find what a process left behind).
"""

from __future__ import annotations

import contextlib
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

SHM_DIR = Path("/dev/shm")


def locked_inodes(pid: int | None = None) -> set[int]:
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


def mapped_inodes() -> set[int]:
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



#: Participant segments (one per participant, ``segment_size`` each: 8 MiB with the shipped profile) and
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
    locked = locked_inodes()
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
    mapped = mapped_inodes()
    for path, is_port in candidates:
        if _in_use(path, mapped, locked):
            result.kept += 1
            continue
        with _PortMutex(path.name) if is_port else contextlib.nullcontext(True) as ours:
            # A participant may have opened the port since the first look: look again, with its mutex ours.
            if not ours or (is_port and _in_use(path, mapped_inodes(), locked_inodes())):
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
