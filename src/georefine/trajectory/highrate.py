"""High-frequency motion rebuilt from the raw IMU: the up-sampling half of Pöppl et al. (2025).

docs/ARCHITECTURE.md §4.6. The adjustment estimates a *low-frequency* trajectory: a spline on
knots ``dt`` apart observed by IMU window means. Motion faster than the knots (the vibration
of a helicopter, 5-30 Hz) is not in the spline. It is in the raw IMU samples, and this module
rebuilds it as a correction relative to the spline::

    R_w_b(t) = R_s(t) Exp(dtheta(t)),     p_w_b(t) = p_s(t) + dp(t)

from the error-corrected readings (biases, scale factors and misalignments of the adjustment removed).

**Orientation.** The residual rate ``domega = omega_wb_b - omega_s`` (the corrected gyro minus
the Earth rate, minus the spline's body rate) drives ``dtheta' = domega - omega_s x dtheta``
(first order in ``dtheta``; the coupling term is applied in a second pass).
**Position.** With the corrected orientation, ``da = R_s (Exp(dtheta) f - f_s)`` is the
residual kinematic acceleration (``f_s`` the spline's specific force), integrated twice.

**Integration** is that of the samples' interpolating cubic spline (``scipy.interpolate.CubicSpline``,
its antiderivative; :func:`_integral`), not the trapezoid rule: the readings are samples of a
smooth motion, and the trapezoid rule misses a line at ``f`` by ``(2 pi f dt)^2 / 12`` of its
amplitude, 5.6 % of a 26 Hz rotor harmonic at 200 Hz, where the spline's integral misses 0.08 %.
With a navigation-grade IMU on a vibrating corridor the trapezoid's error was 55-68 % of the G/I's
pitch error (BENCHMARKS.md, Operating conditions).

**Low frequencies stay in the spline.** Before and after every integration the signal's
projection on the spline space is removed: a least-squares cubic B-spline on the same knot
interval (:func:`high_pass`: banded normal equations from scipy's design matrix, linear in the samples;
the adjustment's splines -- cubic Hermite orientation, quintic Hermite position -- contain
that space). So integrated noise and residual sensor errors cannot drift, the spline keeps
everything it can represent, and ``dtheta``, ``dp`` hold only what it cannot.

**Iteration.** :meth:`HighRateMotion.reading_corrections` gives the readings that the
high-frequency motion produces; :meth:`~HighRateMotion.significant_corrections` keeps of them
what stands out of the sensor noise spectrally (the vibration lines). The adjustment subtracts
those from the raw IMU before the window means (``processing.trajectory.upsampling_iterations``):
the windows then carry the low-frequency motion the spline can follow and the sensor noise
their weights assume, instead of aliased vibration that no knot can fit; the motion is rebuilt
again from the new spline and IMU errors.

Everything is vectorised per contiguous IMU segment (no sample loop); segments shorter than
four knot intervals get no correction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.interpolate import BSpline, CubicSpline
from scipy.linalg import solveh_banded

from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import exp_so3
from georefine.trajectory.sampled import Trajectory
from georefine.trajectory.spline import SplineTrajectory

__all__ = ["HighRateMotion", "high_pass", "reconstruct_high_rate", "significant_content"]

MIN_SEGMENT_KNOTS = 4
STFT_SAMPLES = 2048
"""Short-time Fourier blocks of :func:`significant_content` (about 10 s at 200 Hz)."""
LINE_FACTOR = 12.0
"""A spectral bin is signal when its power exceeds this many times the block's noise power:
for Gaussian noise a bin's power is exponential, so noise passes with probability exp(-12)."""


