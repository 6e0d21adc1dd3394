"""Workflow steps 3-6 of paper 000: tightly-coupled GNSS/IMU/LiDAR trajectory estimation.

3. Preliminary georeferencing of every strip with the current trajectory (IMU rate, per-point
   interpolation).
4. Planar features per view (strip x scanner channel) and their matching across views into
   planar objects.
5. GNSS/IMU/LiDAR adjustment: the GNSS/IMU problem plus the plane observations (robust loss),
   optionally the boresight. Steps 3-5 repeat (outer iterations) until the trajectory changes
   less than the configured thresholds.
6. Final georeferencing into the output CRS.

:func:`run_workflow` writes ``gi/`` and ``gil/`` (trajectory products), ``points/*.laz``,
``features/`` (features and objects as CSV), ``metrics.json`` and the resolved configuration.
"""

from __future__ import annotations

import logging
import time as _time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from georefine.adjustment.gnss_imu import (
    GnssImuProblem,
    GnssImuResult,
    build_gnss_imu_problem,
    solve_gnss_imu,
    with_posterior,
)
from georefine.adjustment.observations.plane import PlaneObservation
from georefine.adjustment.observations.prior import RotationPrior
from georefine.adjustment.robust import make_loss
from georefine.adjustment.solver import SolverOptions
from georefine.config import ProjectConfig, boresight_matrix, load_project, write_yaml
from georefine.errors import InputError
from georefine.geometry.frames import OutputCRS
from georefine.geometry.rotation import log_so3, rph_from_R_n_b
from georefine.io.files import write_json
from georefine.io.las import iter_las_chunks
from georefine.lidar.correspondences import PlanarObjects, match_features, write_objects
from georefine.lidar.georeference import (
    PoseInterpolator,
    georeference,
    georeference_strip,
)
from georefine.lidar.planes import PlanarFeatures, extract_features, write_features
from georefine.progress import Progress, no_progress
from georefine.trajectory.sampled import Trajectory
from georefine.workflows.cache import StepCache, file_stamp
from georefine.workflows.navigation import (
    NavigationData,
    imu_rate_trajectory,
    load_navigation,
    step_adjust_gnss_imu,
    step_initialise,
    write_trajectory_products,
)
from georefine.workflows.project import output_folder

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StripPoints:
    """One strip in memory: scanner-frame points, times relative to the epoch, channels."""

    path: Path
    strip_id: int
    time: np.ndarray
    xyz_s: np.ndarray
    channel: np.ndarray


def read_strips(nav: NavigationData, strips: list[int] | None = None) -> list[StripPoints]:
    """Read the project's strips (optionally only those with the given ``point_source_id``).

    Raises
    ------
    InputError
        A strip without points, without configured ``scanner_channel`` values, or a requested
        strip id that no file holds.
    """
    cfg = nav.config
    channels = {c.id for c in cfg.scanner.channels}
    out = []
    for rel in cfg.scanner.files:
        path = nav.root / rel
        parts = list(iter_las_chunks(path, 5_000_000))
        if not parts or sum(len(p) for p in parts) == 0:
            raise InputError("strip has no points", path=path)
        sid = int(parts[0].point_source_id[0])
        if strips is not None and sid not in strips:
            continue
        t = np.concatenate([p.time_gps for p in parts]) - nav.t0_gps
        ch = np.concatenate([p.scanner_channel for p in parts])
        if not np.any(np.isin(ch, list(channels))):
            raise InputError(
                "no point has a configured scanner_channel", path=path, field="scanner_channel",
                expected="one of " + ", ".join(map(str, sorted(channels))), found=", ".join(map(str, np.unique(ch)[:5])),
            )
        out.append(StripPoints(path, sid, t, np.concatenate([p.xyz for p in parts]), ch))
    if strips is not None:
        missing = set(strips) - {s.strip_id for s in out}
        if missing:
            raise InputError("no strip with this id", field="--strips", expected="ids of the project's strips",
                             found=", ".join(map(str, sorted(missing))))
    return out


