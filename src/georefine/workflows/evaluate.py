"""Evaluate a `georefine run` output the way paper 000 reports it (docs/ARCHITECTURE.md §5).

:func:`evaluate_run` takes the project, the run folder of the full workflow and, optionally,
the run folder of a single-pass run, and writes ``RUN/evaluation/``:

* trajectory differences of G/I, G/I/L and single-pass G/I/L against the reference -- the
  simulated truth when the project has one (``truth/trajectory.sbet``), else the full G/I/L
  (as the paper does) -- during the strips' time spans: ``trajectory.json`` and the Fig. 9 style
  plots ``attitude_differences.png``, ``position_differences.png``;
* the G/I point cloud (``RUN/gi/points``; the run itself writes the G/I/L one), and for both:
  reference planes (Table 1, when the project has ``reference`` surfaces), the strip-difference
  map (Fig. 7) and the differences of every pair of strips (``strip_pairs.csv``, the matrix
  ``strip_pairs.png``: before and after the LiDAR adjustment) in ``evaluation/gi/`` and
  ``evaluation/gil/``, all from one read of each point file;
* ``summary.json``: every figure above (:class:`~georefine.evaluation.summary.RunEvaluation`), which
  the report and the demo's ``metrics.json`` take over.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

import yaml

from georefine.config import load_project
from georefine.errors import ConfigError
from georefine.evaluation.calibration import (
    boresight_figures,
    imu_error_figures,
    plot_imu_errors,
)
from georefine.evaluation.clouds import (
    DEFAULT_CHUNK_POINTS,
    evaluate_reference_planes,
    evaluate_strip_differences,
    reference_boxes,
)
from georefine.evaluation.plots import (
    plot_attitude_differences,
    plot_overview,
    plot_position_differences,
)
from georefine.evaluation.strip_pairs import scan_clouds_with_pairs, write_pairs_csv, write_pairs_png
from georefine.evaluation.summary import (
    ANGLES,
    CloudEvaluation,
    CoverageFigures,
    EvaluationPlots,
    ReferencePlaneFigures,
    RunEvaluation,
    SolutionFigures,
    StripDifferenceFigures,
    StripPairFigures,
    TrajectoryFigures,
)
from georefine.evaluation.trajectory import TrajectoryComparison
from georefine.evaluation.trajectory_files import compare_sbet_files
from georefine.geometry.frames import OutputCRS
from georefine.io.files import write_json
from georefine.io.las import point_files
from georefine.io.reference import read_reference_surfaces
from georefine.io.run_metrics import WorkflowMetrics, read_adjustment_report
from georefine.tasks import DEFAULT_SCHEDULER, TaskRunner, runner_for
from georefine.workflows.navigation import run_georeference
from georefine.workflows.opened import ProjectLike, project_root

log = logging.getLogger(__name__)

__all__ = ["evaluate_run", "evaluate_cloud", "ANGLES", "BASELINE", "CLOUDS"]

CLOUDS = {"G/I": "gi", "G/I/L": "gil"}
"""The point clouds a run is evaluated on and their folders under ``RUN/evaluation``."""
BASELINE = "strip adjustment"
"""The label of the classical strip adjustment a run makes beside the G/I/L (``RUN/baseline/``,
:mod:`georefine.workflows.strip_baseline`), evaluated where the run has it."""
_FOLDERS = {**CLOUDS, BASELINE: "baseline"}


def _windows(metrics: WorkflowMetrics, inset_s: float = 1.0) -> dict[int, tuple[float, float]]:
    """Per strip id, the strip's time span (GPS s) shortened by ``inset_s`` at both ends."""
    return {sid: (t0 + inset_s, t1 - inset_s) for sid, (t0, t1) in metrics.strip_time_gps.items()}


