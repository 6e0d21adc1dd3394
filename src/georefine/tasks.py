"""Where per-tile work runs: in this process, on threads, on local processes or on a Dask cluster.

Per-point stages split their data into tiles (time tiles along a strip for the planar features
and the georeferencing, record ranges of point clouds for the evaluation) and hand one function
call per tile to a :class:`TaskRunner`.
The scheduler is the user's choice (``--scheduler`` on the command line,
docs/ARCHITECTURE.md §4.7):

``sync``
    Every task in this process, one after the other (debugging, profiling).
``threads``
    A ``dask.distributed`` cluster inside this process, one worker with a thread per core: no
    data is copied between tasks. The fastest on 2 cores (BENCHMARKS.md, "Scale"), although the
    tasks share the GIL wherever numpy holds it.
``processes``
    A ``dask.distributed.LocalCluster`` of one single-threaded worker process per core.
``tcp://host:port`` (or any address a ``dask.distributed.Client`` accepts)
    An existing cluster, started with ``dask scheduler`` and ``dask worker`` processes, on this
    machine or others that see the same files.

Results never depend on the scheduler: every task is deterministic and :meth:`TaskRunner.map`
yields the results in the order of the tiles, whatever order they finish in. Memory stays
bounded: at most ``window`` tasks are submitted ahead of the one the caller consumes, so the
results waiting in memory are at most ``window`` tiles.
"""

from __future__ import annotations

import logging
import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from georefine.errors import InputError
from georefine.heap import bound_heap
from georefine.progress import Progress, no_progress

log = logging.getLogger(__name__)

__all__ = ["SCHEDULERS", "DEFAULT_SCHEDULER", "TaskRunner", "check_scheduler", "machine_cores", "runner_for"]

SCHEDULERS = ("sync", "threads", "processes")
"""The named schedulers; any other value must be the address of a ``dask.distributed`` scheduler."""

DEFAULT_SCHEDULER = "threads"
"""The fastest scheduler on a 2-core machine for the per-point stages (BENCHMARKS.md, "Scale")."""


