"""IMU error models from published datasheets and the IMU measurement simulator (docs/ARCHITECTURE.md §6).

Measurement model (the one the adjustment inverts, docs/ARCHITECTURE.md §4.3), per sample time ``t_k``::

    gyro_k = Q_g[(I + S_g + A_g) omega_ib_b(t_k) + G f_s(t_k) + b_g(t_k) + n_g,k]     n_g ~ N(0, (ARW sqrt(rate))^2)
    acc_k  = Q_f[(I + S_f + A_f) f_s(t_k)               + b_f(t_k) + n_f,k]     n_f ~ N(0, (VRW sqrt(rate))^2)
    f_s(t_k) = f_ib_b(t_k) + v(t_k)     (v: the IMU's vibration; v = 0 and Q = identity by default, and
                                          the adjustment's model has neither)

Samples are *instantaneous* values at the sample times (not interval averages). ``S`` is
diagonal and constant, drawn from the datasheet scale-factor figure (1 sigma). ``A`` is the
triad's misalignment and non-orthogonality against the body frame: its six off-diagonal
elements, constant, each drawn from ``*_misalignment_mrad`` (1 sigma; 0, the default of every
preset, leaves ``A = 0``). Its antisymmetric part turns the triad, its symmetric part shears it;
the part common to both triads' rotations is a rotation of the whole IMU against the body frame.
``G`` is the gyros' g-sensitivity (a MEMS gyro's "linear acceleration effect"): nine elements,
constant, each drawn from ``gyro_g_sensitivity_deg_per_h_per_g`` (0 by default). In level
flight ``G f`` is a constant bias (its third column times -g) and only changes of the specific
force (turns, climbs, vibration) reveal the rest.

Temperature: the factory compensates each sensor's bias over temperature, but not exactly; what is
left is a bias ``k (T(t) - T(t_0))`` with a coefficient ``k`` per axis (1 sigma
``*_temperature_*_per_c``) and the unit's temperature ``T`` rising by ``temperature_change_c``
towards its final value with ``temperature_time_constant_s`` (:func:`temperature_profile`, a
warm-up after power-on). This drift is smooth and deterministic, not the random walk the estimator
models; it is part of the true biases written with the project. All four are off by default and
their draws come after every other, so a grade without them draws as before.

Vibration: engine, gearbox and rotor vibration shakes the IMU at frequencies above the motion the
trajectory holds (the airframe vibration of :class:`~georefine.sim.flight.VibrationConfig` is true
motion, in ``f_ib_b``; this is not). ``v`` is a sinusoid per axis at ``vibration_frequency_hz``
with a random phase and the rms ``vibration_g_rms`` (amplitude ``sqrt(2)`` times it); it is
specific force the sensors read like any other, so it passes through ``S``, ``A`` and the gyros'
``G``, and it is zero-mean: a high-frequency error in the output that the true trajectory does
not hold. Sampled instantaneously it aliases at the sample rate (a 3-blade propeller at 2400 rpm,
120 Hz, reads at 200 Hz as 80 Hz; a multiple of the rate would read as a constant), as an
unfiltered sampler would. The accelerometers' *vibration rectification* (VRE, datasheets: micro-g per g^2 rms) turns
it into a bias: ``b_f += c v_rms^2`` with ``c`` per axis drawn with
``acc_vibration_rectification_ug_per_g2`` (1 sigma); this constant is part of the true biases
written with the project. Typical figures (no datasheet transcribed here): a hard-mounted IMU on a
helicopter or a piston aircraft sees a few tenths of a g rms, an isolated one less; navigation
accelerometers' VRE is of order 10-100 micro-g/g^2, some MEMS ones more, so 0.5 g rms and
50 micro-g/g^2 give a 12.5 micro-g bias. No gyro rectification is simulated: the presets' datasheets
as transcribed state no gyro figure per g^2 (only the linear ``G``, which reads ``v`` as a
zero-mean signal).

Quantisation ``Q``: a unit outputs increments (delta-theta, delta-v) in integer counts of a least
significant bit and carries the remainder to the next sample, so the error does not accumulate.
Here the increment ``x_k dt`` of each unquantised sample ``x_k`` is summed, ``S_k = sum_j<=k x_j dt``,
and the output is ``q_k / dt`` with ``q_k = LSB (floor(S_k / LSB) - floor(S_k-1 / LSB))``
(``S_-1 = 0``): every sample is an integer number of ``LSB / dt``, the sum of the quantised
increments stays within one LSB below ``S_k``, and the error on each sample is white-ish, of
``LSB / (dt sqrt(6))`` rms (two independent uniform residues). ``gyro_quantisation_urad`` is the
delta-theta LSB in micro-radians, ``acc_quantisation_mm_per_s`` the delta-v LSB in mm/s (0, the
default, leaves the output unquantised); it draws no random numbers. NovAtel's RAWIMU scale
factors (as in GearBox's ``gbxnovatelacfr`` decoder) give the units' native LSBs: LN-200
``2^-19`` rad = 1.9 micro-rad and ``2^-14`` m/s = 0.061 mm/s; iMAR FSAS 0.1 arcsec = 0.48 micro-rad
and 0.0015 mm/s; HG1700 AG58 ``2^-33`` rad and ``2^-27`` ft/s, far below its noise. The STIM300
outputs rates with a 0.22 deg/h resolution (datasheet, as in the AOGNCS Handbook's STIM300 model),
0.005 micro-rad over 5 ms. At 200 Hz the LN-200's LSBs are 0.38 mrad/s (79 deg/h) and 0.012 m/s^2
per sample, their error 0.16 mrad/s and 0.005 m/s^2 rms: a quarter and a third of the STIM300's
white noise per sample, but not accumulating into an angle or velocity random walk.

Bias process
    ``b(t) = b_on + w(t)``: a turn-on constant ``b_on ~ N(0, turn_on^2)`` plus an in-run
    random walk ``w(0) = 0``, ``w' = q xi`` (white, unit PSD), generated exactly on the
    sample grid by a cumulative sum (``w_k+1 = w_k + q sqrt(dt) N(0, 1)``).

    Mapping of the datasheet *bias instability* ``B`` (the flicker floor of the Allan
    deviation) to ``q``: bias instability is customarily represented by a first-order
    Gauss-Markov process with standard deviation ``B`` and correlation time ``tau``, whose
    driving noise has ``q = B sqrt(2 / tau)`` (e.g. Groves 2013, Ch. 4 and 14). Over spans
    shorter than ``tau`` the Gauss-Markov process *is* this random walk, which is also the
    model of the estimator (piecewise-linear biases with random-walk pseudo-observations,
    docs/ARCHITECTURE.md §4.3): ``q`` is exactly what the estimator's ``q`` should be set to.
    ``tau`` is ``*_bias_correlation_time_s`` (datasheets do not state it; 1 h for
    FOG/RLG units, 1000 s for MEMS, where the Allan minimum typically lies at 100-1000 s).

Noise densities: ARW [deg/sqrt(h)] / 60 -> deg/sqrt(s) = deg/s/sqrt(Hz); VRW [m/s/sqrt(h)] / 60
-> m/s^2/sqrt(Hz). White-noise standard deviation per sample = density * sqrt(rate_hz).
Micro-g use standard gravity ``g0 = 9.80665 m/s^2``.

Presets (:data:`IMU_PRESETS`)
    ``navigation``  Honeywell HG9900 (RLG), brochure N61-1638-000-000: gyro bias 0.003 deg/h,
                    ARW 0.002 deg/sqrt(h), gyro scale factor 5 ppm; accelerometer bias
                    25 ug, scale factor 100 ppm. VRW is not in the brochure: assumed
                    0.002 m/s/sqrt(h) (typical of RLG navigation IMUs).
    ``tactical``    Honeywell HG1700 (AG58 class, RLG), brochure N61-1619-000-001: gyro bias
                    1 deg/h, ARW 0.125 deg/sqrt(h), scale factor 150 ppm; accelerometer bias
                    1 mg, VRW 0.065 ft/s/sqrt(h) = 0.0198 m/s/sqrt(h), scale factor 300 ppm.
                    The brochure states one bias figure: it is used for turn-on and in-run.
    ``mems``        Safran Sensonor STIM300 (high-end MEMS, 10 g accelerometers), datasheet
                    TS1524 (r9): gyro bias instability 0.5 deg/h, ARW 0.15 deg/sqrt(h),
                    scale-factor accuracy 500 ppm, bias over static temperature 5 deg/h rms
                    (used as turn-on); accelerometer bias instability 0.05 mg, VRW
                    0.06 m/s/sqrt(h), scale factor 300 ppm, bias on/off repeatability 0.75 mg.
    ``ideal``       all errors zero.
    (Figures as transcribed in the IS4S NavToolkit ``ImuModel`` documentation, which cites
    the manufacturers' datasheets.)

    The grades above hold only the errors the estimator models (docs/ARCHITECTURE.md §4.3):
    their datasheets' further figures are left out so that a grade is the model's own world.
    A *unit* preset is a real unit with every error its datasheet states:

    ``stim300``     ``mems`` plus the STIM300 datasheet's further terms (the same transcription,
                    which lists them as "not modelled" there): gyro and accelerometer
                    misalignment 1 mrad (each off-diagonal element, taken as 1 sigma); gyro
                    bias from acceleration 1 deg/h/g (with the unit's g-compensation); residual
                    temperature coefficients linearised from the bias over the -40..85 deg C
                    range (gyro 5 deg/h rms, accelerometer 2 mg rms; a uniform spread over the
                    125 deg C range has an rms of 36 deg C: 0.14 deg/h and 55 micro-g per deg C).
                    The unit's warm-up is an assumption, not a datasheet figure: 10 deg C over
                    a 900 s time constant (a unit dissipating 1.5-2 W, powered on in the
                    aircraft). Its output resolution (0.22 deg/h) is far below its noise and
                    not simulated; vibration is the installation's, not the unit's (set
                    ``imu.vibration_g_rms``).

Default grade: ``mems`` (:data:`DEFAULT_IMU_GRADE`). Paper 000's G/I solution differs from
the G/I/L reference by 8 / 4 / 20 mdeg RMS (roll / pitch / yaw) on a helicopter system with
an integrated ALS-class navigation unit. On a straight corridor leg heading is unobservable
from GNSS positions, so between the heading-observable manoeuvre/turns it random-walks
with the ARW: a smoothed (two-sided) solution has an RMS error of ``ARW sqrt(T / 6)`` over
a leg of duration ``T``; for the simulator's shortened corridors (legs of 200-300 s) the
STIM300's 0.15 deg/sqrt(h) gives 14-18 mdeg, plus a few mdeg from the in-run gyro random
walk: the paper's ~20 mdeg. Roll and pitch are limited by the accelerometer biases that
cannot be separated from tilt in straight flight (tilt error ~ b_f / g): the in-run
0.05 mg and the residual of the 0.75 mg turn-on bias give 3-8 mdeg, as in the paper. A
tactical RLG unit (HG1700) gives similar yaw but larger tilt errors (1 mg in-run); a
navigation-grade unit shows almost no heading drift, which would leave nothing to correct.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

G0 = 9.80665
"""Standard gravity (m/s^2) for micro-g conversions."""
_DEG_PER_H = np.pi / 180.0 / 3600.0  # deg/h -> rad/s
_UG = G0 * 1e-6  # micro-g -> m/s^2


class ImuGrade(BaseModel):
    """IMU error specification in datasheet units (all 1 sigma).

    ``*_bias_instability_*`` with ``*_bias_correlation_time_s`` define the in-run random
    walk density ``q = B sqrt(2 / tau)`` (module docstring); the properties give SI values.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = "custom"
    source: str = Field("", description="datasheet the figures come from")
    rate_hz: float = Field(200.0, gt=0)
    gyro_arw_deg_per_sqrt_h: float = Field(0.0, ge=0)
    gyro_bias_instability_deg_per_h: float = Field(0.0, ge=0)
    gyro_bias_correlation_time_s: float = Field(3600.0, gt=0)
    gyro_turn_on_bias_deg_per_h: float = Field(0.0, ge=0)
    gyro_scale_factor_ppm: float = Field(0.0, ge=0)
    acc_vrw_m_per_s_per_sqrt_h: float = Field(0.0, ge=0)
    acc_bias_instability_ug: float = Field(0.0, ge=0)
    acc_bias_correlation_time_s: float = Field(3600.0, gt=0)
    acc_turn_on_bias_ug: float = Field(0.0, ge=0)
    acc_scale_factor_ppm: float = Field(0.0, ge=0)
    gyro_misalignment_mrad: float = Field(0.0, ge=0, description="1 sigma of each off-diagonal element of the "
                                          "gyro triad's sensitivity matrix against the body frame")
    acc_misalignment_mrad: float = Field(0.0, ge=0, description="the same for the accelerometer triad")
    gyro_g_sensitivity_deg_per_h_per_g: float = Field(
        0.0, ge=0, description="1 sigma of each element of the gyros' g-sensitivity matrix (bias per g of specific "
        "force along each axis; MEMS datasheets' 'linear acceleration effect')")
    temperature_change_c: float = Field(
        0.0, description="the IMU's temperature change over the flight (deg C; the warm-up after power-on): "
        "T(t) = T_0 + dT (1 - exp(-t / temperature_time_constant_s))")
    temperature_time_constant_s: float = Field(900.0, gt=0, description="time constant of the temperature change")
    gyro_temperature_deg_per_h_per_c: float = Field(
        0.0, ge=0, description="1 sigma per axis of the gyro bias's residual temperature coefficient (after the "
        "factory compensation)")
    acc_temperature_ug_per_c: float = Field(
        0.0, ge=0, description="1 sigma per axis of the accelerometer bias's residual temperature coefficient")
    gyro_quantisation_urad: float = Field(
        0.0, ge=0, description="least significant bit of the gyros' angle increments (micro-rad; 0: not quantised); "
        "the remainder is carried to the next sample")
    acc_quantisation_mm_per_s: float = Field(
        0.0, ge=0, description="least significant bit of the accelerometers' velocity increments (mm/s; 0: not "
        "quantised)")
    vibration_g_rms: float = Field(
        0.0, ge=0, description="rms per axis of the IMU's vibration (g): a sinusoid per axis with a random phase, "
        "specific force that is not in the trajectory (0: none)")
    vibration_frequency_hz: float = Field(
        70.0, gt=0, description="frequency of that vibration (e.g. a rotor's or propeller's blade-pass frequency); "
        "it aliases at the sample rate")
    acc_vibration_rectification_ug_per_g2: float = Field(
        0.0, ge=0, description="1 sigma per axis of the accelerometers' vibration rectification coefficient "
        "(micro-g per g^2 rms): a bias c vibration_g_rms^2")

    @property
    def gyro_noise_density(self) -> float:
        """Gyro white-noise density (rad/s/sqrt(Hz) = rad/sqrt(s))."""
        return np.radians(self.gyro_arw_deg_per_sqrt_h) / 60.0

    @property
    def acc_noise_density(self) -> float:
        """Accelerometer white-noise density (m/s^2/sqrt(Hz) = m/s/sqrt(s))."""
        return self.acc_vrw_m_per_s_per_sqrt_h / 60.0

    @property
    def gyro_bias_rw_density(self) -> float:
        """Gyro bias random-walk density ``q`` (rad/s/sqrt(s))."""
        return self.gyro_bias_instability_deg_per_h * _DEG_PER_H * np.sqrt(
            2.0 / self.gyro_bias_correlation_time_s)

    @property
    def acc_bias_rw_density(self) -> float:
        """Accelerometer bias random-walk density ``q`` (m/s^2/sqrt(s))."""
        return self.acc_bias_instability_ug * _UG * np.sqrt(2.0 / self.acc_bias_correlation_time_s)

    @property
    def gyro_turn_on_bias(self) -> float:
        """Gyro turn-on bias sigma (rad/s)."""
        return self.gyro_turn_on_bias_deg_per_h * _DEG_PER_H

    @property
    def acc_turn_on_bias(self) -> float:
        """Accelerometer turn-on bias sigma (m/s^2)."""
        return self.acc_turn_on_bias_ug * _UG


