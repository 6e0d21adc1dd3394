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
5. ``OUT/report.html`` and ``OUT/metrics.json``. The report opens with the block's layout and
   shows each point's error as the surveyor reads it (:mod:`georefine.evaluation.block_maps`),
   from the files the cases wrote (``point_residuals.csv``, ``tie_residuals.csv``): maps of the
   check point errors, per-point tables worst first, residual histograms. Its figures are
   ``OUT/layout.png``, ``OUT/point_errors.png`` and ``OUT/caseN/residuals.png``.
"""

from __future__ import annotations

import html
import logging
import shutil
import time as _time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml

from georefine import __version__
from georefine.demo.lanes import Lanes, QueuedProgress, demo_stamp, reusable_project, simulation_scheduler
from georefine.errors import InputError
from georefine.evaluation.block_maps import (
    BlockLayout,
    PointPanel,
    ResidualHistogram,
    ground_footprint,
    nice_ceil,
    plot_block_layout,
    plot_point_vectors,
    plot_residual_histograms,
)
from georefine.evaluation.coadjust import (
    PAPER_004_GRAZ,
    PAPER_004_LOOSDORF,
    CloudErrorSummary,
    cloud_errors,
    plot_cloud_errors,
)
from georefine.evaluation.page import CSS, image, table
from georefine.io import photos as pio
from georefine.io.files import atomic_output, make_output_folder, write_json
from georefine.lidargrammetry.bundle import TIE_INLIER_LOSS_SCALES, PointStats
from georefine.progress import Progress, no_progress
from georefine.sim.scenarios import resolve_scenario, simulate_project
from georefine.tasks import DEFAULT_SCHEDULER
from georefine.workflows.lidar import run_workflow
from georefine.workflows.lidargrammetry import load_photo_project, run_coadjust
from georefine.workflows.lidargrammetry_results import (
    CoadjustResult,
    PhotoLidargramMatches,
    PointResiduals,
    Precision,
    TieReprojection,
    TieResiduals,
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
        """Rows ``[case, points, RMSE X, Y, Z (m), RE (px), paper 004 Graz, paper 004 Loosdorf,
        verdict]``; the verdict (:func:`graz_verdict`) sets the figures against Graz's, the block
        the simulation stands for (5 cm GSD, two strips)."""
        rows = []
        for case, m in sorted(self.metrics.cases.items()):
            for label, st in (("control_points", m.control_points), ("check_points", m.check_points)):
                if st is None:
                    continue
                papers = [PAPER_004_GRAZ[case][label], PAPER_004_LOOSDORF[case][label]]
                rows.append([str(case), f"{'GCPs' if label == 'control_points' else 'ChPs'} ({st.n})",
                             *(f"{v:.3f}" for v in st.rmse_xyz_m), f"{st.reprojection_px:.2f}",
                             *("–" if q is None else " / ".join(f"{v:.3f}" for v in q[:3]) + f", {q[3]:.3f}"
                               for q in papers), graz_verdict(st, papers[0])])
        return rows


def graz_verdict(stats: PointStats, paper: tuple | None) -> str:
    """``✓`` when no figure is worse than paper 004's Graz figure (RMSE X, Y, Z within 5 mm of it,
    the reprojection error within 0.05 px: the paper's rounding and the survey's noise), else
    ``✗`` with each worse figure beside the paper's; ``–`` where the paper has none."""
    if paper is None:
        return "–"
    worse = [f"{name} {ours:.3f} > {theirs:.3f}"
             for name, ours, theirs, slack in zip(("X", "Y", "Z", "RE"), (*stats.rmse_xyz_m, stats.reprojection_px),
                                                  paper, (0.005, 0.005, 0.005, 0.05))
             if np.isfinite(ours) and ours > theirs + slack]
    return "✓" if not worse else "✗ " + ", ".join(worse)


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
    write_point_figures(out, sorted(cases))
    timings["evaluate"] = _time.perf_counter() - t
    timings["total"] = _time.perf_counter() - start
    metrics = BlockDemoMetrics("block", seed, tuple(overrides), method,
                               {c: BlockCase.of(cases[c]) for c in sorted(cases)}, clouds, timings)
    result = BlockDemoResult(out, out / "report.html", metrics)
    _write_report(result)
    write_json(out / "metrics.json", metrics.to_dict())
    return result


