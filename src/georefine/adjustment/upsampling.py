"""Iterated IMU down- and up-sampling (Pöppl et al. 2025; docs/ARCHITECTURE.md §4.6).

The adjustment (:mod:`georefine.adjustment.gnss_imu`) sees the IMU only through window means
and estimates a spline on knots ``knot_interval_s`` apart. This module closes the loop:

1. :func:`corrected_imu`: the raw readings with the estimated biases, scale factors and
   misalignments removed, ``M^-1 (x~ - b(t))`` with ``M = I + S + A``;
2. :func:`rebuild_high_rate`: the motion faster than the knots, rebuilt from them relative to
   the spline (:func:`georefine.trajectory.highrate.reconstruct_high_rate`);
3. :func:`without_high_rate`: the raw readings minus what that motion contributes where it
   stands out of the sensor noise (spectral lines; sensed back through ``M``), for the next
   adjustment's windows. Without this a vibration that no knot can follow reaches the windows
   as aliased noise, tens of times the sensor noise; removing the noise too would leave
   windows that fit better than their weights say, and a meaningless variance factor. The
   noise in the lines' bins goes with them: the cleaned data carry what the same filter takes
   out of unit white noise (``GnssImuData.imu_cleaning``), and the adjustment counts those
   degrees of freedom as spent (:func:`georefine.adjustment.gnss_imu.cleaning_redundancy`).

:func:`adjust_upsampled` runs ``solve -> rebuild -> re-solve on the cleaned windows -> rebuild``
``processing.trajectory.upsampling_iterations`` times -- not at all when hardly any of the
rebuilt readings stands out of the sensor noise (a smooth platform: the re-solve would change
nothing) -- and returns the result with its
:class:`~georefine.trajectory.highrate.HighRateMotion`, which georeferencing and the trajectory
products add to the spline.
"""

from __future__ import annotations

import logging
import time as _time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from georefine.adjustment.gnss_imu import GnssImuData, GnssImuProblem, GnssImuResult, ImuErrorEstimate
from georefine.adjustment.observations.imu import triad_matrix
from georefine.trajectory.highrate import HighRateMotion, reconstruct_high_rate
from georefine.trajectory.spline import KnotGrid

log = logging.getLogger(__name__)

__all__ = ["MIN_SIGNIFICANT_SHARE", "adjust_upsampled", "corrected_imu", "high_rate_share", "rebuild_high_rate",
           "without_high_rate"]


def _inside(data: GnssImuData, hf_or_span) -> np.ndarray:
    t0, t1 = hf_or_span
    return (data.imu_time >= t0) & (data.imu_time <= t1)


