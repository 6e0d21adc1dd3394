"""Co-adjustment of photos and lidargrams (docs/ARCHITECTURE.md §4.8, paper 004 §3.1).

One bundle block on the shared engine (:mod:`georefine.adjustment`): parameter blocks
``image_rotation`` (so3) and ``image_position`` for every image -- photos first, then
lidargrams -- and ``points`` for tie points and control/check points. Observation groups:

* ``ties``: reprojection of tie points (tracks of matched keypoints) in photos and lidargrams,
  Huber loss;
* ``point_measurements``: reprojection of control and check points measured in photos;
* ``control_coordinates``: the surveyed coordinates of control points with their sigma;
* ``photo_eop_prior`` / ``lidargram_eop_prior``: the approximate exterior orientation with its
  sigma (a lidargram's is the pose it was rendered from, with the a-priori accuracy of the
  LiDAR's trajectory).

The cases of the paper are named configurations (:data:`CASES`):

1. *LiDAR refinement*: the photo block is first adjusted on its own with its control points,
   then held fixed; the lidargrams are adjusted to it (their EOP change re-intersects the
   cloud, :mod:`.reintersect`).
2. *Photos and LiDAR*: photos and lidargrams adjusted together with the control points.
3. *Photo refinement*: the lidargrams are held fixed as control; the photos are adjusted
   without any control point (all points are check points).

Check points never enter as coordinates: their image measurements are intersected with the
adjusted photo orientation and compared with their surveyed coordinates (RMSE X/Y/Z as the
paper's Tables 1-6); control points are reported the same way. The reprojection error (RE,
px) is the RMS of the image residuals of those points.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from georefine.adjustment.accuracy_standards import (
    PositionalAccuracy,
    positional_accuracy,
)
from georefine.adjustment.linalg import NotPositiveDefiniteError
from georefine.adjustment.observations.prior import EuclideanPrior, RotationPrior
from georefine.adjustment.observations.reprojection import (
    DepthObservation,
    ReprojectionObservation,
)
from georefine.adjustment.problem import Problem
from georefine.adjustment.robust import make_loss
from georefine.adjustment.solver import SolverOptions
from georefine.geometry.camera import Camera

log = logging.getLogger(__name__)

__all__ = ["CASES", "TIE_INLIER_LOSS_SCALES", "BlockImages", "ControlData", "BundleResult", "PointStats",
           "check_point_consistency", "coadjust", "control_point_stats", "intersect_points", "point_reprojection",
           "stations_per_point"]

TIE_INLIER_LOSS_SCALES = 3.0
"""A tie observation is an inlier when its image residual after the adjustment is below this many
loss scales of the tie sigma (``tie_loss_scale * tie_sigma_px``): the observations the tie
reprojection RMS is taken over."""

CASES = {
    1: "LiDAR refinement: photos adjusted with control points, then fixed; lidargrams adjusted",
    2: "photos and LiDAR: photos and lidargrams adjusted together with control points",
    3: "photo refinement: lidargrams fixed as control; photos adjusted without control points",
}


@dataclass(frozen=True)
class BlockImages:
    """Images of the block: photos then lidargrams, with approximate poses in ``w``."""

    names: tuple[str, ...]
    cameras: tuple[Camera, ...]
    is_lidargram: np.ndarray  # (n,) bool
    R_w_c: np.ndarray  # (n, 3, 3)
    p_w_c: np.ndarray  # (n, 3)
    sigma_position_m: np.ndarray  # (n, 3) a-priori
    sigma_rotation_rad: np.ndarray  # (n, 3) a-priori
    station: np.ndarray | None = None  # (n,) where each image was taken or rendered (None: each its own)

    def stations(self) -> np.ndarray:
        return np.arange(len(self.names)) if self.station is None else np.asarray(self.station)

    def __len__(self) -> int:
        return len(self.names)


@dataclass(frozen=True)
class ControlData:
    """Control and check points (``w``) and their image measurements (photos only)."""

    ids: tuple[str, ...]
    xyz_w: np.ndarray  # (m, 3) surveyed
    sigma_m: np.ndarray  # (m, 3)
    is_control: np.ndarray  # (m,) bool
    image: np.ndarray  # (k,) image index of each measurement
    point: np.ndarray  # (k,) point index
    uv: np.ndarray  # (k, 2)


@dataclass(frozen=True)
class PointStats:
    """RMSE X/Y/Z (m, against the given coordinates) and reprojection error (px) of a point class."""

    n: int
    rmse_xyz_m: np.ndarray
    reprojection_px: float
    accuracy: PositionalAccuracy | None = None  # ASPRS 2023 / NSSDA, the points' survey sigma included

    def to_dict(self) -> dict:
        out = {"n": self.n, "rmse_x_m": float(self.rmse_xyz_m[0]), "rmse_y_m": float(self.rmse_xyz_m[1]),
               "rmse_z_m": float(self.rmse_xyz_m[2]), "reprojection_px": self.reprojection_px}
        if self.accuracy is not None:
            out["asprs"] = self.accuracy.to_dict()
        return out

    @classmethod
    def from_dict(cls, d: dict) -> PointStats:
        """From :meth:`to_dict` or its JSON (where NaN is ``null``)."""
        re_px = d["reprojection_px"]
        asprs = d.get("asprs")
        return cls(int(d["n"]), np.array([d["rmse_x_m"], d["rmse_y_m"], d["rmse_z_m"]], dtype=float),
                   float("nan") if re_px is None else float(re_px),
                   None if asprs is None else PositionalAccuracy.from_dict(asprs))


@dataclass(frozen=True)
class BundleResult:
    """Adjusted poses, tie points and statistics of one case."""

    case: int
    R_w_c: np.ndarray
    p_w_c: np.ndarray
    tie_points_w: np.ndarray
    control: PointStats | None
    check: PointStats | None
    tie_reprojection_px: dict[str, float]  # RMS per image kind ("photos", "lidargrams")
    solve: object
    point_xyz_w: np.ndarray  # (m, 3) control/check points intersected with the adjusted photos
    extra: dict = field(default_factory=dict)
    tie_inlier: np.ndarray | None = None  # (k,) tie observations within 3 loss scales after the adjustment
    # Per tie observation (k, 2): projected minus measured pixel coordinates after the adjustment;
    # NaN where the point was not adjusted (seen from one station without depth) or lies behind.
    tie_residual_px: np.ndarray | None = None
    # Per control/check point (m,): photo measurements (rays) and the RMS of their image residuals
    # (px) with the adjusted photos; NaN where fewer than two rays intersect.
    point_rays: np.ndarray | None = None
    point_reprojection_px: np.ndarray | None = None
    # (m, 3, 3) posterior covariance in ``w`` of the control/check points as points of the
    # adjustment the photos come from (case 1: the photo block's, case 2: the co-adjustment's);
    # None where they are not in it (case 3) or the block gave no covariance.
    point_cov_w: np.ndarray | None = None

    def to_dict(self) -> dict:
        return {"case": self.case, "description": CASES[self.case],
                "control_points": None if self.control is None else self.control.to_dict(),
                "check_points": None if self.check is None else self.check.to_dict(),
                "tie_reprojection_px": self.tie_reprojection_px, "adjustment": self.solve.to_dict(),
                **{k: v.to_dict() if k == "photo_block_adjustment" else v for k, v in self.extra.items()}}


# ---------------------------------------------------------------------------- geometry helpers
def intersect_points(cameras, R_w_c, p_w_c, image: np.ndarray, point: np.ndarray, uv: np.ndarray,
                     n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares intersection of rays (midpoint of all rays of a point); ``(X (m,3), n_rays (m,))``."""
    d = np.empty((len(image), 3))
    cam_index = {c: k for k, c in enumerate(dict.fromkeys(cameras))}  # equal cameras are one
    of_obs = np.array([cam_index[cameras[i]] for i in image], dtype=np.int64)
    for cam, k in cam_index.items():
        sel = of_obs == k
        if sel.any():
            d[sel] = np.einsum("nij,nj->ni", R_w_c[image[sel]], cam.rays(uv[sel]))
    o = p_w_c[image]
    A = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # projector orthogonal to each ray
    M = np.zeros((n_points, 3, 3))
    b = np.zeros((n_points, 3))
    np.add.at(M, point, A)
    np.add.at(b, point, np.einsum("nij,nj->ni", A, o))
    n_rays = np.bincount(point, minlength=n_points)
    X = np.full((n_points, 3), np.nan)
    ok = n_rays >= 2
    X[ok] = np.linalg.solve(M[ok], b[ok][..., None])[..., 0]
    return X, n_rays