def evaluate_run(
    project: ProjectLike,
    run_dir: Path,
    single_dir: Path | None = None,
    *,
    clouds: dict[str, CloudEvaluation] | None = None,
    progress: Callable[[str, float, float], None] | None = None,
    scheduler: str | TaskRunner = DEFAULT_SCHEDULER,
    boresight_run: Path | None = None,
) -> RunEvaluation:
    """Evaluate ``run_dir`` (and ``single_dir``); write ``run_dir/evaluation`` and return the summary.

    ``boresight_run``: a run that estimated the boresight (the demo's calibration run, whose
    project states a wrong one); its estimate is compared with the truth instead of ``run_dir``'s.

    ``clouds`` holds :func:`evaluate_cloud` results computed elsewhere (``georefine demo``
    evaluates the G/I cloud in a second process while the run goes on); the others are
    computed here, their per-chunk work on ``scheduler`` (a name or a running
    :class:`~georefine.tasks.TaskRunner`, :mod:`georefine.tasks`).
    """
    project, run_dir = project_root(project), Path(run_dir)
    report = progress or (lambda *a: None)
    if (project / "project.yaml").is_file() and load_project(project).multi_flight:
        raise ConfigError("the evaluation of a run of several flights is not built yet", field="flights",
                          expected="a project of one flight; for several, each flight's gil/flight_<id>/trajectory.sbet "
                          "against the truth with `georefine evaluate trajectory`, the points with `georefine evaluate "
                          "strip-differences`", found=f"{len(load_project(project).flights)} flights in {project}")
    out = run_dir / "evaluation"
    out.mkdir(parents=True, exist_ok=True)
    metrics = WorkflowMetrics.read(run_dir / "metrics.json")
    truth = project / "truth" / "trajectory.sbet"
    has_truth = truth.is_file()
    reference = truth if has_truth else run_dir / "gil" / "trajectory.sbet"
    reference_name = "truth" if has_truth else "full G/I/L"

    # Trajectory differences during the strips (per strip and over all of them).
    report("trajectory differences", 0, 1)
    baseline = run_dir / "baseline" / "trajectory.sbet"
    cases = [("G/I", run_dir / "gi" / "trajectory.sbet", metrics), ("G/I/L", run_dir / "gil" / "trajectory.sbet", metrics),
             (BASELINE, baseline, metrics)]
    if not has_truth:
        cases = cases[:1]
    if single_dir is not None:
        sm = WorkflowMetrics.read(Path(single_dir) / "metrics.json")
        label = f"{RunEvaluation.SINGLE_PASS} (strip " + ", ".join(map(str, sm.strips)) + ")"
        cases.append((label, Path(single_dir) / "gil" / "trajectory.sbet", sm))
    trajectory: dict[str, SolutionFigures] = {}
    compared: dict[str, TrajectoryComparison] = {}
    for label, sbet, m in cases:
        if not sbet.is_file():
            continue
        wins = _windows(m)
        span = (min(w[0] for w in wins.values()), max(w[1] for w in wins.values()))
        comp = compare_sbet_files(sbet, reference, time_window=span)  # one comparison, cut per strip
        # During the strips only (the turn between passes has no LiDAR data): gaps elsewhere.
        strips = comp.within(list(wins.values()))
        trajectory[label] = SolutionFigures(
            {sid: TrajectoryFigures.from_stats(comp.within([w]).stats) for sid, w in wins.items()},
            TrajectoryFigures.from_stats(strips.stats),
        )
        compared[f"{label} - {reference_name}"] = strips
    plots = None
    if compared:
        plots = EvaluationPlots(
            attitude=plot_attitude_differences(compared, out / "attitude_differences.png",
                                               "roll, pitch, yaw differences (cf. paper 000, Fig. 9)").name,
            position=plot_position_differences(compared, out / "position_differences.png",
                                               "position differences").name,
        )
    report("trajectory differences", 1, 1)
    imu_errors, imu_plot, boresight = _calibration(project, run_dir, out, boresight_run)
    overview = None
    track = next((p for p in (run_dir / "gil" / "trajectory.csv", run_dir / "gi" / "trajectory.csv") if p.is_file()), None)
    if track is not None:
        overview = plot_overview(track, metrics.strip_time_gps, out / "overview.png",
                                 sites=_sites(project / "reference" / "surfaces.csv")).name

    # Point clouds: G/I (georeferenced here) and G/I/L (written by the run).
    clouds = dict(clouds or {})
    reference_planes: dict[str, ReferencePlaneFigures] = {}
    strip_differences: dict[str, StripDifferenceFigures] = {}
    coverage: dict[str, CoverageFigures] = {}
    strip_pairs: dict[str, StripPairFigures] = {}
    own = None
    if any(label not in clouds for label in CLOUDS) and not isinstance(scheduler, TaskRunner):
        own = TaskRunner(scheduler)
    runner = own or scheduler
    try:
        for label in [*CLOUDS, *([BASELINE] if baseline.is_file() else [])]:
            result = clouds.get(label) or evaluate_cloud(project, run_dir, label, progress=report, scheduler=runner)
            if result.reference_planes is not None:
                reference_planes[label] = result.reference_planes
            strip_differences[label] = result.strip_differences
            if result.coverage is not None:
                coverage[label] = result.coverage
            if result.strip_pairs is not None:
                strip_pairs[label] = result.strip_pairs
    finally:
        if own is not None:
            own.close()
    summary = RunEvaluation(reference_name, trajectory, plots, reference_planes, strip_differences, imu_errors,
                            imu_plot, boresight, overview, coverage, strip_pairs)
    write_json(out / "summary.json", summary.to_dict())
    return summary