def step_features(
    nav: NavigationData, trajectory: Trajectory, strips: list[StripPoints], progress: Progress = no_progress
) -> tuple[PlanarFeatures, dict]:
    """Steps 3-4a: georeference each view with ``trajectory`` and extract its planar features."""
    cfg = nav.config
    p_b_s = np.asarray(cfg.scanner.lever_arm_m, dtype=float)
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)
    interp = PoseInterpolator(trajectory)
    parts, stats = [], {"points_outside_trajectory": 0, "views": {}}
    for k, strip in enumerate(strips):
        inside = interp.inside(strip.time)
        stats["points_outside_trajectory"] += int(np.count_nonzero(~inside))
        t, xs, ch = strip.time[inside], strip.xyz_s[inside], strip.channel[inside]
        x_w = georeference(t, xs, interp, p_b_s, R_b_s)
        for c in cfg.scanner.channels:
            m = ch == c.id
            if not np.any(m):
                log.warning("%s: no points of channel %d (%s)", strip.path.name, c.id, c.name)
                continue
            f = extract_features(x_w[m], t[m], strip.strip_id, c.id, interp, p_b_s, R_b_s, cfg.processing.planes)
            stats["views"][f"strip{strip.strip_id}_{c.name}"] = len(f)
            if len(f) == 0:
                log.warning("%s: channel %d (%s) gave no planar features", strip.path.name, c.id, c.name)
            parts.append(f)
        progress("planar features", k + 1, len(strips))
    features = PlanarFeatures.concatenate(parts) if parts else PlanarFeatures.empty()
    if len(features) == 0:
        raise InputError("no planar features in any view", field="processing.planes",
                         expected="planar surfaces (roofs, roads, facades) in the scans")
    return features, stats


@dataclass(frozen=True)
class LidarAdjustment:
    """Result of one G/I/L adjustment (``built``: the problem, for :func:`add_posterior`)."""

    result: GnssImuResult
    features_used: int
    objects_used: int
    boresight_deg: np.ndarray | None
    boresight_sigma_mdeg: np.ndarray | None
    built: GnssImuProblem | None = None


def add_posterior(adj: LidarAdjustment) -> LidarAdjustment:
    """``adj`` with posterior sigma (trajectory, IMU errors, boresight) if it has none yet."""
    if adj.result.sigma_time.size or adj.built is None:
        return adj
    result = with_posterior(adj.built, adj.result)
    bs_sig = None
    if adj.boresight_deg is not None:
        bs_sig = np.degrees(np.sqrt(np.diag(adj.built.problem.covariance("boresight")[0]))) * 1e3
    return LidarAdjustment(result, adj.features_used, adj.objects_used, adj.boresight_deg, bs_sig, adj.built)


def step_adjust_gil(
    nav: NavigationData,
    previous: GnssImuResult,
    features: PlanarFeatures,
    objects: PlanarObjects,
    progress: Progress = no_progress,
    covariance: bool = True,
) -> LidarAdjustment:
    """Step 5: the G/I problem started at ``previous`` plus the plane observations.

    With ``covariance=False`` no posterior sigma is computed (see :func:`add_posterior`).
    """
    cfg = nav.config
    lcfg = cfg.processing.lidar
    built = build_gnss_imu_problem(nav.gnss, cfg.imu.errors, cfg.processing.trajectory, previous.spline)
    e = previous.imu_errors
    P = built.problem
    P.set_values("acc_bias", e.acc_bias)
    P.set_values("gyro_bias", e.gyro_bias)
    P.set_values("acc_scale", np.asarray(e.acc_scale).reshape(1, 3))
    P.set_values("gyro_scale", np.asarray(e.gyro_scale).reshape(1, 3))

    grid = built.grid
    sel = np.flatnonzero((objects.feature_object >= 0) & (features.time >= grid.t_start) & (features.time <= grid.t_end))
    if sel.size > lcfg.max_features:
        sel = np.sort(np.random.default_rng(0).choice(sel, lcfg.max_features, replace=False))
    if sel.size == 0:
        raise InputError("no matched planar features inside the trajectory span", field="processing.matching")
    used_objects, obj_index = np.unique(objects.feature_object[sel], return_inverse=True)
    f = features.select(sel)
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)
    P.add_block("plane_params", np.zeros((used_objects.size, 3)))
    boresight = None
    if lcfg.estimate_boresight:
        P.add_block("boresight", R_b_s[None].copy(), manifold="so3")
        P.add_group(RotationPrior("boresight_prior", "boresight", [0], R_b_s[None], np.radians(lcfg.boresight_prior_deg)))
        boresight = "boresight"
    P.add_group(
        PlaneObservation(
            grid, f.time, f.centre_s, f.axis1_s, f.axis2_s, f.sigma_d_m, f.sigma_slope_rad, obj_index,
            objects.c0[used_objects], objects.k1[used_objects], objects.k2[used_objects], objects.n0[used_objects],
            np.asarray(cfg.scanner.lever_arm_m, dtype=float), R_b_s, boresight=boresight,
            blocks=built.blocks, loss=make_loss(lcfg.plane_loss, lcfg.plane_loss_scale),
        )
    )

    def report(it) -> None:
        progress("G/I/L adjustment", getattr(it, "iteration", 0), cfg.processing.trajectory.max_iterations)

    tcfg = cfg.processing.trajectory
    options = SolverOptions(max_iterations=tcfg.max_iterations, function_tolerance=lcfg.function_tolerance)
    result = solve_gnss_imu(built, options, progress=report, covariance=False)
    bs_deg = None
    if boresight:
        R = P.values("boresight")[0]
        bs_deg = np.degrees(rph_from_R_n_b(R))
        bs_deg[2] = (bs_deg[2] + 180.0) % 360.0 - 180.0
    adj = LidarAdjustment(result, int(sel.size), int(used_objects.size), bs_deg, None, built)
    return add_posterior(adj) if covariance else adj


