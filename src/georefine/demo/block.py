"""`georefine demo --scenario block`: the whole story of paper 004 from one command.

1. Simulate the ``block`` scenario into ``OUT/project`` (GNSS jammed during the LiDAR passes,
   a photo block with control and check points) -- reused when a previous demo simulated the
   same seed and overrides there.
2. ``georefine run --no-lidar`` into ``OUT/run``: the jammed G/I point cloud.
3. ``georefine coadjust`` cases 1 and 2 on that cloud into ``OUT/case1`` and ``OUT/case2`` (one
   matching for both, through the step cache ``OUT/.cache``), and case 3 on the true cloud,
   standing for a LiDAR cloud refined beforehand, into ``OUT/case3``. Case 3 runs in a second
   process while this one runs steps 2 and 3.
4. Evaluation: the paper's tables (RMSE X/Y/Z and reprojection error of control and check
   points) beside the paper's Graz figures, and the refined clouds' errors against the truth
   point by point (:mod:`georefine.evaluation.coadjust`).
5. ``OUT/report.html`` and ``OUT/metrics.json``.
"""

from __future__ import annotations

import html
import logging
import shutil
import time as _time
from dataclasses import dataclass, field, replace
from pathlib import Path

from georefine import __version__
from georefine.demo.lanes import Lanes, QueuedProgress, demo_stamp, reusable_project, simulation_scheduler
from georefine.evaluation.coadjust import (
    PAPER_004_GRAZ,
    PAPER_004_LOOSDORF,
    CloudErrorSummary,
    cloud_errors,
    plot_cloud_errors,
)
from georefine.evaluation.page import CSS, image, table
from georefine.io.files import atomic_output, make_output_folder, write_json
from georefine.lidargrammetry.bundle import PointStats
from georefine.progress import Progress, no_progress
from georefine.sim.scenarios import resolve_scenario, simulate_project
from georefine.tasks import DEFAULT_SCHEDULER
from georefine.workflows.lidar import run_workflow
from georefine.workflows.lidargrammetry import run_coadjust
from georefine.workflows.lidargrammetry_results import (
    CoadjustResult,
    PhotoLidargramMatches,
    Precision,
    TieReprojection,
)

log = logging.getLogger(__name__)

__all__ = ["BlockCase", "BlockDemoMetrics", "BlockDemoResult", "run_block_demo"]


def _stats(d: dict | None) -> PointStats | None:
    return None if d is None else PointStats.from_dict(d)


@dataclass(frozen=True)
class BlockCase:
    """What the demo keeps of one case's :class:`~georefine.workflows.lidargrammetry_results.CoadjustResult`."""

    control_points: PointStats | None
    check_points: PointStats | None
    tie_reprojection: TieReprojection
    photos: int
    lidargrams: int
    tracks: int
    photo_lidargram_matches: PhotoLidargramMatches  # counts only, no pair list
    timings_s: dict[str, float]
    precision: Precision
    photo_block_precision: Precision | None

    @classmethod
    def of(cls, r: CoadjustResult) -> BlockCase:
        return cls(r.control_points, r.check_points, r.tie_reprojection, r.photos, r.lidargrams, r.tracks,
                   r.photo_lidargram_matches.without_pairs(), dict(r.timings_s), r.precision, r.photo_block_precision)

    def to_dict(self) -> dict:
        return {"control_points": None if self.control_points is None else self.control_points.to_dict(),
                "check_points": None if self.check_points is None else self.check_points.to_dict(),
                "tie_reprojection_px": self.tie_reprojection.to_dict(), "photos": self.photos,
                "lidargrams": self.lidargrams, "tracks": self.tracks,
                "photo_lidargram_matches": self.photo_lidargram_matches.to_dict(), "timings_s": dict(self.timings_s),
                "precision": self.precision.to_dict(),
                "photo_block_precision": None if self.photo_block_precision is None
                else self.photo_block_precision.to_dict()}

    @classmethod
    def from_dict(cls, d: dict) -> BlockCase:
        pbp = d.get("photo_block_precision")
        return cls(_stats(d["control_points"]), _stats(d["check_points"]),
                   TieReprojection.from_dict(d["tie_reprojection_px"]), int(d["photos"]), int(d["lidargrams"]),
                   int(d["tracks"]), PhotoLidargramMatches.from_dict(d["photo_lidargram_matches"]),
                   {k: float("nan") if v is None else float(v) for k, v in d["timings_s"].items()},
                   Precision.from_dict(d["precision"]), None if pbp is None else Precision.from_dict(pbp))