# ---------------------------------------------------------------------------- the surveyor's view
def _lidargram_box(png: Path) -> tuple[tuple[float, float, float, float], int] | None:
    """``((u0, v0, u1, v1), width)``: the pixel rectangle holding every pixel the lidargram shows
    (grey above 0; the darkest points show as 0 too, but not along a whole border) and the image's
    width in pixels; None without the file or with nothing shown."""
    import cv2

    image = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE) if png.is_file() else None
    if image is None:
        return None
    rows, cols = np.flatnonzero(image.any(axis=1)), np.flatnonzero(image.any(axis=0))
    if not len(rows):
        return None
    return (float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)), image.shape[1]


def block_layout(project: Path, case_dir: Path | None) -> BlockLayout:
    """The layout map's contents from the files: photo stations from the project's ``eop.csv``,
    points from its ``gcp.csv``, lidargrams from ``case_dir`` (the adjusted ``eop_lidargrams.csv``,
    each lidargram's shown pixels from its PNG in ``colmap/images``; none without ``case_dir``).

    Footprints are the image border (for a lidargram: the rectangle of its shown pixels) intersected
    with the horizontal plane at the mean height of the control and check points (no terrain
    model: at 320 m above ground, 10 m of relief moves a footprint's corner by about 3 %); without
    points, no footprint is drawn.
    """
    pp = load_photo_project(project)
    g = pp.gcps
    height = float(np.mean(g.xyz[:, 2])) if len(g) else float("nan")
    h_w = float(np.mean(pp.crs.to_w(pp.frame, g.xyz)[:, 2])) if len(g) else float("nan")

    def footprint(camera, R, p, box=None) -> np.ndarray:
        if not np.isfinite(h_w):
            return np.zeros((0, 2))
        fp = ground_footprint(camera, R, p, h_w, box)
        if not len(fp):
            return fp
        return pp.crs.from_w(pp.frame, np.column_stack([fp, np.full(len(fp), h_w)]))[:, :2]

    photo_fp = [footprint(pp.camera(i), pp.R_w_c[i], pp.p_w_c[i]) for i in range(len(pp.eop))]
    lg_names: list[str] = []
    lg_xy, lg_fp, lg_group = [], [], []
    eop_path = None if case_dir is None else case_dir / "eop_lidargrams.csv"
    if eop_path is not None and eop_path.is_file():
        eop = pio.read_eop(eop_path)
        R, p = pio.poses_in_w(eop, pp.frame, pp.crs)
        stems = {Path(x).stem: i for i, x in enumerate(pp.eop.images)}
        for k, name in enumerate(eop.images):
            stem = Path(name).stem
            photo = max(((len(st), i) for st, i in stems.items() if stem.endswith("_" + st)), default=(0, None))[1]
            if photo is None:  # not a name run_coadjust gives (LG_<strip>_<photo stem>.png)
                raise InputError("lidargram named after no photo of the project", path=eop_path, line=k + 2,
                                 field="image", expected="LG_<strip>_<photo stem>.png", found=name)
            strip = stem[3:-len(Path(pp.eop.images[photo]).stem) - 1] if stem.startswith("LG_") else "?"
            png = case_dir / "colmap" / "images" / name
            shown = _lidargram_box(png)
            cam, box = pp.camera(photo), None
            if shown is not None:  # the lidargram's camera: the photo's optics on its pixel grid
                box, width = shown
                cam = cam.scaled(width / cam.width_px)
            lg_names.append(name)
            lg_xy.append(eop.xyz[k, :2])
            lg_fp.append(footprint(cam, R[k], p[k], box))
            lg_group.append(strip)
    crs = pp.crs.crs
    return BlockLayout(f"{crs.name} (EPSG:{pp.crs.epsg})", tuple(pp.eop.images), pp.eop.xyz[:, :2].copy(),
                       photo_fp, tuple(g.ids), np.asarray(g.xyz, dtype=float).reshape(-1, 3)[:, :2],
                       np.asarray(g.is_control, dtype=bool), tuple(lg_names),
                       np.asarray(lg_xy, dtype=float).reshape(-1, 2), lg_fp, tuple(lg_group), height)


def _inlier_limit_px(case_dir: Path) -> float | None:
    """The adjustment's inlier limit (:data:`~georefine.lidargrammetry.bundle.TIE_INLIER_LOSS_SCALES`
    loss scales of the tie sigma) from ``config.resolved.yaml``."""
    path = case_dir / "config.resolved.yaml"
    if not path.is_file():
        return None
    st = ((yaml.safe_load(path.read_text()) or {}).get("processing") or {}).get("lidargrammetry") or {}
    try:
        return TIE_INLIER_LOSS_SCALES * float(st["tie_loss_scale"]) * float(st["tie_sigma_px"])
    except (KeyError, TypeError, ValueError):
        return None