def stations_per_point(point: np.ndarray, station_of_obs: np.ndarray, n_points: int) -> np.ndarray:
    """``(n_points,)`` number of distinct stations that observe each point (a photo and the
    lidargrams rendered at its pose are one station: no base between them)."""
    point = np.asarray(point, dtype=np.int64)
    if point.size == 0:
        return np.zeros(n_points, dtype=np.int64)
    st = np.unique(np.column_stack([point, np.asarray(station_of_obs, dtype=np.int64)]), axis=0)
    return np.bincount(st[:, 0], minlength=n_points)


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


def point_reprojection(cameras, R_w_c: np.ndarray, p_w_c: np.ndarray, control: ControlData,
                       X: np.ndarray) -> np.ndarray:
    """``(m,)`` RMS image residual (px) of each control/check point's measurements against the
    projection of ``X`` (its intersection) in the given photo poses; NaN where ``X`` is NaN."""
    out = np.full(len(control.ids), np.nan)
    ok = np.isfinite(X[:, 0])
    meas = ok[control.point] if len(control.point) else np.zeros(0, dtype=bool)
    if not meas.any():
        return out
    grp = ReprojectionObservation("tmp", cameras, control.image[meas], control.point[meas], control.uv[meas])
    uv, _ = grp.predict({"image_rotation": R_w_c, "image_position": p_w_c, "points": np.where(ok[:, None], X, 0.0)})
    sq = np.sum((uv - control.uv[meas]) ** 2, axis=1)
    pts = control.point[meas]
    n = np.bincount(pts, minlength=len(out))
    total = np.bincount(pts, weights=sq, minlength=len(out))
    has = n > 0
    out[has] = np.sqrt(total[has] / n[has])
    return out