IMU_PRESETS: dict[str, ImuGrade] = {
    "navigation": ImuGrade(
        name="navigation",
        source="Honeywell HG9900 IMU brochure N61-1638-000-000 (VRW assumed)",
        gyro_arw_deg_per_sqrt_h=0.002,
        gyro_bias_instability_deg_per_h=0.003,
        gyro_turn_on_bias_deg_per_h=0.003,
        gyro_scale_factor_ppm=5.0,
        acc_vrw_m_per_s_per_sqrt_h=0.002,
        acc_bias_instability_ug=25.0,
        acc_turn_on_bias_ug=25.0,
        acc_scale_factor_ppm=100.0,
    ),
    "tactical": ImuGrade(
        name="tactical",
        source="Honeywell HG1700 IMU brochure N61-1619-000-001 (AG58 class)",
        gyro_arw_deg_per_sqrt_h=0.125,
        gyro_bias_instability_deg_per_h=1.0,
        gyro_turn_on_bias_deg_per_h=1.0,
        gyro_scale_factor_ppm=150.0,
        acc_vrw_m_per_s_per_sqrt_h=0.065 * 0.3048,
        acc_bias_instability_ug=1000.0,
        acc_turn_on_bias_ug=1000.0,
        acc_scale_factor_ppm=300.0,
    ),
    "mems": ImuGrade(
        name="mems",
        source="Safran Sensonor STIM300 datasheet TS1524 r9 (10 g accelerometers)",
        gyro_arw_deg_per_sqrt_h=0.15,
        gyro_bias_instability_deg_per_h=0.5,
        gyro_bias_correlation_time_s=1000.0,
        gyro_turn_on_bias_deg_per_h=5.0,
        gyro_scale_factor_ppm=500.0,
        acc_vrw_m_per_s_per_sqrt_h=0.06,
        acc_bias_instability_ug=50.0,
        acc_bias_correlation_time_s=1000.0,
        acc_turn_on_bias_ug=750.0,
        acc_scale_factor_ppm=300.0,
    ),
    "ideal": ImuGrade(name="ideal", source="no errors"),
}
IMU_PRESETS["stim300"] = IMU_PRESETS["mems"].model_copy(update=dict(
    name="stim300",
    source="Safran Sensonor STIM300 datasheet TS1524 r9 (10 g accelerometers), every stated error; "
           "warm-up assumed",
    gyro_misalignment_mrad=1.0,
    acc_misalignment_mrad=1.0,
    gyro_g_sensitivity_deg_per_h_per_g=1.0,
    gyro_temperature_deg_per_h_per_c=round(5.0 / (125.0 / 12.0 ** 0.5), 3),
    acc_temperature_ug_per_c=round(2000.0 / (125.0 / 12.0 ** 0.5), 1),
    temperature_change_c=10.0,
    temperature_time_constant_s=900.0,
))
"""IMU grades and units by name; see the module docstring for sources. The grades (``navigation``,
``tactical``, ``mems``) hold the errors the estimator models; a unit (``stim300``) every error its
datasheet states."""

