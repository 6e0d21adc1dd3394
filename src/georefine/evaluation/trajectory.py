"""Trajectory differences: an estimated trajectory against a reference (docs/ARCHITECTURE.md §5).

This is the evaluation of paper 000, §3, Fig. 9 (differences in roll, pitch and yaw between
trajectories over time; RMSE per angle in mdeg), in the style of *evo*: one library function
per tool (:func:`compare_trajectories`, and in :mod:`.trajectory_files` ``compare_sbet_files``)
that returns a frozen result, and a writer (``write_trajectory_evaluation``); the CLI only
calls them.

Conventions
-----------
Common time base
    The samples of the *sparser* of the two trajectories (larger median sample interval;
    the reference on a tie), inside the overlap of both spans and ``time_window``, are the
    common times (the denser one's if the sparser has no sample there). The other
    trajectory is interpolated to them: position linearly in ECEF, attitude ``R_e_b``
    geodesically on SO(3) (``R_k Exp(u Log(R_k^T R_k+1))``), i.e. with its own
    local-level frame carried along. At a time equal to one of its samples the
    interpolation returns that sample. Nothing is extrapolated: common times outside the
    other's span by at most ``max_time_offset_s`` (grids that agree up to rounding) take
    its end sample; common times inside a gap of the other longer than ``max_gap_s`` are
    dropped (and counted).
Attitude differences
    ``d_rph = wrap(rph_est - rph_ref)`` of the NED Euler angles (z-y-x; roll, pitch,
    heading; "yaw" is the heading), each of its own trajectory at its own position,
    wrapped to (-pi, pi] so that headings of 359.99 deg and 0.01 deg differ by 0.02 deg.
    Euler differences mix axes at large roll/pitch and are meaningless near pitch +-90
    deg; the body-frame rotation vector ``d_rotvec = Log(R_ref^T R_est)`` (``R = R_e_b``,
    so ``R_est = R_ref Exp(d_rotvec)``: the right, body-frame perturbation of docs/ARCHITECTURE.md §2)
    is reported as well and has no singularity.
Position differences
    ``d_ned = R_e_n(ref)^T (p_e_est - p_e_ref)``: the estimate minus the reference, in
    metres, in the local north-east-down frame at the reference position. "horizontal" is
    ``hypot(north, east)``, "3d" the norm of all three.
Statistics
    Per component: RMSE ``sqrt(mean(d^2))``, mean, standard deviation (population,
    ``ddof=0``, so ``rmse^2 = mean^2 + std^2``) and maximum absolute value; for norms
    (horizontal, 3d, attitude angle) mean, std and max of the norm. Keys carry the unit:
    ``roll_rmse_mdeg``, ``yaw_max_abs_mdeg``, ``horizontal_rmse_m``, ``3d_rmse_m``.
SBET time scales (``compare_sbet_files`` in :mod:`.trajectory_files`)
    SBET times are absolute GPS seconds or seconds of the GPS week (first time < 604800 s).
    With ``gps_week`` given, seconds of week are made absolute with it (a companion file
    ``<name>.json`` stating another week is an error). Without it, a seconds-of-week file
    takes the week its companion file states (Georefine writes one beside every SBET it
    produces); without one it is assumed to lie in the same GPS week as the other file: if the
    other's week is known (absolute times, or its companion file), that week is taken (of its
    first sample); if both are seconds of
    week they are compared as seconds of week directly (``time_scale="seconds_of_week"``,
    the week is unknown). The result's ``notes`` and the JSON say which case applied.

Only positions and roll/pitch/heading are used; the SBET velocities (wander frame), body
rates and accelerations are not, so the wander angle does not matter here.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from georefine.errors import InputError
from georefine.geometry.earth import R_e_n, ecef_to_geodetic, geodetic_to_ecef
from georefine.geometry.rotation import R_n_b_from_rph, exp_so3, log_so3, rph_from_R_n_b, wrap_angle
from georefine.io.files import SECONDS_PER_WEEK, week_from_gps_seconds
from georefine.io.trajectory import SbetData
from georefine.trajectory.sampled import interp_columns

__all__ = [
    "TrajectoryComparison",
    "compare_trajectories",
    "consistency",
    "ATTITUDE_NAMES",
    "POSITION_NAMES",
]

_log = logging.getLogger(__name__)

MDEG_PER_RAD = 180e3 / np.pi
ATTITUDE_NAMES = ("roll", "pitch", "yaw")
"""Components of ``d_rph_rad`` (yaw = heading)."""
ROTVEC_NAMES = ("rotvec_x", "rotvec_y", "rotvec_z")
"""Components of ``d_rotvec_rad``: about body forward, right, down."""
POSITION_NAMES = ("north", "east", "down")
"""Components of ``d_ned_m``."""
_STATS = ("rmse", "mean", "std", "max_abs")


def _stats(name: str, d: np.ndarray, scale: float, unit: str) -> dict[str, float]:
    """RMSE, mean, std (ddof=0) and max |d| of a component, scaled into ``unit``."""
    x = np.asarray(d, dtype=float) * scale
    values = (np.sqrt(np.mean(x * x)), np.mean(x), np.std(x), np.max(np.abs(x)))
    return {f"{name}_{s}_{unit}": float(v) for s, v in zip(_STATS, values)}


def _statistics(d_rph: np.ndarray, d_rotvec: np.ndarray, d_ned: np.ndarray) -> dict[str, float]:
    out: dict[str, float] = {}
    for j, name in enumerate(ATTITUDE_NAMES):
        out |= _stats(name, d_rph[:, j], MDEG_PER_RAD, "mdeg")
    for j, name in enumerate(ROTVEC_NAMES):
        out |= _stats(name, d_rotvec[:, j], MDEG_PER_RAD, "mdeg")
    out |= _stats("attitude_angle", np.linalg.norm(d_rotvec, axis=1), MDEG_PER_RAD, "mdeg")
    for j, name in enumerate(POSITION_NAMES):
        out |= _stats(name, d_ned[:, j], 1.0, "m")
    out |= _stats("horizontal", np.hypot(d_ned[:, 0], d_ned[:, 1]), 1.0, "m")
    out |= _stats("3d", np.linalg.norm(d_ned, axis=1), 1.0, "m")
    return out


@dataclass(frozen=True, eq=False)
class TrajectoryComparison:
    """Differences estimate - reference at common times (module docstring: conventions).

    Attributes
    ----------
    time : (N,) float64
        Seconds relative to ``t0_gps`` (the first common time).
    t0_gps : float
        First common time: GPS seconds, or seconds of week if ``time_scale`` is
        ``"seconds_of_week"``.
    d_rph_rad : (N, 3) float64
        Roll, pitch, yaw (heading) differences, rad, wrapped to (-pi, pi].
    d_rotvec_rad : (N, 3) float64
        Attitude error ``Log(R_ref^T R_est)`` in the body frame (forward, right, down), rad.
    d_ned_m : (N, 3) float64
        Position differences north, east, down at the reference position, m.
    stats : dict[str, float]
        Summary statistics with the unit in the key (``roll_rmse_mdeg``, ``3d_rmse_m``, ...).
    time_base : str
        ``"reference"`` or ``"estimate"``: whose samples are the common times.
    estimate_span, reference_span : tuple[float, float]
        First and last time of each input (same time scale as ``t0_gps``).
    n_interpolated : int
        Common times at which the other trajectory was interpolated (not one of its samples).
    n_dropped : int
        Common times dropped because they fell into a gap of the other trajectory.
    time_scale : str
        ``"gps"`` (absolute GPS seconds) or ``"seconds_of_week"`` (GPS week unknown, both
        inputs assumed to be in the same week).
    notes : tuple[str, ...]
        How the inputs' times were resolved, in sentences.
    sources : dict[str, str]
        Optional file names (``estimate``, ``reference``).
    """

    time: np.ndarray
    t0_gps: float
    d_rph_rad: np.ndarray
    d_rotvec_rad: np.ndarray
    d_ned_m: np.ndarray
    stats: dict[str, float]
    time_base: str
    estimate_span: tuple[float, float]
    reference_span: tuple[float, float]
    n_interpolated: int = 0
    n_dropped: int = 0
    time_scale: str = "gps"
    notes: tuple[str, ...] = ()
    sources: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = np.asarray(self.time).shape[0]
        if np.asarray(self.time).ndim != 1 or n < 1:
            raise ValueError(f"time must be 1-D with at least one sample, got shape {np.shape(self.time)}")
        for name in ("d_rph_rad", "d_rotvec_rad", "d_ned_m"):
            if np.shape(getattr(self, name)) != (n, 3):
                raise ValueError(f"{name} must have shape {(n, 3)}, got {np.shape(getattr(self, name))}")
        if self.time_base not in ("reference", "estimate"):
            raise ValueError(f"time_base must be 'reference' or 'estimate', got {self.time_base!r}")
        if self.time_scale not in ("gps", "seconds_of_week"):
            raise ValueError(f"time_scale must be 'gps' or 'seconds_of_week', got {self.time_scale!r}")

    def __len__(self) -> int:
        return self.time.shape[0]

    def within(self, windows: list[tuple[float, float]]) -> "TrajectoryComparison":
        """The comparison during ``windows`` (``(start, end)`` on this comparison's time scale, e.g.
        the flight strips): differences outside become NaN, so that plots show gaps, and the
        statistics are those of the samples inside."""
        t = self.time_gps
        inside = np.zeros(t.shape[0], dtype=bool)
        for a, b in windows:
            inside |= (t >= a) & (t <= b)
        if not np.any(inside):
            raise ValueError("within(): no sample inside the windows")
        masked = {}
        for name in ("d_rph_rad", "d_rotvec_rad", "d_ned_m"):
            d = np.array(getattr(self, name), dtype=float)
            d[~inside] = np.nan
            masked[name] = d
        stats = _statistics(self.d_rph_rad[inside], self.d_rotvec_rad[inside], self.d_ned_m[inside])
        return replace(self, stats=stats, **masked)

    @property
    def time_gps(self) -> np.ndarray:
        """(N,) common times on the inputs' time scale (``t0_gps + time``)."""
        return self.t0_gps + self.time

    @property
    def gps_week(self) -> int | None:
        """GPS week of the first common time, or None if the week is unknown."""
        if self.time_scale != "gps":
            return None
        return int(week_from_gps_seconds(self.t0_gps)[0])

    def rmse_mdeg(self, name: str) -> float:
        """RMSE of one attitude component (``roll``, ``pitch``, ``yaw``, ``attitude_angle``...), mdeg."""
        return self.stats[f"{name}_rmse_mdeg"]

    def to_dict(self) -> dict:
        """JSON-able summary: metadata and every statistic (units in the keys)."""
        week = self.gps_week
        sow = float(self.t0_gps - week * SECONDS_PER_WEEK) if week is not None else float(self.t0_gps)
        return {
            "n_epochs": len(self),
            "duration_s": float(self.time[-1]),
            "t0_gps_s": float(self.t0_gps) if self.time_scale == "gps" else None,
            "t0_seconds_of_week_s": sow,
            "gps_week": week,
            "time_scale": self.time_scale,
            "time_base": self.time_base,
            "estimate_span_s": [float(v) for v in self.estimate_span],
            "reference_span_s": [float(v) for v in self.reference_span],
            "n_interpolated": int(self.n_interpolated),
            "n_dropped_in_gaps": int(self.n_dropped),
            "notes": list(self.notes),
            "sources": dict(self.sources),
            "conventions": (
                "differences are estimate minus reference; roll/pitch/yaw are NED z-y-x Euler angles "
                "(yaw = heading), wrapped to (-180, 180] deg; rotvec = Log(R_ref^T R_est) in the body "
                "frame (x forward, y right, z down); north/east/down at the reference position; "
                "std is the population standard deviation; max_abs is the largest absolute value"
            ),
            **{k: float(v) for k, v in self.stats.items()},
        }

    def table(self) -> list[tuple[str, str, float, float, float, float]]:
        """Rows ``(quantity, unit, rmse, mean, std, max_abs)`` for a summary table."""
        rows = []
        for name, label, unit in (
            ("roll", "roll", "mdeg"), ("pitch", "pitch", "mdeg"), ("yaw", "yaw (heading)", "mdeg"),
            ("attitude_angle", "attitude angle |Log(R_ref^T R_est)|", "mdeg"),
            ("north", "north", "m"), ("east", "east", "m"), ("down", "down", "m"),
            ("horizontal", "horizontal", "m"), ("3d", "3D", "m"),
        ):
            rows.append((label, unit, *(self.stats[f"{name}_{s}_{unit}"] for s in _STATS)))
        return rows