def write_point_figures(out: Path, cases: list[int]) -> None:
    """``OUT/layout.png``, ``OUT/point_errors.png`` and ``OUT/caseN/residuals.png`` from the files
    the demo's cases wrote (a case without ``point_residuals.csv`` is left out of the maps)."""
    out = Path(out)
    first = next((out / f"case{c}" for c in cases if (out / f"case{c}" / "eop_lidargrams.csv").is_file()), None)
    layout = block_layout(out / "project", first)
    plot_block_layout(layout, out / "layout.png", title="block layout: stations, footprints, control and check points")
    residuals = {c: PointResiduals.read(out / f"case{c}" / "point_residuals.csv") for c in cases
                 if (out / f"case{c}" / "point_residuals.csv").is_file()}
    if residuals:
        panels = [PointPanel(f"case {c}", r.ids, r.xyz[:, :2], r.error_m, r.is_control) for c, r in residuals.items()]
        plot_point_vectors(panels, layout.crs_name, out / "point_errors.png", context=layout)
    ties = {c: TieResiduals.read(out / f"case{c}" / "tie_residuals.csv") for c in cases
            if (out / f"case{c}" / "tie_residuals.csv").is_file()}
    # One scale for every case: the histograms compare side by side; the tail beyond the 97.5th
    # percentile (mostly outliers of the robust loss) is counted in the last bin.
    norms = [t.norm_px[np.isfinite(t.norm_px)] for t in ties.values()]
    max_px = float(np.percentile(np.concatenate(norms), 97.5)) if norms and sum(map(len, norms)) else None
    checks = [r.error_m[~r.is_control] for r in residuals.values()]
    e = np.abs(np.concatenate(checks)) if checks else np.zeros((0, 3))
    e = e[np.all(np.isfinite(e), axis=1)]
    max_err = float(np.percentile(e, 90)) if len(e) else None
    for c in cases:
        if c not in residuals and c not in ties:
            continue
        t = ties.get(c)
        r = residuals.get(c)
        h = ResidualHistogram(f"case {c}", None if t is None else t.norm_px[~t.is_lidargram],
                              None if t is None else t.norm_px[t.is_lidargram],
                              np.zeros((0, 3)) if r is None else r.error_m[~r.is_control],
                              _inlier_limit_px(out / f"case{c}"))
        plot_residual_histograms(h, out / f"case{c}" / "residuals.png",
                                 max_px=None if max_px is None else nice_ceil(max_px),
                                 max_error_m=None if max_err is None else nice_ceil(max_err))


def _cm(v: float, digits: int = 1) -> str:
    return "–" if not np.isfinite(v) else f"{100 * v:.{digits}f}"


def point_table_rows(r: PointResiduals) -> list[list[str]]:
    """Rows ``[id, dX, dY, dZ, horizontal, 3-D (cm), RE (px), rays, sigma X / Y / Z (cm)]``, worst first."""
    r = r.worst_first()
    h, d3 = r.horizontal_m, r.error_3d_m
    rows = []
    for k, pid in enumerate(r.ids):
        sig = r.sigma_m[k]
        rows.append([pid, *(_cm(v) for v in r.error_m[k]), _cm(h[k]), _cm(d3[k]),
                     "–" if not np.isfinite(r.reprojection_px[k]) else f"{r.reprojection_px[k]:.2f}",
                     str(int(r.rays[k])), "–" if not np.all(np.isfinite(sig)) else " / ".join(_cm(v) for v in sig)])
    return rows


_POINT_HEADER = ["point", "dX [cm]", "dY [cm]", "dZ [cm]", "horizontal [cm]", "3-D [cm]", "RE [px]", "rays",
                 "estimated sigma X / Y / Z [cm]"]