def trajectory_change(a, b, *, statistic: str = "rms") -> tuple[float, float]:
    """Attitude (mdeg) and position (m) difference of two splines at ``a``'s knots.

    ``statistic="rms"`` (the outer-iteration criterion) or ``"max"``. The RMS, not the maximum:
    re-extracted and re-matched features differ a little from one outer iteration to the next,
    which moves single knots by a few mdeg without changing the trajectory as a whole.
    """
    t = a.grid.knot_times
    t = t[(t >= b.grid.t_start) & (t <= b.grid.t_end)]
    pa, Ra = a.pose(t)
    pb, Rb = b.pose(t)
    dth = np.linalg.norm(log_so3(np.swapaxes(Ra, 1, 2) @ Rb), axis=1)
    dp = np.linalg.norm(pa - pb, axis=1)
    if statistic == "max":
        return float(np.degrees(dth.max()) * 1e3), float(dp.max())
    if statistic != "rms":
        raise ValueError(f"statistic must be 'rms' or 'max', found {statistic!r}")
    return float(np.degrees(np.sqrt(np.mean(dth**2))) * 1e3), float(np.sqrt(np.mean(dp**2)))


@dataclass(frozen=True)
class WorkflowResult:
    """What :func:`run_workflow` computed and wrote."""

    out: Path
    gi: GnssImuResult
    gil: LidarAdjustment | None
    metrics: dict = field(default_factory=dict)

    def summary(self) -> str:
        m = self.metrics
        lines = [f"Results written to {self.out}"]
        for it in m.get("outer_iterations", []):
            lines.append(
                f"  iteration {it['iteration']}: {it['features']:,} features, {it['objects']:,} objects, "
                f"{it['features_used']:,} used; RMS change {it['attitude_change_mdeg']:.2f} mdeg, "
                f"{it['position_change_m'] * 1e3:.1f} mm"
            )
        if self.gil is not None and self.gil.boresight_deg is not None:
            b = self.gil.boresight_deg
            lines.append(f"  boresight roll/pitch/yaw: {b[0]:.4f} {b[1]:.4f} {b[2]:.4f} deg")
        if m.get("resumed"):
            lines.append("  resumed from the cache: " + ", ".join(m["resumed"]))
        lines.append("  timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in m.get("timings_s", {}).items()))
        return "\n".join(lines)


def _outer_iteration(nav, current, strip_points, it, timings, progress, adjust=True):
    """Steps 3-5 once from ``current``: features, objects, G/I/L adjustment (no posterior) and record."""
    t = _time.perf_counter()
    traj = imu_rate_trajectory(nav, current.spline)
    features, fstats = step_features(nav, traj, strip_points, progress)
    timings[f"features_{it}"] = _time.perf_counter() - t
    t = _time.perf_counter()
    objects = match_features(features, nav.config.processing.matching)
    timings[f"matching_{it}"] = _time.perf_counter() - t
    if not adjust:
        return features, objects, None, None
    t = _time.perf_counter()
    gil = step_adjust_gil(nav, current, features, objects, progress, covariance=False)
    timings[f"gil_adjustment_{it}"] = _time.perf_counter() - t
    d_att, d_pos = trajectory_change(current.spline, gil.result.spline)
    record = {
        "iteration": it, "features": len(features), "objects": len(objects),
        "features_used": gil.features_used, "objects_used": gil.objects_used,
        "attitude_change_mdeg": d_att, "position_change_m": d_pos, **fstats,
    }
    return features, objects, gil, record


def _navigation_key(cfg: ProjectConfig, root: Path) -> str:
    """Key of steps 1-2: the GNSS and IMU files and their configuration (no data read)."""
    files = [file_stamp(root / f, root) for f in [*cfg.gnss.files, cfg.imu.file]]
    return StepCache.key(
        "gi", files, cfg.crs.model_dump(), cfg.gnss.model_dump(), cfg.imu.model_dump(),
        cfg.processing.filter.model_dump(), cfg.processing.trajectory.model_dump(),
    )


def _lidar_key(nav: NavigationData, strips: list[StripPoints], upstream: str, iteration: int) -> str:
    cfg = nav.config
    return StepCache.key(
        "gil", iteration, upstream, [file_stamp(s.path, nav.root) for s in strips], cfg.scanner.model_dump(),
        cfg.processing.planes.model_dump(), cfg.processing.matching.model_dump(), cfg.processing.lidar.model_dump(),
    )


def _gnss_imu(nav: NavigationData, cache: StepCache, timings: dict[str, float],
              progress: Progress = no_progress) -> tuple[GnssImuResult, str]:
    """Steps 1-2 (filter, G/I adjustment), or their cached result; and the cache key."""
    t = _time.perf_counter()
    key = _navigation_key(nav.config, nav.root)
    gi = cache.load("gi", key)
    if gi is None:
        progress("initialisation filter", 0, 1)
        filt = step_initialise(nav)
        timings["filter"] = _time.perf_counter() - t
        t = _time.perf_counter()
        gi = step_adjust_gnss_imu(nav, filt, progress)
        cache.store("gi", key, gi)
    timings["gi_adjustment"] = _time.perf_counter() - t
    return gi, key


def precompute_gnss_imu(project_dir: str | Path, cache_dir: str | Path) -> dict[str, float]:
    """Steps 1-2 of ``project_dir`` into the step cache ``cache_dir``; their timings.

    They need the GNSS and IMU files only, so they can run while the scans are still being
    written (``georefine demo`` runs them in a second process during the simulation); a
    :func:`run_workflow` with the same ``cache_dir`` then resumes them. Nothing is read or
    computed when the cache already holds them.
    """
    timings: dict[str, float] = {}
    root, cache = Path(project_dir), StepCache(Path(cache_dir))
    if not cache.exists("gi", _navigation_key(load_project(root), root)):
        _gnss_imu(load_navigation(root), cache, timings)
    return timings


def _write_matched_features(folder: Path, features: PlanarFeatures, objects: PlanarObjects) -> None:
    """``features.csv`` and ``objects.csv`` of the matched features (members of objects).

    Only the features the adjustment can observe are written (about 4 % of the extracted features on ``corridor``:
    all 1.75 M of them made a 0.5 GB table that took 17 s to write); the objects' member
    indices refer to rows of this ``features.csv``. The extracted count per view is in
    ``metrics.json``.
    """
    used = np.flatnonzero(objects.feature_object >= 0)
    write_features(folder / "features.csv", features.select(used))
    write_objects(folder / "objects.csv", replace(objects, feature_object=objects.feature_object[used]))


def run_workflow(
    project_dir: str | Path,
    out: str | Path,
    *,
    strips: list[int] | None = None,
    lidar: bool = True,
    resume: bool = True,
    points: bool = True,
    cache_dir: str | Path | None = None,
    progress: Progress = no_progress,
) -> WorkflowResult:
    """Steps 1-6 on a project folder (see the module docstring for the outputs).

    Every step's result is cached in ``out/.cache`` (:mod:`georefine.workflows.cache`); with
    ``resume`` a rerun loads what its inputs and configuration have not changed, e.g. after an
    interruption or when only the final georeferencing is repeated. ``metrics.json`` lists the
    resumed steps under ``resumed``. ``points=False`` skips the final point clouds (step 6), e.g.
    when only the trajectory is wanted. ``cache_dir`` puts the cache elsewhere, e.g. one folder shared
    by a full and a single-pass run (they share the GNSS/IMU adjustment).
    """
    timings: dict[str, float] = {}
    t = _time.perf_counter()
    nav = load_navigation(project_dir)
    out = output_folder(out, nav.root)
    strip_points = read_strips(nav, strips)
    timings["read"] = _time.perf_counter() - t
    crs = OutputCRS(nav.config.crs.output_epsg)
    for sub in ("gi", "gil", "points", "features"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    cache = StepCache(Path(cache_dir) if cache_dir is not None else out / ".cache", enabled=resume)

    gi, key = _gnss_imu(nav, cache, timings, progress)
    write_trajectory_products(out / "gi", nav, gi, crs)
    write_json(out / "gi" / "adjustment.json", {"adjustment": gi.solve.to_dict(), "imu_errors": gi.imu_errors.to_dict(),
                                                 "t0_gps": nav.t0_gps, "timings_s": gi.timings_s})
    metrics: dict = {
        "t0_gps": nav.t0_gps, "strips": [s.strip_id for s in strip_points],
        "strip_time_gps": {str(s.strip_id): [float(s.time.min() + nav.t0_gps), float(s.time.max() + nav.t0_gps)]
                           for s in strip_points},
        "outer_iterations": [],
    }

    final = gi
    gil = None
    if lidar:
        lcfg = nav.config.processing.lidar
        current = gi
        features = objects = None
        for it in range(1, lcfg.outer_iterations + 1):
            key = _lidar_key(nav, strip_points, key, it)
            hit = cache.load(f"gil_{it}", key)
            previous = current
            if hit is not None:
                gil, record = hit
                features = objects = None
            else:
                features, objects, gil, record = _outer_iteration(nav, current, strip_points, it, timings, progress)
                cache.store(f"gil_{it}", key, (replace(gil, built=None), record))
                cache.store("gil_features", key, (features, objects), latest_only=True)
            metrics["outer_iterations"].append(record)
            current = gil.result
            if record["attitude_change_mdeg"] < lcfg.convergence_attitude_mdeg and (
                record["position_change_m"] < lcfg.convergence_position_m
            ):
                break
        t = _time.perf_counter()
        if features is None:
            fo = cache.load("gil_features", key)
            if fo is None:  # recompute from the trajectory the last iteration started at (deterministic)
                features, objects, *_ = _outer_iteration(nav, previous, strip_points, it, {}, progress, adjust=False)
            else:
                features, objects = fo
        posterior_key = StepCache.key("gil_posterior", key)
        posterior = cache.load("gil_posterior", posterior_key)
        if posterior is None:
            if gil.built is None:  # the last iteration came from the cache: one more (short) solve
                gil = step_adjust_gil(nav, previous, features, objects, progress, covariance=False)
            gil = add_posterior(gil)
            posterior = replace(gil, built=None)
            cache.store("gil_posterior", posterior_key, posterior)
        key = posterior_key
        gil = posterior
        current = gil.result
        timings["gil_covariance"] = _time.perf_counter() - t
        _write_matched_features(out / "features", features, objects)
        final = current
        write_trajectory_products(out / "gil", nav, final, crs)
        gil_report = {"adjustment": final.solve.to_dict(), "imu_errors": final.imu_errors.to_dict(), "t0_gps": nav.t0_gps,
                      "timings_s": final.timings_s}
        if gil.boresight_deg is not None:
            gil_report["boresight_deg"] = gil.boresight_deg.tolist()
            gil_report["boresight_sigma_mdeg"] = gil.boresight_sigma_mdeg.tolist()
        write_json(out / "gil" / "adjustment.json", gil_report)

    t = _time.perf_counter()
    georef = _final_points(nav, out, final, gil, key, strip_points, crs, cache, progress) if points else []
    timings["final_georeferencing"] = _time.perf_counter() - t
    metrics["points"] = [{k: v for k, v in r.items() if k != "stamp"} for r in georef]
    metrics["resumed"] = list(cache.hits)
    metrics["timings_s"] = timings
    write_json(out / "metrics.json", metrics)
    write_yaml(out / "config.resolved.yaml", nav.config)
    return WorkflowResult(out, gi, gil, metrics)


def _final_points(nav, out, final, gil, key, strip_points, crs, cache, progress) -> list[dict]:
    """Step 6: the strips in the output CRS (cached: skipped while the files are those it wrote)."""
    traj = imu_rate_trajectory(nav, final.spline)  # cheap; the LAZ writing below is what is cached
    p_b_s = np.asarray(nav.config.scanner.lever_arm_m, dtype=float)
    R_b_s = boresight_matrix(nav.config.scanner.boresight_deg)
    if gil is not None and gil.boresight_deg is not None:
        R_b_s = boresight_matrix(tuple(gil.boresight_deg))
    key = StepCache.key("points", key, nav.config.crs.model_dump(), nav.config.scanner.model_dump(),
                        [file_stamp(s.path) for s in strip_points])

    def written(records: list[dict]) -> bool:  # the LAZ files are still those this step wrote
        return all(
            (out / "points" / r["file"]).is_file() and file_stamp(out / "points" / r["file"])[1:] == r["stamp"]
            for r in records
        )

    done = cache.load("points", key, valid=written)
    if done is not None:
        georef = done
    else:
        georef = []
        for s in strip_points:
            path = out / "points" / (s.path.stem + ".laz")
            r = georeference_strip(s.path, path, traj, p_b_s, R_b_s, nav.frame, crs, progress=progress,
                                   protect=(nav.root,))
            georef.append({"strip": s.strip_id, "file": path.name, "points": r.points_written,
                           "outside_trajectory": r.points_outside, "stamp": file_stamp(path)[1:]})
        cache.store("points", key, georef)
    return georef
