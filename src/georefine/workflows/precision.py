"""What the LiDAR planes added to the attitude, per pass: the posterior sigma of G/I and G/I/L.

The G/I/L adjustment leaves a direction that its planes do not observe to the GNSS/IMU
information (paper 000 §2; docs/ARCHITECTURE.md §4.5): roll in straight flight over two
opposite passes whose accelerometer biases differ, heading where the planes are few. Its
posterior then stays near the G/I one in that angle, and ``georefine run`` says so with the
figures rather than leave the user to assume every angle reached the planes' precision.
"""

from __future__ import annotations

import numpy as np

from georefine.adjustment.gnss_imu import GnssImuResult
from georefine.io.run_metrics import PassPrecision
from georefine.trajectory.sampled import interp_columns

__all__ = ["LITTLE_GAIN", "pass_precision", "precision_lines"]

LITTLE_GAIN = 0.7
"""A G/I/L sigma above this fraction of the G/I one: the planes add little to that angle."""

ANGLES = ("roll", "pitch", "yaw")


def _rms_sigma_mdeg(result: GnssImuResult, t0: float, t1: float) -> tuple[float, float, float]:
    """RMS of the roll/pitch/yaw sigma over ``[t0, t1]`` (times of ``result``), sampled every second."""
    t, sig = np.asarray(result.sigma_time, float), np.asarray(result.sigma_rph_rad, float)
    if t.size == 0:
        return (float("nan"),) * 3  # type: ignore[return-value]
    ts = np.linspace(t0, t1, max(2, int(np.ceil(t1 - t0)) + 1))
    s = interp_columns(ts, t, sig)
    return tuple(float(v) for v in 1e3 * np.degrees(np.sqrt(np.mean(s**2, axis=0))))  # type: ignore[return-value]


def pass_precision(gi: GnssImuResult, gil: GnssImuResult, spans: dict[int, tuple[float, float]]) -> tuple[PassPrecision, ...]:
    """Per strip (``spans``: strip id -> first and last time, the results' time base) the RMS attitude sigma."""
    return tuple(PassPrecision(k, _rms_sigma_mdeg(gi, t0, t1), _rms_sigma_mdeg(gil, t0, t1))
                 for k, (t0, t1) in spans.items())


def precision_lines(passes: tuple[PassPrecision, ...]) -> list[str]:
    """The run summary's lines: the sigma per pass, and the angles the planes add little to."""
    if not passes:
        return []
    lines = ["  attitude sigma per pass, G/I -> G/I/L (mdeg): " + "; ".join(
        f"strip {p.strip} " + ", ".join(f"{a} {g:.2f} -> {l_:.2f}" for a, g, l_ in zip(ANGLES, p.gi_sigma_mdeg, p.gil_sigma_mdeg))
        for p in passes)]
    little = [f"strip {p.strip} {a} ({l_ / g:.2f}x)" for p in passes
              for a, g, l_ in zip(ANGLES, p.gi_sigma_mdeg, p.gil_sigma_mdeg) if g > 0 and l_ > LITTLE_GAIN * g]
    if little:
        lines.append("  the planes add little to " + ", ".join(little) + f" (G/I/L sigma above {LITTLE_GAIN:g}x the G/I "
                     "one): there the attitude rests on the GNSS/IMU")
    return lines
