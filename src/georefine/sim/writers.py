"""Write simulated sensor data through the same file formats as real data (docs/ARCHITECTURE.md §3).

Each function converts one simulator product to its :mod:`georefine.io` container and writes
it atomically. The formats are those of real systems, so the whole pipeline runs on the
simulation unchanged.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.files import week_from_gps_seconds
from georefine.io.gnss import GnssSolution, write_pos
from georefine.io.imu import ImuData, write_imr, write_imu_csv
from georefine.io.las import PointCloud
from georefine.io.las_encode import ExtraDim
from georefine.io.las_writer import LasWriter
from georefine.io.reference import ReferenceSurfaces, write_reference_surfaces
from georefine.io.trajectory import SbetCompanion, SbetData, write_sbet, write_sbet_companion
from georefine.lidar.georeference import beam_scan_angles_deg
from georefine.sim.flight import TrueTrajectory
from georefine.sim.gnss import SimulatedGnss
from georefine.sim.imu import SimulatedImu
from georefine.sim.scanner import ScanChunk

LAS_SCALE_M = 1e-4
"""Coordinate resolution of scan and truth strips (0.1 mm, far below the ranging noise)."""

RANGE_ERROR_DIM = ExtraDim("range_error_m", "f4", "simulated range error (m)", no_data=-9999.0)
"""Extra dimension of the truth strips: the range error of each return, noise and (where set) the unit's offset and scale."""


def write_gnss(path: Path, gnss: SimulatedGnss) -> None:
    """RTKLIB ``.pos`` (GPST calendar time, lat/lon/ellipsoidal height, diagonal NEU sd)."""
    n = gnss.time.size
    sd = gnss.sd_neu
    cov_enu = np.zeros((n, 3, 3))
    cov_enu[:, 0, 0] = sd[:, 1] ** 2
    cov_enu[:, 1, 1] = sd[:, 0] ** 2
    cov_enu[:, 2, 2] = sd[:, 2] ** 2
    solution = GnssSolution.from_geodetic(
        gnss.t0_gps + gnss.time, gnss.lat, gnss.lon, gnss.h, cov_enu, gnss.quality, gnss.num_sats,
        age_s=np.zeros(n), ratio=np.full(n, 999.9),
    )
    write_pos(path, solution, time_format="calendar", position_format="llh", time_decimals=3)


CABIN_TEMPERATURE_C = 20.0
"""The simulated IMU's temperature at its first sample (deg C)."""


def write_imu(path: Path, imu: SimulatedImu, imr_path: Path | None = None) -> None:
    """IMU CSV (instantaneous rates, body FRD) and optionally a NovAtel ``.imr`` file.

    Where the unit's temperature changes (``imu.temperature_change_c``), the CSV carries it as its
    last column, from a cabin's 20 deg C at the first sample, as units log it; ``.imr`` has no
    such field."""
    temperature = None
    if imu.temperature_c is not None and np.any(imu.temperature_c):
        temperature = CABIN_TEMPERATURE_C + imu.temperature_c
    data = ImuData(
        time_gps=imu.t0_gps + imu.time, gyro=imu.gyro, acc=imu.acc, rate_hz=imu.grade.rate_hz, kind="rates",
        temperature_c=temperature,
    )
    write_imu_csv(path, data)
    if imr_path is not None:
        week, _ = week_from_gps_seconds(imu.t0_gps)
        # The simulated samples are instantaneous rates, so they are written as rates
        # (bDeltaTheta = bDeltaVelocity = 0), not as approximate increments.
        write_imr(imr_path, data, gps_week=int(week), delta=False)


def write_truth_trajectory(path: Path, traj: TrueTrajectory, time: np.ndarray, output_epsg: int | None = None) -> None:
    """The true IMU trajectory as an SBET (seconds of GPS week, wander angle 0) at ``time``, with the
    companion file ``path.json`` that states its GPS week and the output CRS (as Georefine's products)."""
    state = traj.state(time)
    frame = traj.frame
    lat, lon, h = frame.to_geodetic(state.p_w_b)
    R_w_n = frame.R_w_n(lat, lon)
    R_n_w = np.swapaxes(R_w_n, 1, 2)
    v_n = np.einsum("nij,nj->ni", R_n_w, state.v_w_b)
    rph = frame.rph_from_R_w_b(state.p_w_b, state.R_w_b)
    omega_ib_b, f_ib_b = traj.imu(time)
    sbet = SbetData(
        time_gps=traj.t0_gps + time, lat_rad=lat, lon_rad=lon, h_m=h, velocity_wander=v_n,
        roll_rad=rph[:, 0], pitch_rad=rph[:, 1], heading_rad=rph[:, 2], wander_rad=np.zeros(time.size),
        accel_b=f_ib_b, angular_rate_b=omega_ib_b,
    )
    write_sbet(path, sbet, time_scale="week")
    write_sbet_companion(path, SbetCompanion(int(week_from_gps_seconds(sbet.time_gps[0])[0]), output_epsg))


