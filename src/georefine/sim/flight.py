"""The true helicopter trajectory of a corridor flight (docs/ARCHITECTURE.md §6 "Flight").

The flight follows paper 000 (Eisacktal power-line corridor): take-off from a pad after a
static alignment period, an initialisation manoeuvre (figure-eight or S-turns with bank,
accelerations and climbs, as helicopter crews fly to make heading and accelerometer biases
observable), then one or two straight passes along the corridor at ~160 m above ground
and ~18 m/s: north -> south, a procedure turn, south -> north. The corridor runs along the
``w`` y-axis from ``y = 0`` to ``y = corridor_length_m`` at ``x = 0``; the height follows
the smoothed terrain. A constant cross wind makes the heading differ from the track by the
crab angle on the passes.

Construction (everything in the product is analytic; nothing is differentiated numerically)

1. *Design*: ground speed ``V(t)`` and grid track ``psi(t)`` (clockwise from ``w`` north)
   are closed-form sums of C3 septic smoothsteps, so turns roll in and out smoothly. The
   horizontal path is their integral on a fine grid; the procedure turn is closed so that
   the return pass lies on ``x = 0`` and the whole pre-corridor part is shifted so that
   the first pass does. Height = smoothed terrain along the path + AGL profile.
2. *Position truth*: an interpolating quintic B-spline (C4) through the design sampled
   every 0.2 s. Velocity and acceleration are its exact derivatives.
3. *Attitude truth*: from the position spline, the coordinated-flight attitude is sampled
   (heading = direction of the air velocity, i.e. track + crab; pitch = cruise trim minus
   ``atan(a_forward / g)``; roll such that the specific force has no body-y component,
   ``tan(roll) = a_lateral / g``), and interpolated by quintic B-splines of NED roll, pitch
   and (unwrapped) heading. *Whatever these splines say is the truth*; their derivatives
   give the Euler rates.
4. Optional vibration: sinusoids (5-30 Hz) added to position and Euler angles.

Then ``R_w_b(t) = R_w_n(lat(t), lon(t)) R_n_b(rph(t))`` and
``omega_wb_b = R_b_n omega_en_n + omega_nb_b`` with the exact transport rate of the NED
frame along the path (``w`` is Earth-fixed, so ``omega_wn = omega_en``), and the IMU truth
``f_ib_b = R_w_b^T (a_w + 2 omega_ie_w x v_w - g_w(p_w))``,
``omega_ib_b = omega_wb_b + R_w_b^T omega_ie_w`` (docs/ARCHITECTURE.md §4.1, §4.3).

Before take-off (``t <= static_duration_s``) the body is exactly at rest on the pad.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Literal, Sequence

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.integrate import cumulative_simpson
from scipy.interpolate import BSpline, make_interp_spline
from scipy.ndimage import gaussian_filter1d

from georefine.errors import ConfigError
from georefine.geometry import earth
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import R_n_b_from_rph, omega_nb_b_from_rph_rates, wrap_angle
from georefine.sim.flight_plan import PlannedLine, Primitive, dubins_path

log = logging.getLogger(__name__)

TerrainFn = Callable[[np.ndarray, np.ndarray], np.ndarray]

_SAMPLE_S = 0.2  # spacing of the design samples interpolated by the splines
_FINE = 40  # fine integration steps per sample
_TAIL_S = 10.0  # design continues beyond the end so that the spline end condition is outside
_CHUNK = 500_000  # evaluation chunk (memory bound ~ 0.5 GB at most)


class VibrationConfig(BaseModel):
    """Airframe vibration added to the smooth motion (sinusoids, seeded).

    Applied throughout, also on the pad (rotor running): with vibration enabled the static
    period is not exactly at rest.
    """

    model_config = ConfigDict(extra="forbid")

    enabled: bool = False
    frequencies_hz: tuple[float, ...] = Field(
        (6.5, 13.0, 26.0), description="main-rotor 1/rev and harmonics of a light helicopter"
    )
    angular_amplitude_deg: float = Field(0.005, ge=0, description="per frequency and axis")
    linear_amplitude_m: float = Field(5e-5, ge=0, description="per frequency and axis")
    seed: int = 7

    @model_validator(mode="after")
    def _check(self) -> "VibrationConfig":
        if any(not (0.5 <= f <= 100.0) for f in self.frequencies_hz):
            raise ValueError("vibration frequencies must be within 0.5-100 Hz (typically 5-30 Hz)")
        return self


class FlightConfig(BaseModel):
    """Helicopter corridor flight (defaults: paper 000, 160 m AGL at 18 m/s, two passes)."""

    model_config = ConfigDict(extra="forbid")

    altitude_agl_m: float = Field(160.0, gt=0)
    speed_mps: float = Field(18.0, gt=0)
    passes: Literal[1, 2] = 2
    static_duration_s: float = Field(10.0, ge=0, description="at rest on the pad, for alignment")
    manoeuvre: Literal["figure_eight", "s_turns", "none"] = "figure_eight"
    manoeuvre_turn_rate_deg_per_s: float = Field(10.0, gt=0, le=30)
    manoeuvre_speed_change_mps: float = Field(4.0, ge=0)
    manoeuvre_climb_m: float = Field(20.0, ge=0)
    approach_duration_s: float = Field(15.0, ge=0, description="straight, before the lead-in")
    lead_in_m: float = Field(200.0, ge=0)
    lead_out_m: float = Field(200.0, ge=0)
    turn_radius_m: float = Field(200.0, gt=0, description="procedure turn between passes")
    procedure_turn_angle_deg: float = Field(45.0, gt=5, lt=85)
    roll_in_s: float = Field(3.0, gt=0, description="heading-rate ramp at turn entry/exit")
    crab_angle_deg: float = Field(
        3.0, gt=-30, lt=30, description="heading - track on the N->S pass (wind blows east)"
    )
    cruise_pitch_deg: float = Field(-2.0, description="nose-down trim at cruise speed")
    ground_roll_deg: float = 0.3
    ground_pitch_deg: float = 1.5
    ground_clearance_m: float = Field(1.2, ge=0, description="IMU above ground on the pad")
    hover_s: float = Field(5.0, ge=0, description="vertical lift-off before accelerating")
    acceleration_s: float = Field(20.0, gt=0)
    climb_s: float = Field(40.0, gt=0)
    terrain_smoothing_m: float = Field(150.0, ge=0, description="Gaussian sigma along track")
    start_time_gps_s: float = Field(
        1399708800.0, description="dataset epoch t0: 2024-05-14 08:00:00 GPST (s since 1980-01-06)"
    )
    vibration: VibrationConfig = VibrationConfig()


@dataclass(frozen=True)
class TrueState:
    """True body state at times ``time`` (s rel. epoch): ``p_w_b`` (N,3) m, ``v_w_b`` (N,3) m/s,
    ``a_w_b`` (N,3) m/s^2 (derivatives of ``p_w_b`` in ``w``), ``R_w_b`` (N,3,3),
    ``omega_wb_b`` (N,3) rad/s."""

    time: np.ndarray
    p_w_b: np.ndarray
    v_w_b: np.ndarray
    a_w_b: np.ndarray
    R_w_b: np.ndarray
    omega_wb_b: np.ndarray


@dataclass(frozen=True)
class _Model:
    """Splines and constants behind :class:`TrueTrajectory`."""

    t_static: float
    t_end: float
    pos: BSpline  # p_w (t), valid on [t_static, t_end]
    vel: BSpline
    acc: BSpline
    rph: BSpline  # roll, pitch, unwrapped heading (rad)
    rph_dot: BSpline
    p_static: np.ndarray
    rph_static: np.ndarray
    vib_omega: np.ndarray  # (F,) rad/s
    vib_lin: np.ndarray  # (F, 3) m
    vib_lin_phase: np.ndarray  # (F, 3)
    vib_ang: np.ndarray  # (F, 3) rad
    vib_ang_phase: np.ndarray  # (F, 3)

    def position(self, t: np.ndarray, order: int):
        """Position and up to ``order`` derivatives (list of (N,3))."""
        tc = np.clip(t, self.t_static, self.t_end)
        moving = t > self.t_static
        out = [np.where(moving[:, None], self.pos(tc), self.p_static)]
        for spl in (self.vel, self.acc)[:order]:
            out.append(np.where(moving[:, None], spl(tc), 0.0))
        return self._add_vibration(out, t, self.vib_lin, self.vib_lin_phase)

    def attitude(self, t: np.ndarray, order: int):
        """NED roll, pitch, heading (rad) and optionally their rates (list of (N,3))."""
        tc = np.clip(t, self.t_static, self.t_end)
        moving = t > self.t_static
        out = [np.where(moving[:, None], self.rph(tc), self.rph_static)]
        if order:
            out.append(np.where(moving[:, None], self.rph_dot(tc), 0.0))
        return self._add_vibration(out, t, self.vib_ang, self.vib_ang_phase)

    def _add_vibration(self, out, t, amp, phase):
        if len(self.vib_omega) == 0:
            return out
        for w, a, ph in zip(self.vib_omega, amp, phase):
            arg = w * t[:, None] + ph
            s, c = np.sin(arg), np.cos(arg)
            terms = (a * s, a * w * c, -a * w * w * s)
            for i in range(len(out)):
                out[i] = out[i] + terms[i]
        return out


@dataclass(frozen=True)
class TrueTrajectory:
    """The true body (IMU) trajectory of a simulated flight.

    Attributes
    ----------
    frame : LocalFrame
        The mapping frame ``w``.
    t0_gps : float
        Dataset epoch (GPS seconds since 1980-01-06); all times are seconds relative to it.
    duration_s : float
        The trajectory is defined on ``[0, duration_s]``.
    passes : tuple of (strip_id, t_start, t_end)
        Straight scanning legs (strip 1 north -> south, strip 2 south -> north), including
        the lead-in and lead-out, so that scanning them covers the whole corridor.
    phases : tuple of (name, t_start, t_end)
        Flight phases: ``static``, ``takeoff``, ``manoeuvre``, ``approach``, ``pass``,
        ``turn``, ``end``.
    config : FlightConfig
    corridor_length_m : float
    """

    frame: LocalFrame
    t0_gps: float
    duration_s: float
    passes: tuple
    phases: tuple
    config: FlightConfig
    corridor_length_m: float
    _model: _Model = field(repr=False)

    # ------------------------------------------------------------------ evaluation
    def pose(self, t):
        """Body pose ``(p_w_b (N,3) m, R_w_b (N,3,3))`` at times ``t`` (N,) s; scalar t -> (3,), (3,3)."""
        t, shape = self._times(t)
        p = np.empty((len(t), 3))
        R = np.empty((len(t), 3, 3))
        for sl in _chunks(len(t)):
            (p[sl],) = self._model.position(t[sl], 0)
            (rph,) = self._model.attitude(t[sl], 0)
            R[sl] = self.frame.R_w_b_from_rph(p[sl], rph)
        return p.reshape(shape + (3,)), R.reshape(shape + (3, 3))

    def state(self, t) -> TrueState:
        """Full true state (position, velocity, acceleration, attitude, body rate) at ``t`` (N,)."""
        t, shape = self._times(t)
        n = len(t)
        p, v, a, om = (np.empty((n, 3)) for _ in range(4))
        R = np.empty((n, 3, 3))
        for sl in _chunks(n):
            p[sl], v[sl], a[sl] = self._model.position(t[sl], 2)
            rph, rph_dot = self._model.attitude(t[sl], 1)
            lat, lon, h = self.frame.to_geodetic(p[sl])
            R_w_n = self.frame.R_w_n(lat, lon)
            R_n_b = R_n_b_from_rph(rph[:, 0], rph[:, 1], rph[:, 2])
            R[sl] = R_w_n @ R_n_b
            v_n = np.einsum("nji,nj->ni", R_w_n, v[sl])
            w_en_n = earth.transport_rate_n(lat, h, v_n)
            om[sl] = np.einsum("nji,nj->ni", R_n_b, w_en_n) + omega_nb_b_from_rph_rates(rph, rph_dot)
        return TrueState(
            t.reshape(shape), p.reshape(shape + (3,)), v.reshape(shape + (3,)),
            a.reshape(shape + (3,)), R.reshape(shape + (3, 3)), om.reshape(shape + (3,)),
        )

    def imu(self, t):
        """Exact IMU truth ``(omega_ib_b (N,3) rad/s, f_ib_b (N,3) m/s^2)`` at times ``t`` (N,).

        ``f_ib_b = R_w_b^T (a_w + 2 omega_ie_w x v_w - g_w(p_w))``,
        ``omega_ib_b = omega_wb_b + R_w_b^T omega_ie_w``.
        """
        s = self.state(t)
        w_ie = self.frame.omega_ie_w
        spec_w = s.a_w_b + 2.0 * np.cross(w_ie, s.v_w_b) - self.frame.gravity_w(s.p_w_b)
        f_b = np.einsum("...ji,...j->...i", s.R_w_b, spec_w)
        w_b = s.omega_wb_b + np.einsum("...ji,j->...i", s.R_w_b, w_ie)
        return w_b, f_b

    def rph(self, t) -> np.ndarray:
        """True NED roll, pitch, heading (rad; heading in [0, 2 pi)) at ``t`` (N,) -> (N,3)."""
        t, shape = self._times(t)
        (rph,) = self._model.attitude(t, 0)
        rph = rph.copy()
        rph[:, 2] = np.mod(rph[:, 2], 2.0 * np.pi)
        return rph.reshape(shape + (3,))

    # ------------------------------------------------------------------ helpers
    def _times(self, t):
        t = np.asarray(t, dtype=float)
        shape = t.shape
        t = t.reshape(-1)
        if t.size and (np.nanmin(t) < -1e-9 or np.nanmax(t) > self.duration_s + 1e-9 or np.isnan(t).any()):
            raise ValueError(
                f"times must lie within [0, {self.duration_s:.3f}] s of the trajectory, "
                f"got [{np.nanmin(t):.3f}, {np.nanmax(t):.3f}]"
            )
        return t, shape


def _chunks(n):
    return [slice(i, min(i + _CHUNK, n)) for i in range(0, max(n, 1), _CHUNK)]


# ---------------------------------------------------------------------------- design
def _smoothstep(u):
    """Septic smoothstep (C3): 0 for u <= 0, 1 for u >= 1."""
    u = np.clip(u, 0.0, 1.0)
    return u**4 * (35.0 - 84.0 * u + 70.0 * u**2 - 20.0 * u**3)


def _smoothstep_integral(u):
    """Integral of :func:`_smoothstep` from 0 to ``u`` for ``u`` in [0, 1]."""
    u = np.clip(u, 0.0, 1.0)
    return u**5 * (7.0 - 14.0 * u + 10.0 * u**2 - 2.5 * u**3)


@dataclass
class _Design:
    """Closed-form design: turns (t0, duration, dpsi, ramp), speed and AGL steps (t0, dur, delta)."""

    turns: list = field(default_factory=list)
    speed: list = field(default_factory=list)
    agl: list = field(default_factory=list)
    phases: list = field(default_factory=list)
    marks: dict = field(default_factory=dict)

    def add_turn(self, t0, dpsi, rate, ramp):
        T = abs(dpsi) / rate + ramp
        self.turns.append((t0, T, dpsi, ramp))
        return t0 + T

    def track(self, t):
        """Grid track (rad, clockwise from w north); starts southbound."""
        psi = np.full_like(t, np.pi)
        for t0, T, dpsi, ramp in self.turns:
            tau = np.clip(t - t0, 0.0, T)
            part = np.where(
                tau < ramp,
                ramp * _smoothstep_integral(tau / ramp),
                np.where(tau <= T - ramp, 0.5 * ramp + (tau - ramp),
                         T - ramp - ramp * _smoothstep_integral((T - tau) / ramp)),
            )
            psi = psi + np.sign(dpsi) * (abs(dpsi) / (T - ramp)) * part
        return psi

    @staticmethod
    def _steps(steps, t, base):
        out = np.full_like(t, base)
        for t0, dur, delta in steps:
            out = out + delta * _smoothstep((t - t0) / dur)
        return out

    def speed_at(self, t):
        return self._steps(self.speed, t, 0.0)

    def agl_at(self, t, base):
        return self._steps(self.agl, t, base)


def _preamble(cfg: FlightConfig, D: _Design) -> float:
    """Static alignment, take-off, initialisation manoeuvre and approach; returns the approach's end."""
    V = cfg.speed_mps
    ts = cfg.static_duration_s
    if ts > 0:
        D.phases.append(("static", 0.0, ts))
    D.marks["t_static"] = ts
    D.speed.append((ts + cfg.hover_s, cfg.acceleration_s, V))
    D.agl.append((ts, cfg.climb_s, cfg.altitude_agl_m - cfg.ground_clearance_m))
    t = ts + cfg.hover_s + cfg.acceleration_s
    D.phases.append(("takeoff", ts, t))

    if cfg.manoeuvre != "none":
        rate, ramp = np.radians(cfg.manoeuvre_turn_rate_deg_per_s), cfg.roll_in_s
        angles = [2 * np.pi, -2 * np.pi] if cfg.manoeuvre == "figure_eight" else [
            np.pi / 2, -np.pi, np.pi / 2]
        t_m0 = t
        for i, a in enumerate(angles):
            t = D.add_turn(t, a, rate, ramp) + (2.0 if i < len(angles) - 1 else 0.0)
        t_mid, dv, dh = 0.5 * (t_m0 + t), cfg.manoeuvre_speed_change_mps, cfg.manoeuvre_climb_m
        D.speed += [(t_m0, 8.0, dv), (t_mid - 5.0, 10.0, -2 * dv), (t - 10.0, 10.0, dv)]
        D.agl += [(t_m0 + 3.0, 15.0, dh), (t_mid, 15.0, -2 * dh), (t - 15.0, 15.0, dh)]
        D.phases.append(("manoeuvre", t_m0, t))
    t_a = t
    t += cfg.approach_duration_s
    if t > t_a:
        D.phases.append(("approach", t_a, t))
    return t


