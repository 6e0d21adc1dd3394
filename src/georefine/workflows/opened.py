"""The opened project: a project folder read once per command and handed to every workflow step.

:func:`open_project` reads and validates ``project.yaml`` once; the :class:`Project` it returns
carries the configuration and derives, on first use and then once only, what several steps
share: the navigation data and with them the mapping frame ``w`` (docs/ARCHITECTURE.md §2),
the output CRS and the gravity-related heights of the final point clouds. Every workflow
function takes a :class:`Project` (or a folder, which it opens) and nothing below it reloads
``project.yaml``: a command that runs several workflows (the hybrid runs the G/I, the G/I/L and
the photo block) opens the project once.

A project is made of :class:`Flight` records (:attr:`Project.flights`): the GNSS, IMU and
strips of one sortie, sharing the scanner's calibration (lever arms, boresight, time offset)
with the project's other flights. Today's ``project.yaml`` describes one flight, and the steps
still read its sections from the configuration; a project of several flights adds records
there and per-flight navigation beside :attr:`Project.navigation`, not parameters to every
step (**not built yet**: docs/ARCHITECTURE.md §3).

:class:`Workspace` is what one command writes to: the output folder (checked: never the
project folder or inside it), its step cache and the task runner of the per-tile work.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from georefine.adjustment.gnss_imu import GnssImuData
from georefine.adjustment.trajectory_prior import TrajectoryPriorData
from georefine.config import ProjectConfig, load_project
from georefine.errors import InputError
from georefine.geometry.frames import GeoidHeights, LocalFrame, OutputCRS
from georefine.io.files import check_output_folder
from georefine.io.gnss import gnss_in_w
from georefine.io.imu import ImuData
from georefine.tasks import DEFAULT_SCHEDULER, TaskRunner, runner_for
from georefine.workflows.cache import StepCache, StepRunner
from georefine.workflows.delivered import read_delivered
from georefine.workflows.project import (
    bridge_project_imu,
    check_imu_plausible,
    check_navigation_spans,
    read_project_gnss,
    read_project_imu,
)

log = logging.getLogger(__name__)


__all__ = ["Flight", "NavigationData", "Project", "ProjectLike", "Workspace", "as_project", "open_project", "load_navigation",
           "open_workspace", "output_folder", "project_root"]


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

    def output_folder(self, out: str | Path) -> Path:
        """``out`` as a Path, refused when it is the project folder or inside it (:func:`output_folder`)."""
        return output_folder(out, self.root)


def output_folder(out: str | Path, project_root: Path) -> Path:
    """``out`` as a Path, refusing the project folder or anything inside it (inputs stay untouched),
    and a path that exists but is not a folder, or lies below a file."""
    out = Path(out)
    if out.resolve() == project_root.resolve() or project_root.resolve() in out.resolve().parents:
        raise InputError("refusing to write into the project folder", path=out, expected="an output folder outside the inputs")
    return check_output_folder(out)


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


def project_root(project: ProjectLike) -> Path:
    """The folder of ``project`` (opened or named), for steps that read files beside the
    configuration only (the simulated truth) and open nothing."""
    return project.root if isinstance(project, Project) else Path(project)


@dataclass(frozen=True)
class NavigationData:
    """GNSS and IMU of a project in the mapping frame, validated; or its delivered trajectory.

    A project with raw sensors has ``imu`` and ``gnss``; one with a delivered trajectory
    (``config.delivered_trajectory``, docs/ARCHITECTURE.md §4.9) has ``prior`` instead.
    """

    config: ProjectConfig
    root: Path
    frame: LocalFrame
    t0_gps: float
    imu: ImuData | None
    gnss: GnssImuData | None
    prior: TrajectoryPriorData | None = None

    @property
    def sample_time(self) -> np.ndarray:
        """The times of the trajectory products: the IMU samples, or the delivered SBET's records (s)."""
        return self.prior.time if self.prior is not None else self.gnss.imu_time

    @property
    def span(self) -> tuple[float, float]:
        """Where the navigation data define the trajectory (s): GNSS and IMU overlap, or the SBET."""
        if self.prior is not None:
            return float(self.prior.time[0]), float(self.prior.time[-1])
        g, i = self.gnss.gnss_time, self.gnss.imu_time
        return max(float(g[0]), float(i[0])), min(float(g[-1]), float(i[-1]))


def load_navigation(project: ProjectLike) -> NavigationData:
    """Read and validate GNSS and IMU; define ``w`` at the first usable GNSS fix (or at
    ``crs.reference_point``). A workflow asks :attr:`Project.navigation`, which calls this once.

    Raises
    ------
    InputError
        No usable GNSS epoch, GNSS and IMU spans that do not overlap, or an IMU sampling gap longer
        than ``imu.max_gap_s`` (shorter ones are bridged: :func:`bridge_project_imu`).
    """
    project = as_project(project)
    root, cfg = project.root, project.config
    if cfg.delivered_trajectory:
        frame, t0, prior = read_delivered(root, cfg)
        return NavigationData(cfg, root, frame, t0, None, None, prior)
    gnss = read_project_gnss(root, cfg)
    imu = read_project_imu(root, cfg)
    bridged = bridge_project_imu(root, cfg, imu)  # the same rule as `georefine check`
    if bridged.gaps:
        log.warning("%s: %s", cfg.imu.file, bridged.describe())
    imu = bridged.data
    check_imu_plausible(root, cfg, gnss, imu)
    usable, _, _ = check_navigation_spans(root, cfg, gnss, imu)
    if cfg.crs.reference_point is not None:
        rp = cfg.crs.reference_point
        frame = LocalFrame.from_degrees(rp.lat_deg, rp.lon_deg, rp.h_m)
    else:
        lat, lon, h = gnss.geodetic()
        i = int(np.flatnonzero(usable)[0])
        frame = LocalFrame(float(lat[i]), float(lon[i]), float(h[i]))
    t0 = float(np.floor(imu.time_gps[0]))
    gt, gp, gc = gnss_in_w(frame, t0, gnss, cfg.gnss.min_quality)
    data = GnssImuData(
        frame=frame, t0_gps=t0, imu_time=imu.time_gps - t0, imu_gyro=imu.gyro, imu_acc=imu.acc,
        imu_rate_hz=float(imu.rate_hz), gnss_time=gt, gnss_p_w=gp, gnss_cov_w=gc,
        p_b_a=np.asarray(cfg.gnss.lever_arm_m, dtype=float),
        imu_gyro_sigma=bridged.gyro_sigma if bridged.gaps else None,
        imu_acc_sigma=bridged.acc_sigma if bridged.gaps else None,
        gnss_correlated=cfg.gnss.correlated_error, imu_kind=imu.kind,
    )
    return NavigationData(cfg, root, frame, t0, imu, data)


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