@dataclass(frozen=True)
class BlockDemoMetrics:
    """``OUT/metrics.json`` of the block demo: the three cases, the refined clouds' errors and timings."""

    scenario: str
    seed: int
    overrides: tuple[str, ...]
    method: str
    cases: dict[int, BlockCase]
    refined_cloud: dict[int, CloudErrorSummary]
    timings_s: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"scenario": self.scenario, "seed": self.seed, "overrides": list(self.overrides),
                "method": self.method, "cases": {c: self.cases[c].to_dict() for c in sorted(self.cases)},
                "refined_cloud": {c: d.to_dict() for c, d in self.refined_cloud.items()},
                "timings_s": dict(self.timings_s)}

    @classmethod
    def from_dict(cls, d: dict) -> BlockDemoMetrics:
        """From ``to_dict`` or from the JSON file (whose case keys are strings)."""
        return cls(str(d["scenario"]), int(d["seed"]), tuple(d["overrides"]), str(d["method"]),
                   {int(c): BlockCase.from_dict(v) for c, v in d["cases"].items()},
                   {int(c): CloudErrorSummary.from_dict(v) for c, v in d["refined_cloud"].items()},
                   {k: float("nan") if v is None else float(v) for k, v in d["timings_s"].items()})


@dataclass(frozen=True)
class BlockDemoResult:
    out: Path
    report: Path
    metrics: BlockDemoMetrics

    def summary_table(self) -> list[list[str]]:
        """Rows ``[case, points, RMSE X, Y, Z (m), RE (px), paper 004 Graz, paper 004 Loosdorf]``."""
        rows = []
        for case, m in sorted(self.metrics.cases.items()):
            for label, st in (("control_points", m.control_points), ("check_points", m.check_points)):
                if st is None:
                    continue
                papers = [PAPER_004_GRAZ[case][label], PAPER_004_LOOSDORF[case][label]]
                rows.append([str(case), f"{'GCPs' if label == 'control_points' else 'ChPs'} ({st.n})",
                             *(f"{v:.3f}" for v in st.rmse_xyz_m), f"{st.reprojection_px:.2f}",
                             *("–" if q is None else " / ".join(f"{v:.3f}" for v in q[:3]) + f", {q[3]:.3f}"
                               for q in papers)])
        return rows


def _case3(project: Path, out: Path, cache: Path, method: str, progress: QueuedProgress,
           scheduler: str) -> CoadjustResult:
    """The second process: case 3 on the true cloud."""
    r = run_coadjust(project, [project / "truth"], out / "case3", 3, overrides={"matcher": method}, cache_dir=cache,
                     progress=progress, scheduler=scheduler)
    return replace(r, bundle=None)  # the metrics only come back through the queue