def corrected_imu(data: GnssImuData, errors: ImuErrorEstimate, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angular rate and specific force of samples ``sel`` with biases (their temperature part too, where estimated),
    scale factors and misalignments removed."""
    t = data.imu_time[sel]
    grid = errors.bias_grid
    b_g, b_a = grid.evaluate(errors.gyro_bias, t), grid.evaluate(errors.acc_bias, t)
    if errors.gyro_temperature is not None and data.imu_temperature is not None:
        dT = (data.imu_temperature[sel] - data.imu_temperature[0])[:, None]
        b_g = b_g + dT * np.asarray(errors.gyro_temperature).reshape(1, 3)
        b_a = b_a + dT * np.asarray(errors.acc_temperature).reshape(1, 3)
    gyro = _unsense(data.imu_gyro[sel] - b_g, errors.gyro_scale, errors.gyro_misalignment)
    acc = _unsense(data.imu_acc[sel] - b_a, errors.acc_scale, errors.acc_misalignment)
    return gyro, acc


def _unsense(x: np.ndarray, scale: np.ndarray, misalignment: np.ndarray | None) -> np.ndarray:
    """Rows ``x`` through the inverse of the triad's ``I + S + A`` (as divided by ``1 + s`` without ``A``)."""
    if misalignment is None:
        return x / (1.0 + np.asarray(scale))
    return np.linalg.solve(triad_matrix(scale, misalignment), x.T).T


def _sense(x: np.ndarray, scale: np.ndarray, misalignment: np.ndarray | None) -> np.ndarray:
    """Rows ``x`` through the triad's ``I + S + A``."""
    if misalignment is None:
        return (1.0 + np.asarray(scale)) * x
    return x @ triad_matrix(scale, misalignment).T


def rebuild_high_rate(data: GnssImuData, result: GnssImuResult) -> HighRateMotion:
    """The motion of the raw IMU that ``result``'s spline does not hold (see module docstring)."""
    sel = _inside(data, result.spline.span)
    gyro, acc = corrected_imu(data, result.imu_errors, sel)
    return reconstruct_high_rate(data.frame, result.spline, data.imu_time[sel], gyro, acc, data.imu_rate_hz)


def on_knots(data: GnssImuData, result: GnssImuResult, knot_interval_s: float) -> GnssImuResult:
    """``result`` with its spline resampled onto knots about ``knot_interval_s`` apart over its span
    and, where it has rebuilt high-rate motion, that motion rebuilt against the resampled spline.

    The motion a spline does not hold depends on its knots: rebuilt against the G/I's 0.4 s knots
    it holds everything above 1.25 Hz, of which the G/I/L's 0.1 s knots follow most. Taken out of
    the windows of an adjustment on the finer knots, it would take that band from them and the
    cleaning would count the redundancy it spends twice (the hybrid adjustment of the small block:
    cloud error 0.68 of the G/I's instead of 0.47).
    """
    spline = result.spline
    if abs(spline.grid.dt - knot_interval_s) <= 1e-6 * knot_interval_s:
        return result
    out = replace(result, spline=spline.resampled(KnotGrid.spanning(spline.grid.t_start, spline.grid.t_end,
                                                                     knot_interval_s)))
    if result.high_rate is not None:
        out = replace(out, high_rate=rebuild_high_rate(data, out))
    return out


def without_high_rate(data: GnssImuData, result: GnssImuResult) -> GnssImuData:
    """``data`` whose IMU readings no longer contain ``result.high_rate`` (inputs are not modified)."""
    return _clean(data, result)[0]


def high_rate_share(data: GnssImuData, result: GnssImuResult) -> float:
    """The share of ``result``'s rebuilt high-rate readings that stands out of the IMU noise
    (:func:`_significant`): 1.00 with rotor vibration, a few hundredths on a smooth platform with
    a MEMS IMU (:data:`MIN_SIGNIFICANT_SHARE`; ``georefine.workflows.run_parts.VIBRATION_SHARE``)."""
    return _significant(data, result)[2]


def _significant(data: GnssImuData, result: GnssImuResult, noise: bool = False
                 ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray | None]:
    """The significant part of ``result.high_rate``'s readings (gyro, accelerometer) and its share.

    The share is the larger of gyro and accelerometer of RMS(significant) / RMS(all rebuilt
    readings), away from the segments' ends (:meth:`~HighRateMotion.edges`, where all of it is
    taken): near 0 when the high-frequency content is sensor noise alone, near 1 when it
    is vibration. Empty readings and 0 without a rebuilt motion. Last, with ``noise``, (N, 6) what
    the same filter takes out of unit white noise (:meth:`~HighRateMotion.removed_noise`), else None.
    """
    hf = result.high_rate
    if hf is None or hf.time.size == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), 0.0, (np.zeros((0, 6)) if noise else None)
    all_omega, all_f = hf.reading_corrections(data.frame, result.spline)
    if noise:
        d_omega, d_f, removed = hf.removed_noise(all_omega, all_f, data.imu_rate_hz)
    else:
        (d_omega, d_f), removed = hf.significant_part(all_omega, all_f, data.imu_rate_hz), None
    inner = ~hf.edges(data.imu_rate_hz)
    share = 0.0  # segments shorter than a block: no share to measure
    if np.any(inner):
        share = max(float(np.sqrt(np.mean(d_omega[inner]**2) / max(np.mean(all_omega[inner]**2), 1e-300))),
                    float(np.sqrt(np.mean(d_f[inner]**2) / max(np.mean(all_f[inner]**2), 1e-300))))
    return d_omega, d_f, share, removed