DEFAULT_IMU_GRADE = "mems"
"""Default grade (STIM300 class high-end MEMS): reproduces paper 000's G/I attitude errors."""


def imu_grade(name: str) -> ImuGrade:
    """Preset by name (``navigation``, ``tactical``, ``mems``, ``ideal``, ``stim300``)."""
    try:
        return IMU_PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown IMU grade {name!r}; expected one of {sorted(IMU_PRESETS)}") from None


@dataclass(frozen=True)
class SimulatedImu:
    """Simulated IMU samples and the truth of their errors.

    Attributes
    ----------
    time : ndarray (N,)
        Sample times (s, relative to the epoch ``t0_gps``), uniform at ``grade.rate_hz``.
    gyro : ndarray (N, 3)
        Measured angular rate ``omega_ib_b`` (rad/s), body FRD, instantaneous.
    acc : ndarray (N, 3)
        Measured specific force ``f_ib_b`` (m/s^2), body FRD, instantaneous.
    bias_gyro, bias_acc : ndarray (N, 3)
        True biases (rad/s, m/s^2) at the sample times (turn-on + random walk).
    scale_gyro, scale_acc : ndarray (3,)
        True scale-factor errors (dimensionless, diagonal of ``S``).
    t0_gps : float
        Dataset epoch (GPS seconds).
    grade : ImuGrade
    misalignment_gyro, misalignment_acc : ndarray (3, 3)
        True misalignment ``A`` of each triad (dimensionless, zero diagonal).
    g_sensitivity : ndarray (3, 3)
        True gyro g-sensitivity ``G`` (rad/s per m/s^2): the gyros read ``G f_ib_b`` more.
    temperature_c : ndarray (N,)
        The IMU's temperature change since the first sample (deg C).
    temperature_gyro, temperature_acc : ndarray (3,)
        True temperature coefficients of the biases (rad/s and m/s^2 per deg C); their part
        ``k (T(t) - T(t_0))`` is in ``bias_gyro`` and ``bias_acc``.
    quantisation_gyro, quantisation_acc : ndarray (N, 3) or None
        Quantisation error of each sample (rad/s, m/s^2): ``gyro`` and ``acc`` minus what they would
        read unquantised; None where the grade does not quantise.
    vibration_acc : ndarray (N, 3) or None
        The vibration ``v`` at the sample times (m/s^2, specific force before the sensor model):
        ``sqrt(2) vibration_g_rms g0 sin(2 pi f (t - t_first) + vibration_phase)``; None without.
    vibration_phase : ndarray (3,)
        Its phase per axis (rad) at the first sample.
    vibration_rectification : ndarray (3,)
        True rectification coefficients ``c`` (m/s^2 per (m/s^2)^2, i.e. s^2/m).
    vibration_bias_acc : ndarray (3,)
        The accelerometer bias they give, ``c v_rms^2`` (m/s^2); it is in ``bias_acc``.
    """

    time: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    bias_gyro: np.ndarray
    bias_acc: np.ndarray
    scale_gyro: np.ndarray
    scale_acc: np.ndarray
    t0_gps: float
    grade: ImuGrade
    misalignment_gyro: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    misalignment_acc: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    g_sensitivity: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    temperature_c: np.ndarray | None = None
    temperature_gyro: np.ndarray = field(default_factory=lambda: np.zeros(3))
    temperature_acc: np.ndarray = field(default_factory=lambda: np.zeros(3))
    quantisation_gyro: np.ndarray | None = None
    quantisation_acc: np.ndarray | None = None
    vibration_acc: np.ndarray | None = None
    vibration_phase: np.ndarray = field(default_factory=lambda: np.zeros(3))
    vibration_rectification: np.ndarray = field(default_factory=lambda: np.zeros(3))
    vibration_bias_acc: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        n = len(self.time)
        for name in ("gyro", "acc", "bias_gyro", "bias_acc", "quantisation_gyro", "quantisation_acc", "vibration_acc"):
            a = getattr(self, name)
            if a is not None and a.shape != (n, 3):
                raise ValueError(f"{name} must have shape ({n}, 3)")
        for name in ("misalignment_gyro", "misalignment_acc"):
            a = getattr(self, name)
            if a.shape != (3, 3) or np.any(np.diag(a) != 0):
                raise ValueError(f"{name} must be (3, 3) with a zero diagonal")
        if n > 1 and not np.all(np.diff(self.time) > 0):
            raise ValueError("IMU times must increase strictly")


