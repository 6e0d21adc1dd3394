"""Does the scanner need a calibration the G/I/L did not estimate? (docs/ARCHITECTURE.md §4.5 step 5)

A unit that reads its ranges long or short, or whose facets send their beams off the angles it
records, leaves no trace in the plane residuals that a reviewer would see: the trajectory takes
most of it. On ``corridor`` a range error of 3 cm + 100 ppm put the G/I/L pitch at 1.48 times
the clean run's, with variance factors, plane residuals and outer iterations as on a clean run.

So after the last outer iteration, where the configuration leaves the range calibration or the
channel angles out (``processing.lidar.estimate_range_calibration``, ``estimate_channel_angles``),
the same problem (the last iteration's features and objects) is solved once more with them, started
at its solution, and each is tested against its posterior sigma (a Wald test of the nested model): a
parameter beyond :data:`CHECK_SIGMAS` sigma that moves the points by more than :data:`CHECK_MM` at
the features' median range is a warning that names it, its estimate and sigma, and the setting.
The check's estimates are not applied: what the products hold is what the configuration asked
for. It costs one more G/I/L solve and a factorisation (``processing.lidar.check_scanner_calibration``
switches it off). One flight: the adjustment of several flights does not take these parameters.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from georefine.adjustment.gnss_imu import posterior_scale
from georefine.lidar.correspondences import PlanarObjects
from georefine.lidar.planes import PlanarFeatures
from georefine.progress import Progress, no_progress
from georefine.workflows.gil import CHANNEL_BLOCK, RANGE_BLOCK, step_adjust_gil
from georefine.workflows.opened import NavigationData
from georefine.workflows.time_offset import TimeOffsetStart

log = logging.getLogger(__name__)

__all__ = ["CHECK_MM", "CHECK_SIGMAS", "CalibrationCheck", "check_scanner_calibration", "warn_calibration"]

CHECK_SIGMAS = 5.0
"""A parameter this many of its sigma from zero is significant (a few thousand planes make sigmas small: the
test has no multiple-comparison problem at this level for the six parameters it looks at)."""
CHECK_MM = 2.0
"""...and matters where it moves the points by this much (mm) at the features' median range."""


@dataclass(frozen=True)
class CalibrationCheck:
    """The scanner calibration the G/I/L left out, estimated once for the check.

    ``range`` and ``range_sigma``: ``(r0 m, k)`` and their sigma, or None where the G/I/L estimates them (or
    has no features); ``channels`` and ``channels_sigma``: (C, 2) rad, channel 0 the reference at 0, or None;
    ``median_range_m``: of the features' centres.
    """

    median_range_m: float
    range: tuple[float, float] | None = None
    range_sigma: tuple[float, float] | None = None
    channels: np.ndarray | None = None
    channels_sigma: np.ndarray | None = None

    def findings(self) -> list[str]:
        """One sentence per significant and relevant finding (module docstring), empty where none."""
        out = []
        r = self.median_range_m
        if self.range is not None:
            (r0, k), (s0, sk) = self.range, self.range_sigma
            z = max(abs(r0) / s0, abs(k) / sk)
            if z > CHECK_SIGMAS and (abs(r0) + abs(k) * r) * 1e3 > CHECK_MM:
                out.append(f"the planes show a scanner range offset of {r0 * 1e3:+.1f} ± {s0 * 1e3:.1f} mm and a scale "
                           f"error of {k * 1e6:+.1f} ± {sk * 1e6:.1f} ppm ({z:.0f} sigma; {(abs(r0) + abs(k) * r) * 1e3:.0f} "
                           f"mm at {r:.0f} m), which the G/I/L did not estimate and has taken into the trajectory: set "
                           "processing.lidar.estimate_range_calibration: true")
        if self.channels is not None and len(self.channels) > 1:
            a, s = self.channels[1:], self.channels_sigma[1:]
            z = np.abs(a) / s
            if z.max() > CHECK_SIGMAS and np.abs(a).max() * r * 1e3 > CHECK_MM:
                mdeg = np.degrees(a) * 1e3
                sig = np.degrees(s) * 1e3
                each = "; ".join(f"channel {c + 1}: tilt {mdeg[c, 0]:+.1f} ± {sig[c, 0]:.1f}, scan angle "
                                 f"{mdeg[c, 1]:+.1f} ± {sig[c, 1]:.1f} mdeg" for c in range(len(a)))
                out.append(f"the planes show scanner channels whose beams leave off the recorded angles against "
                           f"channel 0 ({each}; {z.max():.0f} sigma, {np.abs(a).max() * r * 1e3:.0f} mm at {r:.0f} m), "
                           "which the G/I/L did not estimate: set processing.lidar.estimate_channel_angles: true")
        return out


def check_scanner_calibration(nav: NavigationData, start, features: PlanarFeatures, objects: PlanarObjects,
                              time_offset: TimeOffsetStart, progress: Progress = no_progress) -> CalibrationCheck | None:
    """Solve the last outer iteration's G/I/L once more with the calibration the configuration leaves out
    (module docstring); None where it leaves out none or the check is switched off."""
    lcfg = nav.config.processing.lidar
    wanted = {k: True for k in ("estimate_range_calibration", "estimate_channel_angles") if not getattr(lcfg, k)}
    if not wanted or not lcfg.check_scanner_calibration:
        return None
    config = nav.config.model_copy(update={"processing": nav.config.processing.model_copy(
        update={"lidar": lcfg.model_copy(update=wanted)})})
    adj = step_adjust_gil(replace(nav, config=config), start, features, objects, progress, covariance=False,
                          time_offset=time_offset)
    problem = adj.built.problem
    vf = posterior_scale(adj.result.solve)
    used = objects.feature_object >= 0
    median = float(np.median(np.linalg.norm(features.centre_s[used], axis=1))) if np.any(used) else float("nan")
    out = CalibrationCheck(median)
    if "estimate_range_calibration" in wanted:
        cov = problem.covariance(RANGE_BLOCK, scale_by_variance_factor=False)[0] * vf
        out = replace(out, range=tuple(float(v) for v in problem.values(RANGE_BLOCK)[0]),
                      range_sigma=tuple(float(v) for v in np.sqrt(np.diag(cov))))
    if "estimate_channel_angles" in wanted:
        cov = problem.covariance(CHANNEL_BLOCK, scale_by_variance_factor=False) * vf
        zero = np.zeros((1, 2))
        out = replace(out, channels=np.vstack([zero, problem.values(CHANNEL_BLOCK)]),
                      channels_sigma=np.vstack([zero, np.sqrt(np.diagonal(cov, axis1=1, axis2=2))]))
    return out


def warn_calibration(check: CalibrationCheck | None) -> None:
    """Log each finding of ``check`` as a warning."""
    for text in [] if check is None else check.findings():
        log.warning(text)