def _sites(ref_csv: Path) -> list[tuple[str, float, float]] | None:
    """``(surface id, x, y)`` of every reference surface's centre, the mean of its surveyed points
    (output CRS), or None without them."""
    if not ref_csv.is_file():
        return None
    surfaces = read_reference_surfaces(ref_csv)
    return [(sid, *map(float, surfaces.points_of(sid).mean(axis=0)[:2])) for sid in surfaces.surface_ids()]


def _calibration(project: Path, run_dir: Path, out: Path, boresight_run: Path | None = None):
    """The adjustments' IMU errors and boresight against the simulated truth, where there is one
    (:mod:`georefine.evaluation.calibration`): figures per solution, the bias plot, the boresight
    (of ``boresight_run`` where given, started from its configuration's)."""
    truth_npz = project / "truth" / "imu_errors.npz"
    adjustments = {}
    for label, sub in (("G/I", "gi"), ("G/I/L", "gil")):
        path = run_dir / sub / "adjustment.json"
        if path.is_file():
            adjustments[label] = read_adjustment_report(path)
    imu, plot, boresight = {}, None, None
    if truth_npz.is_file() and adjustments:
        for label, adj in adjustments.items():
            figures = imu_error_figures(adj, truth_npz)
            if figures is not None:
                imu[label] = figures
        if imu:
            plot = plot_imu_errors({k: adjustments[k] for k in imu}, truth_npz, out / "imu_errors.png").name
    scenario = project / "truth" / "scenario.yaml"
    source = Path(boresight_run) if boresight_run is not None else run_dir
    adjustment, resolved = source / "gil" / "adjustment.json", source / "config.resolved.yaml"
    if adjustment.is_file() and scenario.is_file():
        true_deg = (yaml.safe_load(scenario.read_text()).get("scenario") or {}).get("boresight_deg")
        if true_deg is not None:
            stated = (yaml.safe_load(resolved.read_text())["scanner"]["boresight_deg"] if resolved.is_file()
                      else load_project(project).scanner.boresight_deg)
            boresight = boresight_figures(read_adjustment_report(adjustment), true_deg, stated)
    return imu, plot, boresight