def _timeline(cfg: FlightConfig, L: float, d_m: float, tail_m: float) -> _Design:
    """Build the closed-form design with procedure-turn straight ``d_m``."""
    D = _Design()
    V = cfg.speed_mps
    t = _preamble(cfg, D)
    leg = (L + cfg.lead_in_m + cfg.lead_out_m) / V
    D.marks["leg1"] = (t, t + leg)
    D.phases.append(("pass", t, t + leg))
    t += leg
    if cfg.passes == 2:
        rate, alpha = V / cfg.turn_radius_m, np.radians(cfg.procedure_turn_angle_deg)
        t_t0 = t
        t = D.add_turn(t, alpha, rate, cfg.roll_in_s)
        t = D.add_turn(t + d_m / V, -(np.pi + alpha), rate, cfg.roll_in_s)
        D.phases.append(("turn", t_t0, t))
        D.marks["turn_end"] = t
    D.marks["t_tail"] = t + tail_m / V
    return D


def _integrate(D: _Design, t_fine: np.ndarray):
    """Horizontal design path (x, y) from rest at the origin, on the fine grid."""
    V, psi = D.speed_at(t_fine), D.track(t_fine)
    x = cumulative_simpson(V * np.sin(psi), x=t_fine, initial=0.0)
    y = cumulative_simpson(V * np.cos(psi), x=t_fine, initial=0.0)
    return x, y


