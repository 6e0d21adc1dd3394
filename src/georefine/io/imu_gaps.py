"""Gaps in the IMU sampling: found, bridged with honest uncertainty, or refused (docs/ARCHITECTURE.md §3.2).

Real IMU logs drop samples: a single one now and then, or a run of them when the logger
stalls. :func:`find_imu_gaps` lists every interval longer than ``1.5 / rate_hz`` (the rule of
:func:`georefine.io.imu.sample_intervals`); ``georefine check`` and the workflow both
call :func:`bridge_imu_gaps`, so they agree on every gap:

* a gap of at most ``max_gap_s`` (``imu.max_gap_s`` in ``project.yaml``) is **bridged**: the
  missing samples are put back on the nominal grid, each reading interpolated linearly between
  the last sample before and the first after the gap. Their uncertainty is widened by the error
  such an interpolation makes on this very data: virtual gaps of the same length are cut into
  the samples on both sides of the real one, interpolated the same way, and the RMS difference
  to the samples they hid (per sensor, over the three axes) is the 1-sigma of each bridged
  reading (:func:`interpolation_sigma`). The platform's vibration and manoeuvres therefore set
  the weight the bridged samples get, not a guess.
* a longer gap is an error naming the file, the record and the gap.

The adjustment averages samples over windows (:mod:`georefine.adjustment.observations.imu`);
a window holding ``k`` of its ``n`` samples bridged adds ``(k / n) sigma`` to its standard
deviation -- the interpolation errors of neighbouring samples are taken as fully correlated,
which is the conservative choice for errors that come from smooth motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from georefine.io.imu import ImuData

__all__ = ["ImuGap", "BridgedImu", "find_imu_gaps", "bridge_imu_gaps", "interpolation_sigma"]

_NEIGHBOURHOOD_S = 10.0
"""Seconds of samples on each side of a gap in which virtual gaps measure the interpolation error."""


@dataclass(frozen=True)
class ImuGap:
    """One sampling gap: the samples around it and how many are missing."""

    index: int
    """Index of the last sample before the gap (the next one is the first after it)."""
    t_before: float
    t_after: float
    missing: int
    """Samples missing on the nominal grid: ``round((t_after - t_before) * rate) - 1``."""

    @property
    def duration_s(self) -> float:
        return self.t_after - self.t_before


@dataclass(frozen=True)
class BridgedImu:
    """IMU data with its short gaps filled, and the widened uncertainty of the filled samples.

    Attributes
    ----------
    data
        The samples, the bridged ones inserted at their nominal times (no gap left).
    gyro_sigma, acc_sigma : (N,)
        1-sigma of the interpolation error of each sample (rad/s, m/s²); 0 for measured ones.
    gaps
        The gaps that were bridged (in the input's indices).
    """

    data: ImuData
    gyro_sigma: np.ndarray
    acc_sigma: np.ndarray
    gaps: tuple[ImuGap, ...]

    @property
    def n_bridged(self) -> int:
        return int(sum(g.missing for g in self.gaps))

    def describe(self) -> str:
        """One line: how many gaps were bridged, with how many samples, the longest and its sigma."""
        if not self.gaps:
            return "no IMU sampling gaps"
        longest = max(self.gaps, key=lambda g: g.duration_s)
        # its first bridged sample: behind the samples bridged into the gaps before it
        k = longest.index + 1 + sum(g.missing for g in self.gaps if g.index < longest.index)
        return (f"{len(self.gaps)} IMU sampling gaps bridged ({self.n_bridged} samples interpolated), the longest "
                f"{longest.duration_s:.3f} s at {longest.t_before:.3f} GPS s (gyro sigma "
                f"{np.degrees(self.gyro_sigma[k]):.3g} deg/s, acc sigma {self.acc_sigma[k]:.3g} m/s²)")


def find_imu_gaps(imu: ImuData, max_gap_factor: float = 1.5) -> list[ImuGap]:
    """Intervals longer than ``max_gap_factor / rate_hz``, in time order."""
    t = imu.time_gps
    idx = np.flatnonzero(np.diff(t) > max_gap_factor / imu.rate_hz)
    return [ImuGap(int(i), float(t[i]), float(t[i + 1]), max(1, int(round((t[i + 1] - t[i]) * imu.rate_hz)) - 1))
            for i in idx]


def interpolation_sigma(values: np.ndarray, missing: int, *, max_starts: int = 400) -> float:
    """RMS error of linearly interpolating ``missing`` consecutive samples of ``values`` from their neighbours.

    ``values`` (M, 3) are measured samples on a regular grid. Every virtual gap of ``missing``
    samples inside it (at most ``max_starts`` of them, evenly spread) is interpolated between
    the samples just outside it; the RMS of the differences over all hidden samples and axes is
    returned. NaN if ``values`` is too short for one virtual gap.
    """
    values = np.asarray(values, dtype=float)
    n_starts = values.shape[0] - missing - 1
    if n_starts < 1:
        return float("nan")
    starts = np.unique(np.linspace(0, n_starts - 1, min(n_starts, max_starts)).round().astype(np.int64))
    j = np.arange(1, missing + 1)
    w = (j / (missing + 1))[None, :, None]
    left, right = values[starts][:, None, :], values[starts + missing + 1][:, None, :]
    hidden = values[starts[:, None] + j[None, :]]
    return float(np.sqrt(np.mean((hidden - (left + w * (right - left))) ** 2)))


def bridge_imu_gaps(imu: ImuData, max_gap_s: float, max_gap_factor: float = 1.5) -> tuple[BridgedImu, ImuGap | None]:
    """Bridge the gaps of at most ``max_gap_s``; the first longer gap, if any, is returned instead of bridged.

    Returns ``(bridged, too_long)``: when ``too_long`` is not None nothing was bridged past it
    and the caller refuses the data (naming the gap). Without gaps ``bridged.data`` is ``imu``.
    """
    gaps = find_imu_gaps(imu, max_gap_factor)
    n = len(imu)
    too_long = next((g for g in gaps if g.duration_s > max_gap_s), None)
    if too_long is not None or not gaps:
        zeros = np.zeros(n)
        return BridgedImu(imu, zeros, zeros.copy(), ()), too_long
    reach = int(round(_NEIGHBOURHOOD_S * imu.rate_hz))
    edges = [0] + [g.index + 1 for g in gaps] + [n]  # the gap-free runs of measured samples
    t_parts, g_parts, a_parts, sg_parts, sa_parts = [], [], [], [], []
    for k, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
        t_parts.append(imu.time_gps[a:b])
        g_parts.append(imu.gyro[a:b])
        a_parts.append(imu.acc[a:b])
        sg_parts.append(np.zeros(b - a))
        sa_parts.append(np.zeros(b - a))
        if k == len(gaps):
            break
        gap = gaps[k]
        i = gap.index
        frac = (np.arange(1, gap.missing + 1) / (gap.missing + 1))[:, None]
        t_parts.append(gap.t_before + (gap.t_after - gap.t_before) * frac[:, 0])
        g_parts.append(imu.gyro[i] + frac * (imu.gyro[i + 1] - imu.gyro[i]))
        a_parts.append(imu.acc[i] + frac * (imu.acc[i + 1] - imu.acc[i]))
        sigmas = []
        for values in (imu.gyro, imu.acc):  # virtual gaps on each side, never across another gap
            before = values[max(edges[k], i + 1 - reach):i + 1]
            after = values[i + 1:min(edges[k + 2], i + 1 + reach)]
            errs = [interpolation_sigma(v, gap.missing) for v in (before, after)]
            errs = [e for e in errs if np.isfinite(e)]
            # too little data around the gap to measure: the spread of the readings bounds the error
            sigmas.append(max(errs) if errs else float(np.std(np.concatenate([before, after]), axis=0).max()))
        sg_parts.append(np.full(gap.missing, sigmas[0]))
        sa_parts.append(np.full(gap.missing, sigmas[1]))
    t = np.concatenate(t_parts)
    temperature = None if imu.temperature_c is None else np.interp(t, imu.time_gps, imu.temperature_c)
    data = ImuData(t, np.concatenate(g_parts), np.concatenate(a_parts), imu.rate_hz, imu.kind, temperature)
    return BridgedImu(data, np.concatenate(sg_parts), np.concatenate(sa_parts), tuple(gaps)), None
