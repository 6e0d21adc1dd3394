"""What an unattended run leaves behind: timestamped stage lines, the output folder's log file,
and an interrupted run's clean-up.

The library reports ``progress(task, done, total)`` (:mod:`georefine.progress`). On a terminal the
command line draws bars; :class:`StageLog` turns the same calls into plain lines, one when a stage
starts, one at most every :data:`STAGE_INTERVAL_S` seconds with its share done and the time left,
and one when it ends. They go to standard error when it is not a terminal (``georefine demo > log
2>&1``) and always to ``OUT/georefine.log`` (:data:`LOG_NAME`), which also takes Georefine's own
log records (INFO and above) whatever ``--verbose`` says. The log is appended to, one header line
per command, so that a resumed run's history stays in one file; unlike the results it is not
written under a temporary name, because it is read while the run goes on.
"""

from __future__ import annotations

import logging
import os
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

__all__ = ["LOG_NAME", "STAGE_INTERVAL_S", "StageLog", "attach_log_file", "remove_new_empty_folders",
           "folder_snapshot", "format_duration"]

LOG_NAME = "georefine.log"
STAGE_INTERVAL_S = 30.0  # least time between two lines of one stage's progress

_STAGE_LOGGER = "georefine.stages"  # the stage lines' records: to the log file only (the CLI prints them)


def format_duration(seconds: float) -> str:
    """``0:01:05`` style (hours unbounded)."""
    s = max(0, int(round(seconds)))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def _stamp(wall: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(wall))


@dataclass
class _Stage:
    started: float  # monotonic
    last_line: float
    done: bool = False


@dataclass
class StageLog:
    """Plain stage lines from ``report(task, done, total)`` calls.

    ``write`` takes each finished line. A stage is finished when it reports ``done >= total``
    (a stage that reports again with less done afterwards starts again) or when :meth:`close`
    ends the run; stages may run at the same time (the demo's navigation steps beside its
    simulation).
    """

    write: Callable[[str], None]
    interval_s: float = STAGE_INTERVAL_S
    clock: Callable[[], float] = time.monotonic
    wall: Callable[[], float] = time.time
    _stages: dict[str, _Stage] = field(default_factory=dict)

    def note(self, text: str) -> None:
        """Write ``text`` as a timestamped line."""
        self.write(f"{_stamp(self.wall())}  {text}")

    def report(self, name: str, done: float, total: float) -> None:
        now = self.clock()
        stage = self._stages.get(name)
        finished = total > 0 and done >= total
        if stage is None or (stage.done and not finished):
            again = stage is not None
            stage = self._stages[name] = _Stage(now, now)
            self.note(f"{name}: started{' again' if again else ''}")
        if stage.done:
            return
        if finished:
            stage.done = True
            self.note(f"{name}: done in {format_duration(now - stage.started)}")
        elif now - stage.last_line >= self.interval_s and total > 0:
            stage.last_line = now
            share = max(0.0, min(1.0, done / total))
            elapsed = now - stage.started
            left = f", about {format_duration(elapsed * (1.0 - share) / share)} left" if share > 0 else ""
            self.note(f"{name}: {100.0 * share:.0f} % after {format_duration(elapsed)}{left}")

    def running(self) -> list[str]:
        """The stages started and not finished, in the order they started."""
        return [name for name, stage in self._stages.items() if not stage.done]

    def close(self) -> None:
        """End every stage still running (the run completed: a stage that stopped short of its
        total, e.g. an adjustment that converged before its iteration limit, is done)."""
        for name in self.running():
            self.report(name, 1.0, 1.0)


class _StageFormatter(logging.Formatter):
    """Stage lines as printed; other records with time, level and logger."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s  %(levelname)s %(name)s: %(message)s", datefmt="%Y-%m-%d %H:%M:%S")

    def format(self, record: logging.LogRecord) -> str:
        if record.name == _STAGE_LOGGER:
            return record.getMessage()
        return super().format(record)


def attach_log_file(out: Path) -> tuple[Callable[[str], None], Callable[[], None]]:
    """Open ``out/georefine.log`` for appending, write the command's header line, and route
    Georefine's log records (INFO and above) into it. Returns ``(write_line, detach)``: the
    function that adds a stage line, and the one that closes the file."""
    from georefine import __version__

    handler = logging.FileHandler(out / LOG_NAME, mode="a", encoding="utf-8")
    handler.setLevel(logging.INFO)
    handler.setFormatter(_StageFormatter())
    package = logging.getLogger("georefine")
    stages = logging.getLogger(_STAGE_LOGGER)
    stages.propagate = False  # printed by the CLI where it prints them; not twice with --verbose
    stages.setLevel(logging.INFO)
    level = package.level
    if package.getEffectiveLevel() > logging.INFO:
        package.setLevel(logging.INFO)  # the console handler keeps its own level (--verbose or not)
    package.addHandler(handler)
    stages.addHandler(handler)
    command = " ".join(shlex.quote(a) for a in [Path(sys.argv[0]).name, *sys.argv[1:]])
    stages.info(f"{_stamp(time.time())}  georefine {__version__}: {command} (in {os.getcwd()})")

    def detach() -> None:
        package.setLevel(level)
        package.removeHandler(handler)
        stages.removeHandler(handler)
        handler.close()

    return (lambda line: stages.info(line)), detach


def folder_snapshot(out: Path) -> set[Path]:
    """Every folder below ``out`` now (to tell the ones a run made from those it found)."""
    return {Path(root) for root, _, _ in os.walk(out)} if out.is_dir() else set()


def remove_new_empty_folders(out: Path, before: set[Path]) -> list[Path]:
    """Remove the empty folders below ``out`` that were not there ``before`` (deepest first, so
    that a folder emptied by its children's removal goes too); ``out`` itself stays. Returns
    what was removed."""
    removed = []
    if not out.is_dir():
        return removed
    for root, _, _ in sorted(os.walk(out), key=lambda entry: -len(Path(entry[0]).parts)):
        folder = Path(root)
        if folder == out or folder in before:
            continue
        try:
            folder.rmdir()  # only an empty folder
            removed.append(folder)
        except OSError:
            pass
    return removed