def _fine_grid(t0, t1):
    n = int(np.ceil((t1 - t0) / _SAMPLE_S))
    return t0 + np.arange(n * _FINE + 1) * (_SAMPLE_S / _FINE)


def _horizontal(cfg: FlightConfig, L: float):
    """Closed design and its horizontal path; returns (design, t_fine, x, y, t_end)."""
    V = cfg.speed_mps
    alpha = np.radians(cfg.procedure_turn_angle_deg)
    d = 2.0 * cfg.turn_radius_m / np.tan(alpha)  # exact for arcs without roll-in
    span = L + cfg.lead_in_m + cfg.lead_out_m
    tail = span + cfg.lead_out_m + 2.0 * cfg.turn_radius_m * (np.sin(alpha) + 2.0) + d + V * (_TAIL_S + 5.0)
    for _ in range(4):
        D = _timeline(cfg, L, d, tail)
        t_fine = _fine_grid(D.marks["t_static"], D.marks["t_tail"])
        x, y = _integrate(D, t_fine)
        t1 = D.marks["leg1"][0]
        x0, y0 = np.interp(t1, t_fine, x), np.interp(t1, t_fine, y)
        x, y = x - x0, y - y0 + L + cfg.lead_in_m
        if cfg.passes == 1:
            break
        x_err = np.interp(D.marks["turn_end"], t_fine, x)
        if abs(x_err) < 1e-7:
            break
        d += x_err / np.sin(alpha)
    if d < 0:
        raise ValueError("procedure turn cannot be closed; increase procedure_turn_angle_deg")
    passes = [(1, *D.marks["leg1"])]
    if cfg.passes == 2:
        t_te = D.marks["turn_end"]
        y_te = np.interp(t_te, t_fine, y)
        t2 = t_te + max(0.0, (-cfg.lead_in_m - y_te) / V)
        t3 = t2 + span / V
        passes.append((2, t2, t3))
        if t2 > t_te:
            D.phases.append(("approach", t_te, t2))
        D.phases.append(("pass", t2, t3))
        t_end = t3 + 3.0
    else:
        t_end = D.marks["leg1"][1] + 3.0
    D.phases.append(("end", passes[-1][2], t_end))
    return D, t_fine, x, y, passes, t_end