def _bias(rng, n, dt, turn_on, q):
    b = np.broadcast_to(rng.normal(0.0, 1.0, 3) * turn_on, (n, 3)).copy()
    if q > 0 and n > 1:
        steps = rng.normal(0.0, q * np.sqrt(dt), (n - 1, 3))
        b[1:] += np.cumsum(steps, axis=0)
    return b


def simulate_imu(traj, grade: ImuGrade, t_start: float, t_end: float,
                 rng: np.random.Generator) -> SimulatedImu:
    """Simulate IMU samples of ``traj`` on ``[t_start, t_end]`` (s rel. epoch).

    Parameters
    ----------
    traj : TrueTrajectory
        Provides ``imu(t) -> (omega_ib_b, f_ib_b)`` and ``t0_gps``.
    grade : ImuGrade
        Error specification (e.g. ``imu_grade("mems")``); sample rate ``grade.rate_hz``.
    t_start, t_end : float
        Sample times are ``t_start + k / rate_hz <= t_end``.
    rng : numpy.random.Generator
        Seeded generator; draws turn-on biases, scale factors, random walks and noise, then, each only
        where the grade states it (so a grade without them draws as before), the misalignments, the
        g-sensitivity, the temperature coefficients, the vibration's phases and the rectification
        coefficients. Quantisation draws nothing.

    Returns
    -------
    SimulatedImu
    """
    if not t_end > t_start:
        raise ValueError(f"need t_start < t_end, got {t_start}, {t_end}")
    dt = 1.0 / grade.rate_hz
    n = int(np.floor((t_end - t_start) * grade.rate_hz + 1e-9)) + 1
    time = t_start + np.arange(n) * dt
    w_true, f_true = traj.imu(time)
    scale_g = rng.normal(0.0, grade.gyro_scale_factor_ppm * 1e-6, 3)
    scale_f = rng.normal(0.0, grade.acc_scale_factor_ppm * 1e-6, 3)
    b_g = _bias(rng, n, dt, grade.gyro_turn_on_bias, grade.gyro_bias_rw_density)
    b_f = _bias(rng, n, dt, grade.acc_turn_on_bias, grade.acc_bias_rw_density)
    sq = np.sqrt(grade.rate_hz)
    n_g = rng.normal(0.0, grade.gyro_noise_density * sq, (n, 3))
    n_f = rng.normal(0.0, grade.acc_noise_density * sq, (n, 3))
    a_g = misalignment_matrix(rng, grade.gyro_misalignment_mrad)
    a_f = misalignment_matrix(rng, grade.acc_misalignment_mrad)
    g_sens = np.zeros((3, 3))
    if grade.gyro_g_sensitivity_deg_per_h_per_g > 0:
        g_sens = rng.normal(0.0, grade.gyro_g_sensitivity_deg_per_h_per_g * _DEG_PER_H / G0, (3, 3))
    temp = temperature_profile(time - time[0], grade.temperature_change_c, grade.temperature_time_constant_s)
    k_g = k_f = np.zeros(3)
    if grade.gyro_temperature_deg_per_h_per_c > 0:
        k_g = rng.normal(0.0, grade.gyro_temperature_deg_per_h_per_c * _DEG_PER_H, 3)
    if grade.acc_temperature_ug_per_c > 0:
        k_f = rng.normal(0.0, grade.acc_temperature_ug_per_c * _UG, 3)
    b_g = b_g + temp[:, None] * k_g
    b_f = b_f + temp[:, None] * k_f
    phase, vre = np.zeros(3), np.zeros(3)
    if grade.vibration_g_rms > 0:
        phase = rng.uniform(0.0, 2.0 * np.pi, 3)
    if grade.acc_vibration_rectification_ug_per_g2 > 0:
        vre = rng.normal(0.0, grade.acc_vibration_rectification_ug_per_g2 * _UG / G0**2, 3)
    vib = None
    f_sensed = f_true
    if grade.vibration_g_rms > 0:
        vib = vibration(time - time[0], grade.vibration_g_rms * G0, grade.vibration_frequency_hz, phase)
        f_sensed = f_true + vib
    vib_bias = vre * (grade.vibration_g_rms * G0) ** 2
    if np.any(vib_bias):
        b_f = b_f + vib_bias
    gyro = sense(w_true, scale_g, a_g) + f_sensed @ g_sens.T + b_g + n_g
    acc = sense(f_sensed, scale_f, a_f) + b_f + n_f
    q_g = q_f = None
    if grade.gyro_quantisation_urad > 0:
        raw, gyro = gyro, quantise(gyro, dt, grade.gyro_quantisation_urad * 1e-6)
        q_g = gyro - raw
    if grade.acc_quantisation_mm_per_s > 0:
        raw, acc = acc, quantise(acc, dt, grade.acc_quantisation_mm_per_s * 1e-3)
        q_f = acc - raw
    return SimulatedImu(time, gyro, acc, b_g, b_f, scale_g, scale_f, float(traj.t0_gps), grade,
                        misalignment_gyro=a_g, misalignment_acc=a_f, g_sensitivity=g_sens,
                        temperature_c=temp, temperature_gyro=k_g, temperature_acc=k_f,
                        quantisation_gyro=q_g, quantisation_acc=q_f, vibration_acc=vib, vibration_phase=phase,
                        vibration_rectification=vre, vibration_bias_acc=vib_bias)