def control_point_stats(cameras, R_w_c: np.ndarray, p_w_c: np.ndarray, control: ControlData, *,
                        all_check: bool = False) -> tuple[dict[str, PointStats | None], np.ndarray]:
    """Control and check points intersected with the given photo poses and compared with their
    surveyed coordinates: ``({"control": ..., "check": ...}, X (m, 3))``. With ``all_check`` every
    point is a check point and ``"control"`` is None (case 3: no control point is used)."""
    X, n_rays = intersect_points(cameras, R_w_c, p_w_c, control.image, control.point, control.uv, len(control.ids))
    stats: dict[str, PointStats | None] = {}
    check_mask = np.ones(len(control.ids), dtype=bool) if all_check else ~control.is_control
    for label, mask in (("control", control.is_control), ("check", check_mask)):
        pts = np.flatnonzero(mask & (n_rays >= 2))
        if (all_check and label == "control") or pts.size == 0:
            stats[label] = None
            continue
        meas = np.isin(control.point, pts)
        grp = ReprojectionObservation("tmp", cameras, control.image[meas], control.point[meas], control.uv[meas])
        uv, _ = grp.predict({"image_rotation": R_w_c, "image_position": p_w_c, "points": X})
        errors = X[pts] - control.xyz_w[pts]  # w: x, y horizontal, z up
        stats[label] = PointStats(int(pts.size), np.sqrt(np.mean(errors**2, axis=0)),
                                  _rms(np.linalg.norm(uv - control.uv[meas], axis=1)),
                                  positional_accuracy(errors, control.sigma_m[pts]))
    return stats, X