def _integrate_from(D: _Design, t0: float, t1: float, p0: np.ndarray) -> np.ndarray:
    """Horizontal position at ``t1`` of the design flown from ``p0`` at ``t0`` (fine grid, Simpson)."""
    n = max(2, 2 * int(np.ceil((t1 - t0) / (2.0 * _SAMPLE_S / _FINE))))
    t = np.linspace(t0, t1, n + 1)
    V, psi = D.speed_at(t), D.track(t)
    return p0 + np.array([cumulative_simpson(V * np.sin(psi), x=t)[-1], cumulative_simpson(V * np.cos(psi), x=t)[-1]])


def _append(D: _Design, t: float, primitives, V: float, ramp: float) -> float:
    """Add ideal ``primitives`` starting at ``t`` (each arc's roll-in centred on its ideal start); returns their end."""
    for q in primitives:
        if q.turn_rad == 0.0:
            t += q.length_m / V
        elif abs(q.turn_rad) > 1e-9:
            # A short arc rolls in and out within its own duration (the ramps of a turn must not overlap).
            arc_s = q.path_length_m / V
            r = min(ramp, arc_s)
            D.add_turn(t - 0.5 * r, q.turn_rad, V / q.radius_m, r)
            t += arc_s
    return t


def _line_primitives(line: PlannedLine, cfg: FlightConfig, bend_radius_m: float):
    """Straights and bends that fly ``line`` from its lead-in to its lead-out (ideal geometry)."""
    v = line.vertices
    seg = np.linalg.norm(np.diff(v, axis=0), axis=1)
    az = np.arctan2(np.diff(v[:, 0]), np.diff(v[:, 1]))
    bends = wrap_angle(np.diff(az), 2.0 * np.pi)
    tangent = bend_radius_m * np.tan(np.abs(bends) / 2.0)
    straight = seg.copy()
    straight[0] += cfg.lead_in_m
    straight[-1] += cfg.lead_out_m
    straight[:-1] -= tangent
    straight[1:] -= tangent
    if np.any(straight < 0):
        raise ConfigError("a bend of the flight plan does not fit its line", field="plan.bend_radius_m",
                          expected=f"segments longer than the bends' tangents ({np.round(tangent, 1).tolist()} m)",
                          found=f"line {line.line_id}: segments {np.round(seg, 1).tolist()} m")
    out = []
    for k, length in enumerate(straight):
        out.append(Primitive(length_m=float(length)))
        if k < len(bends):
            out.append(Primitive(turn_rad=float(bends[k]), radius_m=bend_radius_m))
    return out


