"""What the commands of the ``georefine`` command line share: the consoles, the options used by
several commands, the error and output-folder handling, the progress bar."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Optional

import typer
from rich.console import Console

from georefine.errors import GeorefineError

__all__ = ["console", "force_option", "output_ok", "progress", "scheduler_option", "stdout", "user_errors"]

console = Console(stderr=True)
stdout = Console(soft_wrap=True)

_SCHEDULER_HELP = ("Where the per-tile work runs: sync, threads, processes (a local Dask cluster, one worker "
                   "process per core) or the address of a running dask scheduler, e.g. tcp://127.0.0.1:8786. "
                   "Results do not depend on it.")


def scheduler_option(default: str = "threads"):
    """``--scheduler``; ``default`` is the scheduler measured fastest on 2 cores for the command."""
    return typer.Option(default, "--scheduler", envvar="GEOREFINE_SCHEDULER",
                        help=f"{_SCHEDULER_HELP} Default {default}: the fastest here on 2 cores.")


def force_option():
    return typer.Option(False, "--force", help="Write into an output folder that holds files Georefine did not write "
                        "(its files of the same names are replaced).")


def output_ok(out: Optional[Path], force: bool) -> None:
    """Refuse an output folder that holds files Georefine did not write, unless --force (io.files.refuse_foreign_output)."""
    if out is not None:
        from georefine.io.files import refuse_foreign_output

        refuse_foreign_output(out, force)


@contextmanager
def user_errors() -> Iterator[None]:
    """Turn library errors into one message and exit code 2."""
    try:
        yield
    except GeorefineError as exc:
        console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(2) from None


@contextmanager
def progress() -> Iterator:
    """A rich progress bar; yields ``report(task, done, total)`` for the library to call."""
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(
        TextColumn("{task.description:<28}"),
        BarColumn(),
        TextColumn("{task.percentage:>5.1f}%"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        disable=not console.is_terminal,
    ) as progress:
        tasks: dict[str, int] = {}

        def report(name: str, done: float, total: float) -> None:
            if name not in tasks:
                tasks[name] = progress.add_task(name, total=total)
            progress.update(tasks[name], completed=done, total=total)

        yield report