def _clean(data: GnssImuData, result: GnssImuResult) -> tuple[GnssImuData, float]:
    """:func:`without_high_rate` and the share of the rebuilt readings that was taken out
    (:func:`_significant`). The cleaned data carry what the cleaning took out of unit white noise
    (``imu_cleaning``, per sample; zero outside the rebuilt span): the redundancy it consumed.
    """
    d_omega, d_f, share, removed = _significant(data, result, noise=True)
    hf = result.high_rate
    if hf is None or hf.time.size == 0:
        return data, share
    sel = np.flatnonzero(_inside(data, (hf.time[0], hf.time[-1])))
    if sel.size != hf.time.size or not np.array_equal(data.imu_time[sel], hf.time):
        raise ValueError("the high-rate motion was rebuilt from other IMU samples than these")
    e = result.imu_errors
    gyro = data.imu_gyro.copy()
    acc = data.imu_acc.copy()
    gyro[sel] -= _sense(d_omega, e.gyro_scale, e.gyro_misalignment)
    acc[sel] -= _sense(d_f, e.acc_scale, e.acc_misalignment)
    cleaning = np.zeros((data.imu_time.size, 6))
    cleaning[sel] = removed
    return replace(data, imu_gyro=gyro, imu_acc=acc, imu_cleaning=cleaning), share


MIN_SIGNIFICANT_SHARE = 0.1
"""Below this share of significant content (:func:`_clean`) a re-solve would change nothing:
the rebuilt high-frequency readings are sensor noise, and what stands out of it is a tenth of
the noise at most (measured: 0.024 on the smooth ``corridor-tiny``, 1.00 with rotor vibration)."""


def adjust_upsampled(
    data: GnssImuData,
    result: GnssImuResult,
    rebuild: Callable[[GnssImuData, GnssImuResult], GnssImuProblem],
    solve: Callable[[GnssImuProblem], GnssImuResult],
    iterations: int,
    restart: Callable[[GnssImuResult], GnssImuResult] | None = None,
) -> GnssImuResult:
    """Iterate up-sampling from a first ``result`` (solved on ``data``'s raw windows).

    ``rebuild(data, previous)`` builds the next problem on ``data`` started at ``previous``
    (spline and IMU errors); ``solve`` solves it. ``restart(result)``, if given, is called once
    when the first test finds content to take out, before any re-solve: it solves again on the
    raw windows (the G/I on the G/I/L's finer knots), and the iteration goes on from its result.
    Returns the last result with its ``high_rate`` motion; ``timings_s['solve']`` sums the
    solves, ``timings_s['upsampling']`` is the time spent rebuilding and cleaning.
    """
    t = _time.perf_counter()
    hf = rebuild_high_rate(data, result)
    result = replace(result, high_rate=hf)
    extra = _time.perf_counter() - t
    for i in range(iterations):
        rms = hf.rms()
        log.info("up-sampling %d: high-frequency motion %.2f mdeg, %.2f mm RMS", i + 1, np.degrees(rms[0]) * 1e3,
                 rms[1] * 1e3)
        t = _time.perf_counter()
        cleaned, share = _clean(data, result)
        extra += _time.perf_counter() - t
        log.info("up-sampling %d: %.1f %% of the rebuilt readings stand out of the IMU noise", i + 1, 100 * share)
        if share < MIN_SIGNIFICANT_SHARE:
            log.info("up-sampling: nothing to take out of the IMU windows; no re-solve")
            break
        if restart is not None:
            solve_s = result.timings_s.get("solve", 0.0)
            restarted = restart(result)
            result = replace(restarted, timings_s=dict(restarted.timings_s,
                                                       solve=restarted.timings_s.get("solve", 0.0) + solve_s))
            restart = None
            t = _time.perf_counter()
            hf = rebuild_high_rate(data, result)
            result = replace(result, high_rate=hf)
            cleaned, share = _clean(data, result)
            extra += _time.perf_counter() - t
            log.info("up-sampling %d, restarted: %.1f %% of the rebuilt readings stand out of the IMU noise",
                     i + 1, 100 * share)
            if share < MIN_SIGNIFICANT_SHARE:
                break
        solve_s = result.timings_s.get("solve", 0.0)
        solved = solve(rebuild(cleaned, result))
        solved = replace(solved, timings_s=dict(solved.timings_s, solve=solved.timings_s.get("solve", 0.0) + solve_s))
        t = _time.perf_counter()
        hf = rebuild_high_rate(data, solved)
        result = replace(solved, high_rate=hf)
        extra += _time.perf_counter() - t
    return replace(result, timings_s=dict(result.timings_s, upsampling=extra))