def run_block_demo(out: str | Path, *, seed: int = 3, overrides: list[str] | None = None, method: str = "sift",
                   progress: Progress = no_progress, scheduler: str = DEFAULT_SCHEDULER) -> BlockDemoResult:
    """Simulate, run, co-adjust (cases 1-3), evaluate and report into ``out``.

    ``scheduler``: where each lane's tasks run (scan chunks, lidargrams, keypoints and pairs;
    :mod:`georefine.tasks`).
    """
    out = Path(out)
    overrides = list(overrides or [])
    resolve_scenario("block", seed_overrides=overrides)  # a bad scenario or override leaves no folder behind
    make_output_folder(out)
    project, cache = out / "project", out / ".cache"
    timings: dict[str, float] = {}
    start = _time.perf_counter()
    cases: dict[int, CoadjustResult] = {}
    with Lanes(progress) as lanes:
        t = _time.perf_counter()
        if not reusable_project(project, "block", seed, overrides):
            if project.exists():
                shutil.rmtree(project)
            simulate_project("block", project, seed=seed, overrides=overrides, progress=lanes,
                             scheduler=simulation_scheduler(scheduler))
            write_json(project / "truth" / "demo.json", demo_stamp("block", seed, overrides))
        timings["simulate"] = _time.perf_counter() - t
        third = lanes.submit(_case3, project, out, cache, method, lanes.queued("case 3: "), scheduler)
        t = _time.perf_counter()
        run_workflow(project, out / "run", lidar=False, cache_dir=cache, progress=lanes, scheduler=scheduler)
        timings["run_gi"] = _time.perf_counter() - t
        for case in (1, 2):
            t = _time.perf_counter()
            cases[case] = run_coadjust(project, [out / "run" / "points"], out / f"case{case}", case,
                                       overrides={"matcher": method}, cache_dir=cache, progress=lanes,
                                       scheduler=scheduler)
            timings[f"case{case}"] = _time.perf_counter() - t
        t = _time.perf_counter()
        cases[3] = lanes.result(third)
        timings["wait_for_case3"] = _time.perf_counter() - t
    t = _time.perf_counter()
    clouds = {}
    for case in (1, 2):
        errors = cloud_errors(out / "run" / "points", out / f"case{case}" / "points", project / "truth")
        clouds[case] = errors.summary()
        plot_cloud_errors(errors, out / f"case{case}" / "cloud_errors.png",
                          title=f"case {case}: point errors inside the photo block")
    timings["evaluate"] = _time.perf_counter() - t
    timings["total"] = _time.perf_counter() - start
    metrics = BlockDemoMetrics("block", seed, tuple(overrides), method,
                               {c: BlockCase.of(cases[c]) for c in sorted(cases)}, clouds, timings)
    result = BlockDemoResult(out, out / "report.html", metrics)
    _write_report(result)
    write_json(out / "metrics.json", metrics.to_dict())
    return result


