"""GNSS antenna positions as a post-processed kinematic (PPK) solution would deliver them.

Error model per epoch, in the local north-east-up frame of the true antenna position::

    e_k = white_k + d_k,   white_k ~ N(0, diag(sigma_n, sigma_e, sigma_u)^2)
    d_k = phi d_k-1 + sqrt(1 - phi^2) s w_k,   phi = exp(-dt / tau),  d_0 ~ N(0, s^2)

``d`` is a first-order Gauss-Markov process per axis (the time-correlated part that the
adjustment can model, docs/ARCHITECTURE.md §4.3; structure after Pöppl et al. 2023a, "Modelling of GNSS
positioning errors in a GNSS/INS/LiDAR-integrated georeferencing"). It runs through
outages; epochs inside an outage are removed.

Defaults (:class:`GnssConfig`): carrier-phase fixed solutions. NovAtel's OEM7 family
specifies RTK accuracy as 1 cm + 1 ppm horizontal RMS (SMART7/OEM7 user manuals,
performance specifications), vertical typically twice the horizontal. The default splits
this into white noise (1 cm north/east, 2 cm up) and a correlated part that stands for the
baseline-dependent term at 10-20 km from the base (1.5 cm horizontal, 3 cm up, 300 s),
i.e. 1.8 cm horizontal and 3.6 cm vertical in total per axis. The reported standard
deviations (``sdn sde sdu`` of a ``.pos`` file) are these totals. The default rate is
5 Hz, a common logging rate of airborne survey receivers and hence of the PPK output;
because the errors are time-correlated, higher rates add little information.

Float segments (``float_segments``, none by default): where the ambiguities stay float, RTKLIB
flags the epochs ``Q=2`` and states larger but still centimetric sigmas (``float_sd_m``, 5/5/10 cm),
while the solution is off by about one offset of decimetres: per segment an offset drawn with
``float_offset_sigma_*`` (1 sigma per axis) is added to the errors above, constant over it.

Multipath (``multipath_sigma_*``, off by default): signals reflected off the airframe and, at low
elevation, the ground reach the antenna late; the carrier-phase error they cause changes as the
geometry of aircraft, reflector and satellites does, over seconds to tens of seconds, and
reaches a centimetre or two in a fixed airborne solution (Braasch 2017, "Multipath", in
Teunissen & Montenbruck (eds.), Springer Handbook of Global Navigation Satellite Systems,
ch. 15). It is a second first-order Gauss-Markov process per axis, ``m_k``, like ``d_k`` but
with ``multipath_time_constant_s`` (20 s by default): too short for the adjustment's correlated
error on 5 s knots and 300 s prior to follow, too long to be white. The ``.pos`` sigmas stay as
they are (RTKLIB's formal sigmas do not hold it either).

Ambiguity jumps (``ambiguity_jumps``, none by default): a wrong integer fix. RTKLIB validates a
fix by the ratio test, which a wrong set of integers passes now and then; the solution then
steps by a constant offset of centimetres to decimetres (combinations of the 19 cm L1 and 24 cm
L2 wavelengths) for as long as the wrong fix is held, usually until the next re-fix, while the
file keeps ``Q=1`` and its fixed-solution sigmas (Teunissen & Verhagen 2009, "The GNSS
ambiguity ratio-test revisited", Survey Review 41(312)). Per span ``(t_start, t_end)`` an offset
drawn with ``jump_sigma_*`` (1 sigma per axis) is added to the errors, constant over it.

The multipath and the jump offsets are drawn after everything else, so a configuration without
them draws exactly as before; their truths are kept apart (``multipath_ned``, ``jump_ned``) and
are part of ``error_ned``.

Epochs fall on whole multiples of ``1 / rate_hz`` in GPS time (as receivers output them).
The antenna phase centre is ``p_w_a = p_w_b + R_w_b p_b_a``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.signal import lfilter

from georefine.geometry import earth


class GnssConfig(BaseModel):
    """Simulated PPK position solution (see module docstring for the defaults' source)."""

    model_config = ConfigDict(extra="forbid")

    grade: Literal["ppk", "ideal"] = Field(
        "ppk", description="'ideal': no errors added (the reported sd stay those of 'ppk')"
    )
    rate_hz: float = Field(5.0, ge=1.0, le=10.0)
    sigma_north_m: float = Field(0.01, ge=0, description="white noise")
    sigma_east_m: float = Field(0.01, ge=0, description="white noise")
    sigma_up_m: float = Field(0.02, ge=0, description="white noise")
    gm_sigma_horizontal_m: float = Field(0.015, ge=0, description="Gauss-Markov, per axis")
    gm_sigma_up_m: float = Field(0.03, ge=0, description="Gauss-Markov")
    gm_time_constant_s: float = Field(300.0, gt=0)
    outages: list[tuple[float, float]] = Field(
        default_factory=list, description="(t_start, t_end) s rel. epoch without solution"
    )
    num_sats: int = Field(16, ge=4)
    float_segments: list[tuple[float, float]] = Field(
        default_factory=list, description="(t_start, t_end) s rel. epoch of float solutions (Q=2, an offset each)")
    float_offset_sigma_horizontal_m: float = Field(0.2, ge=0, description="a float segment's offset, per axis")
    float_offset_sigma_up_m: float = Field(0.3, ge=0, description="a float segment's height offset")
    float_sd_m: tuple[float, float, float] = Field(
        (0.05, 0.05, 0.10), description="sd north, east, up the file states for a float epoch (m)")
    multipath_sigma_horizontal_m: float = Field(
        0.0, ge=0, description="multipath: Gauss-Markov sigma per horizontal axis, short-correlated (m; 0: none)")
    multipath_sigma_up_m: float = Field(0.0, ge=0, description="multipath: Gauss-Markov sigma of the height (m; 0: none)")
    multipath_time_constant_s: float = Field(20.0, gt=0, description="multipath: correlation time (s)")
    ambiguity_jumps: list[tuple[float, float]] = Field(
        default_factory=list, description="(t_start, t_end) s rel. epoch of wrong fixes: an offset each, "
        "the file keeps Q=1 and its sigmas")
    jump_sigma_horizontal_m: float = Field(0.08, ge=0, description="a wrong fix's offset, per horizontal axis (m)")
    jump_sigma_up_m: float = Field(0.12, ge=0, description="a wrong fix's height offset (m)")

    @model_validator(mode="after")
    def _check(self) -> "GnssConfig":
        for kind, spans in (("outage", self.outages), ("float segment", self.float_segments),
                            ("ambiguity jump", self.ambiguity_jumps)):
            for a, b in spans:
                if not b > a:
                    raise ValueError(f"{kind} ({a}, {b}) must have t_end > t_start")
        for a, b in self.ambiguity_jumps:
            for c, d in self.float_segments:
                if a <= d and c <= b:
                    raise ValueError(f"ambiguity jump ({a}, {b}) overlaps float segment ({c}, {d}): a wrong fix is a fix")
        return self

    @property
    def sigma_white_neu(self) -> np.ndarray:
        return np.array([self.sigma_north_m, self.sigma_east_m, self.sigma_up_m])

    @property
    def sigma_gm_neu(self) -> np.ndarray:
        return np.array([self.gm_sigma_horizontal_m, self.gm_sigma_horizontal_m, self.gm_sigma_up_m])

    @property
    def sigma_multipath_neu(self) -> np.ndarray:
        return np.array([self.multipath_sigma_horizontal_m, self.multipath_sigma_horizontal_m,
                         self.multipath_sigma_up_m])

    @property
    def sigma_total_neu(self) -> np.ndarray:
        """Reported standard deviation per axis (m): white and correlated parts combined."""
        return np.hypot(self.sigma_white_neu, self.sigma_gm_neu)


@dataclass(frozen=True)
class SimulatedGnss:
    """Simulated GNSS antenna positions (what a ``.pos`` file holds) and their true errors.

    Attributes
    ----------
    time : ndarray (N,)
        Epochs (s, relative to ``t0_gps``).
    lat, lon : ndarray (N,)
        Geodetic WGS84 latitude and longitude (rad) of the measured antenna position.
    h : ndarray (N,)
        Ellipsoidal height (m).
    sd_neu : ndarray (N, 3)
        Reported standard deviations north, east, up (m).
    quality : ndarray (N,) int
        RTKLIB quality flag (1 = fix, 2 = float).
    num_sats : ndarray (N,) int
    error_ned : ndarray (N, 3)
        True error (measured - true) in NED at the true antenna position (m), float offsets,
        multipath and ambiguity jumps included.
    p_b_a : ndarray (3,)
        Antenna lever arm in the body frame (m).
    t0_gps : float
        Dataset epoch (GPS seconds).
    multipath_ned, jump_ned : ndarray (N, 3) or None
        The multipath and the wrong fixes' offsets in ``error_ned`` (NED, m); None: zero.
    """

    time: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    sd_neu: np.ndarray
    quality: np.ndarray
    num_sats: np.ndarray
    error_ned: np.ndarray
    p_b_a: np.ndarray
    t0_gps: float
    multipath_ned: np.ndarray | None = None
    jump_ned: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.time)
        for name in ("lat", "lon", "h", "quality", "num_sats"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name} must have shape ({n},)")
        for name in ("sd_neu", "error_ned", "multipath_ned", "jump_ned"):
            if getattr(self, name) is not None and getattr(self, name).shape != (n, 3):
                raise ValueError(f"{name} must have shape ({n}, 3)")