def vibration(t: np.ndarray, rms: float, frequency_hz: float, phase: np.ndarray) -> np.ndarray:
    """A vibration of ``rms`` per axis (N, 3): ``sqrt(2) rms sin(2 pi f t + phase)``, one phase per axis."""
    return np.sqrt(2.0) * rms * np.sin(2.0 * np.pi * frequency_hz * np.asarray(t, dtype=float)[:, None] + phase)


def quantise(x: np.ndarray, dt: float, lsb: float) -> np.ndarray:
    """Samples ``x`` (N, 3) output as increments in whole ``lsb`` with the remainder carried on, as rates.

    ``q_k = lsb (floor(S_k / lsb) - floor(S_k-1 / lsb))`` with ``S_k`` the running sum of ``x dt``
    (``S_-1 = 0``), returned as ``q_k / dt``: the sum of the increments stays within one ``lsb`` below
    ``S_k``, so the error does not accumulate (module docstring).
    """
    counts = np.floor(np.cumsum(np.asarray(x, dtype=float) * dt, axis=0) / lsb)
    return np.diff(counts, axis=0, prepend=0.0) * (lsb / dt)


def temperature_profile(t: np.ndarray, change_c: float, time_constant_s: float) -> np.ndarray:
    """The IMU's temperature change since ``t = 0`` (deg C): a first-order approach to its final value,
    ``dT (1 - exp(-t / tau))``, as a unit warms up after power-on (or follows the cabin's temperature)."""
    return change_c * -np.expm1(-np.asarray(t, dtype=float) / time_constant_s)


def misalignment_matrix(rng: np.random.Generator, sigma_mrad: float) -> np.ndarray:
    """A triad's misalignment ``A`` (3, 3): off-diagonal elements drawn with ``sigma_mrad`` (1 sigma),
    zero diagonal; all zero, drawing nothing, where ``sigma_mrad`` is 0."""
    a = np.zeros((3, 3))
    if sigma_mrad > 0:
        off = ~np.eye(3, dtype=bool)
        a[off] = rng.normal(0.0, sigma_mrad * 1e-3, 6)
    return a


def sense(x: np.ndarray, scale: np.ndarray, misalignment: np.ndarray) -> np.ndarray:
    """``(I + diag(scale) + misalignment) x`` for rows ``x`` (N, 3): what a triad reads of ``x``
    before bias and noise."""
    out = (1.0 + scale) * x
    if np.any(misalignment):
        out += x @ misalignment.T
    return out