def _point_sections(out: Path, cases: list[int]) -> list[str]:
    """The report's per-case ``<details>``: check and control point tables (worst first) and the histograms."""
    parts = []
    for c in cases:
        path = out / f"case{c}" / "point_residuals.csv"
        if not path.is_file():
            parts.append(f'<p class="note">Case {c}: no point_residuals.csv (written by an older coadjust).</p>')
            continue
        r = PointResiduals.read(path)
        chk, ctl = r.subset(~r.is_control), r.subset(r.is_control)
        worst = chk.worst_first()
        head = (f"case {c}: {len(chk)} check points" + (f", {len(ctl)} control points" if len(ctl) else "")
                + (f"; worst {html.escape(worst.ids[0])}, {_cm(worst.error_3d_m[0])} cm 3-D"
                   if len(worst) and np.isfinite(worst.error_3d_m[0]) else ""))
        body = [f"<summary>{head}</summary>",
                f'<p class="note">Also as <a href="case{c}/point_residuals.csv">case{c}/point_residuals.csv</a> '
                "(metres, every point, worst first).</p>",
                "<h4>Check points</h4>", table(_POINT_HEADER, point_table_rows(chk))]
        if len(ctl):
            body += ["<h4>Control points</h4>", table(_POINT_HEADER, point_table_rows(ctl))]
        body.append(f"<figure>{image(out / f'case{c}' / 'residuals.png', f'case {c} residuals')}"
                    "<figcaption>Left: length of each adjusted tie observation's image residual (projected minus "
                    "measured keypoint), photos and lidargrams, one scale for all cases. Right: the check points' "
                    "dX, dY, dZ.</figcaption></figure>")
        parts.append(f"<details{' open' if c == cases[0] else ''}>{''.join(body)}</details>")
    return parts


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
    cases = sorted(m.cases)
    body = [
        f"<h1>Georefine demo: lidargrammetric co-adjustment (block, seed {m.seed})</h1>",
        '<p class="note">Paper 004: photos and lidargrams (synthetic images of the LiDAR cloud whose pixels '
        "remember their points) matched and adjusted in one block. Case 1 refines the LiDAR (photos "
        "adjusted with control points, then fixed), case 2 adjusts photos and lidargrams together, case 3 "
        "orients the photos on the LiDAR without control points (here on the true cloud, standing for a "
        f"cloud refined beforehand). Matcher: {html.escape(m.method)}. Georefine {__version__}.</p>",
        "<h2>Block layout</h2>",
        f"<figure>{image(out / 'layout.png', 'block layout')}"
        "<figcaption>Left: photo projection centres (approximate orientation, ids where there is room) and "
        "footprints; right: the lidargrams (case 1, adjusted), each outlined where it shows LiDAR points; control "
        "points (triangles) and check points (circles) on both. Footprints are the image borders intersected with "
        "the plane at the mean height of the control and check points (no terrain model).</figcaption></figure>",
        "<h2>Control and check points (the paper's Tables 1-6)</h2>",
        table(["case", "points", "RMSE X [m]", "RMSE Y [m]", "RMSE Z [m]", "RE [px]",
                "paper 004, Graz (5 cm GSD): X / Y / Z [m], RE [px]",
                "paper 004, Loosdorf (8 cm GSD, one strip)", "against Graz (✗: the paper's is better)"], rows),
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
        "<h3>Point by point</h3>",
        f"<figure>{image(out / 'point_errors.png', 'check point errors')}"
        "<figcaption>Each point's error (intersected from the adjusted photos minus surveyed): horizontal as an "
        "arrow from the surveyed position, vertical as the colour, all cases on one scale. Case 3 uses no "
        "control point, so all its points are check points.</figcaption></figure>",
        '<p class="note">Per case, worst first; dX, dY, dZ along the output CRS\'s easting, northing and height, '
        "in centimetres like the standards' table above; RE: RMS of the point's image residuals; rays: photos it "
        "is measured in; estimated sigma: its posterior standard deviation in the adjustment the photos come "
        "from (case 1: the photo block's; case 3 has none, its points are not in the block).</p>",
        *_point_sections(out, cases),
        "<h2>Refined point cloud against the truth</h2>",
        '<p class="note">Points inside the photo block (shown in a lidargram or interpolated within 5 m), '
        "compared record by record with the simulation's truth.</p>",
        table(["", "points", "jammed RMS [m]", "refined RMS [m]", "ratio", "refined RMS X / Y / Z [m]"], cloud_rows),
        "".join(  # one under the other, each at its own size: side by side their labels were 8 px high
            f"<figure>{image(out / f'case{c}' / 'cloud_errors.png', f'case {c} cloud errors')}"
            f"<figcaption>Case {c}: 3-D error of each point, jammed and refined.</figcaption></figure>"
            for c in sorted(m.refined_cloud)),
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