def _gauss_markov(rng, n, dt, sigma, tau):
    """(n, 3) first-order Gauss-Markov sequences, stationary from the first sample."""
    phi = np.exp(-dt / tau)
    w = rng.normal(0.0, 1.0, (n, 3)) * sigma
    if n == 0:
        return w
    out = np.empty_like(w)
    out[0] = w[0]
    if n > 1:
        out[1:], _ = lfilter([np.sqrt(1.0 - phi * phi)], [1.0, -phi], w[1:], axis=0,
                             zi=(phi * w[0])[None, :])
    return out


def gnss_epochs(t0_gps: float, rate_hz: float, t_start: float, t_end: float) -> np.ndarray:
    """Times (s rel. ``t0_gps``) in ``[t_start, t_end]`` that are multiples of ``1/rate_hz`` in GPS time."""
    period = 1.0 / rate_hz
    phase = ((t0_gps * rate_hz) % 1.0) * period  # GPS time of epoch m is t0 - phase + m period
    m0 = int(np.ceil((t_start + phase) / period - 1e-9))
    m1 = int(np.floor((t_end + phase) / period + 1e-9))
    return np.arange(m0, m1 + 1) * period - phase


def simulate_gnss(traj, p_b_a, cfg: GnssConfig, t_start: float, t_end: float,
                  rng: np.random.Generator) -> SimulatedGnss:
    """Simulate GNSS antenna positions of ``traj`` on ``[t_start, t_end]`` (s rel. epoch).

    Parameters
    ----------
    traj : TrueTrajectory
        Provides ``pose(t)``, ``frame`` and ``t0_gps``.
    p_b_a : array_like (3,)
        Antenna phase centre in the body frame (m).
    cfg : GnssConfig
    t_start, t_end : float
    rng : numpy.random.Generator

    Returns
    -------
    SimulatedGnss
    """
    p_b_a = np.asarray(p_b_a, dtype=float).reshape(3)
    if not t_end > t_start:
        raise ValueError(f"need t_start < t_end, got {t_start}, {t_end}")
    t = gnss_epochs(traj.t0_gps, cfg.rate_hz, t_start, t_end)
    n = len(t)
    err_neu = np.zeros((n, 3))
    if cfg.grade == "ppk":
        err_neu = rng.normal(0.0, 1.0, (n, 3)) * cfg.sigma_white_neu
        err_neu += _gauss_markov(rng, n, 1.0 / cfg.rate_hz, cfg.sigma_gm_neu, cfg.gm_time_constant_s)
    quality = np.ones(n, dtype=np.int64)
    sd = np.broadcast_to(cfg.sigma_total_neu, (n, 3)).copy()
    offset_sigma = np.array([cfg.float_offset_sigma_horizontal_m, cfg.float_offset_sigma_horizontal_m,
                             cfg.float_offset_sigma_up_m])
    for a, b in cfg.float_segments:  # drawn after the rest: a project without them draws as before
        inside = (t >= a) & (t <= b)
        offset = rng.normal(0.0, 1.0, 3) * offset_sigma
        if cfg.grade == "ppk":
            err_neu[inside] += offset
        quality[inside] = 2
        sd[inside] = cfg.float_sd_m
    # Multipath and wrong fixes, drawn after everything above; the file's Q and sigmas stay.
    multipath = np.zeros((n, 3))
    if np.any(cfg.sigma_multipath_neu > 0):
        multipath = _gauss_markov(rng, n, 1.0 / cfg.rate_hz, cfg.sigma_multipath_neu, cfg.multipath_time_constant_s)
    jump = np.zeros((n, 3))
    jump_sigma = np.array([cfg.jump_sigma_horizontal_m, cfg.jump_sigma_horizontal_m, cfg.jump_sigma_up_m])
    for a, b in cfg.ambiguity_jumps:
        jump[(t >= a) & (t <= b)] += rng.normal(0.0, 1.0, 3) * jump_sigma
    if cfg.grade != "ppk":
        multipath[:], jump[:] = 0.0, 0.0
    err_neu = err_neu + multipath + jump
    keep = np.ones(n, dtype=bool)
    for a, b in cfg.outages:
        keep &= ~((t >= a) & (t <= b))
    t, err_neu, quality, sd = t[keep], err_neu[keep], quality[keep], sd[keep]
    ned = np.array([1.0, 1.0, -1.0])
    err_ned = err_neu * ned

    p_w_b, R_w_b = traj.pose(t)
    p_e = traj.frame.to_ecef(p_w_b + np.einsum("nij,j->ni", R_w_b, p_b_a))
    lat, lon, _ = earth.ecef_to_geodetic(p_e)
    p_e_meas = p_e + np.einsum("nij,nj->ni", earth.R_e_n(lat, lon), err_ned)
    lat_m, lon_m, h_m = earth.ecef_to_geodetic(p_e_meas)
    m = len(t)
    return SimulatedGnss(
        time=t, lat=lat_m, lon=lon_m, h=h_m,
        sd_neu=sd,
        quality=quality,
        num_sats=np.full(m, cfg.num_sats, dtype=np.int64),
        error_ned=err_ned, p_b_a=p_b_a, t0_gps=float(traj.t0_gps),
        multipath_ned=multipath[keep] * ned, jump_ned=jump[keep] * ned,
    )