# ---------------------------------------------------------------------------- the adjustment
def coadjust(
    images: BlockImages,
    tie_image: np.ndarray,
    tie_point: np.ndarray,
    tie_uv: np.ndarray,
    tie_xyz0: np.ndarray,
    control: ControlData,
    case: int,
    *,
    tie_depth_m: np.ndarray | None = None,
    tie_sigma_px: float = 1.0,
    depth_sigma_m: float = 0.05,
    measurement_sigma_px: float = 0.5,
    tie_loss: str = "huber",
    tie_loss_scale: float = 2.0,
    options: SolverOptions | None = None,
) -> BundleResult:
    """Adjust the block as case ``case`` (module docstring).

    ``tie_*`` are the tie observations (image, point index, uv) and the points' initial
    coordinates in ``w`` (e.g. the ULPI points of lidargram observations). ``tie_depth_m``
    (aligned with the observations, NaN where none): the depth a lidargram shows at the
    keypoint, observed with ``depth_sigma_m`` (``ties_depth`` group); ``None`` keeps the
    paper's image-only formulation.
    """
    if case not in CASES:
        raise ValueError(f"case must be one of {sorted(CASES)}, got {case}")
    options = options or SolverOptions(max_iterations=50, function_tolerance=1e-8)
    photo = ~np.asarray(images.is_lidargram, dtype=bool)
    R, p = images.R_w_c.copy(), images.p_w_c.copy()
    extra: dict = {}
    if case == 1:  # the photo block alone with its control points, then fixed
        sel = np.isin(tie_image, np.flatnonzero(photo))
        pre = _solve(images, R, p, tie_image[sel], tie_point[sel], tie_uv[sel], tie_xyz0, control, None,
                     use_control=True, fixed=~photo, tie_sigma_px=tie_sigma_px, m_sigma=measurement_sigma_px,
                     tie_loss=tie_loss, tie_loss_scale=tie_loss_scale, options=options, depth_sigma_m=depth_sigma_m)
        R, p = pre["R"], pre["p"]
        point_cov = pre.get("cov_points")  # the check points are intersected from these photos
        extra["photo_block_adjustment"] = pre["solve"]  # a SolveResult, as ``solve``
        extra["photo_block_precision"] = _precision(images, pre, control, ~control.is_control)
        fixed, use_control = photo, False
    elif case == 2:
        fixed, use_control = np.zeros(len(images), dtype=bool), True
    else:
        fixed, use_control = ~photo, False
    out = _solve(images, R, p, tie_image, tie_point, tie_uv, tie_xyz0, control, tie_depth_m, use_control=use_control,
                 fixed=fixed, tie_sigma_px=tie_sigma_px, m_sigma=measurement_sigma_px, tie_loss=tie_loss,
                 tie_loss_scale=tie_loss_scale, options=options, depth_sigma_m=depth_sigma_m)
    R, p = out["R"], out["p"]
    if case == 2:
        point_cov = out.get("cov_points")
    elif case == 3:
        point_cov = None
    extra["precision"] = _precision(images, out, control, ~control.is_control)
    # Case 3 uses no control point: all of them are check points (paper 004, Tables 3 and 6).
    stats, X = control_point_stats(images.cameras, R, p, control, all_check=case == 3)
    tie_grp = ReprojectionObservation("tmp", images.cameras, tie_image, tie_point, tie_uv)
    uv, front = tie_grp.predict({"image_rotation": R, "image_position": p, "points": out["ties"]})
    err = np.linalg.norm(uv - tie_uv, axis=1)
    inlier = front & (err < TIE_INLIER_LOSS_SCALES * tie_loss_scale * tie_sigma_px)
    rms = {kind: _rms(err[inlier & (images.is_lidargram[tie_image] == lg)])
           for kind, lg in (("photos", False), ("lidargrams", True))}
    extra["tie_inlier_fraction"] = float(inlier.mean()) if inlier.size else float("nan")
    residual = np.where(front[:, None], uv - tie_uv, np.nan)
    rays = np.bincount(control.point, minlength=len(control.ids)) if len(control.ids) else np.zeros(0, np.int64)
    return BundleResult(case, R, p, out["ties"], stats["control"], stats["check"], rms, out["solve"], X, extra, inlier,
                        residual, rays, point_reprojection(images.cameras, R, p, control, X), point_cov)


