"""The one execution layer of the batch work: units of work run as Ray tasks, on this machine or a cluster.

``pssnet dataset build`` (shards), ``pssnet plausible`` (reference observations) and ``pssnet evaluate``
(reference observations) hand their units to :meth:`TaskRunner.map`, which runs ``function(unit, **shared)``
for every unit and yields ``(unit, result)`` as units finish, with a tqdm bar over units. Where they run is a
:class:`RayConfig`:

- no address and no ``RAY_ADDRESS``: a local Ray with ``workers`` CPUs, started inside the command on first use
  and shut down when the runner closes; with one worker, in this process (see :attr:`RayConfig.in_process`);
- ``"local"``: a local Ray with ``workers`` CPUs, even for one worker (a cluster run, on this machine);
- ``"auto"``, ``"HOST:PORT"`` or ``"ray://HOST:PORT"`` (or the same in ``RAY_ADDRESS``): join that cluster and use
  all of its CPUs; ``workers`` is ignored.

A Ray already initialised in this process (a test fixture, a user's own driver) is used as it is and left running.
Shared inputs (views, meshes, plausible sets, models) go into Ray's object store once per :meth:`TaskRunner.map`
and reach every task by reference. Every unit must depend only on itself and the shared inputs, so results do not
depend on where or in which order units run. Resuming is the callers' business: they pass only unfinished units.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from tqdm import tqdm

RAY_ADDRESS_ENV = "RAY_ADDRESS"
LOCAL = "local"

Unit = TypeVar("Unit")
Result = TypeVar("Result")


class RayTasksError(ValueError):
    """Bad execution settings (workers, address)."""


@dataclass(frozen=True)
class RayConfig:
    """Where the units of a command run.

    Attributes:
        workers: CPUs of a local Ray (one task per CPU); 1 without an address runs in this process.
        address: None (``RAY_ADDRESS`` if set, else local), ``"local"``, ``"auto"``, ``"HOST:PORT"`` or
            ``"ray://HOST:PORT"``.
        object_store_mb: object store of a local Ray; None = Ray's default (30 % of the memory; it is used, not
            reserved, but small machines and tests may want it bounded).
    """

    workers: int = 1
    address: str | None = None
    object_store_mb: int | None = None

    def __post_init__(self) -> None:
        if self.workers < 1:
            raise RayTasksError(f"workers must be >= 1, got {self.workers}")
        if self.address is not None and not self.address.strip():
            raise RayTasksError("the Ray address is empty; leave it out for a local Ray")

    @property
    def resolved_address(self) -> str:
        """The address to use: the given one, else ``RAY_ADDRESS``, else ``"local"``."""
        return self.address or os.environ.get(RAY_ADDRESS_ENV) or LOCAL

    @property
    def in_process(self) -> bool:
        """One worker on this machine runs in this process, without Ray.

        Why: a local Ray costs 2-5 s to start and 1-2 s to stop on this 2-core machine (BENCHMARKS.md), more than
        a small build or plausible set takes, and the test suite makes many of those. The unit functions are the
        same either way, so the results are too (``--ray-address local`` runs one worker under Ray).
        """
        return self.workers == 1 and self.resolved_address == LOCAL and self.address != LOCAL


class TaskRunner:
    """Runs units of work in this process or as Ray tasks (see the module docstring); a context manager.

    Ray starts on the first :meth:`map` that has units, so a command whose work is all done (or cached) never
    starts it.
    """

    def __init__(self, config: RayConfig | None = None) -> None:
        self.config = config or RayConfig()
        self._ray: Any = None  # the ray module once Ray is up
        self._owns_ray = False

    def __enter__(self) -> TaskRunner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Disconnects from the Ray this runner connected to: a local Ray it started stops, a cluster keeps running,
        and a Ray that was initialised before is left as it was."""
        if self._ray is not None and self._owns_ray:
            self._ray.shutdown()
        self._ray = None
        self._owns_ray = False

    def _start(self) -> Any:
        if self._ray is not None:
            return self._ray
        import ray

        if not ray.is_initialized():
            address = self.config.resolved_address
            if address == LOCAL:
                # Quiet and small: no dashboard, worker output stays in Ray's log files (errors come back
                # with the task's exception), only errors logged here.
                store = None if self.config.object_store_mb is None else self.config.object_store_mb * 2**20
                ray.init(address=LOCAL, num_cpus=self.config.workers, object_store_memory=store,
                         include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
            else:
                ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
            self._owns_ray = True
        self._ray = ray
        return ray

    @property
    def parallelism(self) -> int:
        """Tasks that can run at once: 1 in this process, else the Ray cluster's CPUs (starts Ray)."""
        if self.config.in_process:
            return 1
        return max(1, int(self._start().cluster_resources().get("CPU", 1)))

    def describe(self) -> str:
        """Where the units run, for logs and stats."""
        if self.config.in_process:
            return "in this process"
        return f"Ray at {self.config.resolved_address} ({self.parallelism} CPUs)"

    def map(self, function: Callable[..., Result], units: Sequence[Unit], shared: Mapping[str, Any] | None = None,
            desc: str = "units", unit_name: str = "unit", done: int = 0, progress: bool = True,
            postfix: Callable[[Result], Mapping[str, Any]] | None = None,
            gpus_per_task: float = 0.0) -> Iterator[tuple[Unit, Result]]:
        """Runs ``function(unit, **shared)`` for every unit; yields ``(unit, result)`` in order of completion.

        Args:
            function: a module-level function (Ray ships it to workers by reference).
            units: the units still to do.
            shared: inputs every unit reads (put into the object store once).
            desc: progress bar label.
            unit_name: what a unit is called on the bar.
            done: units finished before (the bar starts there).
            progress: show the bar.
            postfix: bar postfix from each result (e.g. a rate).
            gpus_per_task: GPUs each Ray task reserves (0 for CPU work).

        Raises:
            The unit's own exception (the remote traceback chained to it) when a unit fails; no unit is submitted
            after it, and those already submitted (at most twice the parallelism) finish unread.
        """
        shared = dict(shared or {})
        bar = tqdm(total=done + len(units), initial=done, desc=desc, unit=unit_name, disable=not progress,
                   dynamic_ncols=True)
        results = (((u, function(u, **shared)) for u in units) if self.config.in_process or not units
                   else self._map_ray(function, units, shared, gpus_per_task))
        try:
            for unit, result in results:
                if postfix is not None:
                    bar.set_postfix(postfix(result))
                bar.update(1)
                yield unit, result
        finally:
            results.close()
            bar.close()

    def _map_ray(self, function: Callable[..., Result], units: Sequence[Unit], shared: dict[str, Any],
                 gpus_per_task: float) -> Iterator[tuple[Unit, Result]]:
        ray = self._start()
        remote = ray.remote(num_cpus=1, num_gpus=gpus_per_task)(function)
        refs = {name: ray.put(value) for name, value in shared.items()}
        # A bounded window of submitted tasks: enough to keep every CPU busy, few enough that results do not pile
        # up in the object store. Results are collected a batch at a time while the rest of the window keeps the
        # CPUs busy, so that a window of thousands (100 nodes) is not scanned once per result.
        window = 2 * self.parallelism
        batch = max(1, window // 8)
        pending: dict[Any, Unit] = {}
        queue = iter(units)
        # When a unit fails (or the caller stops early) the tasks still in the window are left to finish and their
        # results dropped, not cancelled: in Ray 2.60 a ray.cancel racing a task's completion aborts the driver
        # process ("Check failed: it != submissible_tasks_.end() Tried to complete task that was not pending",
        # task_manager.cc; ray-project/ray#54798 fixed the retry variant of that race). It killed this project's
        # test run once, in the map whose unit 3 raises. The window bounds the work left running.
        while True:
            for unit in queue:
                pending[remote.remote(unit, **refs)] = unit
                if len(pending) >= window:
                    break
            if not pending:
                return
            finished, _ = ray.wait(list(pending), num_returns=min(batch, len(pending)))
            for ref in finished:
                yield pending.pop(ref), self._result(ray, ref)

    @staticmethod
    def _result(ray: Any, ref: Any) -> Any:
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as error:
            if not isinstance(error.cause, Exception):
                raise
            raise error.cause from error  # the unit's own error type and message, for the CLIs' handlers


def add_ray_options(parser: Any, default_workers: int, what: str) -> None:
    """Adds ``--workers`` and ``--ray-address`` to an argparse parser.

    Args:
        parser: the (sub)command's parser.
        default_workers: default of ``--workers``.
        what: the units, for the help text ("shards", "reference observations").
    """
    parser.add_argument("--workers", type=int, default=default_workers,
                        help=f"CPUs of the local Ray that runs the {what} (1 = in this process); ignored on a "
                             f"cluster; default {default_workers}")
    parser.add_argument("--ray-address", default=None,
                        help="run on a Ray cluster: 'auto' (a cluster started with `ray start` on this node), "
                             "HOST:PORT or ray://HOST:PORT; 'local' starts a local Ray even for one worker; "
                             f"default ${RAY_ADDRESS_ENV}, else local")


def ray_config(args: Any) -> RayConfig:
    """The :class:`RayConfig` of parsed ``--workers`` / ``--ray-address`` options."""
    return RayConfig(workers=args.workers, address=getattr(args, "ray_address", None))


__all__ = ["RayConfig", "RayTasksError", "TaskRunner", "add_ray_options", "ray_config"]


def process_stats() -> dict[int, list[str]]:
    """The fields after the command name of /proc/PID/stat for every live (non-zombie) process (Linux)."""
    stats: dict[int, list[str]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:  # the process ended while the table was read
                continue
            if fields[0] != "Z":
                stats[int(entry.name)] = fields
    return stats


def descendants(pid: int, stats: Mapping[int, list[str]] | None = None) -> set[int]:
    """Live processes below ``pid`` (e.g. the Ray workers a local Ray started), from :func:`process_stats`."""
    parents = {p: int(fields[1]) for p, fields in (stats if stats is not None else process_stats()).items()}
    found: set[int] = set()
    frontier = {pid}
    while frontier:
        frontier = {p for p, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found
