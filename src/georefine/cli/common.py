"""What the commands of the ``georefine`` command line share: the consoles, the options used by
several commands, the error and output-folder handling, the progress bar."""

from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Optional

import typer
from rich.console import Console

from georefine.errors import GeorefineError

__all__ = ["console", "force_option", "output_ok", "progress", "scheduler_option", "stdout", "user_errors"]

console = Console(stderr=True)
stdout = Console(soft_wrap=True, markup=False)  # results and tables: "[m]" in a header is a unit, not a style

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


def output_ok(out: Optional[Path], force: bool, project: Optional[Path] = None) -> None:
    """Refuse an output folder that holds files Georefine did not write, unless --force
    (io.files.refuse_foreign_output), and one inside ``project`` (workflows.opened.output_folder):
    before :func:`progress` makes the folder for its log."""
    if out is not None:
        from georefine.io.files import refuse_foreign_output

        if project is not None:
            from georefine.workflows.opened import output_folder

            output_folder(out, Path(project))
        refuse_foreign_output(out, force)


@contextmanager
def user_errors() -> Iterator[None]:
    """Turn library errors into one message and exit code 2."""
    try:
        yield
    except GeorefineError as exc:
        from rich.markup import escape

        console.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True)
        raise typer.Exit(2) from None


@contextmanager
def progress(out: Optional[Path] = None) -> Iterator:
    """Progress of a command; yields ``report(task, done, total)`` for the library to call.

    Bars on a terminal that all end complete; off a terminal plain, timestamped stage lines on
    standard error (:class:`~georefine.cli.stages.StageLog`). With an output folder ``out``
    (made here, as :func:`~georefine.io.files.make_output_folder` does) the stage lines and
    Georefine's log records also go to ``out/georefine.log``; Ctrl-C then removes the empty
    folders the run made, says where it stopped and how to go on, and exits with 130.
    """
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from georefine.cli import stages as st

    terminal = console.is_terminal
    writers = [] if terminal else [lambda line: console.print(line, markup=False, highlight=False, soft_wrap=True)]
    detach, before, created, write_file = None, set(), False, None
    if out is not None:
        from georefine.io.files import make_output_folder

        before, created = st.folder_snapshot(out), not out.exists()
        make_output_folder(out)
        write_file, detach = st.attach_log_file(out)
        writers.append(write_file)
    log = st.StageLog(lambda line: [w(line) for w in writers])
    started = time.monotonic()
    try:
        with Progress(
            TextColumn("{task.description:<28}"),
            BarColumn(),
            TextColumn("{task.percentage:>5.1f}%"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
            console=console,
            disable=not terminal,
        ) as bars:
            tasks: dict[str, int] = {}

            def report(name: str, done: float, total: float) -> None:
                if name not in tasks:
                    tasks[name] = bars.add_task(name, total=total)
                bars.update(tasks[name], completed=done, total=total)
                log.report(name, done, total)

            try:
                yield report
            except KeyboardInterrupt:
                _interrupted(out, before, log.running(), time.monotonic() - started, log)
                raise typer.Exit(130) from None
            except GeorefineError as exc:
                if write_file is not None:  # the command prints it (user_errors); the log keeps it too
                    st.StageLog(write_file).note(f"error: {exc}")
                raise
            for task in bars.tasks:  # a stage that stopped short of its total (converged early) is done
                bars.update(task.id, completed=task.total)
            log.close()
    finally:
        if detach is not None:
            detach()
            if created and out is not None:
                _drop_if_unused(out)


def _drop_if_unused(out: Path) -> None:
    """Remove an output folder this command made if it holds nothing but its mark and the log (a
    command that failed on its input, or was interrupted, before writing anything)."""
    import shutil

    from georefine.cli.stages import LOG_NAME
    from georefine.io.files import OUTPUT_MARK

    if out.is_dir() and {e.name for e in out.iterdir()} <= {OUTPUT_MARK, LOG_NAME}:
        shutil.rmtree(out, ignore_errors=True)


def _interrupted(out: Optional[Path], before: set, running: list[str], elapsed: float, log) -> None:
    from georefine.cli import stages as st

    where = f" during {', '.join(running)}" if running else ""
    message = f"interrupted{where} after {st.format_duration(elapsed)}."
    if out is not None:
        st.remove_new_empty_folders(out, before)
        if (out / ".cache").is_dir():
            message += (f" The steps that finished are kept in {out / '.cache'}: run the same command again "
                        "to resume from there.")
        else:
            message += " Run the same command again to start over."
    log.note(message)
    if console.is_terminal:  # off a terminal the stage log just printed it
        console.print(message, style="bold yellow", markup=False, highlight=False, soft_wrap=True)