def _write_report(result: BlockDemoResult) -> None:
    m, out = result.metrics, result.out
    rows = result.summary_table()
    cloud_rows = [[f"case {c}", f"{d.points:,}", f"{d.rms_before_m:.3f}", f"{d.rms_after_m:.3f}",
                   f"{d.ratio:.2f}", " / ".join(f"{v:.3f}" for v in d.rms_xyz_after_m)]
                  for c, d in sorted(m.refined_cloud.items())]
    match_rows = [[f"case {c}", str(d.lidargrams), str(d.photo_lidargram_matches.n_pairs),
                   f"{d.photo_lidargram_matches.median_verified:.0f}", str(d.tracks),
                   f"{d.tie_reprojection.photos_px:.2f}", f"{d.tie_reprojection.lidargrams_px:.2f}"]
                  for c, d in sorted(m.cases.items())]
    prec_rows = []
    for c, d in sorted(m.cases.items()):
        for label, pr in (("photo block", d.photo_block_precision), ("co-adjustment", d.precision)):
            cp = None if pr is None else pr.check_points
            if cp is not None:
                prec_rows.append([f"case {c}", label, str(cp.n), " / ".join(f"{v:.3f}" for v in cp.sigma_xyz_m_rms),
                                  " / ".join(f"{v:.3f}" for v in cp.error_xyz_m_rms), f"{cp.normalised_rms:.2f}"])
    asprs_rows = []
    for c, d in sorted(m.cases.items()):
        a = None if d.check_points is None else d.check_points.accuracy
        if a is not None:
            asprs_rows.append([f"case {c}", f"{a.n_checkpoints}{'' if a.enough_checkpoints else ' (fewer than 30)'}",
                               *(f"{1e2 * v:.1f}" if v is not None else "–" for v in (
                                   a.rmse_h_m, a.rmse_v_m, a.rmse_3d_m, a.mean_v_m, a.rmse_h2_m, a.rmse_v2_m,
                                   a.nssda_horizontal_95_m, a.nssda_vertical_95_m))])
    body = [
        f"<h1>Georefine demo: lidargrammetric co-adjustment (block, seed {m.seed})</h1>",
        '<p class="note">Paper 004: photos and lidargrams (synthetic images of the LiDAR cloud whose pixels '
        "remember their points) matched and adjusted in one block. Case 1 refines the LiDAR (photos "
        "adjusted with control points, then fixed), case 2 adjusts photos and lidargrams together, case 3 "
        "orients the photos on the LiDAR without control points (here on the true cloud, standing for a "
        f"cloud refined beforehand). Matcher: {html.escape(m.method)}. Georefine {__version__}.</p>",
        "<h2>Control and check points (the paper's Tables 1-6)</h2>",
        table(["case", "points", "RMSE X [m]", "RMSE Y [m]", "RMSE Z [m]", "RE [px]",
                "paper 004, Graz (5 cm GSD): X / Y / Z [m], RE [px]",
                "paper 004, Loosdorf (8 cm GSD, one strip)"], rows),
        "<h3>Estimated precision against the actual errors</h3>",
        '<p class="note">Check points as free points of the adjustment: their posterior sigma (marginal '
        "covariance scaled by the variance factor) beside their actual error; the normalised RMS of "
        "error / sqrt(sigma² + survey sigma²) is about 1 when the sigmas are honest. Case 1 takes them from "
        "its photo-block adjustment; case 3 has none in the block.</p>",
        table(["", "adjustment", "check points", "estimated sigma X / Y / Z [m]", "RMSE X / Y / Z [m]",
                "normalised RMS"], prec_rows),
        "<h3>Accuracy to the standards (check points)</h3>",
        '<p class="note">ASPRS Positional Accuracy Standards, Edition 2 (2023): RMSE_H = sqrt(RMSE_x² + '
        "RMSE_y²) and RMSE_V with the check points' survey accuracy included (RMSE of their stated sigmas); "
        "the data meet the X-cm horizontal / vertical accuracy class for any X at or above them; Edition 2 asks "
        "for at least 30 check points. NSSDA (FGDC-STD-007.3-1998): accuracy at 95 % confidence. Centimetres.</p>",
        table(["", "check points", "RMSE_H [cm]", "RMSE_V [cm]", "RMSE_3D [cm]", "mean V [cm]", "survey H [cm]",
                "survey V [cm]", "NSSDA H 95 % [cm]", "NSSDA V 95 % [cm]"], asprs_rows),
        "<h2>Refined point cloud against the truth</h2>",
        '<p class="note">Points inside the photo block (shown in a lidargram or interpolated within 5 m), '
        "compared record by record with the simulation's truth.</p>",
        table(["", "points", "jammed RMS [m]", "refined RMS [m]", "ratio", "refined RMS X / Y / Z [m]"], cloud_rows),
        '<div class="maps">' + "".join(
            f"<figure>{image(out / f'case{c}' / 'cloud_errors.png', f'case {c} point errors')}"
            f"<figcaption>Case {c}: 3-D error of each point, jammed and refined.</figcaption></figure>"
            for c in sorted(m.refined_cloud)) + "</div>",
        "<h2>Matching</h2>",
        table(["", "lidargrams", "photo-lidargram pairs", "median verified matches", "tie points",
                "tie RE photos [px]", "tie RE lidargrams [px]"], match_rows),
        f"<figure>{image(out / 'case1' / 'matches_lidargram_photo.png', 'matches')}"
        "<figcaption>Verified matches between a lidargram (left) and a photo (cf. the paper's Fig. 6).</figcaption>"
        "</figure>",
        "<h2>Timings</h2>",
        table(["stage", "s"], [[k, f"{v:.0f}"] for k, v in m.timings_s.items()]),
    ]
    doc = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>Georefine demo: block</title>"
           f"<style>{CSS}</style></head><body>{''.join(body)}</body></html>")
    with atomic_output(result.report) as fh:
        fh.write(doc)