def _planned_horizontal(cfg: FlightConfig, lines, bend_radius_m: float, transit_m: float):
    """Design and horizontal path of a flight plan: the preamble, then each line after a Dubins turn.

    Every connection is planned from the pose the design reaches at the end of the line before
    (the roll-in smoothing moves it by decimetres from the ideal arcs) and re-aimed until the
    design flown from that pose starts the next lead-in within 1 mm of the plan. The next turn's
    roll-in, centred on the line's end, begins half a roll-in before that pose, which the
    re-aiming does not see: the lines as flown lie up to about 0.3 m beside the plan (measured;
    the tests allow 0.5 m), parallel to it. The strip is the line's straight flight, lead-in and
    lead-out included, without the half roll-in of the turns at either end.
    """
    V, R, ramp = cfg.speed_mps, cfg.turn_radius_m, cfg.roll_in_s
    D = _Design()
    t = _preamble(cfg, D)
    ts = D.marks["t_static"]
    p = _integrate_from(D, ts, t, np.zeros(2))
    az = float(D.track(np.array([t]))[0])
    first = lines[0]
    s1 = first.vertices[0] - cfg.lead_in_m * np.array([np.sin(first.start_heading), np.cos(first.start_heading)])
    u1 = np.array([np.sin(first.start_heading), np.cos(first.start_heading)])
    # The take-off pad placed so that the first line is reached by a one-sided turn (2 R to the
    # right of the line's lead-in, ``transit_m`` further back): a pad straight behind it would
    # make the turn to the left and the turn to the right equally short.
    shift = s1 - (2.0 * R + transit_m) * u1 + 2.0 * R * np.array([u1[1], -u1[0]]) - p
    p = p + shift
    passes, worst = [], 0.0
    for line in lines:
        u = np.array([np.sin(line.start_heading), np.cos(line.start_heading)])
        goal = line.vertices[0] - cfg.lead_in_m * u
        aim, t_turn = goal.copy(), t
        for _ in range(12):
            trial = _Design(list(D.turns), D.speed, D.agl, D.phases, D.marks)
            t_line = _append(trial, t, dubins_path(p, az, aim, line.start_heading, R), V, ramp)
            reached = _integrate_from(trial, t, t_line, p)
            miss = goal - reached
            aim = aim + miss
            if np.hypot(*miss) < 1e-3:
                break
        worst = max(worst, float(np.hypot(*miss)))
        D.turns = trial.turns
        if t_line > t_turn:
            D.phases.append(("turn", t_turn, t_line))
        t_end = _append(D, t_line, _line_primitives(line, cfg, bend_radius_m), V, ramp)
        passes.append((line.line_id, t_line + 0.5 * ramp, t_end - 0.5 * ramp))
        D.phases.append(("pass", t_line, t_end))
        p = _integrate_from(D, t_line, t_end, reached)
        az, t = line.end_heading, t_end
    if worst > 0.05:
        log.warning("flight plan: a line starts %.2f m from its planned position", worst)
    t_end = t + 3.0
    D.phases.append(("end", t, t_end))
    t_fine = _fine_grid(ts, t_end + _TAIL_S + 5.0)
    x, y = _integrate(D, t_fine)
    return D, t_fine, x + shift[0], y + shift[1], passes, t_end


