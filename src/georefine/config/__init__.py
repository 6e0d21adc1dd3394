"""Configuration: the ``project.yaml`` model (the YAML helpers are in :mod:`georefine.config.yaml_io`,
the lidargrammetry settings in :mod:`georefine.config.lidargrammetry`).

Every model forbids unknown keys (a typo is an error, never silently ignored), carries the
unit in each field name, and documents its default once, here. The resolved configuration is
written beside every output.

Angles of the scanner boresight ``R_b_s`` are given as roll, pitch, yaw in degrees with
``R_b_s = Rz(yaw) Ry(pitch) Rx(roll)`` (the same z-y-x order as the platform attitude).
Lever arms are in the body frame ``b`` (forward-right-down), metres.
"""

from __future__ import annotations

import posixpath
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import (
    Field,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import InitErrorDetails, PydanticCustomError

from georefine.config.base import StrictModel, Vector3
from georefine.config.crs import CrsConfig, ReferencePoint, check_output_epsg, check_vertical_epsg
from georefine.config.lidargrammetry import PAIR_KINDS, LidargrammetryConfig, PairKind
from georefine.config.yaml_io import (
    apply_overrides,
    deep_merge,
    override_fields,
    read_yaml,
    validate_model,
    write_yaml,
)
from georefine.errors import ConfigError

__all__ = [
    "ChannelConfig",
    "CrsConfig",
    "FilterConfig",
    "FlightConfig",
    "GnssCorrelatedError",
    "GnssFileConfig",
    "GnssMultipath",
    "ImuErrorSpec",
    "ImuFileConfig",
    "LidarAdjustmentConfig",
    "LidargrammetryConfig",
    "MatchingConfig",
    "PAIR_KINDS",
    "PairKind",
    "PhotosFileConfig",
    "PlaneExtractionConfig",
    "ProcessingConfig",
    "ProjectConfig",
    "ReferenceConfig",
    "ReferencePoint",
    "ScaleConfig",
    "ScannerFileConfig",
    "StrictModel",
    "TimeOffsetConfig",
    "TrajectoryAdjustmentConfig",
    "TrajectoryPriorConfig",
    "Vector3",
    "apply_overrides",
    "boresight_matrix",
    "check_output_epsg",
    "check_vertical_epsg",
    "deep_merge",
    "default_channels",
    "load_project",
    "override_fields",
    "read_yaml",
    "validate_model",
    "write_yaml",
]


class GnssCorrelatedError(StrictModel):
    """The time-correlated part of the GNSS position error (docs/ARCHITECTURE.md §4.3 GNSS).

    PPK and PPP position errors are not white: residual atmosphere, orbit and multipath errors
    last minutes. The adjustment models them as a first-order Gauss-Markov process per axis of
    ``w`` (east, north, up) with these stationary sigmas and correlation time; the ``.pos``
    sigmas are taken as the total, and their white part is what remains after this (at least
    ``min_white_fraction`` of them).
    """

    sigma_horizontal_m: float = Field(0.015, gt=0.0, description="Stationary sigma per horizontal axis (m).")
    sigma_up_m: float = Field(0.03, gt=0.0, description="Stationary sigma of the height (m).")
    time_constant_s: float = Field(300.0, gt=0.0, description="Correlation time (s).")
    min_white_fraction: float = Field(
        0.3, gt=0.0, le=1.0, description="The white sigma per axis is at least this fraction of the .pos sigma.")


class GnssMultipath(StrictModel):
    """Multipath: a short-correlated part of the GNSS position error (docs/ARCHITECTURE.md §4.3 GNSS).

    Signals reflected off the airframe, the wings in a bank and, low down, the ground make a
    position error of a centimetre or two that lasts tens of seconds: too quick for the
    correlated error's minutes (``gnss.correlated_error``), too slow to average out as white.
    Where stated, it is a second first-order Gauss-Markov process per axis of ``w``, on knots
    of its own (``processing.trajectory.gnss_error_knot_interval_s``, or a quarter of its
    correlation time where that is shorter), added to the correlated error; its variance too
    is taken off the ``.pos`` sigmas. Off (null) by default; the G/I/L warns when its correlated
    error fits its prior badly, which an unstated multipath does.
    """

    sigma_horizontal_m: float = Field(0.02, gt=0.0, description="Stationary sigma per horizontal axis (m).")
    sigma_up_m: float = Field(0.04, gt=0.0, description="Stationary sigma of the height (m).")
    time_constant_s: float = Field(20.0, gt=0.0, description="Correlation time (s).")


class GnssFloatOffset(StrictModel):
    """An offset per segment of GNSS epochs without a fixed solution (docs/ARCHITECTURE.md §4.3 GNSS).

    Epochs of RTKLIB quality worse than a fix (Q=2 float, and Q=3-6 where ``gnss.min_quality`` lets
    them in) are grouped into segments: consecutive such epochs, a fix or a gap longer than
    ``max_gap_s`` ending one. Each segment gets one offset in ``w`` (east, north, up) with this
    prior; its epochs keep their ``.pos`` sigma. A float solution's error is mostly one offset of
    decimetres while the ambiguities stay float, which the file's sigmas (often 5/5/10 cm) do not
    state and which, taken as white, the epochs of a minute averaged to millimetres.

    A wrong fix (``detect_jumps``) is the same error under ``Q=1``: the G/I's GNSS residuals step at
    its start and end (:mod:`georefine.adjustment.gnss_jumps`); fixed epochs found off their
    neighbours so get an offset of their own with this prior, and the G/I runs again once.
    """

    sigma_horizontal_m: float = Field(0.3, gt=0.0, description="Prior sigma of a segment's offset per horizontal axis (m).")
    sigma_up_m: float = Field(0.5, gt=0.0, description="Prior sigma of a segment's height offset (m).")
    max_gap_s: float = Field(10.0, gt=0.0, description="A longer gap between non-fix epochs starts a new segment (s).")
    detect_jumps: bool = Field(
        True, description="Search the G/I's GNSS residuals for fixed epochs that stand off their neighbours (a wrong "
        "ambiguity fix, which the file flags Q=1): each such run is warned of and gets an offset of its own, "
        "the G/I runs again once; false: fixed epochs are taken as they are.")
    jump_threshold_sigma: float = Field(
        6.0, gt=0.0, description="A step of the residuals counts where it exceeds this many of its own spread, "
        "as the norm over the three axes (the windowed mean difference's spread, which holds the residuals' "
        "correlation; 0 false alarms in 50 h of simulated residuals).")
    jump_window_s: float = Field(
        2.0, gt=0.0, description="Length of each of the two windows of residuals compared at an epoch (s).")


class GnssFileConfig(StrictModel):
    files: list[str] = Field(
        default_factory=list, description="RTKLIB .pos files, relative to the project folder (at least one; with "
        "flights, absent or empty: each flight lists its own gnss_files).")
    lever_arm_m: Vector3 = Field(description="Antenna phase centre in the body frame, p_b_a (m).")
    min_quality: int = Field(
        2, ge=1, le=6, description="Worst RTKLIB quality flag accepted (1 fix, 2 float, ... 6 PPP)."
    )
    format: Literal["pos", "sbet"] = Field(
        "pos", description="pos: RTKLIB solutions; sbet: the positions of a delivered SBET (one file, at the IMU: "
        "lever arm 0) observe the trajectory with the raw IMU (docs/ARCHITECTURE.md §4.9).")
    gps_week: int | None = Field(None, ge=0, description="format sbet: GPS week of the SBET (else its companion file).")
    smrmsg: str | None = Field(None, description="format sbet: its smrmsg accuracy file (else gnss.sbet_sigma_m).")
    sbet_rate_hz: float = Field(5.0, gt=0.0, le=50.0, description="format sbet: positions taken at this rate.")
    sbet_sigma_m: float = Field(0.05, gt=0.0, description="format sbet: position sigma without smrmsg (m).")
    correlated_error: GnssCorrelatedError | None = Field(
        default_factory=GnssCorrelatedError,
        description="The GNSS error that lasts minutes, estimated on its own knots "
        "(processing.trajectory.gnss_error_knot_interval_s); null: every epoch's error is white.")
    multipath: GnssMultipath | None = Field(
        None, description="The GNSS error that lasts tens of seconds (multipath), estimated on its own knots beside "
        "correlated_error, which it needs; null (the default): not modelled.")
    float_offset: GnssFloatOffset | None = Field(
        default_factory=GnssFloatOffset,
        description="An offset per segment of epochs worse than a fix (RTKLIB Q > 1), estimated with this prior; "
        "null: such epochs are taken as fixes with their .pos sigma.")

    @model_validator(mode="after")
    def _one_sbet(self) -> "GnssFileConfig":
        if self.format == "sbet" and len(self.files) > 1:  # none: ProjectConfig says the file is missing
            raise ValueError(f"format sbet takes one SBET file, got {len(self.files)}")
        if self.multipath is not None and self.correlated_error is None:
            raise ValueError("multipath is estimated beside correlated_error: state correlated_error too, or set "
                             "multipath to null")
        return self


class ImuErrorSpec(StrictModel):
    """IMU error specification in datasheet units (docs/ARCHITECTURE.md §4.3 IMU model).

    White noise: angle random walk (ARW) and velocity random walk (VRW). Biases: turn-on
    (constant per run, 1 sigma) plus an in-run random walk of density
    ``q = B sqrt(2 / tau)`` from the bias instability ``B`` over the correlation time ``tau``
    (``*_bias_correlation_time_s``). Scale factors: 1 sigma, constant. Misalignment: 1 sigma of
    each off-diagonal element of a triad's sensitivity matrix against the body frame, constant;
    0 (the default) where the datasheet states none.
    """

    gyro_arw_deg_per_sqrt_h: float = Field(ge=0.0)
    gyro_bias_instability_deg_per_h: float = Field(ge=0.0)
    gyro_turn_on_bias_deg_per_h: float = Field(ge=0.0)
    gyro_scale_factor_ppm: float = Field(ge=0.0)
    acc_vrw_m_per_s_per_sqrt_h: float = Field(ge=0.0)
    acc_bias_instability_ug: float = Field(ge=0.0)
    acc_turn_on_bias_ug: float = Field(ge=0.0)
    acc_scale_factor_ppm: float = Field(ge=0.0)
    gyro_bias_correlation_time_s: float = Field(3600.0, gt=0.0)
    acc_bias_correlation_time_s: float = Field(3600.0, gt=0.0)
    gyro_misalignment_mrad: float = Field(
        0.0, ge=0.0, description="Gyro triad misalignment and non-orthogonality, 1 sigma per off-diagonal element "
        "(mrad); > 0 lets processing.trajectory.estimate_misalignment 'auto' estimate it.")
    acc_misalignment_mrad: float = Field(0.0, ge=0.0, description="The same for the accelerometer triad (mrad).")
    gyro_g_sensitivity_deg_per_h_per_g: float = Field(
        0.0, ge=0.0, description="Gyro g-sensitivity ('linear acceleration effect'), 1 sigma per element of its 3 x 3 "
        "matrix (deg/h per g). Not estimated: in flight its effect is a near-constant bias that the turn-on bias "
        "takes (docs/ARCHITECTURE.md §4.3).")
    temperature_change_c: float = Field(
        0.0, description="The IMU's temperature change over the flight (deg C, e.g. its warm-up), with "
        "temperature_time_constant_s; with the temperature coefficients it widens the bias random walk "
        "(docs/ARCHITECTURE.md §4.3).")
    temperature_time_constant_s: float = Field(900.0, gt=0.0, description="Time constant of that change (s).")
    gyro_temperature_deg_per_h_per_c: float = Field(
        0.0, ge=0.0, description="Residual temperature coefficient of the gyro biases after the factory's "
        "compensation, 1 sigma per axis (deg/h per deg C).")
    acc_temperature_ug_per_c: float = Field(
        0.0, ge=0.0, description="The same for the accelerometer biases (micro-g per deg C).")

    def bias_random_walk_si(self, gyro_floor_deg_per_h: float = 0.0, acc_floor_ug: float = 0.0,
                            temperature_modelled: bool = False) -> tuple[float, float]:
        """The gyro (rad/s/sqrt(s)) and accelerometer (m/s^2/sqrt(s)) bias random-walk densities.

        ``q = B sqrt(2 / tau)`` from the bias instability ``B`` (at least the floor) over its
        correlation time, widened where a temperature change is stated: a bias that drifts by
        ``D = k dT`` (the coefficient times the change) as ``D (1 - exp(-t / tau_T))`` is one standard
        deviation of a random walk of density ``D / sqrt(2 tau_T)`` (its rate ``D / tau_T exp(-t / tau_T)``
        squared and integrated is ``D^2 / (2 tau_T)``, the walk's chi-square ``q^2`` per second); the two
        add in variance. A drift that is smooth, not random, is so covered without a temperature
        record (docs/ARCHITECTURE.md §4.3). ``temperature_modelled``: the adjustment estimates the
        coefficients against the unit's logged temperature, so the walk is not widened.
        """
        deg_per_h, ug = np.pi / 180.0 / 3600.0, 9.80665e-6
        q_g = max(self.gyro_bias_instability_deg_per_h, gyro_floor_deg_per_h) * deg_per_h * np.sqrt(
            2.0 / self.gyro_bias_correlation_time_s)
        q_a = max(self.acc_bias_instability_ug, acc_floor_ug) * ug * np.sqrt(2.0 / self.acc_bias_correlation_time_s)
        if temperature_modelled:
            return float(q_g), float(q_a)
        root_tau = np.sqrt(2.0 * self.temperature_time_constant_s)
        d_g = self.gyro_temperature_deg_per_h_per_c * abs(self.temperature_change_c) * deg_per_h / root_tau
        d_a = self.acc_temperature_ug_per_c * abs(self.temperature_change_c) * ug / root_tau
        return float(np.hypot(q_g, d_g)), float(np.hypot(q_a, d_a))


class ImuFileConfig(StrictModel):
    file: str | None = Field(
        None, description="IMU data file relative to the project folder (.csv or .imr); with flights, absent: each "
        "flight names its own imu_file.")
    format: Literal["csv", "imr"] = "csv"
    rate_hz: float = Field(200.0, gt=0.0, description="Nominal sample rate.")
    gps_week: int | None = Field(
        None, ge=0, description="GPS week of .imr files (their time tags are seconds of week)."
    )
    max_gap_s: float = Field(
        5.0, gt=0.0, description="Longest sampling gap bridged (s): the missing samples are interpolated, their "
        "uncertainty widened by the interpolation error measured around the gap; a longer gap is an error.",
    )
    errors: ImuErrorSpec


class ChannelConfig(StrictModel):
    id: int = Field(ge=0, le=3, description="LAS scanner_channel value.")
    name: str
    tilt_deg: float = Field(description="Nominal tilt of the view from nadir, positive forward.")


def default_channels() -> list[ChannelConfig]:
    return [
        ChannelConfig(id=0, name="nadir", tilt_deg=0.0),
        ChannelConfig(id=1, name="forward", tilt_deg=10.0),
        ChannelConfig(id=2, name="backward", tilt_deg=-10.0),
    ]


class ScannerFileConfig(StrictModel):
    files: list[str] = Field(
        default_factory=list, description="LAS/LAZ strips in the scanner frame s (at least one; with flights, absent "
        "or empty: each flight lists its own strips).")
    lever_arm_m: Vector3 = Field(description="Scanner origin in the body frame, p_b_s (m).")
    boresight_deg: Vector3 = Field(
        (0.0, 0.0, 0.0), description="Roll, pitch, yaw of R_b_s (deg), R_b_s = Rz(y) Ry(p) Rx(r)."
    )
    range_sigma_m: float = Field(0.005, gt=0.0)
    channels: list[ChannelConfig] = Field(default_factory=default_channels)
    time_offset_s: float = Field(
        0.0, ge=-86400.0, le=86400.0,
        description="Added to the strips' gps_time to give the navigation's GPS time (s): 18 for time stamps in UTC "
        "(GPS - UTC since 2017). processing.lidar.time_offset searches and estimates a correction; the output strips "
        "carry the corrected times.",
    )

    @field_validator("channels")
    @classmethod
    def _unique_channels(cls, v: list[ChannelConfig]) -> list[ChannelConfig]:
        ids = [c.id for c in v]
        if len(set(ids)) != len(ids):
            raise ValueError(f"channel ids must be unique, found {ids}")
        return v


def _same_file(path: str) -> str:
    """A file name as the flights' rules compare them (``scans/./a.laz`` is ``scans/a.laz``)."""
    return posixpath.normpath(path.replace("\\", "/"))


class FlightConfig(StrictModel):
    """One flight (sortie) of a project flown in several (docs/ARCHITECTURE.md §3): one take-off's GNSS, IMU
    record and strips.

    Each flight has its own IMU record (its own static alignment and turn-on biases). The scanner's
    calibration and the sensors' specifications are those of the sections ``gnss``, ``imu`` and
    ``scanner``, shared by all flights; a flight that states one of the optional values below
    overrides the shared one for its own data only (a scanner remounted between flights, a
    different IMU format).
    """

    id: int = Field(ge=0, description="The flight's number, unique in the project.")
    name: str | None = Field(None, min_length=1, description="A label, unique in the project (default flight_<id>).")
    gnss_files: list[str] = Field(min_length=1, description="The flight's RTKLIB .pos files, relative to the project "
                                  "folder (several are joined in time, as gnss.files).")
    imu_file: str = Field(description="The flight's IMU record relative to the project folder (.csv or .imr).")
    imu_format: Literal["csv", "imr"] | None = Field(None, description="Its format, if not imu.format.")
    imu_rate_hz: float | None = Field(None, gt=0.0, description="Its nominal sample rate, if not imu.rate_hz.")
    imu_gps_week: int | None = Field(None, ge=0, description="GPS week of an .imr record, if not imu.gps_week.")
    strips: list[str] = Field(min_length=1, description="The flight's LAS/LAZ strips in the scanner frame s.")
    gnss_lever_arm_m: Vector3 | None = Field(None, description="p_b_a of this flight (m), if not gnss.lever_arm_m.")
    scanner_lever_arm_m: Vector3 | None = Field(
        None, description="p_b_s of this flight (m), if not scanner.lever_arm_m.")
    boresight_deg: Vector3 | None = Field(
        None, description="Roll, pitch, yaw of R_b_s of this flight (deg), if not scanner.boresight_deg.")
    scanner_time_offset_s: float | None = Field(
        None, ge=-86400.0, le=86400.0, description="The strips' time offset (s), if not scanner.time_offset_s.")

    @property
    def label(self) -> str:
        """``name``, or ``flight_<id>``."""
        return self.name if self.name is not None else f"flight_{self.id}"

    @field_validator("strips", "gnss_files")
    @classmethod
    def _no_repeats(cls, v: list[str]) -> list[str]:
        seen = [_same_file(f) for f in v]
        twice = sorted({f for f in seen if seen.count(f) > 1})
        if twice:
            raise ValueError(f"each file once: {', '.join(twice)} listed more than once")
        return v


class TrajectoryPriorConfig(StrictModel):
    """A delivered trajectory instead of raw GNSS and IMU (docs/ARCHITECTURE.md §4.9).

    The SBET a GNSS/IMU post-processor wrote (POSPac, Inertial Explorer) and its ``smrmsg``
    accuracy file; ``georefine import-strips`` writes this section. The SBET's error is modelled
    as a first-order Gauss-Markov process with the ``smrmsg`` sigmas
    (:mod:`georefine.adjustment.trajectory_prior`).
    """

    sbet: str = Field(description="SBET file relative to the project folder (times: seconds of the GPS week).")
    smrmsg: str | None = Field(None, description="Its smrmsg accuracy file; without it the default sigmas below.")
    gps_week: int = Field(ge=0, description="GPS week of the SBET's first record.")
    correlation_time_s: float = Field(
        300.0, gt=0.0,
        description="Correlation time of the SBET's position and heading error (an INS/GNSS heading error lasts minutes).")
    tilt_correlation_time_s: float = Field(
        30.0, gt=0.0,
        description="Correlation time of its roll and pitch error (levelled by the GNSS: it wanders in seconds).")
    error_knot_interval_s: float = Field(0.5, gt=0.0, description="Knot spacing of the piecewise-linear error.")
    sigma_scale: float = Field(1.0, gt=0.0, description="Factor on the smrmsg (or default) sigmas.")
    default_sigma_position_m: float = Field(0.05, gt=0.0, description="Position sigma without smrmsg.")
    default_sigma_roll_pitch_deg: float = Field(0.005, gt=0.0, description="Roll and pitch sigma without smrmsg.")
    default_sigma_heading_deg: float = Field(0.01, gt=0.0, description="Heading sigma without smrmsg.")
    white_sigma_position_m: float = Field(
        0.002, gt=0.0, description="Sigma of the SBET's short-term noise about the spline plus error.")
    white_sigma_attitude_mdeg: float = Field(1.0, gt=0.0, description="The same for the attitude.")


class ReferenceConfig(StrictModel):
    surfaces: str | None = Field(None, description="Reference surfaces CSV (evaluation only).")


class FilterConfig(StrictModel):
    """Initialisation filter settings (defaults for a helicopter/aircraft survey flight)."""

    covariance_rate_hz: float = Field(20.0, gt=0, description="covariance propagation (filter epochs)")
    gnss_gate_probability: float = Field(
        0.9999, gt=0, le=1, description="chi-square (3 dof) gate; 1 disables gating")
    gnss_gate_reset_s: float = Field(10.0, gt=0, description="open the gate after this long rejected")
    gnss_sigma_scale: float = Field(1.0, gt=0, description="factor on the reported GNSS sigmas")
    alignment_speed_mps: float = Field(5.0, gt=0, description="horizontal speed for heading alignment")
    alignment_hold_s: float = Field(1.0, ge=0, description="speed must stay above the threshold")
    static_window_s: float = Field(8.0, gt=0, description="levelling window at the start")
    static_max_speed_mps: float = Field(0.05, gt=0, description="GNSS speed below which at rest")
    initial_velocity_sigma_mps: float = Field(0.3, gt=0)
    initial_tilt_sigma_deg: float = Field(2.0, gt=0, description="roll/pitch after in-motion alignment")
    coarse_window_s: float = Field(2.0, gt=0, description="GNSS/IMU window of the in-motion alignment")
    levelling_sigma_deg: float = Field(0.005, gt=0, description="levelling error beyond the acc bias")
    initial_heading_sigma_deg: float = Field(10.0, gt=0, description="after in-motion alignment")
    gyro_arw_floor_deg_per_sqrt_h: float = Field(0.002, gt=0)
    acc_vrw_floor_m_per_s_per_sqrt_h: float = Field(0.002, gt=0)
    gyro_bias_floor_deg_per_h: float = Field(0.003, gt=0, description="turn-on and instability floor")
    acc_bias_floor_ug: float = Field(10.0, gt=0, description="turn-on and instability floor")
    estimate_scale_factors: bool = Field(True, description="else the scale factors are held at 0")
    scale_factor_floor_ppm: float = Field(1.0, gt=0, description="prior floor when estimated")


class PlaneExtractionConfig(StrictModel):
    """Planar feature extraction per view (defaults: helicopter ALS, ~5-10 points/m² per view)."""

    seed_spacing_m: float = Field(2.0, gt=0, description="horizontal seed grid in x, y of w")
    seed_layer_m: float = Field(2.0, gt=0, description="height of the seed layers of a column (facades)")
    radius_m: float = Field(1.0, gt=0, description="3-D neighbourhood radius around the seed point")
    min_points: int = Field(10, ge=4, description="points in the neighbourhood")
    max_roughness_m: float = Field(0.02, gt=0, description="sqrt of the smallest PCA eigenvalue")
    max_linearity: float = Field(0.8, gt=0, le=1, description="(l1 - l2)/l1; rejects wires, edges")
    min_extent_m: float = Field(0.5, ge=0, description="2 sqrt(l2): smaller in-plane extent")
    max_time_span_s: float = Field(
        0.5, gt=0, description="last minus first point time of a patch; time tiles overlap by twice this")
    range_sigma_m: float = Field(0.005, gt=0, description="ranging noise, floor of the point scatter")
    min_sigma_d_m: float = Field(0.001, ge=0, description="floor of the normal-distance sigma")
    min_sigma_slope_mdeg: float = Field(30.0, ge=0, description="floor of the slope sigma")


class MatchingConfig(StrictModel):
    """Matching of planar features into planar objects (rules in the module docstring)."""

    max_centre_distance_m: float = Field(1.5, gt=0.0, description="Search radius between feature centres.")
    max_normal_angle_deg: float = Field(3.0, gt=0.0, lt=90.0, description="Normals agree up to sign within this.")
    max_plane_distance_m: float = Field(
        0.3, gt=0.0, description="Distance of each centre to the other feature's plane (and to the object plane)."
    )
    cross_view_only: bool = Field(True, description="Match only features of different views (strip, channel).")
    max_object_radius_m: float = Field(
        3.0, gt=0.0, description="Anti-chaining: members lie within this of the object centre c0."
    )
    max_features_per_object: int = Field(12, ge=2)
    balance_cell_m: float = Field(
        25.0, gt=0.0,
        description="Cell size of the balancing. Fewer, well-spread objects keep the normal equations sparse: "
        "every object couples the knots of all times it was seen at.",
    )
    max_objects_per_cell: int = Field(3, ge=1)
    min_views_per_object: int = Field(2, ge=1)
    vertical_max_tilt_deg: float = Field(
        20.0, gt=0.0, lt=90.0, description="Planes within this angle of vertical are vertical objects (facades)."
    )


class TimeOffsetConfig(StrictModel):
    """The LiDAR's time offset against the navigation (docs/ARCHITECTURE.md §4.5)."""

    search: bool = Field(
        True, description="Before the first G/I/L adjustment, search the offset at which the strips agree best "
        "(whole seconds included: UTC time stamps, leap seconds) and go on from it if it is clearly better than "
        "scanner.time_offset_s, with a warning. Needs strips flown in different directions.",
    )
    search_range_s: float = Field(20.0, gt=0.0, le=120.0, description="Candidates within scanner.time_offset_s ± this.")
    estimate: bool = Field(True, description="Estimate the offset in the G/I/L adjustment (one parameter).")
    prior_sigma_s: float = Field(
        0.005, gt=0.0, description="Prior sigma of the estimated offset around scanner.time_offset_s (or the "
        "search's result).",
    )
    warn_ms: float = Field(
        0.5, gt=0.0, description="Warn when the estimate differs from scanner.time_offset_s by more than this and "
        "three sigmas (the adjustment's and what GNSS errors lasting a pass add): the configuration should state it.",
    )


class LidarAdjustmentConfig(StrictModel):
    """GNSS/IMU/LiDAR adjustment and its outer iterations (docs/ARCHITECTURE.md §4.5 steps 3-6)."""

    outer_iterations: int = Field(3, ge=1, le=10, description="Re-georeference, re-extract, re-match, re-adjust.")
    convergence_attitude_mdeg: float = Field(
        1.5, gt=0.0, description="Stop when the RMS attitude change (over the knots) between outer iterations "
        "is below this. Re-extracted and re-matched features alone move the corridor solution by about 1 mdeg RMS "
        "without changing its accuracy (measured), so a tighter threshold only adds iterations.",
    )
    convergence_position_m: float = Field(0.005, gt=0.0, description="... and the RMS position change below this.")
    first_knot_interval_s: float | None = Field(
        0.25, gt=0.0, le=1.0,
        description="The first outer iteration adjusts a trajectory with knots about this far apart (IMU windows "
        "in proportion) when that is coarser than processing.trajectory.knot_interval_s and more outer "
        "iterations may follow; the later ones use the configured knots, and it never ends the outer iterations. "
        "It starts from the G/I trajectory, tens of mdeg away, and only has to bring it near enough to "
        "re-extract and re-match: on coarse knots its Cauchy reweighting converges in fewer and much cheaper "
        "iterations (BENCHMARKS.md, Flight length). Not on a vibrating platform (up-sampling found vibration): "
        "there the coarse knots would alias it into the trajectory. null: every outer iteration on the "
        "configured knots.",
    )
    plane_loss: Literal["cauchy", "huber", "none"] = "cauchy"
    plane_loss_scale: float = Field(2.0, gt=0.0, description="Cauchy c / Huber delta in units of sigma.")
    estimate_boresight: bool = Field(False, description="Estimate the scanner boresight (needs two passes).")
    strip_baseline: bool = Field(
        True, description="Also run the classical strip adjustment (a rotation and translation per strip) from the "
        "first outer iteration's planes, as a baseline: RUN/baseline/ (docs/ARCHITECTURE.md §4.5).")
    boresight_prior_deg: float = Field(0.1, gt=0.0, description="Prior sigma of the boresight angles when estimated.")
    estimate_range_calibration: bool = Field(
        False, description="Estimate the scanner's range offset and scale error (the unit reads (1 + k) r + r0 of a "
        "range r; docs/ARCHITECTURE.md §4.3) from the planes, as RiPROCESS and TerraMatch calibrate them; the "
        "final points are corrected with them. Several flights share one; not in the hybrid adjustment.")
    range_offset_prior_m: float = Field(0.05, gt=0.0, description="Prior sigma of the range offset r0 (m).")
    range_scale_prior_ppm: float = Field(200.0, gt=0.0, description="Prior sigma of the range scale error k (ppm).")
    estimate_channel_angles: bool = Field(
        False, description="Estimate each scanner channel's facet-tilt and scan-angle error against channel 0's (its "
        "beams leave at angles the unit does not record; docs/ARCHITECTURE.md §4.3) from the planes, as RiPROCESS and "
        "TerraMatch calibrate a mirror's facets; the final points are corrected with them. Channel 0's own errors are "
        "the boresight's (estimate_boresight). Several flights share one; not in the hybrid adjustment.")
    channel_angle_prior_mdeg: float = Field(
        20.0, gt=0.0, description="Prior sigma of each channel's tilt and scan-angle error (mdeg).")
    estimate_encoder_error: bool = Field(
        False, description="Estimate the scan-angle encoder's error across the field of view, the same on every "
        "channel (four Legendre terms of the scan angle; docs/ARCHITECTURE.md §4.3), from the planes; the final "
        "points are corrected with it. Its mean over the field of view is the boresight's roll "
        "(estimate_boresight). Several flights share one; not in the hybrid adjustment.")
    encoder_error_prior_mdeg: float = Field(
        20.0, gt=0.0, description="Prior sigma of each of the encoder error's four terms (mdeg).")
    check_scanner_calibration: bool = Field(
        True, description="After the last outer iteration, solve its G/I/L once more with the range calibration, "
        "channel angles, encoder error and boresight it leaves out, and once more with a range bias growing with the "
        "incidence angle, and warn where one is significant (5 sigma) and moves the points by more than 2 mm (docs/ARCHITECTURE.md §4.5 step 5): one more "
        "G/I/L solve. Not applied; one flight.")
    time_offset: TimeOffsetConfig = Field(default_factory=TimeOffsetConfig)
    max_features: int = Field(
        200_000, ge=100, description="Ceiling on matched features in the adjustment, which today's solver needs to "
        "bound its memory on long flights: the windows of selection_window_s share it evenly (each the same budget, "
        "a window with fewer features leaving its room to the others), as whole objects.",
    )
    max_features_per_minute: int = Field(
        20_000, ge=100, description="Budget of matched features per minute of flight: in every window of "
        "selection_window_s at most this many (pro rata) are taken, as whole objects, those seen from more strips "
        "first, then facades, then by a min-hash that keeps the same ones in every outer iteration as far as the "
        "re-matching allows (lidar/feature_sample.py).",
    )
    selection_window_s: float = Field(
        60.0, gt=0.0, description="Window of flight time over which max_features_per_minute applies.")

    @property
    def window_budget(self) -> int:
        """Matched features taken at most per window of ``selection_window_s`` (before ``max_features``)."""
        return max(1, round(self.max_features_per_minute * self.selection_window_s / 60.0))

    function_tolerance: float = Field(
        1e-3, gt=0.0,
        description="Stop the G/I/L Levenberg-Marquardt when an iteration lowers the cost by less than this "
        "fraction. Under the Cauchy loss the last per-mille of the cost comes slowly (IRLS converges linearly) "
        "and moved roll/pitch/yaw RMSE by less than 0.01 mdeg on corridor-tiny (10 against 25 iterations); "
        "the next outer iteration starts from the result anyway. Where the variance factor exceeds 1 the fraction "
        "is of the cost divided by it: misfit the model cannot remove (vibration left in the IMU windows) must "
        "not loosen the test (docs/ARCHITECTURE.md §4.4).",
    )
    initial_lambda: float = Field(
        1e-9, gt=0.0,
        description="Initial Levenberg-Marquardt damping of the G/I/L adjustment, relative to diag(N). Planes "
        "see every pass's pitch only together with its climb rate; a tilt of the whole scene (pitch and climb "
        "rate of all passes at once) they cannot see, and the GNSS/IMU hold it with an eigenvalue far below "
        "the diagonal. From the solver's general 1e-4, divided by at most 3 per step, that direction barely "
        "moved before the cost-change test stopped: a navigation-grade corridor kept a 0.3 mdeg world tilt "
        "the G/I did not have (pitch error/sigma 2.3). From 1e-9 the same outer iterations end at 0.01-0.03 mdeg "
        "in about as many steps (docs/ARCHITECTURE.md §4.4).",
    )


class TrajectoryAdjustmentConfig(StrictModel):
    """GNSS/IMU(/LiDAR) adjustment of the spline trajectory (docs/ARCHITECTURE.md §4.2-4.4, §4.6)."""

    knot_interval_s: float = Field(0.1, gt=0.0, le=1.0, description="Spline knot spacing.")
    imu_window_s: float = Field(
        0.02, gt=0.0, le=1.0, description="IMU samples are averaged over windows of this length (down-sampling)."
    )
    gnss_imu_knot_interval_s: float | None = Field(
        0.4, gt=0.0, le=1.0,
        description="Knot spacing of the GNSS/IMU adjustment (step 2) and of the trajectory it delivers; the "
        "G/I/L and the hybrid adjustment use knot_interval_s. Alone, the GNSS/IMU adjustment does not notice "
        "coarser knots: roll/pitch/yaw on the corridor at 0.4 s / 0.1 s within 1 % of 0.1 s / 0.02 s (yaw "
        "1 % lower) at a quarter of the unknowns, the motion faster than the knots rebuilt by up-sampling "
        "(BENCHMARKS.md, IMU down- and up-sampling; Georefine against gtsam). null: knot_interval_s.",
    )
    gnss_imu_window_s: float | None = Field(
        0.1, gt=0.0, le=1.0,
        description="IMU window of the GNSS/IMU adjustment (with gnss_imu_knot_interval_s). null: imu_window_s.",
    )
    quadrature_nodes: int = Field(
        3, ge=1, le=5, description="Nodes per IMU window: Gauss-Legendre over a window of increments, the "
        "discrete Gauss rule over the samples of a window of rates; one fewer where that moves no window "
        "mean by more than 0.01 of its sigma at the adjustment's start (docs/ARCHITECTURE.md §4.6).")
    upsampling: bool = Field(
        True,
        description="Rebuild the motion faster than the knots from the raw, error-corrected IMU and "
        "georeference with it (up-sampling, docs/ARCHITECTURE.md §4.6).",
    )
    upsampling_iterations: int = Field(
        2, ge=0, le=5,
        description="With upsampling: times the G/I adjustment is solved again with the rebuilt "
        "high-frequency motion taken out of the IMU windows (each G/I/L outer iteration does so anyway). "
        "Two: the first re-solve's windows are cleaned with the motion rebuilt from a spline that "
        "followed the raw windows' aliased vibration, and keep part of it; the second's fit as the "
        "G/I/L's do, so the G/I's variance factor measures the sensors, not that leftover.",
    )
    bias_knot_interval_s: float = Field(10.0, gt=0.0, description="Knot spacing of the piecewise-linear biases.")
    gnss_error_knot_interval_s: float = Field(
        5.0, gt=0.0, description="Knot spacing of the piecewise-linear correlated GNSS error (gnss.correlated_error).")
    estimate_scale_factors: bool = True
    estimate_misalignment: Literal["auto"] | bool = Field(
        "auto",
        description="Estimate each IMU triad's misalignment and non-orthogonality (six off-diagonal elements per "
        "triad, docs/ARCHITECTURE.md §4.3) with the datasheet's imu.errors.*_misalignment_mrad as prior. auto: "
        "where the datasheet states one; true with none stated: misalignment_prior_mrad. The rotation common to "
        "both triads is a turn of the whole IMU, which GNSS and IMU cannot tell from attitude: in the G/I its "
        "prior widens the attitude sigma, in the G/I/L the planes observe it through the scanner.")
    estimate_temperature_coefficients: Literal["auto"] | bool = Field(
        "auto",
        description="Estimate the biases' temperature coefficients (three per triad: b += k (T - T_first)) against "
        "the temperature the IMU file logs (its temperature_c column), with the datasheet's "
        "imu.errors.*_temperature_* as prior. auto: where the file logs a temperature and the datasheet states a "
        "coefficient; true: wherever the file logs one (temperature_prior_* where the datasheet states none). "
        "Estimated, the bias random walk is not widened for the temperature change.")
    temperature_prior_gyro_deg_per_h_per_c: float = Field(
        0.1, gt=0.0, description="Prior sigma of the gyro coefficients where the datasheet states none.")
    temperature_prior_acc_ug_per_c: float = Field(
        10.0, gt=0.0, description="Prior sigma of the accelerometer coefficients where the datasheet states none.")
    misalignment_prior_mrad: float = Field(
        1.0, gt=0.0, description="Prior sigma of the misalignment where estimate_misalignment is true and the "
        "datasheet states none (mrad; MEMS datasheets give up to 1).")
    gnss_loss: Literal["huber", "cauchy", "none"] = "huber"
    gnss_loss_scale: float = Field(3.0, gt=0.0, description="Huber delta / Cauchy c in units of sigma.")
    max_iterations: int = Field(30, ge=1)
    linear_solver: Literal["auto", "cholmod", "cvxopt", "qdldl", "cholespy", "scipy"] = Field(
        "auto",
        description="Sparse Cholesky backend of the trajectory adjustments (docs/ARCHITECTURE.md §4.4): auto takes "
        "scikit-sparse's CHOLMOD, CVXOPT's (the fast extra), QDLDL (installed), cholespy, SciPy, the first installed; "
        "for the G/I and the delivered trajectory, whose factors are narrow, QDLDL.",
    )
    initial_lambda: float = Field(
        1e-9, gt=0.0,
        description="Initial Levenberg-Marquardt damping of the G/I adjustment, relative to diag(N). The "
        "adjustment starts from the smoother and is near-linear: the solver's general 1e-4, divided by at most "
        "3 per step, held heading (the weak direction of straight flight, whose eigenvalue is far below the "
        "diagonal) back for 9 iterations on the corridor, and the cost-change test could stop it early; 1e-9 "
        "takes 2 (2.4x faster) to a lower cost.",
    )
    function_tolerance: float = Field(
        1e-5, gt=0.0,
        description="Stop when an iteration lowers the cost by less than this fraction (1e-5 of a cost of "
        "~1e5 is far below one unit of chi-square) of the cost, divided by the variance factor where that exceeds "
        "1 (docs/ARCHITECTURE.md §4.4).",
    )
    covariance_interval_s: float = Field(
        5.0, gt=0.0, description="Posterior roll/pitch/yaw sigma are computed at knots this far apart ..."
    )
    variance_components: bool = Field(
        True,
        description="Posterior sigma with a variance factor for the planes and one for the navigation sensors "
        "(GNSS, IMU, their priors and random walks), each floored at 1, instead of one factor for all "
        "(georefine.adjustment.gnss_imu.POSTERIOR_POOLS, docs/ARCHITECTURE.md §4.4).",
    )
    max_covariance_knots: int = Field(
        150, ge=2,
        description="... but at no more knots than this (each costs a solve of the whole system, so the "
        "covariance cost stays linear in the flight duration).",
    )
    min_gyro_noise_deg_per_sqrt_h: float = Field(
        0.001, gt=0.0, description="Floor of the gyro ARW used for weighting (an ideal IMU spec is all zeros)."
    )
    min_acc_noise_m_per_s_per_sqrt_h: float = Field(0.0005, gt=0.0, description="Floor of the VRW used for weighting.")
    min_gyro_bias_rw_deg_per_h_per_sqrt_h: float = Field(0.001, gt=0.0, description="Floor of the gyro bias random walk.")
    min_acc_bias_rw_ug_per_sqrt_h: float = Field(1.0, gt=0.0, description="Floor of the accelerometer bias random walk.")
    min_turn_on_gyro_deg_per_h: float = Field(0.01, gt=0.0, description="Floor of the gyro turn-on bias prior.")
    min_turn_on_acc_ug: float = Field(10.0, gt=0.0, description="Floor of the accelerometer turn-on bias prior.")
    min_scale_factor_ppm: float = Field(1.0, gt=0.0, description="Floor of the scale-factor prior.")

    @model_validator(mode="after")
    def _enough_imu_windows(self) -> "TrajectoryAdjustmentConfig":
        # The quintic position spline has 3 free states per axis and knot interval, the
        # orientation spline 2; each IMU window observes one value per axis. With fewer than
        # four windows per interval (GNSS adds < 1) the normal equations are singular.
        for knot, window, names in (
            (self.knot_interval_s, self.imu_window_s, ("knot_interval_s", "imu_window_s")),
            (self.gnss_imu().knot_interval_s, self.gnss_imu().imu_window_s,
             ("gnss_imu_knot_interval_s", "gnss_imu_window_s")),
        ):
            if knot < 4.0 * window - 1e-12:
                raise ValueError(
                    f"{names[1]} ({window}) must be at most a quarter of {names[0]} "
                    f"({knot}): each knot interval needs >= 4 IMU windows"
                )
        return self

    def gnss_imu(self) -> "TrajectoryAdjustmentConfig":
        """This configuration with the GNSS/IMU adjustment's knots and windows as ``knot_interval_s``
        and ``imu_window_s`` (what step 2 builds its problem with)."""
        upd = {}
        if self.gnss_imu_knot_interval_s is not None:
            upd["knot_interval_s"] = self.gnss_imu_knot_interval_s
        if self.gnss_imu_window_s is not None:
            upd["imu_window_s"] = self.gnss_imu_window_s
        return self.model_copy(update=upd) if upd else self


class ScaleConfig(StrictModel):
    """Bounded memory of the per-point stages (docs/ARCHITECTURE.md §4.7).

    Strips are cut into time tiles sized so that the tiles in work at once -- one per task slot
    of the scheduler -- fit ``memory_budget_gb`` together, whatever the number of points.
    """

    memory_budget_gb: float = Field(3.0, gt=0, description="memory of the point tiles in work at once (all tasks)")
    min_tile_points: int = Field(500_000, ge=10_000, description="smallest time tile (records), whatever the budget")
    feature_tile_m: float | None = Field(
        200.0, gt=0,
        description="Planar features go to disk in ground tiles of this side (m, rounded to whole "
        "processing.matching.balance_cell_m) and each tile is matched on its own with a margin that settles its "
        "objects: memory holds a tile, not the flight's features, and the objects are the whole flight's. null: "
        "match the whole flight's features held at once (the same objects; memory grows with the flight).",
    )


class ProcessingConfig(StrictModel):
    """Processing options (all optional; defaults documented in each model)."""

    scale: ScaleConfig = Field(default_factory=ScaleConfig)
    filter: FilterConfig = Field(default_factory=FilterConfig)
    trajectory: TrajectoryAdjustmentConfig = Field(default_factory=TrajectoryAdjustmentConfig)
    planes: PlaneExtractionConfig = Field(default_factory=PlaneExtractionConfig)
    matching: MatchingConfig = Field(default_factory=MatchingConfig)
    lidar: LidarAdjustmentConfig = Field(default_factory=LidarAdjustmentConfig)
    lidargrammetry: LidargrammetryConfig = Field(default_factory=LidargrammetryConfig)


class PhotosFileConfig(StrictModel):
    """Aerial photos of the project (optional; docs/ARCHITECTURE.md §3): files relative to the project folder."""

    folder: str = Field("photos", description="Folder of the image files named in eop.csv.")
    cameras: str = Field("photos/cameras.yaml", description="Interior orientation (georefine.io.photos).")
    eop: str = Field("photos/eop.csv", description="Approximate exterior orientation, output CRS.")
    gcp: str | None = Field("photos/gcp.csv", description="Control and check points, output CRS.")
    image_points: str | None = Field("photos/image_points.csv", description="Image measurements of the points.")


def _rule_error(loc: tuple[str | int, ...], message: str, found: object) -> ValidationError:
    """The error of a rule between sections, placed at the field it is about (``loc``), so that the
    :class:`ConfigError` names that field and its line in ``project.yaml``."""
    return ValidationError.from_exception_data("ProjectConfig", [InitErrorDetails(
        type=PydanticCustomError("project_rule", "{message}", {"message": message}), loc=loc,
        input={} if found is None else found)])  # a mapping is not printed as found (validate_model)


class ProjectConfig(StrictModel):
    """``project.yaml``: where the sensor files are and how the system is built.

    One flight: its files are ``gnss.files``, ``imu.file`` and ``scanner.files``. Several flights
    (``flights``): each lists its own GNSS files, IMU record and strips, and those three fields
    are absent; the rest of ``gnss``, ``imu`` and ``scanner`` is shared by the flights
    (:meth:`flight_config`).
    """

    name: str = "project"
    crs: CrsConfig = Field(default_factory=CrsConfig)
    gnss: GnssFileConfig | None = None
    imu: ImuFileConfig | None = None
    trajectory: TrajectoryPriorConfig | None = None
    scanner: ScannerFileConfig
    flights: list[FlightConfig] | None = Field(
        None, min_length=1, description="The flights of a project flown in several (docs/ARCHITECTURE.md §3); "
        "null: one flight, made of gnss.files, imu.file and scanner.files.")
    reference: ReferenceConfig = Field(default_factory=ReferenceConfig)
    photos: PhotosFileConfig | None = None
    processing: ProcessingConfig = Field(default_factory=ProcessingConfig)

    @model_validator(mode="after")
    def _navigation_source(self) -> "ProjectConfig":
        """Raw GNSS and IMU, or a delivered trajectory (docs/ARCHITECTURE.md §3, §4.9); the files of
        one flight, or the list of flights."""
        raw = (self.gnss is not None, self.imu is not None)
        if self.trajectory is None and not all(raw):
            missing = " and ".join(k for k, have in zip(("gnss", "imu"), raw) if not have)
            raise ValueError(f"section {missing} missing: a project needs gnss and imu, or a delivered trajectory "
                             "(section trajectory: sbet, smrmsg, gps_week)")
        if self.trajectory is not None and any(raw) and not all(raw):
            raise ValueError("a delivered trajectory with only one of gnss and imu: give neither (the SBET is adjusted) "
                             "or both (the trajectory section is then not used; with the raw IMU, gnss.format: sbet "
                             "takes the SBET's positions)")
        if self.flights is None:
            self._one_flight_files()
        else:
            self._check_flights()
        return self

    def _one_flight_files(self) -> None:
        if self.gnss is not None and not self.gnss.files:
            raise _rule_error(("gnss", "files"), "no GNSS file: list the .pos files here (at least one), or the "
                              "project's flights under flights, each with its gnss_files", self.gnss.files)
        if self.imu is not None and self.imu.file is None:
            raise _rule_error(("imu", "file"), "no IMU file: name it here, or list the project's flights under "
                              "flights, each with its imu_file", None)
        if not self.scanner.files:
            raise _rule_error(("scanner", "files"), "no strip: list the LAS/LAZ files here (at least one), or the "
                              "project's flights under flights, each with its strips", self.scanner.files)

    def _check_flights(self) -> None:
        assert self.flights is not None
        if self.gnss is None or self.imu is None:
            raise _rule_error(("flights",), "flights need the sections gnss and imu (the values the flights share: "
                              "lever arm, quality, IMU errors); a delivered trajectory (section trajectory) is one "
                              "flight, without a flights list", None)
        both = "given both here and under flights: with flights, each flight lists its own {}, and {} is absent " \
               "or empty (the section keeps the values the flights share)"
        if self.gnss.files:
            raise _rule_error(("gnss", "files"), "GNSS files " + both.format("gnss_files", "gnss.files"),
                              self.gnss.files)
        if self.imu.file is not None:
            raise _rule_error(("imu", "file"), "IMU file " + both.format("imu_file", "imu.file"), self.imu.file)
        if self.scanner.files:
            raise _rule_error(("scanner", "files"), "strips " + both.format("strips", "scanner.files"),
                              self.scanner.files)
        if self.gnss.format == "sbet":
            raise _rule_error(("gnss", "format"), "gnss.format sbet takes the one delivered SBET of a single-flight "
                              "project: with flights, each flight's gnss_files are RTKLIB .pos files (format pos)",
                              self.gnss.format)
        ids: dict[int, int] = {}
        labels: dict[str, int] = {}
        strips: dict[str, int] = {}
        for k, f in enumerate(self.flights):
            if f.id in ids:
                raise _rule_error(("flights", k, "id"), f"flight id {f.id} is also that of flights.{ids[f.id]}: each "
                                  "flight has its own id", f.id)
            ids[f.id] = k
            if f.label in labels:
                raise _rule_error(("flights", k, "name"), f"flight name {f.label!r} is also that of "
                                  f"flights.{labels[f.label]}: each flight has its own name", f.name)
            labels[f.label] = k
            for j, rel in enumerate(f.strips):
                other = strips.get(_same_file(rel))
                if other is not None:
                    raise _rule_error(("flights", k, "strips", j), f"strip {rel} is also listed in flight "
                                      f"{self.flights[other].id} (flights.{other}.strips): each strip belongs to "
                                      "exactly one flight", rel)
                strips[_same_file(rel)] = k

    @property
    def delivered_trajectory(self) -> bool:
        """True when the project has no raw GNSS/IMU and adjusts the delivered SBET (§4.9)."""
        return self.gnss is None

    @property
    def multi_flight(self) -> bool:
        """True when ``project.yaml`` lists its flights (``flights``), even a single one."""
        return self.flights is not None

    @property
    def flight_ids(self) -> tuple[int, ...]:
        """The ids of the project's flights in the order listed; ``(1,)`` for a project without ``flights``."""
        return (1,) if self.flights is None else tuple(f.id for f in self.flights)

    def flight(self, flight_id: int) -> FlightConfig:
        """The entry of ``flights`` with this id.

        Raises
        ------
        ConfigError
            No ``flights`` list, or no flight with this id.
        """
        for f in self.flights or ():
            if f.id == flight_id:
                return f
        raise ConfigError("no such flight", field="flights",
                          expected="one of the ids " + ", ".join(map(str, self.flight_ids)), found=repr(flight_id))

    def flight_config(self, flight_id: int) -> "ProjectConfig":
        """The configuration of one flight as a single-flight project: its GNSS files, IMU record and
        strips as ``gnss.files``, ``imu.file`` and ``scanner.files``, the flight's own calibration
        where it states one and the shared values elsewhere, no ``flights``.

        What reads one flight's files (the navigation, :mod:`georefine.workflows.project`) reads
        it as it reads a project of one flight. A project without ``flights`` is its flight 1:
        itself.

        Raises
        ------
        ConfigError
            No flight with this id.
        """
        if self.flights is None:
            if flight_id != 1:
                raise ConfigError("no such flight", field="flights", expected="1 (a project without a flights list "
                                  "is one flight)", found=repr(flight_id))
            return self
        f = self.flight(flight_id)
        assert self.gnss is not None and self.imu is not None
        gnss = self.gnss.model_copy(update={"files": list(f.gnss_files)} | (
            {"lever_arm_m": f.gnss_lever_arm_m} if f.gnss_lever_arm_m is not None else {}), deep=True)
        imu_update: dict[str, object] = {"file": f.imu_file}
        for own, shared in (("imu_format", "format"), ("imu_rate_hz", "rate_hz"), ("imu_gps_week", "gps_week")):
            if getattr(f, own) is not None:
                imu_update[shared] = getattr(f, own)
        scanner_update: dict[str, object] = {"files": list(f.strips)}
        for own, shared in (("scanner_lever_arm_m", "lever_arm_m"), ("boresight_deg", "boresight_deg"),
                            ("scanner_time_offset_s", "time_offset_s")):
            if getattr(f, own) is not None:
                scanner_update[shared] = getattr(f, own)
        return self.model_copy(deep=True, update={
            "gnss": gnss, "imu": self.imu.model_copy(update=imu_update, deep=True),
            "scanner": self.scanner.model_copy(update=scanner_update, deep=True), "flights": None})


def boresight_matrix(boresight_deg: Vector3) -> np.ndarray:
    """``R_b_s`` from boresight roll, pitch, yaw in degrees (``Rz(yaw) Ry(pitch) Rx(roll)``)."""
    from georefine.geometry.rotation import R_n_b_from_rph

    r, p, y = np.radians(np.asarray(boresight_deg, dtype=float))
    return R_n_b_from_rph(r, p, y)


def load_project(project_dir: str | Path) -> ProjectConfig:
    """Load ``PROJECT/project.yaml`` (validated; unknown keys are errors; a geoid grid it names must
    exist and open in PROJ, :meth:`CrsConfig.geoid`)."""
    path = Path(project_dir) / "project.yaml"
    if not path.is_file():
        raise ConfigError("no project.yaml in the project folder", path=path)
    cfg = validate_model(ProjectConfig, read_yaml(path), path)
    cfg.crs.geoid(path.parent)  # the geoid grid exists and PROJ reads it: refused now, not at the last step
    return cfg  # type: ignore[return-value]
