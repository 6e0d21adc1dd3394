"""One adjustment of GNSS, IMU, LiDAR and photos (docs/ARCHITECTURE.md §4.10).

Paper 004 corrects a LiDAR cloud by moving each lidargram rigidly; the error of a jammed
trajectory changes within the seconds a lidargram's footprint takes to scan, so a rigid move
cannot follow it. Here the lidargram ties observe the trajectory itself: a lidargram keypoint
names (through its ULPI) the LiDAR return it shows, whose position is a function of the
trajectory at the return's time, the lever arm and the boresight
(:class:`~georefine.adjustment.observations.lidar_point.LidarPointObservation`); the photos
observe the same tie point by reprojection. One Levenberg-Marquardt problem holds the spline
trajectory, the IMU errors, GNSS, the IMU readings, the plane observations where the LiDAR has
planes (``planes``), the photo orientations, the tie, control and check points (and the
boresight and LiDAR time offset where ``processing.lidar`` estimates them).

:func:`run_hybrid`:

1. steps 1-2 of paper 000 (filter, G/I adjustment), and with ``planes`` steps 3-5 (the G/I/L
   outer iterations), into ``OUT/gi`` and ``OUT/gil`` as ``georefine run`` writes them, cached
   in ``OUT/.cache``;
2. the preliminary cloud georeferenced with that trajectory (``OUT/preliminary/points``, every
   record in scan order, as :func:`~georefine.workflows.returns.returns_of_points` needs);
3. lidargrams rendered from it at the photos' poses, matched with the photos
   (:func:`~georefine.workflows.lidargrammetry.match_block`, cached), the tracks' lidargram
   keypoints turned into the LiDAR returns they show;
4. the hybrid adjustment, as co-adjustment case 1 (the default: the photo block adjusted on
   its own with its control points, then held fixed) or case 2 (photos, trajectory and control
   together); case 3 of paper 004 (photos refined with the LiDAR as control, no control point)
   refines no cloud and is not offered. Case 1 is the default because on the jammed ``block``
   it was as good or better in both the cloud and the check points: case 2 lets what is left
   of the LiDAR's error pull on the photos (BENCHMARKS.md, "The hybrid adjustment");
5. every point re-georeferenced with the adjusted trajectory (``OUT/points``, same files and
   record order as the scans): no re-intersection and no interpolation between lidargrams;
6. ``OUT/hybrid`` (trajectory products, ``adjustment.json``), ``OUT/eop_photos.csv``,
   ``OUT/metrics.json`` (:class:`HybridResult`) and ``config.resolved.yaml``.

Weights of a return observing a tie point: ``processing.planes.range_sigma_m`` and
``return_sigma_range_m`` along the beam (the return is on the surface, the keypoint's surface
point beside it differs in height where the surface slopes), ``return_sigma_across_px``
lidargram pixels across it (the keypoint's localisation in the lidargram and the pixel's
footprint); the tie loss (``tie_loss``, ``tie_loss_scale``) against wrong matches. With
``return_keypoint_offset`` a return observes the keypoint's surface point beside it
(:func:`hybrid_ties` says when that helps).
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from georefine.adjustment.gnss_imu import (
    GnssImuProblem,
    GnssImuResult,
    build_gnss_imu_problem,
    solve_gnss_imu,
    start_imu_errors,
    trajectory_sigma,
    trajectory_solver_options,
)
from georefine.adjustment.linalg import NotPositiveDefiniteError
from georefine.adjustment.observations.lidar_point import LidarPointObservation
from georefine.adjustment.observations.prior import EuclideanPrior, RotationPrior
from georefine.adjustment.observations.reprojection import ReprojectionObservation
from georefine.adjustment.problem import Problem
from georefine.adjustment.robust import make_loss
from georefine.adjustment.solver import SolverOptions
from georefine.adjustment.statistics import SolveResult
from georefine.adjustment.upsampling import on_knots, without_high_rate
from georefine.config import boresight_matrix, write_yaml
from georefine.errors import ConfigError, InputError
from georefine.geometry.rotation import rph_from_R_n_b, wrap_angle
from georefine.io import photos as pio
from georefine.io.files import write_json
from georefine.io.run_metrics import write_adjustment_report
from georefine.lidargrammetry.bundle import (
    ControlData,
    PointStats,
    check_point_consistency,
    control_point_stats,
    stations_per_point,
)
from georefine.progress import Progress, no_progress
from georefine.tasks import DEFAULT_SCHEDULER, TaskRunner
from georefine.workflows.cache import StepCache
from georefine.workflows.gil import LidarAdjustment, build_gil_problem
from georefine.workflows.lidar import (
    features_and_objects,
    lidar_stages,
    stage_gi_products,
    stage_points,
    stage_read_inputs,
    untimed,
)
from georefine.workflows.lidargrammetry import (
    block_images,
    block_matches,
    control_data,
    open_block,
    tie_observations,
)
from georefine.workflows.navigation import NavigationData, write_trajectory_products
from georefine.workflows.opened import Project, ProjectLike, Workspace, as_project, open_workspace
from georefine.workflows.photo_block import read_cloud
from georefine.workflows.returns import LidarReturns, returns_of_points
from georefine.workflows.run_parts import adjustment_report, stage_gnss_imu
from georefine.workflows.time_offset import OFFSET_BLOCK, TimeOffsetStart

log = logging.getLogger(__name__)

__all__ = ["HYBRID_CASES", "HybridTies", "HybridResult", "hybrid_ties", "photo_lidargram_matches", "run_hybrid"]

HYBRID_CASES = {
    1: "photo block adjusted with its control points, then fixed; trajectory adjusted to it",
    2: "photos, trajectory and control points adjusted together",
}

IMAGE_POOL = ("ties", "lidar_ties", "point_measurements")
"""The groups of the photogrammetric observations: one variance component in the posterior,
beside the planes' and the navigation sensors' (:data:`~georefine.adjustment.gnss_imu.POSTERIOR_POOLS`)."""


@dataclass(frozen=True)
class HybridTies:
    """The block's ties in the hybrid form.

    ``photo_image``, ``photo_point``, ``photo_uv``: photo keypoints observing tie points (index
    into ``xyz0``); ``lidar_point``: the tie point each LiDAR return observes, ``returns`` those
    returns, ``beam_w`` their unit beam in ``w``, ``sigma_across_m`` their sigma across it and
    ``offset_w`` the keypoint's surface point beside the return (zero unless asked for;
    ``LidarPointObservation``);
    ``xyz0`` the tie points' starting coordinates (the returns' preliminary positions, else the
    photos' intersection).
    """

    photo_image: np.ndarray
    photo_point: np.ndarray
    photo_uv: np.ndarray
    lidar_point: np.ndarray
    returns: LidarReturns
    beam_w: np.ndarray
    sigma_across_m: np.ndarray
    offset_w: np.ndarray
    xyz0: np.ndarray

    @property
    def n_points(self) -> int:
        return len(self.xyz0)


def hybrid_ties(blk, matches, keep: np.ndarray, xyz0: np.ndarray, point_files: list[Path], scan_files: list[Path],
                nav: NavigationData, start: GnssImuResult, R_b_s: np.ndarray, across_px: float,
                keypoint_offset: bool = False) -> HybridTies:
    """The tracks' kept observations (``keep``,
    :func:`~georefine.workflows.lidargrammetry.tie_observations`) as photo keypoints and LiDAR returns.

    A lidargram keypoint becomes the return its pixel shows (one per track and return: the
    lidargrams of one strip rendered at neighbouring photos often show the same return); its
    sigma across the beam is ``across_px`` times the pixel's footprint (depth over focal length).
    With ``keypoint_offset`` the observed point is offset by the keypoint's distance from the
    return's exact projection, in the image plane at the return's depth (the lidargrams' mean
    where several show the return). That helps where a pixel shows a return up to half a point
    spacing away (the tests' 50 kHz block: 0.130 -> 0.095 m inside the photos) and hurts on a
    dense cloud (the default block, seed 5: 0.019 -> 0.034 m): the z-buffer lets the nearer
    surface's splats cover a pixel, so an edge in a lidargram lies up to a splat radius outside
    the returns that make it, and the keypoint with it.
    A tie point is kept when its observations determine it with redundancy: two photo
    keypoints, two returns, or one of each (``2 n_photo + 3 n_return >= 5``).
    """
    tr = matches.tracks
    n = blk.n_photos
    obs = np.flatnonzero(keep)
    is_lg = tr.image[obs] >= n
    ph, lg = obs[~is_lg], obs[is_lg]
    ulpi = np.full(lg.size, -1, np.int64)
    foot = np.full(lg.size, np.nan)
    offset = np.zeros((lg.size, 3))
    for k, o in enumerate(lg):
        g = blk.lgs[tr.image[o] - n][0]
        ulpi[k] = g.ulpi_at(tr.uv[o][None])[0]
        if ulpi[k] < 0:
            continue
        c, r = np.floor(tr.uv[o]).astype(int)
        z = float(g.depth[r, c])  # the shown return's depth
        foot[k] = z / g.camera.fx_px
        # The keypoint's surface point beside the return: the keypoint's offset from the
        # return's exact projection, in the image plane at the return's depth.
        du, dv = tr.uv[o] - g.point_uv[np.searchsorted(g.point_index, ulpi[k])]
        offset[k] = g.R_w_c @ np.array([du * z / g.camera.fx_px, dv * z / g.camera.fy_px, 0.0])
    if not keypoint_offset:
        offset[:] = 0.0
    ok = (ulpi >= 0) & np.isfinite(foot)
    keys = np.column_stack([tr.track[lg[ok]], ulpi[ok]])
    pairs, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    foot = foot[ok][first]
    # One observation per track and return; the lidargrams that show it give their offsets' mean.
    inverse = inverse.reshape(-1)
    offset = np.stack([np.bincount(inverse, offset[ok][:, j], minlength=len(pairs)) for j in range(3)], axis=1)
    offset /= np.maximum(np.bincount(inverse, minlength=len(pairs)), 1)[:, None]
    n_ph = np.bincount(tr.track[ph], minlength=tr.n_tracks)
    n_ret = np.bincount(pairs[:, 0], minlength=tr.n_tracks) if len(pairs) else np.zeros(tr.n_tracks, np.int64)
    used = np.isfinite(xyz0[:, 0]) & (2 * n_ph + 3 * n_ret >= 5)
    remap = np.full(tr.n_tracks, -1, np.int64)
    remap[used] = np.arange(used.sum())
    ph = ph[used[tr.track[ph]]]
    pairs_used = used[pairs[:, 0]] if len(pairs) else np.zeros(0, bool)
    pairs, foot, offset = pairs[pairs_used], foot[pairs_used], offset[pairs_used]
    if len(pairs) == 0:
        raise InputError("no lidargram keypoint of a tie point shows a LiDAR return", field="processing.lidargrammetry",
                         expected="photo-lidargram matches (see `georefine match`)")
    returns = returns_of_points(point_files, scan_files, pairs[:, 1])
    t = returns.time_gps - nav.t0_gps
    _, R_w_b = start.spline.pose(t)
    beam = np.einsum("nij,nj->ni", R_w_b, returns.x_s @ R_b_s.T)
    beam /= np.linalg.norm(beam, axis=1, keepdims=True)
    return HybridTies(tr.image[ph], remap[tr.track[ph]], tr.uv[ph], remap[pairs[:, 0]], returns, beam,
                      across_px * foot, offset, xyz0[used])


@dataclass(frozen=True)
class HybridResult:
    """What :func:`run_hybrid` computed and wrote (``metrics.json``)."""

    case: int
    planes: bool
    photos: int
    lidargrams: int
    tie_points: int
    photo_observations: int
    lidar_returns: int
    control_points: PointStats | None
    check_points: PointStats | None
    tie_rms: dict[str, float]
    adjustment: SolveResult
    precision: dict
    photo_block_adjustment: SolveResult | None  # case 1's first step, the photo block alone
    trajectory: dict
    matches: dict = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    gi: GnssImuResult | None = None
    result: GnssImuResult | None = None

    def to_dict(self) -> dict:
        return {
            "case": self.case, "description": HYBRID_CASES[self.case], "planes": self.planes,
            "photos": self.photos, "lidargrams": self.lidargrams, "tie_points": self.tie_points,
            "photo_observations": self.photo_observations, "lidar_returns": self.lidar_returns,
            "control_points": None if self.control_points is None else self.control_points.to_dict(),
            "check_points": None if self.check_points is None else self.check_points.to_dict(),
            "tie_rms": self.tie_rms, "adjustment": self.adjustment.to_dict(), "precision": self.precision,
            "photo_block_adjustment": None if self.photo_block_adjustment is None
            else self.photo_block_adjustment.to_dict(), "trajectory": self.trajectory,
            "photo_lidargram_matches": self.matches, "timings_s": self.timings_s,
        }

    def summary(self) -> str:
        lines = [f"hybrid adjustment, case {self.case} ({HYBRID_CASES[self.case]})"
                 + (", with LiDAR planes" if self.planes else ""),
                 f"  {self.photos} photos, {self.lidargrams} lidargrams: {self.tie_points:,} tie points, "
                 f"{self.photo_observations:,} photo keypoints, {self.lidar_returns:,} LiDAR returns"]
        for label, st in (("control", self.control_points), ("check", self.check_points)):
            if st is not None:
                x, y, z = st.rmse_xyz_m
                lines.append(f"  {label} points ({st.n}): RMSE X/Y/Z {x:.3f} / {y:.3f} / {z:.3f} m, "
                             f"RE {st.reprojection_px:.2f} px")
        m = self.matches
        if m:
            lines.append(f"  photo-lidargram pairs: {m['pairs']}, median {m['median']:.0f} verified matches; "
                         f"across stations {m['cross_station_pairs']}, median {m['cross_station_median']:.0f}")
        lines.append(f"  ties: photos {self.tie_rms['photos_px']:.2f} px, LiDAR returns "
                     f"{self.tie_rms['returns_m'] * 1e3:.0f} mm RMS")
        return "\n".join(lines)


def photo_lidargram_matches(blk, matches) -> dict:
    """Verified matches per photo-lidargram pair: median, pairs, and the same across stations
    (a lidargram rendered at another photo's pose: the pairs that tie the block together)."""
    lg = np.asarray(blk.is_lidargram, dtype=bool)
    same, cross = [], []
    for m in matches.pairs:
        if lg[m.a] == lg[m.b]:
            continue
        (same if blk.station[m.a] == blk.station[m.b] else cross).append(len(m))

    def med(v):
        return float(np.median(v)) if v else float("nan")

    return {"pairs": len(same) + len(cross), "median": med(same + cross), "cross_station_pairs": len(cross),
            "cross_station_median": med(cross), "same_station_median": med(same)}


def _photo_priors(pp, st) -> tuple[np.ndarray, np.ndarray]:
    n = len(pp.eop)
    sp = pp.eop.sigma_xyz if pp.eop.sigma_xyz is not None else np.full((n, 3), st.photo_sigma_position_m)
    so = pp.eop.sigma_opk_deg if pp.eop.sigma_opk_deg is not None else np.full((n, 3), st.photo_sigma_rotation_deg)
    return np.asarray(sp, dtype=float), np.radians(np.asarray(so, dtype=float))


def _add_photos(P: Problem, pp, st, ties: HybridTies, control: ControlData, R: np.ndarray, p: np.ndarray, *,
                fixed: bool, use_control: bool, photo_points_only: bool = False) -> np.ndarray:
    """The photo blocks, the tie and control points and their photo observations; returns the
    tie points' rows in ``points`` (-1 for those left out)."""
    cams = tuple(pp.camera(i) for i in range(len(pp.eop)))
    img, pt, uv = ties.photo_image, ties.photo_point, ties.photo_uv
    keep = np.ones(ties.n_points, bool)
    if photo_points_only:  # the photo block alone: tie points of two photos or more
        keep = stations_per_point(pt, img, ties.n_points) >= 2
    rows = np.full(ties.n_points, -1, np.int64)
    rows[keep] = np.arange(keep.sum())
    sel = keep[pt]
    n_tie = int(keep.sum())
    P.add_block("image_rotation", R.copy(), manifold="so3", constant=fixed)
    P.add_block("image_position", p.copy(), constant=fixed)
    pts0 = [ties.xyz0[keep]] + ([control.xyz_w] if use_control else [])
    P.add_block("points", np.concatenate(pts0))
    loss = make_loss(st.tie_loss, st.tie_loss_scale)
    P.add_group(ReprojectionObservation("ties", cams, img[sel], rows[pt[sel]], uv[sel], st.tie_sigma_px, loss=loss))
    if not fixed:
        sp, so = _photo_priors(pp, st)
        el = np.arange(len(pp.eop))
        P.add_group(EuclideanPrior("photo_position_prior", "image_position", el, pp.p_w_c, sp))
        P.add_group(RotationPrior("photo_rotation_prior", "image_rotation", el, pp.R_w_c, so))
    if use_control and len(control.ids):
        P.add_group(ReprojectionObservation("point_measurements", cams, control.image, n_tie + control.point,
                                            control.uv, st.measurement_sigma_px))
        ctl = np.flatnonzero(control.is_control)
        P.add_group(EuclideanPrior("control_coordinates", "points", n_tie + ctl, control.xyz_w[ctl],
                                   control.sigma_m[ctl]))
    return rows


def _check_precision(P: Problem, n_tie: int, control: ControlData, scale_by_vf: bool) -> dict:
    """The check points' posterior sigma against their actual errors (``normalised_rms`` about 1
    when the sigmas are honest); empty when the block holds none."""
    chk = np.flatnonzero(~control.is_control)
    if chk.size == 0:
        return {}
    try:
        cov = P.covariance("points", n_tie + chk, scale_by_variance_factor=scale_by_vf)
    except (NotPositiveDefiniteError, ValueError) as exc:
        log.warning("no posterior precision of the check points: %s", exc)
        return {}
    return check_point_consistency(P.values("points")[n_tie + chk], np.sqrt(np.einsum("kii->ki", cov)),
                                   control.xyz_w[chk], control.sigma_m[chk])


def _photo_block(pp, st, ties: HybridTies, control: ControlData) -> tuple[np.ndarray, np.ndarray, SolveResult, dict]:
    """Case 1's first step: the photo block alone with its control points: ``(R, p, solve, precision)``."""
    P = Problem()
    rows = _add_photos(P, pp, st, ties, control, pp.R_w_c, pp.p_w_c, fixed=False, use_control=True,
                       photo_points_only=True)
    result = P.solve(SolverOptions(max_iterations=50, function_tolerance=1e-8))
    return (P.values("image_rotation"), P.values("image_position"), result,
            _check_precision(P, int((rows >= 0).sum()), control, True))


@dataclass(frozen=True)
class _Built:
    """The hybrid problem: the trajectory's (G/I or G/I/L) with the photo part."""

    built: GnssImuProblem
    rows: np.ndarray
    boresight: str | None
    time_offset_start: TimeOffsetStart | None
    lidar_group: LidarPointObservation


def _build(nav: NavigationData, start: GnssImuResult, gil: LidarAdjustment | None, planes, pp, st, ties: HybridTies,
           control: ControlData, R, p, case: int) -> _Built:
    cfg = nav.config
    tcfg = cfg.processing.trajectory
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)
    boresight, offset_block, offset_start = None, None, None
    if planes is not None:  # the G/I/L problem started at the last outer iteration, its features at its offset
        features, objects = planes
        offset_start = TimeOffsetStart(gil.time_offset_s, gil.time_offset_start.prior_s
                                       if gil.time_offset_start is not None else gil.time_offset_s)
        g = build_gil_problem(nav, start, features, objects, time_offset=offset_start)
        built, boresight = g.built, g.boresight
        offset_block = OFFSET_BLOCK if g.estimates_offset else None
    else:
        start = on_knots(nav.gnss, start, tcfg.knot_interval_s)  # the G/I's, on the G/I/L's knots (as build_gil_problem)
        spline = start.spline
        data = without_high_rate(nav.gnss, start)
        built = start_imu_errors(build_gnss_imu_problem(data, cfg.imu.errors, tcfg, spline), start.imu_errors,
                                 start.gnss_error)
    P = built.problem
    rows = _add_photos(P, pp, st, ties, control, R, p, fixed=case == 1, use_control=case == 2)
    planes_cfg = cfg.processing.planes
    group = LidarPointObservation(
        built.grid, ties.returns.time_gps - nav.t0_gps, ties.returns.x_s, rows[ties.lidar_point], ties.beam_w,
        np.hypot(planes_cfg.range_sigma_m, st.return_sigma_range_m), ties.sigma_across_m,
        np.asarray(cfg.scanner.lever_arm_m, dtype=float), R_b_s, offset_w=ties.offset_w, boresight=boresight,
        time_offset=offset_block,
        blocks=built.blocks, loss=make_loss(st.tie_loss, st.tie_loss_scale), name="lidar_ties")
    P.add_group(group)
    return _Built(built, rows, boresight, offset_start, group)


def _solve(nav: NavigationData, hb: _Built, progress: Progress) -> GnssImuResult:
    cfg = nav.config
    tcfg, lcfg = cfg.processing.trajectory, cfg.processing.lidar

    def report(it) -> None:
        progress("hybrid adjustment", getattr(it, "iteration", 0), tcfg.max_iterations)

    # The G/I's cost-change test, not the G/I/L's 1e-3: the G/I/L's outer iterations start each
    # from the last, this adjustment is the last. Under the Huber loss on the returns the small
    # block's hybrid had stopped after 5 steps at 0.2 % of the cost above its solution, its cloud
    # 0.095 m inside the photos against 0.093 m at the solution (11 steps).
    options = trajectory_solver_options(tcfg, initial_lambda=lcfg.initial_lambda)
    result = solve_gnss_imu(hb.built, options, progress=report, covariance=False)
    progress("hybrid adjustment", 1, 1)  # it reports iterations of its limit; it ended here
    return result


def _posterior(nav: NavigationData, hb: _Built, result: GnssImuResult, n_tie: int, control: ControlData,
               case: int) -> tuple[GnssImuResult, dict]:
    """Trajectory sigma and, in case 2, the check points' (variance components per sensor)."""
    P, cfg = hb.built.problem, nav.config.processing.trajectory
    pools = (("planes",), IMAGE_POOL)
    comps = P.use_variance_components(pools) if result.solve.redundancy > 0 else ()
    solve = replace(result.solve, variance_components=comps)
    tk, s_rph, s_p, s_v = trajectory_sigma(P, hb.built.blocks, hb.built.grid, cfg, nav.frame, result.spline,
                                           scale=1.0)
    out = replace(result, solve=solve, sigma_time=tk, sigma_rph_rad=s_rph, sigma_position_m=s_p,
                  sigma_velocity_m_s=s_v)
    precision = {"check_points": _check_precision(P, n_tie, control, False)} if case == 2 else {}
    return out, precision


def _lidar_sigma(P: Problem, hb: _Built) -> tuple[np.ndarray | None, float | None]:
    """Posterior 1-sigma of the boresight (mdeg, roll/pitch/yaw) and of the LiDAR time offset (s)
    where the hybrid problem estimates them (else None), after :func:`_posterior`: a few columns of
    the inverse whose factor the trajectory's sigma made, scaled as those are (per variance component)."""
    bs = offset = None
    try:
        if hb.boresight is not None:
            cov = P.covariance(hb.boresight, scale_by_variance_factor=False)[0]
            bs = np.degrees(np.sqrt(np.clip(np.diag(cov), 0.0, None))) * 1e3
        if hb.lidar_group.time_offset is not None:
            offset = float(np.sqrt(max(P.covariance(OFFSET_BLOCK, scale_by_variance_factor=False)[0, 0, 0], 0.0)))
    except NotPositiveDefiniteError as exc:
        log.warning("no posterior sigma of the boresight and time offset: %s", exc)
    return bs, offset


def _tie_rms(P: Problem, hb: _Built) -> dict[str, float]:
    """RMS of the photo keypoints' residuals (px) and of the returns' distance to their tie point (m)."""
    values = {name: P.values(name) for name in P.blocks}
    ties = next(g for g in P.groups if g.name == "ties")
    uv, _ = ties.predict(values)
    d_ph = np.linalg.norm(uv - ties.uv, axis=1)
    x = hb.lidar_group.georeference(values) - values["points"][hb.lidar_group.point_index]
    d_ret = np.linalg.norm(x, axis=1)

    def rms(v):
        return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")

    return {"photos_px": rms(d_ph), "returns_m": rms(d_ret), "photos_px_median": float(np.median(d_ph)),
            "returns_m_median": float(np.median(d_ret))}


MISFIT_FACTOR = 4.0
"""A group of the hybrid problem's photogrammetric observations fitting worse than this variance
factor (the robust losses' sigma0^2) is reported: wrong matches or weights that do not describe them."""


def _warn_misfit(solve) -> None:
    """Warnings, with the figures, where the adjustment says the model does not fit."""
    if solve.termination == "max_iterations":
        log.warning("the hybrid adjustment stopped at its iteration limit (%d) before converging", solve.iterations)
    for g in solve.groups:
        if g.name in IMAGE_POOL and np.isfinite(g.variance_factor) and g.variance_factor > MISFIT_FACTOR:
            log.warning("%s fit at a variance factor of %.1f (%d residuals): the matches or their sigmas "
                        "(processing.lidargrammetry tie_sigma_px, return_sigma_*) do not describe the data",
                        g.name, g.variance_factor, g.n_residuals)


def run_hybrid(project: ProjectLike, out: str | Path, *, case: int = 1, planes: bool = True,
               overrides: Mapping[str, Any] | None = None, matcher=None, resume: bool = True,
               progress: Progress = no_progress, scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> HybridResult:
    """Steps 1-6 of the module docstring on a project with GNSS, IMU, scans and photos (an opened
    :class:`~georefine.workflows.opened.Project` or its folder): the stages of ``georefine run``
    and of the co-adjustment on one opened project, in one workspace (output folder, step cache,
    task runner), timed by its step runner.

    ``case``: 1 (default) or 2 (:data:`HYBRID_CASES`); ``planes``: start from the G/I/L adjustment and keep
    its plane observations in the hybrid one; off, the G/I adjustment without planes (a scanner
    too sparse for planar features: ``georefine run`` stops there with "no planar features");
    ``overrides``: fields of ``processing.lidargrammetry``; ``matcher``: a matcher object
    instead of the one the settings name; ``resume``: reuse ``OUT/.cache``.

    Raises
    ------
    InputError
        An unknown ``case``; bad navigation, scan or photo files; no tie point shown by a return.
    ConfigError
        A bad setting, before anything is written.
    """
    if case not in HYBRID_CASES:
        raise InputError("unknown case of the hybrid adjustment", field="case", expected="1 or 2 (case 3 refines "
                         "the photos with the LiDAR as control and no cloud: `georefine coadjust --case 3`)",
                         found=str(case))
    project = as_project(project)
    for key, what in (("estimate_range_calibration", "range calibration"), ("estimate_channel_angles", "channel angles"),
                      ("estimate_encoder_error", "encoder error")):
        if getattr(project.config.processing.lidar, key):
            raise ConfigError(f"the hybrid adjustment does not take the scanner's {what} yet: its LiDAR points and "
                              "final cloud would be read uncorrected", path=project.root / "project.yaml",
                              field=f"processing.lidar.{key}", expected="false", found="true")
    with open_workspace(project, out, resume=resume, scheduler=scheduler) as ws:
        return _run(ws, project, case, planes, overrides, matcher, progress)


def _run(ws: Workspace, project: Project, case: int, planes: bool, overrides, matcher,
         progress: Progress) -> HybridResult:
    steps, runner = ws.steps, ws.runner
    # The navigation read once (it defines w, where the hybrid problem lives); then the settings,
    # matcher and photos checked, the photo poses built in w, before anything is written.
    nav = project.navigation
    opened = open_block(project, ws.out, overrides, matcher, frame=nav.frame)
    inputs = stage_read_inputs(steps, project, ws.out, None, runner)
    pp, st = opened.pp, opened.settings
    gi, key = stage_gnss_imu(steps, nav, progress)
    stage_gi_products(inputs, gi)
    start, gil, plane_data = gi, None, None
    if planes:
        gil, key, _ = lidar_stages(steps, inputs, gi, key, progress)
        start = gil.result
        strips = [s.shifted(gil.time_offset_s) for s in inputs.strips]
        with steps.timed("plane_observations"):
            features, objects, _, _ = features_and_objects(nav, start, strips, 0, untimed, progress, runner,
                                                           scratch=inputs.out)
        plane_data = (features, objects)
    # The preliminary cloud: every record of every scan, in order (returns_of_points relies on it).
    with steps.timed("preliminary_georeferencing"):
        prelim = replace(inputs, out=inputs.out / "preliminary")
        written = stage_points(steps, prelim, start, gil, key, progress)
        point_files = [prelim.out / "points" / w.file for w in written]
    with steps.timed("lidargrams"):
        cloud = read_cloud(point_files, pp, runner=runner, progress=progress)
        blk = block_images(pp, cloud, st, progress, runner)
    with steps.timed("matching"):
        matches = block_matches(opened, cloud, blk, inputs.out / ".cache", progress, runner)
    keep, xyz0, _ = tie_observations(blk.lgs, blk.R0, blk.p0, blk.cameras, blk.station, matches, cloud, blk.n_photos,
                          st.max_initial_reprojection_px)
    cfg = nav.config
    R_b_s = boresight_matrix(tuple(gil.boresight_deg) if gil is not None and gil.boresight_deg is not None
                             else cfg.scanner.boresight_deg)
    ties = hybrid_ties(blk, matches, keep, xyz0, point_files, [s.path for s in inputs.strips], nav, start, R_b_s,
                       st.return_sigma_across_px, st.return_keypoint_offset)
    control = control_data(pp)
    with steps.timed("hybrid_adjustment"):
        R, p, pre, pre_precision = pp.R_w_c, pp.p_w_c, None, {}
        if case == 1:
            R, p, pre, pre_precision = _photo_block(pp, st, ties, control)
        hb = _build(nav, start, gil, plane_data, pp, st, ties, control, R, p, case)
        result = _solve(nav, hb, progress)
        P = hb.built.problem
        R, p = P.values("image_rotation"), P.values("image_position")
        n_tie = int((hb.rows >= 0).sum())
        tie_rms = _tie_rms(P, hb)
        _warn_misfit(result.solve)
    with steps.timed("covariance"):
        result, precision = _posterior(nav, hb, result, n_tie, control, case)
        if case == 1:
            precision = {"check_points": pre_precision}
        bs_sigma, offset_sigma = _lidar_sigma(P, hb)
    bs_deg, offset = None, cfg.scanner.time_offset_s if gil is None else gil.time_offset_s
    if hb.boresight is not None:
        bs_deg = np.degrees(rph_from_R_n_b(P.values(hb.boresight)[0]))
        bs_deg[2] = wrap_angle(bs_deg[2], 360.0, closed="lower")
    estimated = hb.lidar_group.time_offset is not None
    if estimated:
        offset = hb.time_offset_start.features_s + float(P.values(OFFSET_BLOCK)[0, 0])
    final = LidarAdjustment(result, 0, 0, bs_deg, bs_sigma, time_offset_s=offset,
                            time_offset_start=hb.time_offset_start, time_offset_sigma_s=offset_sigma,
                            time_offset_gnss_sigma_s=gil.time_offset_gnss_sigma_s if estimated else None,
                            time_offset_held=None if gil is None else gil.time_offset_held)
    # Every point with the adjusted trajectory.
    with steps.timed("final_georeferencing"):
        digest = hashlib.sha256(b"".join(np.ascontiguousarray(a).tobytes() for a in (
            result.spline.p_w_b, result.spline.R_w_b, R_b_s, np.atleast_1d(bs_deg if bs_deg is not None else 0.0),
            np.atleast_1d(offset)))).hexdigest()
        hkey = StepCache.key("hybrid", key, digest)
        stage_points(steps, inputs, result, final, hkey, progress)
    (inputs.out / "hybrid").mkdir(exist_ok=True)
    write_trajectory_products(inputs.out / "hybrid", nav, result, inputs.crs)
    write_adjustment_report(inputs.out / "hybrid" / "adjustment.json", adjustment_report(nav, result, "hybrid", final))
    pio.write_eop(inputs.out / "eop_photos.csv",
                  pio.eop_from_w(pp.eop.images, R, p, pp.frame, pp.crs, pp.eop.cameras))
    stats, _ = control_point_stats(tuple(pp.camera(i) for i in range(len(pp.eop))), R, p, control)
    sigma = {"sigma_rph_mdeg_median": (np.degrees(np.median(result.sigma_rph_rad, axis=0)) * 1e3).tolist(),
             "sigma_position_m_median": np.median(result.sigma_position_m, axis=0).tolist()}
    metrics = HybridResult(
        case, planes, len(pp.eop), len(blk.lgs), ties.n_points, len(ties.photo_image), len(ties.returns),
        stats["control"], stats["check"], tie_rms, result.solve, precision, pre, sigma,
        photo_lidargram_matches(blk, matches), dict(steps.timings_s), gi=gi, result=result)
    write_json(inputs.out / "metrics.json", metrics.to_dict())
    write_yaml(inputs.out / "config.resolved.yaml",
               cfg.model_copy(update={"processing": cfg.processing.model_copy(update={"lidargrammetry": st})}))
    return metrics