def write_reference(
    root: Path, surfaces, frame: LocalFrame, crs: OutputCRS, survey_sigma_m: float, rng: np.random.Generator
) -> None:
    """Reference surfaces: surveyed corners (with survey noise) and the exact corners (truth)."""
    sid = np.repeat([s.surface_id for s in surfaces], 4)
    pid = np.array([f"{s.surface_id}-{k + 1}" for s in surfaces for k in range(4)])
    corners_w = np.concatenate([s.corners_w for s in surfaces])
    exact = crs.from_w(frame, corners_w)
    surveyed = exact + rng.normal(0.0, survey_sigma_m, exact.shape)
    write_reference_surfaces(root / "reference" / "surfaces.csv", ReferenceSurfaces(sid, pid, np.round(surveyed, 4)))
    write_reference_surfaces(root / "truth" / "reference_surfaces.csv", ReferenceSurfaces(sid, pid, exact))


def strip_records(chunk: ScanChunk, strip_id: int, t0_gps: float, frame: LocalFrame,
                  crs: OutputCRS, scan_time_offset_s: float = 0.0) -> tuple[PointCloud, PointCloud]:
    """The scan-file and truth-file records of one chunk (the per-chunk work of :func:`write_strip`,
    done inside the scan task so that the writer only encodes).

    The scan file's time stamps run ``scan_time_offset_s`` behind GPS time (a scanner that is not
    synchronised); the truth file keeps GPS time.

    Scan angles (LAS ``scan_angle``, :mod:`georefine.io.las`): in the scan file, whose coordinates
    are the scanner frame, the angle the mirror fired at, ``alpha`` (from the scanner's +z axis,
    positive towards +y, the right; a view's forward tilt does not enter it), which is the LAS
    angle with the scanner frame as the data's frame; in the truth file, the angle of the true
    beam from the local vertical, with the roll (:func:`~georefine.lidar.georeference.scan_angles_deg`'s
    definition), as a georeferencing with the true trajectory computes it."""
    m = chunk.time.size
    ones = np.ones(m, dtype=np.uint8)
    sid = np.full(m, strip_id, dtype=np.uint16)
    t_gps = t0_gps + chunk.time
    scan = PointCloud(t_gps - scan_time_offset_s if scan_time_offset_s else t_gps, chunk.xyz_s, chunk.intensity,
                      chunk.channel, sid, ones, ones, scan_angle_deg=np.degrees(chunk.scan_angle_rad))
    # Measured point georeferenced with the true pose: the true hit moved by the range noise
    # along the beam (exactly what the scanner model measured).
    measured_w = chunk.xyz_w_true + chunk.range_error_m[:, None] * chunk.beam_w
    lat, lon, h = frame.to_geodetic(measured_w)
    truth = PointCloud(t_gps, crs.from_geodetic(lat, lon, h), chunk.intensity, chunk.channel, sid, ones, ones,
                       extra={"range_error_m": chunk.range_error_m},
                       scan_angle_deg=beam_scan_angles_deg(chunk.beam_w, chunk.forward_w, frame.up_w(lat, lon)))
    return scan, truth


def write_strip(
    scan_path: Path,
    truth_path: Path,
    records: Iterable[tuple[PointCloud, PointCloud]],
    tick: Callable[[float], None] | None = None,
    crs: OutputCRS | None = None,
) -> int:
    """Write one strip: scanner-frame points and their true georeferenced positions.

    ``records``: ``(scan, truth)`` record pairs of consecutive chunks (:func:`strip_records`).
    The truth file holds the *measured* point (with its range noise) georeferenced with the
    true trajectory, in the output CRS ``crs``, in the same order; ``range_error_m`` gives the
    noise, so the noiseless surface point is ``truth - range_error_m * beam direction``.
    ``tick(t_gps)`` after each chunk. Returns the number of points written.
    """
    n = 0
    with LasWriter(scan_path, scale=LAS_SCALE_M, offset=(0.0, 0.0, 0.0)) as scans, LasWriter(
        truth_path, scale=LAS_SCALE_M, crs=None if crs is None else crs.crs, extra_dims=[RANGE_ERROR_DIM]
    ) as truth:
        for scan_records, truth_records in records:
            if len(scan_records) == 0:
                continue
            scans.write(scan_records)
            truth.write(truth_records)
            n += len(scan_records)
            if tick is not None:
                tick(float(scan_records.time_gps[-1]))
    return n

