"""The opened project: a project folder read once per command and handed to every workflow step.

:func:`open_project` reads and validates ``project.yaml`` once; the :class:`Project` it returns
carries the configuration and derives, on first use and then once only, what several steps
share: the navigation data and with them the mapping frame ``w`` (docs/ARCHITECTURE.md §2),
the output CRS and the gravity-related heights of the final point clouds. Every workflow
function takes a :class:`Project` (or a folder, which it opens) and nothing below it reloads
``project.yaml``: a command that runs several workflows (the hybrid runs the G/I, the G/I/L and
the photo block) opens the project once.

A project is made of :class:`Flight` records: the GNSS, IMU and strips of one sortie, sharing
the scanner's calibration (lever arms, boresight, time offset) with the project's other
flights. Today's ``project.yaml`` describes one flight; the steps read the flights through
:attr:`Project.flights`, so a project of several flights adds records there, not parameters
to every step.

:class:`Workspace` is what one command writes to: the output folder (checked: never the
project folder or inside it), its step cache and the task runner of the per-tile work.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

from georefine.config import ProjectConfig, load_project
from georefine.errors import InputError
from georefine.geometry.frames import GeoidHeights, OutputCRS
from georefine.tasks import DEFAULT_SCHEDULER, TaskRunner, runner_for
from georefine.workflows.cache import StepCache, StepRunner

if TYPE_CHECKING:  # navigation imports this module's types only under TYPE_CHECKING too
    from georefine.geometry.frames import LocalFrame
    from georefine.workflows.navigation import NavigationData

__all__ = ["Flight", "Project", "ProjectLike", "Workspace", "as_project", "open_project", "open_workspace"]


@dataclass(frozen=True)
class Flight:
    """One sortie of a project: its navigation files and strips (paths relative to the project folder).

    ``gnss_files`` and ``imu_file`` are empty for a project with a delivered trajectory
    (docs/ARCHITECTURE.md §4.9), whose SBET is ``trajectory_file``.
    """

    name: str
    gnss_files: tuple[str, ...]
    imu_file: str | None
    strip_files: tuple[str, ...]
    trajectory_file: str | None = None


@dataclass(frozen=True, eq=False)
class Project:
    """A project folder with its validated ``project.yaml`` (:func:`open_project`).

    The derived values are computed on first use and kept: :attr:`navigation` reads and checks
    the GNSS and IMU (or the delivered SBET) once, whichever step asks first.
    """

    root: Path
    config: ProjectConfig

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def flights(self) -> tuple[Flight, ...]:
        """The project's flights (one today: the sections gnss, imu and scanner of ``project.yaml``)."""
        cfg = self.config
        if cfg.delivered_trajectory:
            return (Flight("flight_1", (), None, tuple(cfg.scanner.files), cfg.trajectory.sbet),)
        return (Flight("flight_1", tuple(cfg.gnss.files), cfg.imu.file, tuple(cfg.scanner.files)),)

    @cached_property
    def navigation(self) -> NavigationData:
        """GNSS and IMU in the mapping frame, validated (or the delivered trajectory); read once."""
        from georefine.workflows.navigation import load_navigation

        return load_navigation(self)

    @property
    def frame(self) -> LocalFrame:
        """The mapping frame ``w`` (defined by the navigation data: :attr:`navigation`)."""
        return self.navigation.frame

    @cached_property
    def crs(self) -> OutputCRS:
        """The output CRS (``crs.output_epsg``)."""
        return OutputCRS(self.config.crs.output_epsg)

    @cached_property
    def heights(self) -> GeoidHeights | None:
        """The final point clouds' gravity-related heights (``crs.geoid_grid``), or None for ellipsoidal ones."""
        return self.config.crs.geoid(self.root)

    def with_config(self, config: ProjectConfig) -> Project:
        """The same folder with another configuration (derived values computed anew)."""
        return replace(self, config=config)

    def output_folder(self, out: str | Path) -> Path:
        """``out`` as a Path, refused when it is the project folder or inside it (inputs stay
        untouched), or exists and is not a folder (:func:`~georefine.workflows.project.output_folder`)."""
        from georefine.workflows.project import output_folder

        return output_folder(out, self.root)


ProjectLike = Project | str | Path
"""What the workflow functions take: an opened :class:`Project`, or a folder they open."""


def open_project(project_dir: str | Path) -> Project:
    """Read and validate ``PROJECT/project.yaml`` (:func:`georefine.config.load_project`).

    Raises
    ------
    InputError
        The folder does not exist.
    ConfigError
        No ``project.yaml``, or a setting that does not validate (file, field, expected, found).
    """
    root = Path(project_dir)
    if not root.is_dir():
        raise InputError("project folder not found", path=root)
    return Project(root, load_project(root))


def as_project(project: ProjectLike) -> Project:
    """``project`` itself, or the folder it names opened (:func:`open_project`)."""
    return project if isinstance(project, Project) else open_project(project)


@dataclass(frozen=True)
class Workspace:
    """Where one command writes: its output folder, the step cache and the per-tile task runner."""

    out: Path
    steps: StepRunner
    runner: TaskRunner


@contextmanager
def open_workspace(project: Project, out: str | Path, *, resume: bool = True, cache_dir: str | Path | None = None,
                   scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> Iterator[Workspace]:
    """The :class:`Workspace` of a command writing into ``out`` (checked, not yet created: the
    first step that writes makes it); the cache in ``out/.cache`` or ``cache_dir``, used only
    with ``resume``; the runner started here (or ``scheduler`` itself, when it is a running one)."""
    out = project.output_folder(out)
    steps = StepRunner(StepCache(Path(cache_dir) if cache_dir is not None else out / ".cache", enabled=resume))
    with runner_for(scheduler) as runner:
        yield Workspace(out, steps, runner)
