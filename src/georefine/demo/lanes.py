"""Two lanes, one per core: the demos run a second process beside their own.

A demo submits work to :class:`Lanes` (one spawned worker process) and goes on in its own
process. The worker's stages report progress through a :class:`QueuedProgress` that carries
the queue with it (a managed queue, picklable), and :class:`Lanes` relays those reports to the
demo's own progress callback while it waits. The lanes share only files and the step cache,
so every result is that of the same command run alone. No module state is involved: the queue
travels as an argument.
"""

from __future__ import annotations

import json
import multiprocessing
import queue
import signal
import threading
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from georefine.progress import Progress

__all__ = ["Lanes", "QueuedProgress", "demo_stamp", "reusable_project", "simulation_scheduler"]


def demo_stamp(scenario: str, seed: int, overrides: list[str]) -> dict:
    """What a demo writes to ``truth/demo.json``: the simulation's inputs and the simulator's version."""
    from georefine.sim.scenarios import SIMULATOR_VERSION

    return {"scenario": scenario, "seed": seed, "overrides": overrides, "simulator": SIMULATOR_VERSION}


def simulation_scheduler(scheduler: str) -> str:
    """Where a demo simulates: a cluster's address as given; on this machine ``sync``, since Embree
    and the LAZ encoder already use every core (scan tasks on threads or processes were slower,
    BENCHMARKS.md, "Scenario simulation")."""
    return scheduler if "://" in str(scheduler) else "sync"


def reusable_project(project: Path, scenario: str, seed: int, overrides: list[str]) -> bool:
    """Whether ``project`` was simulated by this simulator for a demo with the same scenario, seed and overrides."""
    stamp = project / "truth" / "demo.json"
    if not stamp.is_file() or not (project / "project.yaml").is_file():
        return False
    return json.loads(stamp.read_text()) == demo_stamp(scenario, seed, overrides)


@dataclass(frozen=True)
class QueuedProgress:
    """A progress callback for the worker: puts ``(prefix + task, done, total)`` on ``events``."""

    events: Any  # a managed queue proxy (picklable into the worker)
    prefix: str = ""

    def __call__(self, name: str, done: float, total: float) -> None:
        self.events.put((f"{self.prefix}{name}", done, total))


def _ignore_interrupts() -> None:
    """The worker leaves Ctrl-C to the main process, which ends it (a terminal sends SIGINT to the
    whole process group: without this the worker printed its own traceback)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class Lanes:
    """A one-worker process pool (spawn) whose progress reports reach ``progress``.

    Use as a context manager; :meth:`__call__` is itself a progress callback (it reports and
    then relays what the worker queued), so the demo passes the lanes object to its own stages.
    A thread relays the worker's reports every :data:`RELAY_S` seconds too, so that they reach
    ``progress`` when they happen (the stage lines' times) while this process is in a long step
    that reports nothing; one lock keeps the two threads' calls apart.
    """

    RELAY_S = 0.25

    def __init__(self, progress: Progress) -> None:
        self.progress = progress
        self._ctx = multiprocessing.get_context("spawn")
        self._manager = None
        self._pool: ProcessPoolExecutor | None = None
        self.events = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._relay: threading.Thread | None = None

    def __enter__(self) -> "Lanes":
        self._manager = self._ctx.Manager()
        self.events = self._manager.Queue()
        self._pool = ProcessPoolExecutor(max_workers=1, mp_context=self._ctx, initializer=_ignore_interrupts)
        self._relay = threading.Thread(target=self._relay_loop, name="demo-progress-relay", daemon=True)
        self._relay.start()
        return self

    def _relay_loop(self) -> None:
        while not self._stop.wait(self.RELAY_S):
            self.drain()

    def __exit__(self, exc_type, *exc) -> None:
        self._stop.set()
        if self._relay is not None:
            self._relay.join(timeout=5)
        try:
            if self._pool is not None:
                if exc_type is None:
                    self._pool.shutdown(wait=True)
                else:  # Ctrl-C or an error in this process: the worker's job is abandoned, not awaited
                    workers = list(getattr(self._pool, "_processes", {}).values())
                    self._pool.shutdown(wait=False, cancel_futures=True)
                    for worker in workers:
                        worker.terminate()
                        worker.join(timeout=10)
            if exc_type is None:
                self.drain()
        finally:
            if self._manager is not None:
                self._manager.shutdown()

    def queued(self, prefix: str = "") -> QueuedProgress:
        """A progress callback to hand to work submitted to the worker."""
        return QueuedProgress(self.events, prefix)

    def submit(self, fn: Callable, *args, **kwargs) -> Future:
        """Run ``fn(*args, **kwargs)`` in the worker process."""
        assert self._pool is not None, "Lanes is used outside its with-block"
        return self._pool.submit(fn, *args, **kwargs)

    def __call__(self, name: str, done: float, total: float) -> None:
        with self._lock:
            self.progress(name, done, total)
        self.drain()

    def drain(self) -> None:
        """Report what the worker has queued so far."""
        if self.events is None:
            return
        with self._lock:  # one thread at a time: the reports keep their order
            while True:
                try:
                    name, done, total = self.events.get_nowait()
                except (queue.Empty, EOFError, OSError):
                    return
                self.progress(name, done, total)

    def result(self, future: Future):
        """``future.result()``, relaying the worker's progress meanwhile."""
        while True:
            try:
                value = future.result(timeout=0.25)
            except FutureTimeout:
                self.drain()
                continue
            self.drain()
            return value
