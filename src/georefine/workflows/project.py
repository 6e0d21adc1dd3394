"""A project's sensor files read with the strict readers of :mod:`georefine.io`, and the checks
that only the files together can tell: GNSS and IMU time spans overlap, the IMU is a
forward-right-down record in SI units, its sampling gaps can be bridged. The same rules serve
``georefine check`` (:mod:`georefine.workflows.check`) and every workflow
(:func:`georefine.workflows.opened.load_navigation`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from georefine.config import ProjectConfig
from georefine.errors import InputError
from georefine.geometry.earth import normal_gravity
from georefine.geometry.frames import LocalFrame
from georefine.io.gnss import GnssSolution, gnss_in_w, read_pos
from georefine.io.imu import ImuData, read_imr, read_imu_csv
from georefine.io.imu_gaps import BridgedImu, bridge_imu_gaps
from georefine.trajectory.imu_check import check_imu_frame
from georefine.trajectory.sampled import interp_columns


def gnss_from_sbet(root: Path, cfg: ProjectConfig) -> GnssSolution:
    """``gnss.format: sbet``: the delivered SBET's positions at ``gnss.sbet_rate_hz`` as GNSS epochs.

    The covariance is the ``smrmsg`` north/east/down sigma (or ``gnss.sbet_sigma_m``) rotated to
    ECEF; quality 1. The raw IMU then rebuilds the attitude with them as from GNSS
    (docs/ARCHITECTURE.md §4.9).
    """
    from georefine.geometry.earth import R_e_n, geodetic_to_ecef
    from georefine.io.trajectory import read_sbet, read_smrmsg

    g = cfg.gnss
    sbet = read_sbet(root / g.files[0], gps_week=g.gps_week)
    step = max(1, int(round(1.0 / (g.sbet_rate_hz * float(np.median(np.diff(sbet.time_gps)))))))
    k = np.arange(0, len(sbet), step)
    t = sbet.time_gps[k]
    lat, lon, h = sbet.lat_rad[k], sbet.lon_rad[k], sbet.h_m[k]
    if g.smrmsg:
        acc = read_smrmsg(root / g.smrmsg, gps_week=g.gps_week if g.gps_week is not None else int(t[0] // 604800))
        sig = interp_columns(t, acc.time_gps, acc.sigma_ned_m)
    else:
        sig = np.full((t.size, 3), g.sbet_sigma_m)
    R = R_e_n(lat, lon)
    cov = np.einsum("nij,nj,nkj->nik", R, sig**2, R)
    n = t.size
    return GnssSolution(t, geodetic_to_ecef(lat, lon, h), cov, np.ones(n, dtype=np.int64), np.zeros(n, dtype=np.int64),
                        np.zeros(n), np.zeros(n))


def read_project_gnss(root: Path, cfg: ProjectConfig) -> GnssSolution:
    """Read and concatenate the project's ``.pos`` files (time-ordered, no duplicates), or the SBET's positions."""
    if cfg.gnss.format == "sbet":
        return gnss_from_sbet(root, cfg)
    parts = [read_pos(root / f) for f in cfg.gnss.files]
    if len(parts) == 1:
        return parts[0]
    order = np.argsort(np.concatenate([p.time_gps for p in parts]), kind="stable")
    cat = {
        name: np.concatenate([getattr(p, name) for p in parts])[order]
        for name in ("time_gps", "position_ecef", "covariance_ecef", "quality", "num_sats", "age_s", "ratio")
    }
    if np.any(np.diff(cat["time_gps"]) <= 0):
        raise InputError(
            "GNSS files overlap in time", path=root / cfg.gnss.files[1], field="time", expected="disjoint files"
        )
    return GnssSolution(**cat)


def read_project_imu(root: Path, cfg: ProjectConfig) -> ImuData:
    """Read the project's IMU file in the configured format."""
    path = root / cfg.imu.file
    if cfg.imu.format == "imr":
        return read_imr(path, gps_week=cfg.imu.gps_week)
    return read_imu_csv(path, rate_hz=cfg.imu.rate_hz)


def usable_gnss(root: Path, cfg: ProjectConfig, gnss: GnssSolution) -> np.ndarray:
    """The epochs of quality ``gnss.min_quality`` or better (a boolean mask).

    Raises
    ------
    InputError
        None is, naming the first GNSS file.
    """
    usable = gnss.quality <= cfg.gnss.min_quality
    if not np.any(usable):
        raise InputError(
            "no epoch of sufficient quality",
            path=root / cfg.gnss.files[0],
            field="Q",
            expected=f"Q <= {cfg.gnss.min_quality} (gnss.min_quality)",
            found=f"best Q = {int(gnss.quality.min())}",
        )
    return usable