def machine_cores() -> int:
    """Cores this process may use (the affinity mask, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


def check_scheduler(value: str) -> str:
    """``value`` if it names a scheduler or looks like a scheduler address; else an :class:`InputError`."""
    v = str(value).strip()
    if v in SCHEDULERS or "://" in v:
        return v
    raise InputError("unknown scheduler", field="scheduler",
                     expected="sync, threads, processes or a scheduler address such as tcp://127.0.0.1:8786",
                     found=repr(value))


class TaskRunner:
    """Runs tile tasks on the chosen scheduler; a context manager that owns its cluster.

    Parameters
    ----------
    scheduler
        ``sync``, ``threads``, ``processes`` or a scheduler address (module docstring).
    workers
        Workers of a local cluster (threads of ``threads``, processes of ``processes``);
        default: the cores of this machine. Ignored for ``sync`` and for an address.
    memory_limit
        Memory a local worker process may use before Dask pauses it (bytes or ``"4GB"``);
        default: Dask's share of the machine.
    timeout
        How long to try reaching a scheduler address before giving up.
    """

    def __init__(self, scheduler: str = DEFAULT_SCHEDULER, *, workers: int | None = None,
                 memory_limit: str | int | None = None, timeout: str = "30s") -> None:
        self.scheduler = check_scheduler(scheduler)
        # glibc's heap thresholds fixed (georefine.heap), here and, through the environment, in a
        # local cluster's worker processes, before any of them starts.
        bound_heap()
        self._client = None
        self._cluster = None
        self._workers = workers or machine_cores()
        self._memory_limit = memory_limit
        self._timeout = timeout

    # -- life cycle ---------------------------------------------------------------------------

    def __enter__(self) -> TaskRunner:
        # Nothing is started here: the cluster starts with the first task, shared value or worker
        # count that needs it (:meth:`start`). A run that stops on its inputs (a bad project.yaml,
        # a missing file) then never starts and stops a cluster, whose shutdown straight after its
        # start could log asyncio's "Future exception was never retrieved" beside the one-line error.
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> TaskRunner:
        """Start (or connect to) the cluster; nothing for ``sync``. Idempotent."""
        if self.scheduler == "sync" or self._client is not None:
            return self
        import dask
        from dask.distributed import Client, LocalCluster  # deferred: heavy import

        # The cluster's own INFO lines (workers starting, closing) are not the user's business;
        # its warnings and errors still show. Spawned workers inherit the configuration.
        dask.config.set({"logging.distributed": "warning", "distributed.admin.system-monitor.gil.enabled": False})
        logging.getLogger("distributed").setLevel(max(logging.WARNING, logging.getLogger("distributed").level))
        # A local cluster's scheduler does not drop the workers it has not heard from for a while
        # (``worker-ttl``, 5 minutes by default): they live and die with this process. A run whose
        # process was stopped for longer (a suspended machine, a paused job) lost them on resuming
        # and then waited for ever, or failed with "No valid workers found". A dead worker process
        # is still noticed by its nanny and its closed connections.
        with dask.config.set({"distributed.scheduler.worker-ttl": None}):
            if self.scheduler == "threads":
                self._cluster = LocalCluster(n_workers=1, threads_per_worker=self._workers, processes=False,
                                             dashboard_address=":0")
            elif self.scheduler == "processes":
                kw = {} if self._memory_limit is None else {"memory_limit": self._memory_limit}
                self._cluster = LocalCluster(n_workers=self._workers, threads_per_worker=1, processes=True,
                                             dashboard_address=":0", **kw)
        try:
            self._client = Client(self._cluster if self._cluster is not None else self.scheduler,
                                  set_as_default=False, timeout=self._timeout)
        except (OSError, TimeoutError) as exc:
            self.close()
            raise InputError(f"cannot reach the Dask scheduler ({exc})", field="scheduler",
                             expected="a running `dask scheduler` at that address", found=self.scheduler) from exc
        return self

    def close(self) -> None:
        """Disconnect; a local cluster is shut down, an external one is left running."""
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    @property
    def workers(self) -> int:
        """Tasks that run at once: 1 for ``sync``, else the cluster's threads (a local cluster's
        without starting it: one worker of ``workers`` threads, or ``workers`` one-thread processes)."""
        if self.scheduler == "sync":
            return 1
        if self._client is None and self.scheduler in ("threads", "processes"):
            return self._workers
        self.start()
        info = self._client.scheduler_info(n_workers=-1) if _takes_n_workers(self._client) else \
            self._client.scheduler_info()
        return max(1, sum(w.get("nthreads", 1) for w in info.get("workers", {}).values()))

    def describe(self) -> str:
        """One line for logs and metrics: the scheduler and its task slots."""
        return f"{self.scheduler} ({self.workers} task slot{'s' if self.workers != 1 else ''})"

    # -- tasks --------------------------------------------------------------------------------

    def share(self, value: Any) -> Any:
        """``value`` as an argument that is sent to every worker once, not with every task.

        Also on ``threads``: an object handed to ``submit`` is pickled into the task graph and every
        task gets its own copy, while a scattered one is the object itself (measured: 25 MB of
        trajectory per feature task on a 30-minute flight).
        """
        if self.scheduler == "sync":
            return value
        self.start()
        # One future for the whole value (scatter would split a list, tuple or dict into items).
        return self._client.scatter([value], broadcast=True, hash=False)[0]

    def map(
        self,
        fn: Callable[..., Any],
        args: Iterable[Sequence[Any]],
        *,
        label: str = "tasks",
        total: int | None = None,
        window: int | None = None,
        progress: Progress = no_progress,
    ) -> Iterator[Any]:
        """``fn(*a)`` for every ``a`` in ``args``, yielded in the order of ``args``.

        At most ``window`` tasks (default two per task slot) are submitted ahead of the result the
        caller takes next, so memory holds at most that many results. ``progress(label, done,
        total)`` is reported before the first task and as results are taken. An exception in a task is raised here, with
        the pending tasks cancelled.
        """
        items = iter(args)
        if total is None and hasattr(args, "__len__"):
            total = len(args)  # type: ignore[arg-type]
        total_f = float(total) if total is not None else float("nan")
        progress(label, 0, total_f)  # the stage starts now, not when its first task ends
        if self.scheduler == "sync":
            for done, a in enumerate(items, 1):
                value = fn(*a)
                progress(label, done, total_f)
                yield value
            return
        self.start()
        window = max(1, window or 2 * self.workers)
        pending: deque = deque()
        exhausted = False
        done = 0
        try:
            while True:
                while not exhausted and len(pending) < window:
                    try:
                        a = next(items)
                    except StopIteration:
                        exhausted = True
                        break
                    pending.append(self._client.submit(fn, *a, pure=False))
                if not pending:
                    return
                fut = pending.popleft()
                value = fut.result()
                fut.release()
                done += 1
                progress(label, done, total_f)
                yield value
        finally:
            for f in pending:
                f.cancel()


@contextmanager
def runner_for(scheduler: str | TaskRunner) -> Iterator[TaskRunner]:
    """``scheduler`` itself if it is a running :class:`TaskRunner` (left open), else a new one that
    is closed on leaving: the argument a library function takes when its caller may own a cluster."""
    if isinstance(scheduler, TaskRunner):
        yield scheduler
        return
    with TaskRunner(scheduler) as runner:
        yield runner


def _takes_n_workers(client) -> bool:
    """Whether ``Client.scheduler_info`` takes ``n_workers`` (newer distributed lists only 5 by default)."""
    import inspect

    return "n_workers" in inspect.signature(client.scheduler_info).parameters
