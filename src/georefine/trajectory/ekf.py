"""Initialisation filter: error-state EKF on the strapdown mechanisation in ``w`` + RTS smoother.

Workflow step 1 (docs/ARCHITECTURE.md §4.5; paper 000 §2: "suitable starting values ... obtained by a simple
GNSS/IMU Kalman filter"). The output initialises the spline of the adjustment.

State and error state
    Nominal state ``(p_w_b, v_w_b, R_w_b, b_a, b_g, s_a, s_g)``, mechanised at every IMU sample
    with the RKMK4 step of :mod:`georefine.trajectory.strapdown` on the corrected IMU
    ``f = (f~ - b_a) / (1 + s_a)``, ``omega_ib_b = (omega~ - b_g) / (1 + s_g)`` (elementwise; the
    sensor model of docs/ARCHITECTURE.md §4.3 with diagonal scale factors). Error state, truth = nominal (+)
    error::

        x = [dp_w (3), dv_w (3), dtheta_b (3), db_a (3), db_g (3) | ds_a (3), ds_g (3)]
        p = p^ + dp,  v = v^ + dv,  R = R^ Exp(dtheta)  (right, body-frame error),  b = b^ + db

    The first 15 are the navigation error states of the brief; the six scale-factor states
    are appended because an unmodelled gyro scale factor dominates the heading error of a
    MEMS unit after the turns of the initialisation manoeuvre (500 ppm of 360 deg = 0.18 deg;
    with them the heading error drops from ~70 to ~20 mdeg RMS on the simulator's flight).
    ``estimate_scale_factors=False`` holds them at zero. Linearised dynamics in the Earth-fixed
    ``w`` (Groves 2013 §14.2, written for a right attitude error)::

        dp'     = dv
        dv'     = Gamma dp - 2 [omega_ie_w]x dv - R^ [f]x dtheta - R^ (db_a + diag(f) ds_a + n_a)
        dtheta' = -[omega_ib_b]x dtheta - db_g - diag(omega_ib_b) ds_g - n_g
        db_a'   = w_a,   db_g' = w_g  (random walks),   ds' = 0

    ``Gamma = (g / r) diag(-1, -1, 2)`` is the gravity gradient (w is east-north-up).
    White-noise densities: VRW and ARW; bias random walks ``q = B sqrt(2 / tau)``
    (:class:`georefine.config.ImuErrorSpec`); each with a floor (:class:`FilterConfig`) so that
    an all-zero ('ideal') specification still gives a well-posed filter.

Covariance propagation
    The transition ``Phi = prod (I + F_k dt_k)`` is accumulated at every IMU sample (structured
    products in numba) and applied to ``P`` only at the *filter epochs*: a regular grid at
    ``covariance_rate_hz`` plus every sample with a GNSS update. Process noise over an epoch
    interval ``T``: ``Q = (Phi Qc Phi^T + Qc) T / 2`` (trapezoid; ``Qc`` is diagonal and does not
    depend on the attitude because the densities are isotropic).

GNSS update (docs/ARCHITECTURE.md §4.3, paper 000 Eq. 3)
    At the last IMU sample ``k`` with ``t_k <= t_g`` (``d = t_g - t_k < dt``)::

        z_w = p_w_b + d v_w_b + R_w_b (p_b_a + d omega_wb_b x p_b_a) + e,   e ~ N(0, Sigma_w)
        H   = [I, d I, -R_w_b [p_b_a]x, 0 ...]

    Epochs whose normalised innovation ``nu^T S^-1 nu`` exceeds the chi-square quantile
    (3 dof, ``gnss_gate_probability``) are rejected (multipath jumps). If consecutive epochs
    are rejected for ``gnss_gate_reset_s``, the gate opens once (then the filter is wrong, not
    the GNSS). Joseph-form update, then the correction is injected into the nominal state and
    the error state is reset (the small reset Jacobian of the attitude is neglected).

Alignment (in-motion, heading from the GNSS track)
    The alignment epoch ``t_a`` is the first GNSS epoch from which the horizontal speed (central
    differences of the GNSS positions) stays above ``alignment_speed_mps`` for
    ``alignment_hold_s``. The attitude at ``t_a``:

    * platform at rest during the first ``static_window_s`` (GNSS speed and specific force):
      roll/pitch by levelling from the mean specific force ``f`` there, carried to ``t_a`` by
      the gyros, heading = GNSS track at ``t_a``. The tilt error is fully correlated with the
      horizontal accelerometer bias, ``dtheta = [f]x db_a / |f|^2``; the initial covariance
      says so (plus ``levelling_sigma_deg``).
    * otherwise (data starting in flight): TRIAD at ``t_a`` (:func:`_triad`) from the specific
      force in ``w`` (quadratic fit of the GNSS positions over ``coarse_window_s``) and the
      track, ``initial_tilt_sigma_deg``.

    The heading error is the crab/sideslip angle plus GNSS noise (``initial_heading_sigma_deg``).
    The filter does not start at ``t_a`` but at the first IMU sample of the span covered by
    GNSS: the attitude at ``t_a`` is carried back to the start through the gyro-integrated
    rotation between the two (drift over this interval is far below the heading sigma). So the
    whole span, including the time on the pad and the lift-off, is GNSS-aided and smoothed
    with consistent covariances, rather than reached by a free backward integration, and the
    smoother carries the heading learnt in the manoeuvre back to the start. In straight flight
    without manoeuvres the heading stays unobservable (error = crab angle, sigma says so).

Smoother and output
    Rauch-Tung-Striebel over the filter epochs on the error state: with ``dx_e`` the correction
    injected at epoch ``e`` and ``s_e`` the smoothed correction of the filtered state ``x+_e``::

        C_e = P+_e Phi_e+1^T (P-_e+1)^-1
        s_e = C_e (s_e+1 + dx_e+1),   P^s_e = P+_e + C_e (P^s_e+1 - P-_e+1) C_e^T

    Stored per epoch: ``P+`` and the nine non-trivial rows of ``Phi`` (``P-`` and ``C`` are
    recomputed backwards), 5.3 kB; one hour at the default 20 Hz needs ~400 MB, plus ~300 MB
    at IMU rate (IMU, nominal trajectory, output).
    At every IMU sample between two epochs the smoothed correction is linearly interpolated
    between ``s_e`` and ``s_e+1 + dx_e+1`` (both refer to the nominal trajectory mechanised from
    ``x+_e``) and applied. The reported ``sigma`` is the smoothed 1-sigma at the filter epochs,
    linearly interpolated to the IMU samples.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.special import chdtri  # chi-square quantiles without scipy.stats (0.4 s to import)

from georefine.config import FilterConfig, ImuErrorSpec
from georefine.errors import InputError
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import skew
from georefine.trajectory import strapdown as sd
from georefine.trajectory._ekf_kernels import apply_smoothed, forward_pass, rts_smooth
from georefine.trajectory.sampled import Trajectory

__all__ = ["FilterConfig", "FilterResult", "ImuSamples", "run_filter"]


class ImuSamples(Protocol):
    """The raw IMU samples the filter reads (as :class:`georefine.io.imu.ImuData` holds them).

    ``time_gps`` (N,) GPS seconds; ``kind`` ``"rates"`` (``gyro`` (N, 3) rad/s, ``acc`` (N, 3)
    m/s^2, body FRD) or ``"increments"`` (read through ``increments()``: rad and m/s per
    sample); ``rate_hz`` the nominal rate.
    The trajectory layer reads no files (docs/ARCHITECTURE.md §1), so it names what it needs
    instead of importing the reader's type.
    """

    time_gps: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    rate_hz: float
    kind: str

    def increments(self) -> tuple[np.ndarray, np.ndarray]: ...

log = logging.getLogger(__name__)

_DEG_PER_H = np.pi / 180.0 / 3600.0
_UG = 9.80665e-6
_USED, _REJECTED, _FORCED, _OUTSIDE = 1, 0, 2, -1
_NX = 21  # error states: 15 navigation + 6 scale factors


@dataclass(frozen=True)
class FilterResult:
    """Smoothed trajectory at the IMU samples covered by GNSS.

    Attributes
    ----------
    time : (N,) float64
        IMU sample times, s relative to ``t0_gps``.
    p_w_b, v_w_b : (N, 3)
        IMU position (m) and velocity (m/s) in ``w``.
    R_w_b : (N, 3, 3)
        Attitude.
    bias_acc, bias_gyro : (N, 3)
        Estimated accelerometer (m/s^2) and gyro (rad/s) biases.
    sigma : (N, 15)
        Smoothed 1-sigma of the error state ``[dp_w, dv_w, dtheta_b, db_a, db_g]`` (SI units,
        rad), computed at the filter epochs and linearly interpolated to ``time``.
    scale_acc, scale_gyro : (3,)
        Estimated scale-factor errors (dimensionless), sensor model ``(1 + s) x + b``.
    scale_sigma : (6,)
        Their smoothed 1-sigma (acc, gyro).
    t0_gps : float
        Dataset epoch (GPS seconds).
    gnss_status : (G,) int8
        Per input GNSS epoch: 1 used, 0 rejected by the gate, 2 used after the gate was
        reopened, -1 outside the IMU span.
    gnss_nis : (G,) float64
        Normalised innovation squared of each epoch inside the span (NaN outside).
    alignment_time : float
        Epoch of the heading alignment (s rel. ``t0_gps``).
    levelled : bool
        Whether roll/pitch were initialised by static levelling.
    """

    time: np.ndarray
    p_w_b: np.ndarray
    v_w_b: np.ndarray
    R_w_b: np.ndarray
    bias_acc: np.ndarray
    bias_gyro: np.ndarray
    sigma: np.ndarray
    scale_acc: np.ndarray
    scale_gyro: np.ndarray
    scale_sigma: np.ndarray
    t0_gps: float
    gnss_status: np.ndarray
    gnss_nis: np.ndarray
    alignment_time: float
    levelled: bool

    def __post_init__(self) -> None:
        n = self.time.shape[0]
        shapes = {"p_w_b": (n, 3), "v_w_b": (n, 3), "R_w_b": (n, 3, 3), "bias_acc": (n, 3),
                  "bias_gyro": (n, 3), "sigma": (n, 15)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {getattr(self, name).shape}")
        if self.gnss_status.shape != self.gnss_nis.shape:
            raise ValueError("gnss_status and gnss_nis must have the same shape")

    @property
    def n_gnss_updates(self) -> int:
        """Number of GNSS epochs used."""
        return int(np.count_nonzero((self.gnss_status == _USED) | (self.gnss_status == _FORCED)))

    @property
    def n_gnss_rejected(self) -> int:
        """Number of GNSS epochs rejected by the gate."""
        return int(np.count_nonzero(self.gnss_status == _REJECTED))

    def to_sampled(self) -> Trajectory:
        """The trajectory as :class:`georefine.trajectory.sampled.Trajectory`."""
        return Trajectory(self.time, self.p_w_b, self.R_w_b, t0_gps=self.t0_gps, v_w_b=self.v_w_b)


# ---------------------------------------------------------------------------- njit kernels


def _gnss_velocity(time, p_w, max_gap_s):
    """Central-difference velocities (G, 3) of the GNSS positions; NaN where the gap is too long."""
    v = np.full_like(p_w, np.nan)
    if len(time) >= 3:
        dt = time[2:] - time[:-2]
        ok = dt <= max_gap_s
        v[1:-1][ok] = (p_w[2:] - p_w[:-2])[ok] / dt[ok, None]
    return v


def _alignment(frame, time, p_w, cfg):
    """Time of the alignment epoch and the track there (rad, NED) from the GNSS velocity."""
    v = _gnss_velocity(time, p_w, 2.5 * np.median(np.diff(time)) if len(time) > 1 else 1.0)
    R_n_w = np.swapaxes(frame.R_w_n_at(p_w), 1, 2)
    v_n = np.einsum("nij,nj->ni", R_n_w, np.nan_to_num(v))
    speed = np.where(np.isnan(v[:, 0]), 0.0, np.hypot(v_n[:, 0], v_n[:, 1]))
    fast = speed > cfg.alignment_speed_mps
    for i in np.flatnonzero(fast):
        window = (time >= time[i]) & (time <= time[i] + cfg.alignment_hold_s)
        if np.all(fast[window]) and time[-1] >= time[i] + cfg.alignment_hold_s:
            vm = v_n[window].mean(axis=0)
            return float(time[window].mean()), float(np.arctan2(vm[1], vm[0]))
    raise InputError(
        "the horizontal GNSS speed never exceeds the alignment threshold: heading cannot be aligned",
        field="alignment_speed_mps", expected=f"> {cfg.alignment_speed_mps} m/s for {cfg.alignment_hold_s} s",
        found=f"max {speed.max():.2f} m/s")


def _gnss_fit(g_time, g_p, t_c, half_s):
    """Position, velocity, acceleration (3,) at ``t_c`` from a quadratic fit over ``t_c +- half_s``."""
    sel = np.abs(g_time - t_c) <= half_s
    if np.count_nonzero(sel) < 4:
        return None
    tau = g_time[sel] - t_c
    c = np.linalg.lstsq(np.column_stack([np.ones_like(tau), tau, tau**2]), g_p[sel], rcond=None)[0]
    return c[0], c[1], 2.0 * c[2]


def _triad(frame, t, f, g_time, g_p, t_a, half_s):
    """In-motion coarse attitude ``R_w_b`` at ``t_a`` from GNSS kinematics and the mean specific force.

    Specific force in ``w`` from a quadratic fit of the GNSS positions over ``t_a +- half_s``,
    ``f_w = a_w + 2 omega_ie_w x v_w - g_w``, matched exactly to the mean IMU ``f_b``; the
    rotation about it puts the body x-axis into the plane of ``f_w`` and the horizontal track
    (coordinated flight without sideslip). TRIAD (Black 1964).
    """
    fit = _gnss_fit(g_time, g_p, t_a, half_s)
    if fit is None:
        return None
    p, v, a = fit
    f_w = a + 2.0 * np.cross(frame.omega_ie_w, v) - frame.gravity_w(p)
    up = -frame.R_w_n_at(p)[:, 2]
    f_b = f[np.abs(t - t_a) <= half_s].mean(axis=0)

    def basis(v1, v2):
        e1 = v1 / np.linalg.norm(v1)
        e2 = np.cross(e1, v2)
        e2 /= np.linalg.norm(e2)
        return np.column_stack([e1, e2, np.cross(e1, e2)])

    return basis(f_w, v - (v @ up) * up) @ basis(f_b, np.array([1.0, 0.0, 0.0])).T


def _static_levelling(frame, t, f, w, g_time, g_p, cfg):
    """Mean specific force (3,) over the start window if the platform is at rest there, else None."""
    t_end = t[0] + cfg.static_window_s
    sel = g_time <= t_end
    if np.count_nonzero(sel) < 3 or t[-1] < t_end:
        return None
    X = np.column_stack([np.ones(np.count_nonzero(sel)), g_time[sel] - g_time[0]])
    coef, *_ = np.linalg.lstsq(X, g_p[sel], rcond=None)
    rms = np.sqrt(np.mean((g_p[sel] - X @ coef) ** 2))
    imu_sel = t <= t_end
    f_mean = f[imu_sel].mean(axis=0)
    g = np.linalg.norm(frame.gravity_w(g_p[0]))
    at_rest = (np.linalg.norm(coef[1]) < cfg.static_max_speed_mps and rms < 0.2
               and abs(np.linalg.norm(f_mean) - g) < 0.01 * g
               and np.linalg.norm(w[imu_sel].mean(axis=0)) < np.radians(0.5))
    return f_mean if at_rest else None


def _noise_si(spec: ImuErrorSpec, cfg: FilterConfig):
    """Continuous process-noise densities (21,) and initial sensor-error sigmas (12,), SI."""
    arw = np.radians(max(spec.gyro_arw_deg_per_sqrt_h, cfg.gyro_arw_floor_deg_per_sqrt_h)) / 60.0
    vrw = max(spec.acc_vrw_m_per_s_per_sqrt_h, cfg.acc_vrw_floor_m_per_s_per_sqrt_h) / 60.0
    q_bg, q_ba = spec.bias_random_walk_si(cfg.gyro_bias_floor_deg_per_h, cfg.acc_bias_floor_ug)
    qc = np.repeat([0.0, vrw**2, arw**2, q_ba**2, q_bg**2, 0.0, 0.0], 3)
    s_ba = max(spec.acc_turn_on_bias_ug, cfg.acc_bias_floor_ug) * _UG
    s_bg = max(spec.gyro_turn_on_bias_deg_per_h, cfg.gyro_bias_floor_deg_per_h) * _DEG_PER_H
    if cfg.estimate_scale_factors:
        s_sa = max(spec.acc_scale_factor_ppm, cfg.scale_factor_floor_ppm) * 1e-6
        s_sg = max(spec.gyro_scale_factor_ppm, cfg.scale_factor_floor_ppm) * 1e-6
    else:  # a tiny prior keeps the smoother's gain well defined
        s_sa = s_sg = 1e-12
    return qc, np.repeat([s_ba, s_bg, s_sa, s_sg], 3)


def _initial_covariance(u_b, f_level, cov_gnss, p_b_a, s_sensor, cfg):
    """Initial P (21, 21); ``u_b`` is the up direction in the body frame, ``s_sensor`` (12,) sigmas."""
    P0 = np.zeros((_NX, _NX))
    s_h = np.radians(cfg.initial_heading_sigma_deg)
    s_t = np.radians(cfg.levelling_sigma_deg if f_level is not None else cfg.initial_tilt_sigma_deg)
    P0[:3, :3] = cov_gnss + (np.linalg.norm(p_b_a) * max(s_h, s_t)) ** 2 * np.eye(3)
    P0[3:6, 3:6] = cfg.initial_velocity_sigma_mps**2 * np.eye(3)
    uu = np.outer(u_b, u_b)
    P0[6:9, 6:9] = s_t**2 * (np.eye(3) - uu) + s_h**2 * uu
    P0[9:, 9:] = np.diag(s_sensor**2)
    if f_level is not None:  # levelling: dtheta = [f]x db_a / |f|^2
        M = skew(f_level) / (f_level @ f_level)
        P0[6:9, 6:9] += M @ P0[9:12, 9:12] @ M.T
        P0[6:9, 9:12] = M @ P0[9:12, 9:12]
        P0[9:12, 6:9] = P0[6:9, 9:12].T
    return P0


# ---------------------------------------------------------------------------- public API
def run_filter(frame: LocalFrame, t0_gps: float, imu: ImuSamples, gnss_time: np.ndarray,
               gnss_p_w: np.ndarray, gnss_cov_w: np.ndarray, p_b_a: np.ndarray,
               spec: ImuErrorSpec, cfg: FilterConfig | None = None) -> FilterResult:
    """Error-state EKF with in-motion alignment and RTS smoother (module docstring).

    Parameters
    ----------
    frame : LocalFrame
        Mapping frame ``w``.
    t0_gps : float
        Dataset epoch (GPS seconds); ``imu.time_gps - t0_gps`` are the filter times.
    imu : ImuSamples
        Raw IMU (rates or increments), body FRD.
    gnss_time : (G,) float64
        GNSS epochs, s relative to ``t0_gps``, strictly increasing.
    gnss_p_w : (G, 3)
        Antenna positions in ``w`` (m).
    gnss_cov_w : (G, 3, 3)
        Their covariances in ``w`` (m^2), see :func:`georefine.io.gnss.gnss_in_w`.
    p_b_a : (3,)
        Antenna lever arm in the body frame (m).
    spec : ImuErrorSpec
        IMU error specification (datasheet units).
    cfg : FilterConfig, optional

    Returns
    -------
    FilterResult
        Smoothed states at all IMU samples within the GNSS span.

    Raises
    ------
    InputError
        Too little overlap of IMU and GNSS, or no epoch fast enough for the heading alignment.
    """
    cfg = cfg or FilterConfig()
    g_time = np.ascontiguousarray(gnss_time, dtype=float)
    g_p = np.ascontiguousarray(gnss_p_w, dtype=float)
    g_cov = np.ascontiguousarray(gnss_cov_w, dtype=float) * cfg.gnss_sigma_scale**2
    p_b_a = np.asarray(p_b_a, dtype=float).reshape(3)
    G = g_time.shape[0]
    if g_p.shape != (G, 3) or g_cov.shape != (G, 3, 3):
        raise ValueError(f"gnss_p_w must be ({G}, 3) and gnss_cov_w ({G}, 3, 3)")
    if G > 1 and np.any(np.diff(g_time) <= 0):
        raise InputError("GNSS times must increase strictly", field="gnss_time")
    t = imu.time_gps - t0_gps
    k0 = max(int(np.searchsorted(t, g_time[0] if G else np.inf, side="right")) - 1, 0)
    k1 = min(int(np.searchsorted(t, g_time[-1] if G else -np.inf, side="left")), len(t) - 1)
    inside = (g_time >= t[k0]) & (g_time <= t[k1])
    if k1 - k0 < 2 or np.count_nonzero(inside) < 3:
        raise InputError("IMU and GNSS do not overlap", field="time",
                         expected="at least three GNSS epochs within the IMU span",
                         found=f"IMU {t[0]:.3f}..{t[-1]:.3f} s, {np.count_nonzero(inside)} epochs")
    if imu.kind == "increments":
        dtheta, dv = imu.increments()
        w, wm = sd.rates_from_increments(t, dtheta)
        f, fm = sd.rates_from_increments(t, dv)
    else:
        w, f = imu.gyro, imu.acc
        wm, fm = sd.midpoints_from_samples(t, w), sd.midpoints_from_samples(t, f)
    gt, gp, gc = g_time[inside], g_p[inside], g_cov[inside]

    # ---- alignment: attitude at the alignment epoch, carried back to the start by the gyros
    span = slice(k0, k1 + 1)
    f_level = _static_levelling(frame, t[span], f[span], w[span], gt, gp, cfg)
    t_align, track = _alignment(frame, gt, gp, cfg)
    if f_level is not None:
        roll, pitch = np.arctan2(-f_level[1], -f_level[2]), np.arctan2(f_level[0], np.hypot(*f_level[1:]))
    else:
        roll = pitch = 0.0
    fit = None if f_level is not None else _gnss_fit(gt, gp, t[k0], cfg.coarse_window_s)
    v0 = np.zeros(3) if fit is None else fit[1]
    p0_a = gp[0] - v0 * (gt[0] - t[k0]) if fit is None else fit[0]
    ka = min(int(np.searchsorted(t, t_align)), k1)
    R_start = frame.R_w_b_from_rph(p0_a, np.array([roll, pitch, 0.0]))
    fwd = sd.integrate(frame, t[k0:ka + 2], w[k0:ka + 2], f[k0:ka + 2], p0_a, v0, R_start)
    R_int = fwd.R_w_b[ka - k0]
    R_a = None if f_level is not None else _triad(frame, t, f, gt, gp, t[ka], cfg.coarse_window_s / 2)
    if R_a is None:  # levelled (or too few fixes): keep roll/pitch, rotate the heading to the track
        rph_a = frame.rph_from_R_w_b(fwd.p_w_b[ka - k0], R_int)
        R_a = frame.R_w_b_from_rph(fwd.p_w_b[ka - k0], np.array([rph_a[0], rph_a[1], track]))
    R0 = R_a @ R_int.T @ R_start
    u_b = R0.T @ frame.R_w_n_at(p0_a)[:, 2] * -1.0
    qc, s_sensor = _noise_si(spec, cfg)
    P0 = _initial_covariance(u_b, f_level, gc[0], p_b_a, s_sensor, cfg)

    # ---- schedule: regular epochs and GNSS samples
    N = len(t)
    g_k = np.clip(np.searchsorted(t, gt, side="right") - 1, k0, k1)
    g_dt = gt - t[g_k]
    ep_flag = np.zeros(N, dtype=np.bool_)
    step = max(1, round(imu.rate_hz / cfg.covariance_rate_hz))
    ep_flag[k0:k1 + 1:step] = True
    ep_flag[[k0, k1]] = True
    ep_flag[g_k] = True
    n_ep = int(np.count_nonzero(ep_flag))

    # ---- forward filter
    P_n, V_n, R_n = np.empty((N, 3)), np.empty((N, 3)), np.empty((N, 3, 3))
    P_n[k0], V_n[k0], R_n[k0] = p0_a - R0 @ p_b_a, v0, R0
    g0 = np.linalg.norm(frame.gravity_w(P_n[k0]))
    Gam = g0 / (6371e3 + frame.h0_m + P_n[k0, 2]) * np.diag([-1.0, -1.0, 2.0])
    gate = chdtri(3, 1.0 - cfg.gnss_gate_probability) if cfg.gnss_gate_probability < 1 else np.inf
    ep_idx = np.empty(n_ep, dtype=np.int64)
    ep_Pp, ep_Phi = np.empty((n_ep, _NX, _NX)), np.empty((n_ep, 9, _NX))
    ep_dx, ep_nom = np.empty((n_ep, _NX)), np.empty((n_ep, 12))
    st = np.full(len(gt), _OUTSIDE, dtype=np.int8)
    nis = np.full(len(gt), np.nan)
    e = forward_pass(t, np.ascontiguousarray(w), np.ascontiguousarray(f), np.ascontiguousarray(wm),
                 np.ascontiguousarray(fm), k0, k1, ep_flag, g_k, g_dt, gp, gc, p_b_a, P0, qc, Gam,
                 float(gate), cfg.gnss_gate_reset_s, *sd.frame_arrays(frame), P_n, V_n, R_n,
                 ep_idx, ep_Pp, ep_Phi, ep_dx, ep_nom, st, nis)
    if e != n_ep:  # cannot happen: the schedule and the kernel disagree
        raise RuntimeError(f"filter produced {e} epochs, expected {n_ep}")

    # ---- smoother and corrections at every sample
    ep_t = t[ep_idx]
    ds, sig = np.empty((n_ep, _NX)), np.empty((n_ep, _NX))
    rts_smooth(ep_t, ep_Pp, ep_Phi, ep_dx, qc, ds, sig)
    del ep_Pp, ep_Phi
    bias = np.empty((N, 6))
    apply_smoothed(t, ep_idx, ds, ep_dx, ep_nom, P_n, V_n, R_n, bias)
    scale = ep_nom[0, 6:] + ds[0, 15:]
    ts = t[span]
    sigma = np.empty((len(ts), 15))
    for i in range(15):
        sigma[:, i] = np.interp(ts, ep_t, sig[:, i])

    status = np.full(G, _OUTSIDE, dtype=np.int8)
    status[inside] = st
    nis_all = np.full(G, np.nan)
    nis_all[inside] = nis
    result = FilterResult(ts, P_n[span], V_n[span], R_n[span], bias[span, :3], bias[span, 3:], sigma,
                          scale[:3], scale[3:], sig[0, 15:], float(t0_gps), status, nis_all, t_align,
                          f_level is not None)
    log.info("EKF/RTS: %d samples, %d filter epochs, %d GNSS updates, %d rejected; heading aligned "
             "at %.1f s, %s", len(ts), n_ep, result.n_gnss_updates, result.n_gnss_rejected, t_align,
             "levelled" if f_level is not None else "not levelled")
    return result