# ---------------------------------------------------------------------------
# Sampling
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Poses:
    """Poses at common times: ECEF position, ``R_e_b``, NED rph, latitude/longitude."""

    p_e: np.ndarray
    R_e_b: np.ndarray
    rph: np.ndarray
    lat: np.ndarray
    lon: np.ndarray


def _poses_at_samples(s: SbetData, idx: np.ndarray) -> _Poses:
    """Poses of the samples ``idx`` as stored in the file (no interpolation)."""
    lat, lon = s.lat_rad[idx], s.lon_rad[idx]
    rph = np.column_stack([s.roll_rad[idx], s.pitch_rad[idx], s.heading_rad[idx]])
    R_e_b = R_e_n(lat, lon) @ R_n_b_from_rph(rph[:, 0], rph[:, 1], rph[:, 2])
    return _Poses(geodetic_to_ecef(lat, lon, s.h_m[idx]), R_e_b, rph, lat, lon)


def _interpolate(s: SbetData, t: np.ndarray) -> tuple[_Poses, np.ndarray]:
    """Poses of ``s`` at times ``t`` (clamped to its span) and the mask of times on a sample.

    Position linear in ECEF, attitude ``R_e_b`` geodesic; at a sample time the stored sample
    is used unchanged.
    """
    ts = s.time_gps
    t = np.clip(t, ts[0], ts[-1])
    if len(ts) == 1:
        return _poses_at_samples(s, np.zeros(t.size, dtype=np.int64)), np.ones(t.size, dtype=bool)
    k = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(ts) - 2)
    u = (t - ts[k]) / (ts[k + 1] - ts[k])
    a, b = _poses_at_samples(s, k), _poses_at_samples(s, k + 1)
    p_e = a.p_e + u[:, None] * (b.p_e - a.p_e)
    R_e_b = a.R_e_b @ exp_so3(u[:, None] * log_so3(np.swapaxes(a.R_e_b, 1, 2) @ b.R_e_b))
    lat, lon, _ = ecef_to_geodetic(p_e)
    rph = rph_from_R_n_b(np.swapaxes(R_e_n(lat, lon), 1, 2) @ R_e_b)
    out = _Poses(p_e, R_e_b, rph, lat, lon)
    hit = (u == 0.0) | (u == 1.0)
    if hit.any():
        exact = _poses_at_samples(s, np.where(u == 1.0, k + 1, k)[hit])
        for name in ("p_e", "R_e_b", "rph", "lat", "lon"):
            getattr(out, name)[hit] = getattr(exact, name)
    return out, hit


