"""Trajectory products: SBET at IMU rate with its companion and accuracy files, trajectory CSV
in the output CRS, and exports for evaluation tools (docs/ARCHITECTURE.md §4.5 step 6).

The pipeline's trajectory product is an SBET (WGS84, wander angle 0, NED velocity,
roll/pitch/true heading, body specific force and angular rate) at the IMU's sample times, in
seconds of the GPS week as POSPac and Inertial Explorer write it, so that any downstream tool
can georeference with it. Beside it: the companion ``<name>.json`` stating the GPS week and
the output CRS, and the POSPac-style accuracy file ``smrmsg_<stem>.out`` with the posterior
1-sigma (formats in :mod:`georefine.io.trajectory`). The CSV carries the position in the
output CRS, the attitude in degrees and the posterior 1-sigma. :func:`export_trajectory`
writes an SBET or CSV as TUM (evo) or trajectopy's format (:mod:`georefine.io.pose_files`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.errors import InputError
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.files import PathLike, week_from_gps_seconds
from georefine.io.pose_files import POSE_FORMATS, PoseTable, poses_from_geodetic, write_poses
from georefine.io.trajectory import (
    SbetCompanion,
    SbetData,
    SmrmsgData,
    read_sbet,
    read_sbet_companion,
    smrmsg_path,
    write_sbet,
    write_sbet_companion,
    write_smrmsg,
)
from georefine.io.trajectory_csv import TrajectoryTable, read_trajectory_csv, write_trajectory_csv

log = logging.getLogger(__name__)


def sbet_from_states(
    frame: LocalFrame,
    t0_gps: float,
    time: np.ndarray,
    p_w_b: np.ndarray,
    v_w_b: np.ndarray,
    R_w_b: np.ndarray,
    f_ib_b: np.ndarray | None = None,
    omega_ib_b: np.ndarray | None = None,
) -> SbetData:
    """SBET records of body states in ``w`` at ``time`` (s relative to ``t0_gps``)."""
    lat, lon, h = frame.to_geodetic(p_w_b)
    R_n_w = np.swapaxes(frame.R_w_n(lat, lon), 1, 2)
    v_n = np.einsum("nij,nj->ni", R_n_w, v_w_b)
    rph = frame.rph_from_R_w_b(p_w_b, R_w_b)
    n = time.size
    return SbetData(
        time_gps=t0_gps + time, lat_rad=lat, lon_rad=lon, h_m=h, velocity_wander=v_n,
        roll_rad=rph[:, 0], pitch_rad=rph[:, 1], heading_rad=rph[:, 2], wander_rad=np.zeros(n),
        accel_b=np.zeros((n, 3)) if f_ib_b is None else f_ib_b,
        angular_rate_b=np.zeros((n, 3)) if omega_ib_b is None else omega_ib_b,
    )


def body_kinematics(frame: LocalFrame, spline, time: np.ndarray) -> tuple[np.ndarray, ...]:
    """Pose, velocity, specific force and angular rate of a spline trajectory at ``time``."""
    p = spline.position(time, 0)
    v = spline.position(time, 1)
    a = spline.position(time, 2)
    R, omega_wb, _ = spline.orientation(time, rate=True)
    Rt = np.swapaxes(R, 1, 2)
    W = frame.omega_ie_w
    f = np.einsum("nij,nj->ni", Rt, a + 2.0 * np.cross(W, v) - frame.gravity_w(p))
    omega_ib = omega_wb + Rt @ W
    return p, v, R, f, omega_ib


def accuracy_from_sigmas(
    frame: LocalFrame, t0_gps: float, time: np.ndarray, p_w_b: np.ndarray, sigma_p_w: np.ndarray,
    sigma_v_w: np.ndarray, sigma_rph_rad: np.ndarray,
) -> SmrmsgData:
    """Accuracy records (``smrmsg``) of posterior sigmas at ``time`` (s relative to ``t0_gps``).

    Position and velocity sigmas are per ``w`` axis (east, north, up at the reference point);
    their diagonal covariance is rotated into the local north-east-down frame at ``p_w_b``
    (correlations between the axes are not in the sigmas and not in the file).
    """
    R_n_w = np.swapaxes(frame.R_w_n_at(p_w_b), 1, 2)

    def ned(sigma_w: np.ndarray) -> np.ndarray:
        return np.sqrt(np.einsum("nij,nj->ni", R_n_w**2, np.asarray(sigma_w, dtype=float) ** 2))

    return SmrmsgData(t0_gps + np.asarray(time, dtype=float), ned(sigma_p_w), ned(sigma_v_w), sigma_rph_rad)


def write_sbet_product(
    path: Path, frame: LocalFrame, t0_gps: float, time, p, v, R, f=None, w=None, *,
    output_epsg: int | None = None, accuracy: SmrmsgData | None = None,
) -> None:
    """``path`` (SBET, seconds of the GPS week), its companion ``path.json`` and, with
    ``accuracy``, the accuracy file ``smrmsg_<stem>.out`` beside it (same week)."""
    sbet = sbet_from_states(frame, t0_gps, time, p, v, R, f, w)
    week = int(week_from_gps_seconds(sbet.time_gps[0])[0])
    write_sbet(path, sbet, time_scale="week")
    accuracy_file = None
    if accuracy is not None:
        accuracy_file = write_smrmsg(smrmsg_path(path), accuracy, gps_week=week).name
    write_sbet_companion(path, SbetCompanion(week, output_epsg, accuracy_file))


def write_csv_product(
    path: Path,
    frame: LocalFrame,
    crs: OutputCRS,
    t0_gps: float,
    time: np.ndarray,
    p_w_b: np.ndarray,
    R_w_b: np.ndarray,
    sigma_rph_rad: np.ndarray | None = None,
    sigma_p_m: np.ndarray | None = None,
) -> None:
    """Trajectory CSV: time, position in the output CRS, roll/pitch/heading (deg), 1-sigma."""
    xyz = crs.from_w(frame, p_w_b)
    rph = frame.rph_from_R_w_b(p_w_b, R_w_b)
    sig_xyz = None
    if sigma_p_m is not None:
        sig_xyz = sigma_p_m  # w is ENU; the output CRS axes agree with it to the meridian convergence
    table = TrajectoryTable(t0_gps + time, xyz, rph, sigma_xyz_m=sig_xyz, sigma_rpy_rad=sigma_rph_rad,
                            crs=f"EPSG:{crs.epsg}")
    write_trajectory_csv(path, table)


# ---------------------------------------------------------------------------
# Export for evaluation tools
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class TrajectoryExport:
    """What :func:`export_trajectory` wrote."""

    out: Path
    fmt: str
    poses: int
    epsg: int
    gps_week: int
    source: Path

    def summary(self) -> str:
        return (f"{self.poses:,} poses of {self.source.name} written to {self.out} ({self.fmt}, EPSG:{self.epsg}, "
                f"GPS week {self.gps_week})")


def _csv_epsg(table: TrajectoryTable, path: Path) -> int | None:
    if table.crs is None:
        return None
    code = table.crs.strip().upper().removeprefix("EPSG:")
    if not code.isdigit():
        raise InputError("the trajectory CSV's CRS is not an EPSG code", path=path, field="crs",
                         expected="'# crs: EPSG:<code>'", found=repr(table.crs))
    return int(code)


def read_trajectory_poses(
    source: PathLike, epsg: int | None = None, gps_week: int | None = None, name: str | None = None,
) -> PoseTable:
    """An SBET or a trajectory CSV (``.csv``) as poses in ``epsg`` (:mod:`georefine.io.pose_files`).

    Parameters
    ----------
    epsg
        CRS of the poses; default: the SBET companion's output CRS, or the CSV's CRS.
    gps_week
        GPS week of an SBET in seconds of week without a companion file.

    Raises
    ------
    InputError
        From the readers; no CRS given or found; a CSV without a CRS.
    """
    path = Path(source)
    if path.suffix.lower() == ".csv":
        table = read_trajectory_csv(path)
        csv_epsg = _csv_epsg(table, path)
        if csv_epsg is None:
            raise InputError("the trajectory CSV names no CRS", path=path, field="crs",
                             expected="a '# crs: EPSG:<code>' line", found="none")
        lat, lon, h = OutputCRS(csv_epsg).to_geodetic(table.xyz)
        time, rph = table.time_gps, table.rpy_rad
        default_epsg = csv_epsg
    else:
        sbet = read_sbet(path, gps_week=gps_week)
        companion = read_sbet_companion(path)
        lat, lon, h = sbet.lat_rad, sbet.lon_rad, sbet.h_m
        time = sbet.time_gps
        rph = np.column_stack([sbet.roll_rad, sbet.pitch_rad, sbet.heading_rad])
        default_epsg = companion.output_epsg if companion is not None else None
    target = epsg if epsg is not None else default_epsg
    if target is None:
        raise InputError("no CRS for the poses", path=path, field="epsg",
                         expected="--epsg (an SBET without a companion file names no output CRS)", found="none")
    return poses_from_geodetic(time, lat, lon, h, rph, int(target), name=name or path.stem)


def export_trajectory(
    source: PathLike, out: PathLike, fmt: str, *, epsg: int | None = None, gps_week: int | None = None,
) -> TrajectoryExport:
    """Write an SBET or a trajectory CSV as TUM (evo) or trajectopy's format (``fmt``).

    Every pose of the source is written, in ``epsg`` (default: the SBET companion's output
    CRS, or the CSV's), with the body attitude as the quaternion of ``R_c_b``
    (:mod:`georefine.io.pose_files` states the frames). The file is written atomically and
    never over the source.

    Raises
    ------
    InputError
        From :func:`read_trajectory_poses`; an unknown format; ``out`` is the source.
    """
    source = Path(source)
    if fmt not in POSE_FORMATS:
        raise InputError("unknown trajectory format", field="format", expected=" or ".join(POSE_FORMATS),
                         found=repr(fmt))
    poses = read_trajectory_poses(source, epsg, gps_week)
    written = write_poses(out, poses, fmt, protect=(source,))
    week = int(week_from_gps_seconds(poses.time_gps[0])[0])
    return TrajectoryExport(written, fmt, len(poses), int(poses.epsg), week, source)