def high_pass(t: np.ndarray, y: np.ndarray, knot_interval_s: float) -> np.ndarray:
    """``y`` minus its least-squares cubic B-spline on knots ``knot_interval_s`` apart.

    ``t`` (N,) strictly increasing, ``y`` (N, ...). The knots are anchored at ``t[0]``; the
    last interval is stretched to end at ``t[-1]``. With fewer than
    ``MIN_SEGMENT_KNOTS`` intervals the whole signal counts as low frequency (zeros).
    """
    span = float(t[-1] - t[0])
    n = int(np.floor(span / knot_interval_s))
    if n < MIN_SEGMENT_KNOTS:
        return np.zeros_like(y)
    inner = t[0] + knot_interval_s * np.arange(1, n)
    if span - (inner[-1] - t[0]) < 0.5 * knot_interval_s:  # no sliver interval at the end
        inner = inner[:-1]
    k = 3
    knots = np.concatenate([np.full(k + 1, t[0]), inner, np.full(k + 1, t[-1])])
    # Normal equations, well conditioned with many samples per knot interval, solved as the
    # banded system they are: the design matrix (4 non-zeros per row) from scipy, B^T B by
    # diagonals, ``solveh_banded``. Same coefficients as ``make_lsq_spline(method="norm-eq")``
    # to rounding, 16x faster on 0.1 s knots (its accumulation loop is per sample and knot).
    # ``extrapolate=True``: t lies within the clamped knots by construction, and SciPy's bounds
    # check otherwise runs Python's min and max over the samples (0.15 s each on a 60-minute series).
    B = BSpline.design_matrix(t, knots, k, extrapolate=True).tocsr()
    N = (B.T @ B).todia()
    bands = np.zeros((k + 1, B.shape[1]))
    for offset in range(k + 1):  # upper form: bands[k - offset, offset:] is diagonal ``offset``
        bands[k - offset, offset:] = N.diagonal(offset)
    flat = y.reshape(y.shape[0], -1)
    coef = solveh_banded(bands, B.T @ flat, check_finite=False)
    return y - (B @ coef).reshape(y.shape)


def significant_content(x: np.ndarray, factor: float = LINE_FACTOR, block: int = STFT_SAMPLES,
                        also: np.ndarray | None = None) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """The part of uniformly sampled ``x`` (N, C) that stands out of its noise, spectrally.

    Short-time Fourier transform (``scipy.signal.stft``, Hann blocks of ``block`` samples, half
    overlapping); per channel and block the noise power is the median bin power over ``ln 2``
    (the median of an exponential variable; lines occupy few bins), and only the bins above
    ``factor`` times it are kept (``istft``). Vibration lines pass whole, white noise does not:
    removing them from the readings takes out the vibration and leaves the noise the window
    weights assume.

    ``also`` (N, C): another signal put through the same bins (the same linear filter), returned
    second: what the filter takes out of a known noise (:meth:`HighRateMotion.removed_noise`).
    """
    n = x.shape[0]
    nper = min(block, n)
    if nper < 64:
        return np.zeros_like(x) if also is None else (np.zeros_like(x), np.zeros_like(also))
    # Block by block of time: every block's bins and noise are its own, so a stretch of samples
    # with a margin of one window either side gives exactly the whole series' result there, with
    # the stretch's start on the blocks' grid. Over the whole 60-minute series at once the
    # transforms' arrays left the cache (the inverse took 15x the time for 6x the samples).
    hop = nper // 2
    step = STFT_CHUNK_BLOCKS * hop
    if n <= step + 2 * nper:
        return _significant_stretch(x, nper, factor, also)
    out = np.empty_like(x, dtype=np.float64)
    out_also = None if also is None else np.empty_like(also, dtype=np.float64)
    for a in range(0, n, step):
        b = min(a + step, n)
        lo, hi = max(0, a - nper), min(n, b + nper)
        part = _significant_stretch(x[lo:hi], nper, factor, None if also is None else also[lo:hi])
        if also is None:
            out[a:b] = part[a - lo:b - lo]
        else:
            out[a:b] = part[0][a - lo:b - lo]
            out_also[a:b] = part[1][a - lo:b - lo]
    return out if also is None else (out, out_also)


STFT_CHUNK_BLOCKS = 128
"""Hops of the short-time Fourier transform per stretch of :func:`significant_content` (131,072
samples with the default blocks, 13 MB of transform for six channels)."""