def evaluate_cloud(
    project: ProjectLike,
    run_dir: Path,
    label: str,
    *,
    trajectory: Path | None = None,
    strips: list[int] | None = None,
    progress: Callable[[str, float, float], None] | None = None,
    scheduler: str | TaskRunner = DEFAULT_SCHEDULER,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
) -> CloudEvaluation:
    """Reference planes, the strip-difference map and the strip-pair differences of one point cloud of a run.

    ``label`` is ``"G/I"`` (georeferenced here into ``RUN/gi/points`` with ``trajectory``,
    by default ``RUN/gi/trajectory.sbet``, unless the points there are newer than it), :data:`BASELINE`
    (the same from ``RUN/baseline/``) or ``"G/I/L"`` (``RUN/points``, written by the run); ``strips`` (default: those of ``RUN/metrics.json``, else all) selects
    the strip files. Writes ``RUN/evaluation/gi`` or ``.../gil``; the reference planes are
    evaluated only when the project has reference surfaces.

    The strip files are read once, in record ranges of ``chunk_points``, each a task on
    ``scheduler`` (a name or a running :class:`~georefine.tasks.TaskRunner`), and reduced to the
    cell sums of the strip differences and the points near the reference surfaces
    (:func:`georefine.evaluation.clouds.scan_clouds`, docs/ARCHITECTURE.md §5); the strip pairs
    take the same chunks' cell sums (:func:`georefine.evaluation.strip_pairs.scan_clouds_with_pairs`),
    so each file is read once. Memory does not grow with the number of points. The G/I
    georeferencing runs on the same scheduler.
    """
    project, run_dir = project_root(project), Path(run_dir)
    report = progress or (lambda *a: None)
    sub = _FOLDERS[label]
    if strips is None and (run_dir / "metrics.json").is_file():
        strips = list(WorkflowMetrics.read(run_dir / "metrics.json").strips)
    out = run_dir / "evaluation" / sub
    out.mkdir(parents=True, exist_ok=True)
    with runner_for(scheduler) as runner:
        if label != "G/I/L":  # georeferenced here with the solution's trajectory
            folder = run_dir / sub / "points"
            sbet = Path(trajectory or run_dir / sub / "trajectory.sbet")
            laz = list(folder.glob("*.laz"))
            if not laz or min(f.stat().st_mtime_ns for f in laz) < sbet.stat().st_mtime_ns:  # none, or older
                run_georeference(project, sbet, folder, progress=report, scheduler=runner)
        else:
            folder = run_dir / "points"
        ref_csv = project / "reference" / "surfaces.csv"
        zoom = boxes = None
        if ref_csv.is_file():  # a 250 m detail around the first reference site (cf. paper 000, Fig. 7)
            c = read_reference_surfaces(ref_csv).xyz[:4].mean(axis=0)
            zoom = (c[0] - 125.0, c[0] + 125.0, c[1] - 125.0, c[1] + 125.0)
            boxes = reference_boxes(ref_csv)
        files = [f for f in point_files([folder])
                 if strips is None or f.stem in {f"strip_{s}" for s in strips} or not f.stem.startswith("strip_")]
        # With crs.geoid_grid the run's clouds hold gravity-related heights; the reference surfaces
        # and the simulated truth are ellipsoidal (as everything inside Georefine), so the clouds
        # are read back to ellipsoidal heights with the same grid (scan_clouds) rather than the
        # references converted: the figures are those of an ellipsoidal run.
        cfg = load_project(project) if (project / "project.yaml").is_file() else None
        geoid = None if cfg is None else cfg.crs.geoid(project)
        heights = None if geoid is None else (OutputCRS(cfg.crs.output_epsg), geoid)
        scan, pairs = scan_clouds_with_pairs(files, cell_size_m=1.0, boxes=boxes, runner=runner,
                                             chunk_points=chunk_points, progress=report,
                                             label=f"point cloud evaluation {label}", heights=heights)
    planes = None
    if ref_csv.is_file():
        _, rp = evaluate_reference_planes(files, ref_csv, out, scan=scan)
        planes = ReferencePlaneFigures.from_summary(rp)
    sites = _sites(ref_csv)  # the reference surfaces, marked on the maps
    sd = evaluate_strip_differences(files, out, title=f"strip differences, {label}", zoom=zoom, scan=scan, sites=sites)
    differences = StripDifferenceFigures.from_map(
        sd, f"{sub}/strip_differences.png", None if zoom is None else f"{sub}/strip_differences_zoom.png")
    coverage = None if scan.coverage is None else CoverageFigures.from_map(
        scan.coverage, f"{sub}/coverage_density.png", f"{sub}/coverage_overlap.png")
    write_pairs_csv(out / "strip_pairs.csv", pairs)
    write_pairs_png(out / "strip_pairs.png", pairs, title=f"strip-pair differences, {label}")
    strip_pairs = StripPairFigures(pairs, f"{sub}/strip_pairs.csv", f"{sub}/strip_pairs.png")
    return CloudEvaluation(differences, planes, coverage, strip_pairs)