def _span(s: SbetData) -> tuple[float, float]:
    return float(s.time_gps[0]), float(s.time_gps[-1])


def _median_step(s: SbetData) -> float:
    """Median sample interval (s); infinite for a single sample."""
    return float(np.median(np.diff(s.time_gps))) if len(s) > 1 else np.inf


def _fmt_span(span: tuple[float, float]) -> str:
    return f"[{span[0]:.3f}, {span[1]:.3f}] s"


def compare_trajectories(
    estimate: SbetData,
    reference: SbetData,
    *,
    time_window: tuple[float, float] | None = None,
    max_time_offset_s: float = 1e-4,
    max_gap_s: float | None = None,
) -> TrajectoryComparison:
    """Differences of an estimated trajectory minus a reference at common times.

    Parameters
    ----------
    estimate, reference
        Trajectories with times on the same scale (``time_gps``: GPS seconds, or both
        seconds of the same week).
    time_window
        ``(start, end)`` on the inputs' time scale; only common times inside it are used.
    max_time_offset_s
        Common times outside the interpolated trajectory's span by at most this (s) take
        its first or last sample instead of being dropped, so that grids which agree up to
        rounding (float64 GPS seconds resolve ~0.2 µs) keep their end samples. The pose
        error this admits is at most rate x offset, at the ends only.
    max_gap_s
        Common times inside an interval of the interpolated trajectory longer than this
        (s) are dropped and counted in ``n_dropped``. None: 10 times its median sample
        interval (at least ``max_time_offset_s``).

    Returns
    -------
    TrajectoryComparison
        Differences and statistics (module docstring: conventions).

    Raises
    ------
    InputError
        If the spans do not overlap, ``time_window`` does not meet the overlap, or no
        common time remains (message with both spans).
    """
    if max_time_offset_s < 0:
        raise ValueError(f"max_time_offset_s must be >= 0, got {max_time_offset_s}")
    span_e, span_r = _span(estimate), _span(reference)
    lo, hi = max(span_e[0], span_r[0]), min(span_e[1], span_r[1])
    spans = f"estimate {_fmt_span(span_e)}, reference {_fmt_span(span_r)}"
    if lo > hi + max_time_offset_s:
        raise InputError("the trajectories do not overlap in time", expected="overlapping time spans",
                         found=spans)
    lo, hi = lo - max_time_offset_s, hi + max_time_offset_s
    if time_window is not None:
        w0, w1 = (float(v) for v in time_window)
        if not w0 <= w1:
            raise InputError("time window start after its end", field="time_window",
                             expected="start <= end", found=f"[{w0:.3f}, {w1:.3f}] s")
        lo, hi = max(lo, w0), min(hi, w1)
        if lo > hi:
            raise InputError("the time window does not meet the overlap of the trajectories",
                             field="time_window", expected=f"a window inside the overlap ({spans})",
                             found=f"[{w0:.3f}, {w1:.3f}] s")

    def inside(s: SbetData) -> np.ndarray:
        return np.flatnonzero((s.time_gps >= lo) & (s.time_gps <= hi))

    idx_e, idx_r = inside(estimate), inside(reference)
    # The sparser trajectory (larger median sample interval; the reference on a tie) gives the
    # common times, unless it has no sample inside the overlap.
    estimate_sparser = _median_step(estimate) > _median_step(reference)
    if (estimate_sparser and idx_e.size) or not idx_r.size:
        time_base, base, idx, other = "estimate", estimate, idx_e, reference
    else:
        time_base, base, idx, other = "reference", reference, idx_r, estimate
    t = base.time_gps[idx]

    # Drop common times that fall into a gap of the other trajectory (no interpolation across it).
    n_dropped = 0
    if len(other) >= 2:
        dt_other = np.diff(other.time_gps)
        gap = max_gap_s if max_gap_s is not None else max(10.0 * float(np.median(dt_other)), max_time_offset_s)
        k = np.clip(np.searchsorted(other.time_gps, t, side="right") - 1, 0, len(other) - 2)
        in_gap = (dt_other[k] > gap) & (t > other.time_gps[k]) & (t < other.time_gps[k + 1])
        n_dropped = int(np.count_nonzero(in_gap))
        if n_dropped:
            _log.warning("dropped %d common times inside gaps (> %.3f s) of the %s", n_dropped, gap,
                         "reference" if time_base == "estimate" else "estimate")
        t, idx = t[~in_gap], idx[~in_gap]
    if t.size == 0:
        raise InputError("no common times in the overlap of the trajectories",
                         expected="samples of one trajectory inside the span of the other", found=spans)

    base_poses = _poses_at_samples(base, idx)
    other_poses, hit = _interpolate(other, t)
    est, ref = (base_poses, other_poses) if time_base == "estimate" else (other_poses, base_poses)

    d_rph = wrap_angle(est.rph - ref.rph)
    d_rotvec = log_so3(np.swapaxes(ref.R_e_b, 1, 2) @ est.R_e_b)
    d_ned = np.einsum("nji,nj->ni", R_e_n(ref.lat, ref.lon), est.p_e - ref.p_e)
    t0 = float(t[0])
    _log.info("compared %d epochs (%s time base, %d interpolated)", t.size, time_base, int(np.sum(~hit)))
    return TrajectoryComparison(
        time=t - t0, t0_gps=t0, d_rph_rad=d_rph, d_rotvec_rad=d_rotvec, d_ned_m=d_ned,
        stats=_statistics(d_rph, d_rotvec, d_ned), time_base=time_base, estimate_span=span_e,
        reference_span=span_r, n_interpolated=int(np.sum(~hit)), n_dropped=n_dropped,
    )