def _significant_stretch(x: np.ndarray, nper: int, factor: float, also: np.ndarray | None):
    """:func:`significant_content` of one stretch, transformed whole."""
    from scipy.signal import istft, stft

    n = x.shape[0]

    def spectrum(signal):
        return stft(signal.T, nperseg=nper, noverlap=nper // 2, window="hann")[2]

    def kept(Z):
        return istft(np.where(keep, Z, 0.0), nperseg=nper, noverlap=nper // 2, window="hann")[1][:, :n].T

    Z = spectrum(x)
    power = np.abs(Z) ** 2
    noise = np.median(power, axis=1, keepdims=True) / np.log(2.0)
    keep = power > factor * noise
    return kept(Z) if also is None else (kept(Z), kept(spectrum(also)))


def _integral(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``int_{t[0]}^{t} y`` at the samples ``t``: the antiderivative of the interpolating cubic
    spline (not-a-knot) of ``y`` (N, ...), zero at ``t[0]`` (module docstring).

    The spline's slopes solve SciPy's tridiagonal system (``CubicSpline``'s, not-a-knot ends) by
    elimination in numba (:func:`_not_a_knot_slopes`), and each piece's integral is Hermite's
    ``h (y_i + y_i+1) / 2 + h^2 (m_i - m_i+1) / 12``, summed: the numbers of
    ``CubicSpline(t, y).antiderivative()(t)`` to 1e-13, without its quartic spline, its search of
    every sample's piece and its stacked coefficient arrays, which made the up-sampling grow faster
    than the flight (0.6 s of SciPy for 720,000 samples against 0.03 s)."""
    if t.size < 4:  # SciPy's special cases (a line, a parabola)
        return CubicSpline(t, y, axis=0).antiderivative()(t) if t.size >= 2 else np.zeros_like(y, dtype=np.float64)
    flat = np.ascontiguousarray(np.asarray(y, dtype=np.float64).reshape(t.size, -1))
    out = np.empty_like(flat)
    _cubic_integral(np.ascontiguousarray(t, dtype=np.float64), flat, out)
    return out.reshape(np.shape(y))


@numba.njit(cache=True, nogil=True)
def _cubic_integral(x, y, out):  # pragma: no cover - numba
    """Cumulative integral of the not-a-knot cubic spline through ``(x, y[:, c])`` for every column."""
    n = x.size
    m = np.empty(n)
    for c in range(y.shape[1]):
        _not_a_knot_slopes(x, y[:, c], m)
        out[0, c] = 0.0
        for i in range(n - 1):
            h = x[i + 1] - x[i]
            out[i + 1, c] = out[i, c] + 0.5 * h * (y[i, c] + y[i + 1, c]) + h * h * (m[i] - m[i + 1]) / 12.0


@numba.njit(cache=True, nogil=True)
def _not_a_knot_slopes(x, y, m):  # pragma: no cover - numba
    """The slopes ``m`` of the not-a-knot cubic spline through ``(x, y)`` (n >= 4): SciPy's system
    (``CubicSpline``: C2 rows ``h_i m_i-1 + 2 (h_i-1 + h_i) m_i + h_i-1 m_i+1 = 3 (h_i d_i-1 +
    h_i-1 d_i)``, ``d`` the divided differences, and its two not-a-knot rows), by tridiagonal
    elimination (the system is diagonally dominant but for its end rows, whose pivots are the
    spacings)."""
    n = x.size
    sub = np.empty(n)  # (i, i-1)
    dia = np.empty(n)
    sup = np.empty(n)  # (i, i+1)
    rhs = np.empty(n)
    h0, h1 = x[1] - x[0], x[2] - x[1]
    d0, d1 = (y[1] - y[0]) / h0, (y[2] - y[1]) / h1
    dia[0], sup[0], sub[0] = h1, x[2] - x[0], 0.0
    rhs[0] = ((h0 + 2.0 * (x[2] - x[0])) * h1 * d0 + h0 * h0 * d1) / (x[2] - x[0])
    for i in range(1, n - 1):
        ha, hb = x[i] - x[i - 1], x[i + 1] - x[i]
        da, db = (y[i] - y[i - 1]) / ha, (y[i + 1] - y[i]) / hb
        sub[i], dia[i], sup[i] = hb, 2.0 * (ha + hb), ha
        rhs[i] = 3.0 * (hb * da + ha * db)
    ha, hb = x[n - 2] - x[n - 3], x[n - 1] - x[n - 2]
    da, db = (y[n - 2] - y[n - 3]) / ha, (y[n - 1] - y[n - 2]) / hb
    span = x[n - 1] - x[n - 3]
    sub[n - 1], dia[n - 1], sup[n - 1] = span, ha, 0.0
    rhs[n - 1] = (hb * hb * da + (2.0 * span + hb) * ha * db) / span
    for i in range(1, n):  # forward elimination
        w = sub[i] / dia[i - 1]
        dia[i] -= w * sup[i - 1]
        rhs[i] -= w * rhs[i - 1]
    m[n - 1] = rhs[n - 1] / dia[n - 1]
    for i in range(n - 2, -1, -1):
        m[i] = (rhs[i] - sup[i] * m[i + 1]) / dia[i]


def _segments(time: np.ndarray, rate_hz: float, max_gap_factor: float = 1.5) -> list[slice]:
    """Contiguous runs of samples (no interval above ``max_gap_factor / rate_hz``)."""
    cut = np.flatnonzero(np.diff(time) > max_gap_factor / rate_hz) + 1
    edges = np.concatenate([[0], cut, [time.size]])
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b - a >= 2]


def _spline_kinematics(frame: LocalFrame, spline: SplineTrajectory, t: np.ndarray):
    """Spline pose, velocity, acceleration, body rate and specific force at ``t``."""
    p = spline.position(t, 0)
    v = spline.position(t, 1)
    a = spline.position(t, 2)
    R, omega, _ = spline.orientation(t, rate=True)
    f = np.einsum("nji,nj->ni", R, a + 2.0 * np.cross(frame.omega_ie_w, v) - frame.gravity_w(p))
    return p, v, a, R, omega, f


@dataclass(frozen=True)
class HighRateMotion:
    """The motion the spline cannot represent, at the IMU samples.

    Attributes
    ----------
    time : (N,) s
        IMU sample times inside the spline's span.
    dtheta : (N, 3) rad
        Body-frame rotation: ``R_w_b = R_s Exp(dtheta)``.
    dtheta_rate : (N, 3) rad/s
        Its derivative (from the integration, not by differencing).
    dp, dv, da : (N, 3) m, m/s, m/s²
        Position offset in ``w`` (``p_w_b = p_s + dp``) and its first two derivatives.
    knot_interval_s : float
        The low-pass cut of the reconstruction (the spline's knot interval).
    """

    time: np.ndarray
    dtheta: np.ndarray
    dtheta_rate: np.ndarray
    dp: np.ndarray
    dv: np.ndarray
    da: np.ndarray
    knot_interval_s: float

    def rms(self) -> tuple[float, float]:
        """RMS rotation (rad, norm of ``dtheta``) and RMS offset (m, norm of ``dp``)."""
        if self.time.size == 0:
            return 0.0, 0.0
        return (float(np.sqrt(np.mean(np.sum(self.dtheta**2, axis=1)))),
                float(np.sqrt(np.mean(np.sum(self.dp**2, axis=1)))))

    def trajectory(self, spline: SplineTrajectory) -> Trajectory:
        """Spline plus high-frequency motion, sampled at :attr:`time` (for georeferencing)."""
        p, R = spline.pose(self.time)
        v = spline.velocity(self.time) + self.dv
        return Trajectory(self.time, p + self.dp, R @ exp_so3(self.dtheta), t0_gps=spline.t0_gps, v_w_b=v)

    def reading_corrections(self, frame: LocalFrame, spline: SplineTrajectory) -> tuple[np.ndarray, np.ndarray]:
        """Angular rate and specific force (N, 3) that the high-frequency motion adds to the readings.

        ``omega_ib`` changes by ``dtheta' + omega_s x dtheta``; the specific force becomes
        ``Exp(dtheta)^T (f_s + R_s^T dp'')``. The derivatives are those of the integration
        (central differences would damp 26 Hz at 200 Hz by a fifth).
        """
        _, _, _, R, omega, f_s = _spline_kinematics(frame, spline, self.time)
        d_omega = self.dtheta_rate + np.cross(omega, self.dtheta)
        f_total = np.einsum("nji,nj->ni", exp_so3(self.dtheta), f_s + np.einsum("nji,nj->ni", R, self.da))
        return d_omega, f_total - f_s

    def significant_corrections(self, frame: LocalFrame, spline: SplineTrajectory, rate_hz: float):
        """:meth:`reading_corrections` reduced to what stands out of the noise (:func:`significant_content`).

        These are taken out of the IMU windows: the vibration goes, the sensor noise stays, so
        the windows' weights and the variance factor keep their meaning. Within half a
        short-time Fourier block of a segment's ends (:meth:`edges`) all of the corrections are
        taken: the blocks there are half zeros, a line leaks over every bin, and the test keeps
        only part of it. With rotor vibration and a navigation-grade IMU what it left made the
        first and last 2 s of windows fit at 1,800-19,000 times their noise, 38 % of the G/I's
        misfit; taken whole, they fit as the rest does, and their few seconds of windows lose
        the sensor noise above the knots (BENCHMARKS.md, Operating conditions).
        """
        return self.significant_part(*self.reading_corrections(frame, spline), rate_hz)

    def significant_part(self, d_omega: np.ndarray, d_f: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """What :meth:`significant_corrections` keeps of the corrections ``d_omega``, ``d_f``
        (:meth:`reading_corrections`, for a caller that has them already)."""
        return self._significant(d_omega, d_f, rate_hz, None)[:2]

    def removed_noise(self, d_omega: np.ndarray, d_f: np.ndarray, rate_hz: float, seed: int = 0
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`significant_part`, and (N, 6) what the same filter takes out of unit white noise.

        The filter is linear once its bins are chosen: the rebuild high-passes the readings'
        residual (:func:`high_pass`), the test keeps the lines' bins, and near the segments'
        ends all of it (:meth:`edges`). Put through it, seeded white noise of unit variance per
        sample and channel (gyro x, y, z, accelerometer x, y, z) gives the share of the sensor
        noise that the cleaned readings no longer hold: the windows' residuals lose those
        degrees of freedom (:func:`georefine.adjustment.gnss_imu.cleaning_redundancy`).
        """
        return self._significant(d_omega, d_f, rate_hz, np.random.default_rng(seed))

    def _significant(self, d_omega, d_f, rate_hz, rng):
        both = np.hstack([d_omega, d_f])
        out = np.zeros_like(both)
        noise = None if rng is None else np.zeros_like(both)
        edges = self.edges(rate_hz)
        for s in _segments(self.time, rate_hz):
            if rng is None:
                out[s] = significant_content(both[s])
                continue
            u = high_pass(self.time[s], rng.standard_normal(both[s].shape), self.knot_interval_s)
            out[s], noise[s] = significant_content(both[s], also=u)
            noise[s][edges[s]] = u[edges[s]]
        out[edges] = both[edges]
        return out[:, :3], out[:, 3:], noise

    def edges(self, rate_hz: float, block: int = STFT_SAMPLES) -> np.ndarray:
        """(N,) bool: the samples within half a short-time Fourier block of their segment's ends,
        where :func:`significant_content` cannot tell lines from noise."""
        out = np.zeros(self.time.size, dtype=bool)
        for s in _segments(self.time, rate_hz):
            n = s.stop - s.start
            h = min(block, n) // 2
            out[s.start:s.start + h] = True
            out[s.stop - h:s.stop] = True
        return out


def reconstruct_high_rate(
    frame: LocalFrame,
    spline: SplineTrajectory,
    time: np.ndarray,
    gyro: np.ndarray,
    acc: np.ndarray,
    rate_hz: float,
) -> HighRateMotion:
    """Rebuild the motion faster than ``spline``'s knots from error-corrected IMU readings.

    Parameters
    ----------
    frame
        Mapping frame (gravity, Earth rate).
    spline
        The adjusted low-frequency trajectory; its knot interval is the cut.
    time : (N,) s
        IMU sample times (relative to the epoch); samples outside the spline are dropped.
    gyro, acc : (N, 3)
        Angular rate ``omega_ib_b`` (rad/s) and specific force (m/s²), already corrected for
        the estimated biases, scale factors and misalignments.
    rate_hz
        Nominal IMU rate (for finding sampling gaps).
    """
    time = np.asarray(time, dtype=float)
    inside = (time >= spline.grid.t_start) & (time <= spline.grid.t_end)
    t, gyro, acc = time[inside], np.asarray(gyro, float)[inside], np.asarray(acc, float)[inside]
    dt_k = spline.grid.dt
    dtheta, dtheta_rate, dp, dv, da = (np.zeros((t.size, 3)) for _ in range(5))
    for s in _segments(t, rate_hz):
        ts = t[s]
        if ts[-1] - ts[0] < MIN_SEGMENT_KNOTS * dt_k:
            continue
        p, v, a, R, omega, f_s = _spline_kinematics(frame, spline, ts)
        omega_wb = gyro[s] - np.einsum("nji,j->ni", R, frame.omega_ie_w)
        d_omega = omega_wb - omega
        th = np.zeros((ts.size, 3))
        for _ in range(2):  # second pass: the coupling term with the first pass's dtheta
            rate = high_pass(ts, d_omega - np.cross(omega, th), dt_k)
            th = high_pass(ts, _integral(ts, rate), dt_k)
        acc_w = np.einsum("nij,nj->ni", R, np.einsum("nij,nj->ni", exp_so3(th), acc[s]) - f_s)
        da[s] = high_pass(ts, acc_w, dt_k)
        dv[s] = high_pass(ts, _integral(ts, da[s]), dt_k)
        dp[s] = high_pass(ts, _integral(ts, dv[s]), dt_k)
        dtheta[s], dtheta_rate[s] = th, rate
    return HighRateMotion(t, dtheta, dtheta_rate, dp, dv, da, dt_k)