def _bc(n, left, right):
    z = np.zeros(n) if n > 1 else 0.0
    return ([(left[0], z), (left[1], z)], [(right[0], z), (right[1], z)])


def simulate_flight(
    cfg: FlightConfig, frame: LocalFrame, corridor_length_m: float, terrain_height: TerrainFn,
    lines: Sequence[PlannedLine] | None = None, *, bend_radius_m: float = 600.0, transit_m: float = 0.0,
) -> TrueTrajectory:
    """Build the true trajectory of a corridor flight, or of a flight plan's ``lines``.

    Parameters
    ----------
    cfg : FlightConfig
    frame : LocalFrame
        Mapping frame ``w``; the corridor runs along its y-axis (north).
    corridor_length_m : float
        Corridor from ``y = 0`` to ``y = corridor_length_m`` at ``x = 0`` [m].
    terrain_height : callable
        ``terrain_height(x, y) -> z`` of the ground in ``w`` [m], vectorised.
    lines : sequence of PlannedLine, optional
        A flight plan (:func:`georefine.sim.flight_plan.plan_lines`), flown in order after the
        preamble with Dubins turns of ``cfg.turn_radius_m`` between the lines; bends inside a line
        are flown at ``bend_radius_m``; ``transit_m`` of straight flight lead to the first line.
        ``cfg.passes`` and the procedure turn are then unused; each line is a pass (strip).

    Returns
    -------
    TrueTrajectory
    """
    L = float(corridor_length_m)
    if not L > 0:
        raise ValueError(f"corridor_length_m must be positive, got {corridor_length_m}")
    if lines:
        D, t_fine, x_f, y_f, passes, t_end = _planned_horizontal(cfg, list(lines), bend_radius_m, transit_m)
    else:
        D, t_fine, x_f, y_f, passes, t_end = _horizontal(cfg, L)
    ts = D.marks["t_static"]
    t_s = t_fine[::_FINE]
    x, y = x_f[::_FINE], y_f[::_FINE]

    # Height: terrain under the pad blended into the along-track smoothed terrain, plus AGL.
    ground = np.asarray(terrain_height(x, y), dtype=float)
    sigma = cfg.terrain_smoothing_m / cfg.speed_mps / _SAMPLE_S
    smooth = gaussian_filter1d(ground, sigma, mode="nearest") if sigma > 0 else ground
    beta = _smoothstep((t_s - ts) / cfg.climb_s)
    z = (1.0 - beta) * ground[0] + beta * smooth + D.agl_at(t_s, cfg.ground_clearance_m)
    P = np.stack([x, y, z], axis=1)
    pos = make_interp_spline(t_s, P, k=5, bc_type=_bc(3, (1, 2), (3, 4)))
    vel, acc = pos.derivative(1), pos.derivative(2)

    # Coordinated-flight attitude sampled from the position spline.
    a_w = acc(t_s)
    lat, lon, h = frame.to_geodetic(P)
    R_n_w = np.swapaxes(frame.R_w_n(lat, lon), 1, 2)
    g = earth.normal_gravity(lat, h)
    a_n = np.einsum("nij,nj->ni", R_n_w, a_w)
    psi = D.track(t_s)
    V = D.speed_at(t_s)
    u_w = np.stack([np.sin(psi), np.cos(psi), np.zeros_like(psi)], axis=1)
    u_n = np.einsum("nij,nj->ni", R_n_w, u_w)
    track = np.arctan2(u_n[:, 1], u_n[:, 0])
    wind_w = np.array([cfg.speed_mps * np.tan(np.radians(cfg.crab_angle_deg)), 0.0, 0.0])
    air_n = np.einsum("nij,nj->ni", R_n_w, V[:, None] * u_w - wind_w)
    crab = wrap_angle(np.arctan2(air_n[:, 1], air_n[:, 0]) - track, closed="lower")
    airborne = _smoothstep((V - 3.0) / 8.0)
    heading = np.unwrap(track + airborne * crab)
    ch, sh = np.cos(heading), np.sin(heading)
    a_fwd = ch * a_n[:, 0] + sh * a_n[:, 1]
    a_right = -sh * a_n[:, 0] + ch * a_n[:, 1]
    f_down = a_n[:, 2] - g
    pitch_f = np.radians(cfg.cruise_pitch_deg) * np.clip(V / cfg.speed_mps, 0.0, 1.5) - np.arctan2(a_fwd, g)
    # Specific force in the heading-pitch frame; roll zeroes its body-y component.
    cp, sp = np.cos(pitch_f), np.sin(pitch_f)
    f2, f3 = a_right, sp * (ch * a_n[:, 0] + sh * a_n[:, 1]) + cp * f_down
    roll_f = np.arctan2(f2, -f3)
    roll = (1.0 - beta) * np.radians(cfg.ground_roll_deg) + beta * roll_f
    pitch = (1.0 - beta) * np.radians(cfg.ground_pitch_deg) + beta * pitch_f
    RPH = np.stack([roll, pitch, heading], axis=1)
    rph = make_interp_spline(t_s, RPH, k=5, bc_type=_bc(3, (1, 2), (3, 4)))

    vib = cfg.vibration
    rng = np.random.default_rng(vib.seed)
    nf = len(vib.frequencies_hz) if vib.enabled else 0
    model = _Model(
        t_static=ts,
        t_end=float(t_end),
        pos=pos, vel=vel, acc=acc, rph=rph, rph_dot=rph.derivative(1),
        p_static=P[0].copy(), rph_static=RPH[0].copy(),
        vib_omega=2.0 * np.pi * np.asarray(vib.frequencies_hz[:nf], dtype=float),
        vib_lin=vib.linear_amplitude_m * rng.uniform(0.5, 1.0, (nf, 3)),
        vib_lin_phase=rng.uniform(0.0, 2.0 * np.pi, (nf, 3)),
        vib_ang=np.radians(vib.angular_amplitude_deg) * rng.uniform(0.5, 1.0, (nf, 3)),
        vib_ang_phase=rng.uniform(0.0, 2.0 * np.pi, (nf, 3)),
    )
    traj = TrueTrajectory(
        frame=frame,
        t0_gps=float(cfg.start_time_gps_s),
        duration_s=float(t_end),
        passes=tuple((int(i), float(a), float(b)) for i, a, b in passes),
        phases=tuple((n, float(a), float(b)) for n, a, b in D.phases),
        config=cfg,
        corridor_length_m=L,
        _model=model,
    )
    log.info(
        "flight: %.1f s, %d pass(es), corridor %.0f m, %.0f m AGL at %.1f m/s",
        t_end, len(passes), L, cfg.altitude_agl_m, cfg.speed_mps,
    )
    return traj