def _solve(images: BlockImages, R, p, t_img, t_pt, t_uv, t_xyz0, control: ControlData, t_depth, *,
           use_control: bool, fixed: np.ndarray, tie_sigma_px: float, m_sigma: float, tie_loss: str,
           tie_loss_scale: float, options: SolverOptions, depth_sigma_m: float) -> dict:
    # Tie points seen from two stations or more (a photo and the lidargrams rendered at its pose
    # are one station: no base), or from one with a lidargram depth; the others have a free
    # depth (the damping of Levenberg-Marquardt hides that, the covariance does not).
    ok = stations_per_point(t_pt, images.stations()[t_img], len(t_xyz0))[t_pt] >= 2
    if t_depth is not None:
        ok |= np.isin(t_pt, t_pt[np.isfinite(t_depth)])
    t_img, t_pt, t_uv = t_img[ok], t_pt[ok], t_uv[ok]
    t_depth = None if t_depth is None else t_depth[ok]
    used = np.unique(t_pt)
    remap = np.full(len(t_xyz0), -1)
    remap[used] = np.arange(used.size)
    n_tie = used.size
    pts0 = [t_xyz0[used]]
    if use_control:
        pts0.append(control.xyz_w)
    P = Problem()
    P.add_block("image_rotation", R, manifold="so3", constant=fixed)
    P.add_block("image_position", p, constant=fixed)
    P.add_block("points", np.concatenate(pts0))
    P.add_group(ReprojectionObservation("ties", images.cameras, t_img, remap[t_pt], t_uv, tie_sigma_px,
                                        loss=make_loss(tie_loss, tie_loss_scale)))
    if t_depth is not None and np.isfinite(t_depth).any():
        d = np.isfinite(t_depth)
        P.add_group(DepthObservation("ties_depth", t_img[d], remap[t_pt[d]], t_depth[d], depth_sigma_m,
                                     loss=make_loss(tie_loss, tie_loss_scale)))
    for kind, mask in (("photo", ~images.is_lidargram), ("lidargram", images.is_lidargram)):
        el = np.flatnonzero(mask & ~fixed)
        if el.size:
            P.add_group(EuclideanPrior(f"{kind}_position_prior", "image_position", el, images.p_w_c[el],
                                       images.sigma_position_m[el]))
            P.add_group(RotationPrior(f"{kind}_rotation_prior", "image_rotation", el, images.R_w_c[el],
                                      images.sigma_rotation_rad[el]))
    if use_control:
        P.add_group(ReprojectionObservation("point_measurements", images.cameras, control.image,
                                            n_tie + control.point, control.uv, m_sigma))
        ctl = np.flatnonzero(control.is_control)
        P.add_group(EuclideanPrior("control_coordinates", "points", n_tie + ctl, control.xyz_w[ctl],
                                   control.sigma_m[ctl]))
        # Check points: observed in the images but free (no coordinates).
    result = P.solve(options)
    ties = np.full_like(t_xyz0, np.nan)
    ties[used] = P.values("points")[:n_tie]
    out = {"R": P.values("image_rotation"), "p": P.values("image_position"), "ties": ties, "solve": result}
    # Posterior precision (marginal covariances, scaled by sigma0^2) of the free images and, when
    # they are in the block, of the control and check points.
    free = np.flatnonzero(~fixed)
    out["sigma_position"] = np.full((len(images), 3), np.nan)
    out["sigma_rotation"] = np.full((len(images), 3), np.nan)
    try:
        if free.size:
            for key, block in (("sigma_position", "image_position"), ("sigma_rotation", "image_rotation")):
                cov = P.covariance(block, free)
                out[key][free] = np.sqrt(np.einsum("kii->ki", cov))
        if use_control and len(control.ids):
            cov = P.covariance("points", n_tie + np.arange(len(control.ids)))
            out["points"] = P.values("points")[n_tie:]
            out["cov_points"] = cov
            out["sigma_points"] = np.sqrt(np.einsum("kii->ki", cov))
    except (NotPositiveDefiniteError, ValueError) as exc:  # a weak block: no precision, the estimate stands
        log.warning("no posterior precision: %s", exc)
    return out


def _precision(images: BlockImages, sol: dict, control: ControlData, check_mask: np.ndarray) -> dict:
    """Estimated precision and, on the check points, its consistency with the actual errors.

    ``normalised_rms``: RMS over check points and axes of (adjusted - surveyed) / sqrt(sigma_est^2
    + sigma_survey^2); about 1 when the estimated sigmas are honest.
    """
    out: dict = {}
    deg = np.degrees
    for kind, mask in (("photos", ~images.is_lidargram), ("lidargrams", images.is_lidargram)):
        sp, sr = sol["sigma_position"][mask], sol["sigma_rotation"][mask]
        ok = np.isfinite(sp[:, 0])
        if ok.any():
            out[kind] = {"images": int(ok.sum()), "sigma_position_m_median": np.median(sp[ok], axis=0).tolist(),
                         "sigma_rotation_deg_median": deg(np.median(sr[ok], axis=0)).tolist()}
    if "sigma_points" in sol and check_mask.any():
        out["check_points"] = check_point_consistency(sol["points"][check_mask], sol["sigma_points"][check_mask],
                                                      control.xyz_w[check_mask], control.sigma_m[check_mask])
    return out


def check_point_consistency(xyz: np.ndarray, sigma: np.ndarray, surveyed: np.ndarray, survey_sigma: np.ndarray) -> dict:
    """Adjusted check points ``xyz`` with posterior ``sigma`` against their ``surveyed`` coordinates:
    RMS sigma and error per axis, and ``normalised_rms``, the RMS over points and axes of the error
    over ``sqrt(sigma^2 + survey_sigma^2)`` (about 1 when the sigmas are honest)."""
    e = xyz - surveyed
    s = np.sqrt(sigma**2 + survey_sigma**2)
    return {"n": int(len(xyz)), "sigma_xyz_m_rms": np.sqrt(np.mean(sigma**2, axis=0)).tolist(),
            "error_xyz_m_rms": np.sqrt(np.mean(e**2, axis=0)).tolist(),
            "normalised_rms": float(np.sqrt(np.mean((e / s) ** 2)))}
