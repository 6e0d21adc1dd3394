"""The opened project: a project folder read once per command and handed to every workflow step.

:func:`open_project` reads and validates ``project.yaml`` once; the :class:`Project` it returns
carries the configuration and derives, on first use and then once only, what several steps
share: the navigation data and with them the mapping frame ``w`` (docs/ARCHITECTURE.md §2),
the output CRS and the gravity-related heights of the final point clouds. Every workflow
function takes a :class:`Project` (or a folder, which it opens) and nothing below it reloads
``project.yaml``: a command that runs several workflows (the hybrid runs the G/I, the G/I/L and
the photo block) opens the project once.

A project is made of :class:`Flight` records (:attr:`Project.flights`): the GNSS, IMU and
strips of one sortie, with the scanner's calibration (lever arms, boresight, time offset) the
project's flights share unless one states its own. A ``project.yaml`` without ``flights`` is one
flight, whose navigation is :attr:`Project.navigation`; a project of several flights
(``flights:``, docs/ARCHITECTURE.md §3) has one navigation per flight,
:meth:`Project.navigation_of`, all in one mapping frame (:attr:`Project.frame`). The workflow
steps take a project of one flight (the steps on several flights together are **not built
yet**): on a project of several flights :attr:`Project.navigation` is an error that says so, and
:meth:`Project.flight_project` gives one of its flights as a project of its own.

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
from georefine.config import ProjectConfig, ReferencePoint, Vector3, load_project
from georefine.errors import ConfigError, InputError
from georefine.geometry.frames import GeoidHeights, LocalFrame, OutputCRS
from georefine.io.files import check_output_folder
from georefine.io.gnss import GnssSolution, gnss_in_w
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
    usable_gnss,
)

log = logging.getLogger(__name__)


__all__ = ["Flight", "NavigationData", "Project", "ProjectLike", "Workspace", "as_project", "first_fix_frame",
           "open_project", "load_navigation", "open_workspace", "output_folder", "project_root"]


@dataclass(frozen=True)
class Flight:
    """One sortie of a project: its navigation files and strips (paths relative to the project folder)
    and the calibration its strips are georeferenced with (the project's shared values where the
    flight states none: :meth:`georefine.config.ProjectConfig.flight_config`).

    ``gnss_files`` and ``imu_file`` are empty for a project with a delivered trajectory
    (docs/ARCHITECTURE.md §4.9), whose SBET is ``trajectory_file``; ``gnss_lever_arm_m`` is then None.
    """

    id: int
    name: str
    gnss_files: tuple[str, ...]
    imu_file: str | None
    strip_files: tuple[str, ...]
    scanner_lever_arm_m: Vector3
    """``p_b_s`` (m)."""
    boresight_deg: Vector3
    """Roll, pitch, yaw of ``R_b_s`` (deg)."""
    scanner_time_offset_s: float
    gnss_lever_arm_m: Vector3 | None = None
    """``p_b_a`` (m)."""
    trajectory_file: str | None = None


def _flight(flight_id: int, name: str, cfg: ProjectConfig) -> Flight:
    """The :class:`Flight` of a single-flight configuration (a project's, or one flight's view of it)."""
    sc = cfg.scanner
    cal = dict(scanner_lever_arm_m=tuple(sc.lever_arm_m), boresight_deg=tuple(sc.boresight_deg),
               scanner_time_offset_s=float(sc.time_offset_s))
    if cfg.delivered_trajectory:
        return Flight(flight_id, name, (), None, tuple(sc.files), trajectory_file=cfg.trajectory.sbet, **cal)
    return Flight(flight_id, name, tuple(cfg.gnss.files), cfg.imu.file, tuple(sc.files),
                  gnss_lever_arm_m=tuple(cfg.gnss.lever_arm_m), **cal)


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
        """The project's flights in the order ``project.yaml`` lists them; one (id 1, ``flight_1``) made of
        the sections gnss, imu and scanner when it has no ``flights``."""
        cfg = self.config
        if cfg.flights is None:
            return (_flight(1, "flight_1", cfg),)
        return tuple(_flight(f.id, f.label, cfg.flight_config(f.id)) for f in cfg.flights)

    @property
    def multi_flight(self) -> bool:
        """True when ``project.yaml`` lists its flights (:meth:`navigation_of` then reads each)."""
        return self.config.multi_flight

    @cached_property
    def navigation(self) -> NavigationData:
        """GNSS and IMU in the mapping frame, validated (or the delivered trajectory); read once.

        Raises
        ------
        ConfigError
            A project of several flights (``flights``): it has a navigation per flight, :meth:`navigation_of`.
        """
        return load_navigation(self)

    def navigation_of(self, flight_id: int) -> NavigationData:
        """One flight's GNSS and IMU (its files only) in the project's mapping frame, validated as
        :func:`load_navigation` validates a project's; read once per flight. For a project without
        ``flights``, flight 1 is :attr:`navigation`.

        Raises
        ------
        ConfigError
            No flight with this id.
        InputError
            As :func:`load_navigation`, naming the flight's files.
        """
        if not self.multi_flight:
            self.config.flight_config(flight_id)  # refuses another id than 1
            return self.navigation
        cached = self._flight_navigation
        if flight_id not in cached:
            cached[flight_id] = load_navigation(self.flight_project(flight_id))
        return cached[flight_id]

    def flight_project(self, flight_id: int) -> Project:
        """One flight of the project as a single-flight :class:`Project` (same folder): its files as
        ``gnss.files``, ``imu.file`` and ``scanner.files``, its calibration, and, for a project of
        several flights, the project's mapping frame as ``crs.reference_point`` (every flight's
        navigation in the same ``w``)."""
        cfg = self.config.flight_config(flight_id)
        if not self.multi_flight:
            return self
        if cfg.crs.reference_point is None:
            lat, lon, h = self._frame_origin_deg
            cfg.crs.reference_point = ReferencePoint(lat_deg=lat, lon_deg=lon, h_m=h)
        return Project(self.root, cfg)

    @cached_property
    def _flight_navigation(self) -> dict[int, NavigationData]:
        return {}

    @cached_property
    def _frame_origin_deg(self) -> tuple[float, float, float]:
        """Latitude, longitude (deg) and height (m) of ``w`` for a project of several flights."""
        rp = self.config.crs.reference_point
        if rp is not None:
            return rp.lat_deg, rp.lon_deg, rp.h_m
        first = self.config.flight_config(self.config.flight_ids[0])
        f = first_fix_frame(self.root, first, read_project_gnss(self.root, first))
        return float(np.degrees(f.lat0_rad)), float(np.degrees(f.lon0_rad)), f.h0_m

    @cached_property
    def frame(self) -> LocalFrame:
        """The mapping frame ``w``: defined by the navigation data (:attr:`navigation`); for a project of
        several flights, at ``crs.reference_point`` or else at the first usable GNSS fix of the first
        flight listed (only its GNSS files are read for it), the same for every flight's navigation."""
        if not self.multi_flight:
            return self.navigation.frame
        return LocalFrame.from_degrees(*self._frame_origin_deg)

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
    if cfg.flights is not None:
        ids = ", ".join(map(str, cfg.flight_ids))
        raise ConfigError(
            "a project of several flights has one navigation per flight, and the workflow steps read one flight's "
            "project (the adjustment of several flights together is not built yet)",
            path=root / "project.yaml", field="flights",
            expected=f"the navigation of one flight, Project.navigation_of(flight_id) with flight_id one of {ids}",
            found=f"{len(cfg.flights)} flight{'s' if len(cfg.flights) != 1 else ''}")
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
    check_navigation_spans(root, cfg, gnss, imu)
    frame = first_fix_frame(root, cfg, gnss)
    t0 = float(np.floor(imu.time_gps[0]))
    gt, gp, gc = gnss_in_w(frame, t0, gnss, cfg.gnss.min_quality)
    data = GnssImuData(
        frame=frame, t0_gps=t0, imu_time=imu.time_gps - t0, imu_gyro=imu.gyro, imu_acc=imu.acc,
        imu_rate_hz=float(imu.rate_hz), gnss_time=gt, gnss_p_w=gp, gnss_cov_w=gc,
        p_b_a=np.asarray(cfg.gnss.lever_arm_m, dtype=float),
        imu_gyro_sigma=bridged.gyro_sigma if bridged.gaps else None,
        imu_acc_sigma=bridged.acc_sigma if bridged.gaps else None,
        gnss_correlated=cfg.gnss.correlated_error, imu_kind=imu.kind,
        gnss_quality=gnss.quality[gnss.quality <= cfg.gnss.min_quality], gnss_float=cfg.gnss.float_offset,
        gnss_multipath=cfg.gnss.multipath, imu_temperature=imu.temperature_c,
    )
    return NavigationData(cfg, root, frame, t0, imu, data)


def first_fix_frame(root: Path, cfg: ProjectConfig, gnss: GnssSolution) -> LocalFrame:
    """The mapping frame ``w`` of a single-flight configuration: at ``crs.reference_point``, else at
    the first GNSS fix of the configured quality (:func:`check_navigation_spans` refuses GNSS without one)."""
    if cfg.crs.reference_point is not None:
        rp = cfg.crs.reference_point
        return LocalFrame.from_degrees(rp.lat_deg, rp.lon_deg, rp.h_m)
    usable = usable_gnss(root, cfg, gnss)
    lat, lon, h = gnss.geodetic()
    i = int(np.flatnonzero(usable)[0])
    return LocalFrame(float(lat[i]), float(lon[i]), float(h[i]))


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
