"""Georefine's public Python API: the functions the ``georefine`` command line calls, and nothing else.

Every command of the CLI is one function here, named by what it does; the command that calls
it is named in its docstring. The functions that work on a project take it first, as a
:class:`Project` (:func:`open_project`: ``project.yaml`` read and validated once) or as the
project's folder, then the output folder, then keyword-only options; ``progress`` (a
:data:`~georefine.progress.Progress` callback, ``report(task, done, total)``) and
``scheduler`` (where the per-tile work runs: ``"sync"``, ``"threads"``, ``"processes"``, a Dask
scheduler's address or a running :class:`~georefine.tasks.TaskRunner`; the results do not
depend on it) come last. Each returns a frozen result whose ``summary()`` is what the command
prints. Bad input raises :class:`~georefine.errors.InputError` or
:class:`~georefine.errors.ConfigError` (both :class:`~georefine.errors.GeorefineError`), naming
the file, the line or record, the field, what was expected and what was found; nothing is
half-written.

>>> import georefine as gr
>>> gr.simulate("corridor-tiny", "tiny", seed=7)            # doctest: +SKIP
>>> result = gr.run("tiny", "tiny-run")                     # doctest: +SKIP
>>> result.metrics.pass_precision                           # doctest: +SKIP

The package ``georefine`` re-exports every name of :data:`__all__` (loaded on first use, so that
``import georefine`` stays light); the layers below (docs/ARCHITECTURE.md §1) are the library's
inside and may change between versions.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from georefine.demo.block import BlockDemoResult, run_block_demo
from georefine.demo.corridor import DemoResult
from georefine.demo.corridor import run_demo as run_corridor_demo
from georefine.errors import ConfigError, GeorefineError, InputError
from georefine.evaluation.strip_differences import StripDifferenceMap
from georefine.evaluation.summary import ReferencePlaneFigures, RunEvaluation
from georefine.evaluation.trajectory import TrajectoryComparison
from georefine.heap import bound_heap
from georefine.progress import Progress, no_progress
from georefine.sim.scenarios import SimulationResult, simulate_project
from georefine.tasks import DEFAULT_SCHEDULER, TaskRunner, runner_for
from georefine.workflows.check import ProjectSummary, inspect_project
from georefine.workflows.flights import FlightsResult
from georefine.workflows.hybrid import HybridResult, run_hybrid
from georefine.workflows.import_strips import ImportResult
from georefine.workflows.lidar import WorkflowResult, run_workflow
from georefine.workflows.lidargrammetry import run_coadjust, run_lidargrams, run_match
from georefine.workflows.lidargrammetry_results import CoadjustResult, MatchSummary
from georefine.workflows.navigation import GeoreferenceRunResult, TrajectoryRunResult, run_georeference, run_trajectory
from georefine.workflows.opened import Flight, Project, ProjectLike, open_project
from georefine.workflows.products import TrajectoryExport

bound_heap()  # freed arrays go back to the system (georefine.heap)

__all__ = [
    # the project
    "Flight", "Project", "open_project",
    # the commands
    "adjust_hybrid", "check", "clean", "coadjust", "estimate_trajectory", "evaluate_reference_planes",
    "evaluate_run", "evaluate_strip_differences", "evaluate_trajectory", "export_trajectory", "georeference",
    "import_strips", "match", "render_lidargrams", "run", "run_demo", "simulate",
    # their results
    "BlockDemoResult", "CleanResult", "CoadjustResult", "DemoResult", "GeoreferenceRunResult", "HybridResult",
    "ImportResult", "MatchSummary", "ProjectSummary", "ReferencePlaneFigures", "RunEvaluation", "SimulationResult",
    "StripDifferenceMap", "TrajectoryComparison", "TrajectoryEvaluation", "TrajectoryExport", "TrajectoryRunResult",
    "FlightsResult", "WorkflowResult",
    # errors, progress, where the work runs
    "ConfigError", "GeorefineError", "InputError", "Progress", "TaskRunner",
]

PathLike = str | Path


# --- Simulation --------------------------------------------------------------------------------


def simulate(scenario: str, out: PathLike, *, seed: int = 42, overrides: Sequence[str] = (),
             config_file: PathLike | None = None, imu_grade: str | None = None, gnss_grade: str | None = None,
             write_imr: bool = False, progress: Progress = no_progress,
             scheduler: str | TaskRunner = "sync") -> SimulationResult:
    """Simulate a flight into the project folder ``out``: the files a real system writes, and the truth
    (``georefine simulate``; docs/ARCHITECTURE.md §6).

    ``scenario``: ``corridor``, ``corridor-tiny``, ``corridor-paper``, ``corridor-paper-full``, ``block``, ``area`` or ``area-tiny``;
    ``overrides``: ``"key.sub=value"`` strings; ``config_file``: a YAML file of overrides;
    ``imu_grade`` (``navigation``, ``tactical``, ``mems``, ``ideal``, or the unit ``stim300``) and ``gnss_grade`` (``ppk``,
    ``ideal``): presets; ``write_imr``: the IMU also as a NovAtel ``.imr`` file. The same seed
    gives the same files. ``scheduler`` defaults to ``sync``: the ray caster and the LAZ encoder
    already use every core.
    """
    return simulate_project(scenario, out, seed=seed, overrides=list(overrides), config_file=config_file,
                            imu_grade=imu_grade, gnss_grade=gnss_grade, write_imr=write_imr, progress=progress,
                            scheduler=scheduler)


# --- A project's workflows ---------------------------------------------------------------------


def check(project: ProjectLike, *, progress: Progress = no_progress) -> ProjectSummary:
    """Validate a project: ``project.yaml``, every file it names and their time spans (``georefine check``).

    Nothing is written. Raises :class:`InputError` on the first problem; the warnings (IMU gaps
    bridged, GNSS gaps, points outside the navigation) are in the summary.
    """
    return inspect_project(project, progress=progress)


def estimate_trajectory(project: ProjectLike, out: PathLike, *, filter_only: bool = False,
                        progress: Progress = no_progress) -> TrajectoryRunResult:
    """Workflow steps 1-2 (initialisation filter, GNSS/IMU adjustment) into ``out``
    (``georefine trajectory``): ``trajectory.sbet``, ``trajectory.csv``, ``adjustment.json``.

    ``filter_only``: stop after the filter (its trajectory is written instead).
    """
    return run_trajectory(project, out, filter_only=filter_only, progress=progress)


def run(project: ProjectLike, out: PathLike, *, strips: Sequence[int] | None = None, lidar: bool = True,
        points: bool = True, resume: bool = True, cache_dir: PathLike | None = None,
        progress: Progress = no_progress, scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> WorkflowResult | FlightsResult:
    """The whole workflow of paper 000, steps 1-6, into ``out`` (``georefine run``); a project of
    several flights adjusts them together and returns a :class:`FlightsResult`.

    Writes ``gi/`` and ``gil/`` (trajectory products, ``adjustment.json``), ``points/*.laz``,
    ``features/``, ``metrics.json`` and ``config.resolved.yaml``. ``strips``: the strip ids
    (``point_source_id``) to use; ``lidar=False``: steps 1, 2 and 6 only (the G/I trajectory and
    its clouds); ``points=False``: no step 6; ``resume``: load from ``out/.cache`` (or
    ``cache_dir``) what the inputs and settings have not changed.
    """
    return run_workflow(project, out, strips=None if strips is None else list(strips), lidar=lidar, resume=resume,
                        points=points, cache_dir=cache_dir, progress=progress, scheduler=scheduler)


def georeference(project: ProjectLike, trajectory: PathLike, out: PathLike, *, gps_week: int | None = None,
                 progress: Progress = no_progress,
                 scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> GeoreferenceRunResult:
    """Every strip of the project georeferenced with a trajectory SBET into ``out/*.laz``
    (``georefine georeference``): LAS 1.4 in the output CRS.

    ``gps_week``: the week of an SBET in seconds of the week without a companion file
    (default: the strips' week).
    """
    return run_georeference(project, trajectory, out, gps_week=gps_week, progress=progress, scheduler=scheduler)


def import_strips(strips: Sequence[PathLike], sbet: PathLike, out: PathLike, *,
                  lever_arm_m: tuple[float, float, float], boresight_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  smrmsg: PathLike | None = None, gps_week: int | None = None, imu: PathLike | None = None,
                  progress: Progress = no_progress,
                  scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> ImportResult:
    """A project made from delivered data: georeferenced strips and their SBET (``georefine import-strips``;
    docs/ARCHITECTURE.md §4.9).

    Every point goes back into the scanner frame with the SBET, ``lever_arm_m`` (scanner origin
    in the IMU body frame, FRD) and ``boresight_deg``; :func:`run` on ``out`` then adjusts the
    SBET with the LiDAR planes. ``smrmsg``: the SBET's accuracy file; ``imu``: a YAML file with
    the ``imu`` section for the raw IMU.
    """
    from georefine.workflows.import_strips import import_strips as _import

    return _import(list(strips), sbet, out, lever_arm_m=lever_arm_m, boresight_deg=boresight_deg, smrmsg=smrmsg,
                   gps_week=gps_week, imu=imu, progress=progress, scheduler=scheduler)


# --- Lidargrammetry (paper 004) and the hybrid adjustment --------------------------------------


def render_lidargrams(project: ProjectLike, points: Sequence[PathLike], out: PathLike, *,
                      overrides: Mapping[str, Any] | None = None, progress: Progress = no_progress,
                      scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> list[str]:
    """Lidargrams at the photos' approximate orientation, ``out/NAME.png`` and ``NAME.npz`` (the ULPI
    raster) (``georefine lidargrams``). ``overrides``: fields of ``processing.lidargrammetry``.
    Returns the image files' names."""
    return run_lidargrams(project, list(points), out, overrides=overrides, progress=progress, scheduler=scheduler)


def match(project: ProjectLike, points: Sequence[PathLike], out: PathLike, *,
          overrides: Mapping[str, Any] | None = None, matcher=None, progress: Progress = no_progress,
          scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> MatchSummary:
    """Photos and lidargrams matched: verified matches, tracks and pictures in ``out`` (``georefine match``).

    ``overrides``: fields of ``processing.lidargrammetry`` (e.g. ``{"matcher": "xfeat"}``);
    ``matcher``: a matcher object instead of the one the settings name.
    """
    return run_match(project, list(points), out, overrides=overrides, matcher=matcher, progress=progress,
                     scheduler=scheduler)


def coadjust(project: ProjectLike, points: Sequence[PathLike], out: PathLike, case: int, *,
             overrides: Mapping[str, Any] | None = None, matcher=None, cache_dir: PathLike | None = None,
             progress: Progress = no_progress, scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> CoadjustResult:
    """Co-matching and co-adjustment of photos and lidargrams, paper 004's case 1, 2 or 3
    (``georefine coadjust``; docs/ARCHITECTURE.md §4.8).

    Writes ``eop_photos.csv``, ``eop_lidargrams.csv``, the refined cloud ``points/*.laz`` (cases
    1 and 2), the residual tables and ``metrics.json``. ``cache_dir``: a step cache shared by
    the cases of one cloud (they match once).
    """
    return run_coadjust(project, list(points), out, case, overrides=overrides, matcher=matcher, cache_dir=cache_dir,
                        progress=progress, scheduler=scheduler)


def adjust_hybrid(project: ProjectLike, out: PathLike, *, case: int = 1, planes: bool = True,
                  overrides: Mapping[str, Any] | None = None, matcher=None, resume: bool = True,
                  progress: Progress = no_progress, scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> HybridResult:
    """One adjustment of GNSS, IMU, LiDAR and photos, the lidargram ties on the trajectory
    (``georefine hybrid``; docs/ARCHITECTURE.md §4.10).

    ``case`` 1: the photo block adjusted with its control first, then fixed; 2: photos and
    trajectory together. ``planes``: start from the G/I/L adjustment and keep its planes.
    """
    return run_hybrid(project, out, case=case, planes=planes, overrides=overrides, matcher=matcher, resume=resume,
                      progress=progress, scheduler=scheduler)


# --- Evaluation and export ---------------------------------------------------------------------


def evaluate_run(project: ProjectLike, run_dir: PathLike, single_dir: PathLike | None = None, *,
                 progress: Progress = no_progress,
                 scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> RunEvaluation:
    """A run of :func:`run` on a simulated project evaluated against its truth as paper 000 reports
    it (trajectory differences, reference planes, strip differences, strip pairs), into ``run_dir/evaluation``
    (``georefine evaluate run``).
    ``single_dir``: a single-pass run of the same project, evaluated beside it."""
    from georefine.workflows.evaluate import evaluate_run as _evaluate

    return _evaluate(project, Path(run_dir), None if single_dir is None else Path(single_dir), progress=progress,
                     scheduler=scheduler)


@dataclass(frozen=True)
class TrajectoryEvaluation:
    """What :func:`evaluate_trajectory` compared, and the files it wrote (none without ``out``)."""

    comparison: TrajectoryComparison
    files: tuple[Path, ...]


def evaluate_trajectory(estimate: PathLike, reference: PathLike, out: PathLike | None = None, *,
                        gps_week: int | None = None,
                        span: tuple[float, float] | None = None) -> TrajectoryEvaluation:
    """Roll/pitch/yaw and position differences of an SBET minus a reference SBET (paper 000, Fig. 9;
    ``georefine evaluate trajectory``); with ``out``, ``trajectory_comparison.json`` and the plots.

    ``gps_week``: the week of SBETs in seconds of the week without a companion file; ``span``:
    only this time window (seconds of the week or GPS seconds).
    """
    from georefine.evaluation.trajectory_files import compare_sbet_files, write_trajectory_evaluation

    comparison = compare_sbet_files(estimate, reference, gps_week=gps_week, time_window=span)
    files = () if out is None else tuple(
        write_trajectory_evaluation(out, comparison, protect=(estimate, reference)).all())
    return TrajectoryEvaluation(comparison, files)


def evaluate_reference_planes(points: Sequence[PathLike], reference: PathLike, out: PathLike | None = None, *,
                              inset_m: float = 0.25, max_distance_m: float = 0.3, progress: Progress = no_progress,
                              scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> ReferencePlaneFigures:
    """Distances of georeferenced points (files or folders) to surveyed reference planes per strip x
    channel (paper 000, Table 1; ``georefine evaluate reference-planes``); with ``out``,
    ``reference_planes.json`` and ``.csv``."""
    from georefine.evaluation.clouds import evaluate_reference_planes as _evaluate
    from georefine.io.las import point_files

    with runner_for(scheduler) as runner:
        _, summary = _evaluate(point_files([Path(p) for p in points]), Path(reference),
                               None if out is None else Path(out), inset_m=inset_m, max_distance_m=max_distance_m,
                               runner=runner, progress=progress)
    return ReferencePlaneFigures.from_summary(summary)


def evaluate_strip_differences(points: Sequence[PathLike], out: PathLike | None = None, *, cell_size_m: float = 1.0,
                               max_roughness_m: float = 0.03, max_slope_deg: float = 60.0,
                               max_normal_angle_deg: float = 5.0, progress: Progress = no_progress,
                               scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> StripDifferenceMap:
    """Strip differences of georeferenced points (files or folders) on a raster of planar cells
    (paper 000, Fig. 7; ``georefine evaluate strip-differences``); with ``out``, the map (PNG,
    GeoTIFF), ``strip_differences.json``, the density and overlap maps, and the differences of
    every pair of strips from the same read (``strip_pairs.csv``, the matrix ``strip_pairs.png``;
    :mod:`georefine.evaluation.strip_pairs`, strips told apart by their point source id)."""
    from georefine.evaluation.clouds import evaluate_strip_differences as _evaluate
    from georefine.evaluation.strip_pairs import scan_clouds_with_pairs, write_pairs_csv, write_pairs_png
    from georefine.io.las import point_files

    files = point_files([Path(p) for p in points])
    gate = dict(cell_size_m=cell_size_m, max_roughness_m=max_roughness_m, max_slope_deg=max_slope_deg,
                max_normal_angle_deg=max_normal_angle_deg)
    with runner_for(scheduler) as runner:
        if out is None:
            return _evaluate(files, None, **gate, runner=runner, progress=progress)
        scan, pairs = scan_clouds_with_pairs(files, **gate, runner=runner, progress=progress)
    out = Path(out)
    result = _evaluate(files, out, **gate, scan=scan)
    write_pairs_csv(out / "strip_pairs.csv", pairs)
    write_pairs_png(out / "strip_pairs.png", pairs, title="strip-pair differences")
    return result


def export_trajectory(source: PathLike, out: PathLike, fmt: str, *, epsg: int | None = None,
                      gps_week: int | None = None) -> TrajectoryExport:
    """An SBET or a trajectory CSV of Georefine written as TUM (``fmt="tum"``, for evo) or
    trajectopy's ``.traj`` (``georefine export trajectory``)."""
    from georefine.workflows.products import export_trajectory as _export

    return _export(source, out, fmt, epsg=epsg, gps_week=gps_week)


@dataclass(frozen=True)
class CleanResult:
    """What :func:`clean` removed, and the bytes it held."""

    removed: tuple[Path, ...]
    bytes_freed: int

    def summary(self) -> str:
        if not self.removed:
            return "nothing to clean: no step cache"
        return f"removed {', '.join(str(p) for p in self.removed)} ({self.bytes_freed / 1e6:,.1f} MB)"


def clean(out: PathLike, *, everything: bool = False) -> CleanResult:
    """The step caches of an output folder Georefine made removed (``georefine clean``); with
    ``everything`` the whole folder. Folders Georefine did not make are refused."""
    from georefine.io.files import clean_output

    removed, size = clean_output(out, everything)
    return CleanResult(tuple(removed), int(size))


# --- The demo ----------------------------------------------------------------------------------


def run_demo(out: PathLike | None = None, *, scenario: str = "corridor", seed: int | None = None,
         overrides: Sequence[str] = (), single_pass: bool = True, boresight: bool = True, method: str = "sift",
         progress: Progress = no_progress,
         scheduler: str = DEFAULT_SCHEDULER) -> DemoResult | BlockDemoResult:
    """Simulate a scenario, run the whole method on it, evaluate it as the paper does and write
    ``out/report.html`` and ``out/metrics.json`` (``georefine demo``).

    ``scenario="corridor"`` (default out ``georefine-demo``, seed 42): paper 000's workflow on
    both passes, on a single pass (``single_pass``) and with a boresight calibration started
    0.05 deg off (``boresight``). ``scenario="block"`` (``georefine-demo-block``, seed 3): the
    jammed G/I cloud and paper 004's three co-adjustment cases, matched by ``method`` (``sift``
    or ``xfeat``).
    """
    if scenario == "block":
        if method not in ("sift", "xfeat"):
            raise InputError("unknown matching method for the demo", field="--method", expected="sift or xfeat",
                             found=method)
        return run_block_demo(Path(out or "georefine-demo-block"), seed=3 if seed is None else seed,
                              overrides=list(overrides), method=method, progress=progress, scheduler=scheduler)
    return run_corridor_demo(Path(out or "georefine-demo"), scenario=scenario, seed=42 if seed is None else seed,
                    overrides=list(overrides), single_pass=single_pass, boresight=boresight, progress=progress,
                    scheduler=scheduler)