def check_navigation_spans(
    root: Path, cfg: ProjectConfig, gnss: GnssSolution, imu: ImuData
) -> tuple[np.ndarray, tuple[float, float], tuple[float, float]]:
    """Usable GNSS epochs and the GNSS/IMU time spans (GPS s); they must overlap.

    Raises
    ------
    InputError
        No epoch of the configured quality, or GNSS and IMU spans that do not overlap.
    """
    usable = usable_gnss(root, cfg, gnss)
    g_span = (float(gnss.time_gps[usable][0]), float(gnss.time_gps[usable][-1]))
    i_span = (float(imu.time_gps[0]), float(imu.time_gps[-1]))
    if g_span[1] <= i_span[0] or i_span[1] <= g_span[0]:
        raise InputError(
            "GNSS and IMU time spans do not overlap",
            path=root / cfg.imu.file,
            field="time",
            expected=f"overlap with GNSS {g_span[0]:.3f} .. {g_span[1]:.3f} GPS s",
            found=f"{i_span[0]:.3f} .. {i_span[1]:.3f} GPS s",
        )
    return usable, g_span, i_span


def bridge_project_imu(root: Path, cfg: ProjectConfig, imu: ImuData) -> BridgedImu:
    """The project's IMU with its sampling gaps bridged (:mod:`georefine.io.imu_gaps`), as check and run see it.

    Raises
    ------
    InputError
        A gap longer than ``imu.max_gap_s``, naming the file and the record after it.
    """
    bridged, too_long = bridge_imu_gaps(imu, cfg.imu.max_gap_s)
    if too_long is not None:
        k = too_long.index + 1  # the first sample after the gap: CSV line k + 2 (a header line), IMR record k + 1
        raise InputError(
            f"IMU sampling gap of {too_long.duration_s:.3f} s ({too_long.missing} samples missing), longer than "
            "imu.max_gap_s can bridge",
            path=root / cfg.imu.file, line=k + 2 if cfg.imu.format == "csv" else k + 1,
            record_kind="line" if cfg.imu.format == "csv" else "record", field="time",
            expected=f"gaps of at most {cfg.imu.max_gap_s:g} s (imu.max_gap_s)",
            found=f"{too_long.t_before:.6f} -> {too_long.t_after:.6f} GPS s",
        )
    return bridged


def gnss_gaps(gnss: GnssSolution, usable: np.ndarray, factor: float = 3.0) -> np.ndarray:
    """(K, 2) GPS seconds around each gap between usable GNSS epochs longer than ``factor`` nominal intervals.

    Missing epochs and epochs of a quality worse than ``gnss.min_quality`` both open a gap: the
    adjustment bridges it on the IMU alone (its sigma grows with the gap).
    """
    t = gnss.time_gps[usable]
    if t.size < 3:
        return np.empty((0, 2))
    dt = np.diff(t)
    idx = np.flatnonzero(dt > factor * float(np.median(dt)))
    return np.column_stack([t[idx], t[idx + 1]]) if idx.size else np.empty((0, 2))


def check_imu_plausible(root: Path, cfg: ProjectConfig, gnss: GnssSolution, imu: ImuData) -> None:
    """Units, axes and signs of the IMU record against the GNSS trajectory (:mod:`georefine.trajectory.imu_check`).

    The same rule for ``georefine check`` and every workflow, run before any work (about a second).

    Raises
    ------
    InputError
        Naming the IMU file, the fields, what a forward-right-down record in SI units would show
        and what this one shows.
    """
    keep = gnss.quality <= cfg.gnss.min_quality
    if keep.sum() < 2:
        return  # check_navigation_spans reports it
    i = int(np.flatnonzero(keep)[0])
    lat, lon, h = (np.atleast_1d(a)[i] for a in gnss.geodetic())
    frame = LocalFrame(float(lat), float(lon), float(h))
    t0 = float(np.floor(imu.time_gps[0]))
    g_time, g_p, _ = gnss_in_w(frame, t0, gnss, cfg.gnss.min_quality)
    finding = check_imu_frame(imu.time_gps - t0, imu.gyro, imu.acc, g_time, g_p,
                              float(normal_gravity(frame.lat0_rad, frame.h0_m)))
    if finding is not None:
        raise InputError(finding.message, path=root / cfg.imu.file, field=finding.field, expected=finding.expected,
                         found=finding.found)