# ---------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------


def consistency(
    comparison: TrajectoryComparison,
    sigma_rph_rad: np.ndarray,
    sigma_time_gps: np.ndarray | None = None,
) -> np.ndarray:
    """RMS of the normalised attitude differences ``d_rph / sigma`` per angle.

    Values near 1 mean that the stated standard deviations match the actual errors
    (pyins' test: below 1.5); much larger means over-optimistic sigmas.

    Parameters
    ----------
    comparison
        Result of :func:`compare_trajectories`.
    sigma_rph_rad
        Standard deviations of roll, pitch, heading (rad): ``(N, 3)`` on the comparison's
        common times, or ``(M, 3)`` at ``sigma_time_gps`` (e.g.
        :attr:`~georefine.io.trajectory_csv.TrajectoryTable.sigma_rpy_rad`). For a reference
        that is not the truth pass the combined ``sqrt(sigma_est^2 + sigma_ref^2)``.
    sigma_time_gps
        ``(M,)`` times of ``sigma_rph_rad`` on the comparison's time scale; sigmas are then
        linearly interpolated to the common times (held constant beyond the ends).

    Returns
    -------
    numpy.ndarray
        ``(3,)`` RMS of ``d / sigma`` for roll, pitch, yaw.
    """
    sigma = np.asarray(sigma_rph_rad, dtype=float)
    if sigma_time_gps is not None:
        ts = np.asarray(sigma_time_gps, dtype=float)
        if ts.ndim != 1 or sigma.shape != (ts.shape[0], 3):
            raise ValueError(f"sigma_rph_rad must have shape ({ts.shape[0]}, 3), got {sigma.shape}")
        tq = comparison.time_gps
        sigma = interp_columns(tq, ts, sigma)
    if sigma.shape != comparison.d_rph_rad.shape:
        raise ValueError(f"sigma_rph_rad must have shape {comparison.d_rph_rad.shape}, got {sigma.shape}")
    if not np.all(sigma > 0):
        raise ValueError("sigma_rph_rad must be positive")
    z = comparison.d_rph_rad / sigma
    return np.sqrt(np.mean(z * z, axis=0))


# ---------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------
