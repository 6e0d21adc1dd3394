"""Does the scanner need a calibration the G/I/L did not estimate? (docs/ARCHITECTURE.md §4.5 step 5)

A unit that reads its ranges long or short, or whose facets send their beams off the angles it
records, leaves no trace in the plane residuals that a reviewer would see: the trajectory takes
most of it. On ``corridor`` a range error of 3 cm + 100 ppm put the G/I/L pitch at 1.48 times
the clean run's, with variance factors, plane residuals and outer iterations as on a clean run.

So after the last outer iteration the same problem (the last iteration's features and objects) is
solved once more with what the configuration leaves out, started at its solution: the range calibration
and the channel angles where it does not estimate them (``processing.lidar.estimate_range_calibration``,
``estimate_channel_angles``). Where it leaves out the encoder error or the boresight
(``estimate_encoder_error``, ``estimate_boresight``), a third solve holds them free beside the first one's: the
encoder's periodic error shows as a scan-angle error that varies across the field of view
(:func:`~georefine.adjustment.observations.plane.encoder_basis`), its mean as the boresight's roll (on
``corridor`` 20 and 10 mdeg in its first two harmonics, unestimated, put the G/I/L roll at 17 times the clean
run's, and five warnings named other causes). A solve of its own, nested on the first: its linear term stretches
the swath as a range scale error does, so beside them the range offset's sigma grew from 5.5 to 9.6 mm
on ``corridor-tiny`` and a 5 cm + 100 ppm range error fell below the test, while without the range calibration
the encoder terms would take that error. Where the third solve finds the encoder error or the boresight, its
range calibration and channel angles are the ones tested (the first solve's take what the encoder does), and the
incidence solve below holds them too. Where the range calibration is left out it is solved once more with a
range bias that grows with the incidence angle, ``b (1 / cos(phi) - 1)``, in its place
(:data:`~georefine.workflows.gil.INCIDENCE_BLOCK`: the centroid of a return from a surface seen obliquely
lies in its footprint's far part, and a detector's range walk with a weaker return does the same). Not
both in one solve: the range offset and ``b`` then trade against each other along the height the
correlated GNSS error can take (on ``corridor-tiny`` with ``b`` = 10 cm: alone 97.0 ± 1.9 mm; with the
range calibration 47.8 ± 10.4 mm and an offset of -51.6 ± 10.7 mm). Where both are significant, the
solve with the lower cost names its own. Each is tested against its posterior sigma (a Wald test of the nested model): a
parameter beyond :data:`CHECK_SIGMAS` sigma that moves the points by more than :data:`CHECK_MM` (at the
features' median range; the incidence bias at their 95th-percentile incidence) is a warning that names
it, its estimate and sigma, and the setting, or, for the incidence bias, which Georefine cannot take
out of the points (their incidence is unknown where they are georeferenced), what it does to them.
The check's estimates are not applied: what the products hold is what the configuration asked
for. It costs one to three more G/I/L solves, each with a factorisation for its covariance (28 and 30 s on
``corridor``; ``processing.lidar.check_scanner_calibration`` switches it off). One flight: a run of several flights estimates what ``project.yaml`` asks of
these parameters (one scanner for all flights) but does not check for the rest yet.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from georefine.adjustment.gnss_imu import block_sigma, posterior_scale
from georefine.adjustment.observations.plane import encoder_basis, incidence_term
from georefine.config import boresight_matrix
from georefine.geometry.rotation import log_so3
from georefine.lidar.correspondences import PlanarObjects
from georefine.lidar.planes import PlanarFeatures
from georefine.progress import Progress, no_progress
from georefine.workflows.gil import INCIDENCE_BLOCK, scanner_estimates, step_adjust_gil
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
    ``median_range_m``: of the features' centres; ``incidence`` and ``incidence_sigma``: the bias ``b`` (m) and
    its sigma, or None (no check); ``incidence_p95``: the features' 95th percentile of ``1 / cos(phi) - 1``;
    ``range_cost``, ``incidence_cost``: the final cost of the solve with the range calibration and of the one with
    the incidence bias in its place (NaN: not solved); ``encoder`` and ``encoder_sigma``: (4,) the encoder error's
    Legendre coefficients (rad) and their sigma, or None; ``encoder_alpha``: the features' scan angles (rad) at their
    5th and 95th percentiles, where the encoder error is read; ``boresight`` and ``boresight_sigma``: (3,) the
    boresight's rotation from the stated one (rad, scanner frame) and its sigma, or None.
    """

    median_range_m: float
    range: tuple[float, float] | None = None
    range_sigma: tuple[float, float] | None = None
    channels: np.ndarray | None = None
    channels_sigma: np.ndarray | None = None
    incidence: float | None = None
    incidence_sigma: float | None = None
    incidence_p95: float = float("nan")
    range_cost: float = float("nan")
    incidence_cost: float = float("nan")
    encoder: np.ndarray | None = None
    encoder_sigma: np.ndarray | None = None
    encoder_alpha: tuple[float, float] = (float("nan"), float("nan"))
    boresight: np.ndarray | None = None
    boresight_sigma: np.ndarray | None = None

    def encoder_extent(self) -> tuple[float, float]:
        """The encoder error's largest magnitude (rad) over the features' scan angles and the scan angle (rad)
        where it is; ``(0, nan)`` without it."""
        if self.encoder is None or not np.all(np.isfinite(self.encoder_alpha)):
            return 0.0, float("nan")
        alpha = np.linspace(*self.encoder_alpha, 201)
        e = encoder_basis(alpha) @ self.encoder
        i = int(np.argmax(np.abs(e)))
        return float(abs(e[i])), float(alpha[i])

    def findings(self) -> list[str]:
        """One sentence per significant and relevant finding (module docstring), empty where none."""
        out = []
        r = self.median_range_m
        range_found, incidence_found = self._range_found(), self._incidence_found()
        if range_found and incidence_found:  # one explains what the other does: name the better fit
            better = "incidence" if self.incidence_cost <= self.range_cost else "range"
            range_found, incidence_found = better == "range", better == "incidence"
            other = (f" (a range bias growing with the incidence angle fits the planes less well: cost "
                     f"{self.incidence_cost:.1f} against {self.range_cost:.1f})" if range_found else
                     f" (a range offset and scale fit the planes less well: cost {self.range_cost:.1f} against "
                     f"{self.incidence_cost:.1f})")
        else:
            other = ""
        if range_found:
            (r0, k), (s0, sk) = self.range, self.range_sigma
            z = max(abs(r0) / s0, abs(k) / sk)
            out.append(f"the planes show a scanner range offset of {r0 * 1e3:+.1f} ± {s0 * 1e3:.1f} mm and a scale "
                       f"error of {k * 1e6:+.1f} ± {sk * 1e6:.1f} ppm ({z:.0f} sigma; {(abs(r0) + abs(k) * r) * 1e3:.0f} "
                       f"mm at {r:.0f} m), which the G/I/L did not estimate and has taken into the trajectory{other}: set "
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
        if self._encoder_found():
            z = np.abs(self.encoder) / self.encoder_sigma
            top, where = self.encoder_extent()
            mdeg, sig = np.degrees(self.encoder) * 1e3, np.degrees(self.encoder_sigma) * 1e3
            terms = ", ".join(f"P{j + 1} {mdeg[j]:+.1f} ± {sig[j]:.{1 if sig[j] >= 0.1 else 2}f}"
                              for j in range(mdeg.size))
            lo, hi = np.degrees(self.encoder_alpha)
            out.append(f"the planes show a scan-angle error that varies across the field of view, as a scan-angle "
                       f"encoder's periodic error does, the same on every channel ({terms} mdeg; {z.max():.0f} "
                       f"sigma): up to {np.degrees(top) * 1e3:.1f} mdeg at a scan angle of {np.degrees(where):+.0f} "
                       f"degrees between {lo:+.0f} and {hi:+.0f}, {top * r * 1e3:.0f} mm at {r:.0f} m, which the "
                       "G/I/L did not estimate and has taken into the trajectory: set "
                       "processing.lidar.estimate_encoder_error: true" + self._encoder_mean())
        if self._boresight_found():
            z = np.abs(self.boresight) / self.boresight_sigma
            mdeg, sig = np.degrees(self.boresight) * 1e3, np.degrees(self.boresight_sigma) * 1e3
            each = ", ".join(f"{a} {mdeg[i]:+.1f} ± {sig[i]:.1f}" for i, a in enumerate(("roll", "pitch", "yaw")))
            out.append(f"the planes show the scanner's boresight off the stated one about the scanner's axes ({each} "
                       f"mdeg; {z.max():.0f} sigma, {np.abs(self.boresight).max() * r * 1e3:.0f} mm at {r:.0f} m), "
                       "which the G/I/L did not estimate and has taken into the trajectory (a scan-angle error "
                       "common to every channel, an encoder's offset among them, is a roll about the scanner's x "
                       "axis): set processing.lidar.estimate_boresight: true, or correct scanner.boresight_deg")
        if incidence_found:
            b, sb, g = self.incidence, self.incidence_sigma, self.incidence_p95
            phi = np.degrees(np.arccos(1.0 / (1.0 + g)))
            out.append(f"the planes show a scanner range bias that grows with the incidence angle phi, b (1/cos(phi) "
                       f"- 1) with b = {b * 1e3:+.1f} ± {sb * 1e3:.1f} mm ({abs(b) / sb:.0f} sigma; {abs(b) * g * 1e3:.0f} mm "
                       f"at {phi:.0f} degrees, the features' 95th percentile, {abs(b) * 1e3:.0f} mm at 60 degrees){other}, "
                       "which the G/I/L does not model and has taken into the trajectory. On level ground it acts as a "
                       "range offset of -b: processing.lidar.estimate_range_calibration: true takes it out of the "
                       "trajectory, not out of oblique surfaces (roofs, slopes, walls), which lie along the beams by "
                       "up to that much; the scanner's range correction for incidence or return strength (its "
                       "manufacturer's calibration) is due")
        return out

    def _encoder_found(self) -> bool:
        if self.encoder is None:
            return False
        z = np.abs(self.encoder) / self.encoder_sigma
        return bool(z.max() > CHECK_SIGMAS and self.encoder_extent()[0] * self.median_range_m * 1e3 > CHECK_MM)

    def _boresight_found(self) -> bool:
        if self.boresight is None:
            return False
        z = np.abs(self.boresight) / self.boresight_sigma
        return bool(z.max() > CHECK_SIGMAS and np.abs(self.boresight).max() * self.median_range_m * 1e3 > CHECK_MM)

    def _encoder_mean(self) -> str:
        """Where the boresight was checked and not found significant: its roll, which takes the encoder error's mean
        over the field of view (a boresight beyond the test is a finding of its own)."""
        if self.boresight is None or self._boresight_found():
            return ""
        roll, sigma = np.degrees(self.boresight[0]) * 1e3, np.degrees(self.boresight_sigma[0]) * 1e3
        return (f". Its mean over the field of view is a roll of the boresight, which came out {roll:+.1f} ± "
                f"{sigma:.1f} mdeg off the stated one ({abs(roll) / sigma:.1f} sigma, below the check's "
                f"{CHECK_SIGMAS:.0f}): estimate both (processing.lidar.estimate_boresight: true)")

    def _range_found(self) -> bool:
        if self.range is None:
            return False
        (r0, k), (s0, sk) = self.range, self.range_sigma
        return max(abs(r0) / s0, abs(k) / sk) > CHECK_SIGMAS and (abs(r0) + abs(k) * self.median_range_m) * 1e3 > CHECK_MM

    def _incidence_found(self) -> bool:
        if self.incidence is None:
            return False
        return (abs(self.incidence) / self.incidence_sigma > CHECK_SIGMAS
                and abs(self.incidence) * self.incidence_p95 * 1e3 > CHECK_MM)


def check_scanner_calibration(nav: NavigationData, start, features: PlanarFeatures, objects: PlanarObjects,
                              time_offset: TimeOffsetStart, progress: Progress = no_progress) -> CalibrationCheck | None:
    """Solve the last outer iteration's G/I/L once more with the calibration the configuration leaves out, and
    once more with the incidence bias in place of the range calibration (module docstring); None where the check
    is switched off or there is nothing to check."""
    lcfg = nav.config.processing.lidar
    if not lcfg.check_scanner_calibration:
        return None
    wanted = {k: True for k in ("estimate_range_calibration", "estimate_channel_angles", "estimate_encoder_error",
                                "estimate_boresight") if not getattr(lcfg, k)}
    if not wanted:  # nothing left out, nothing to check
        return None
    incidence = "estimate_range_calibration" in wanted
    first = {k: v for k, v in wanted.items() if k in ("estimate_range_calibration", "estimate_channel_angles")}

    def solve(update: dict, with_incidence: bool):
        config = nav.config.model_copy(update={"processing": nav.config.processing.model_copy(
            update={"lidar": lcfg.model_copy(update=update)})})
        adj = step_adjust_gil(replace(nav, config=config), start, features, objects, progress, covariance=False,
                              time_offset=time_offset, range_incidence=with_incidence)
        return adj.built.problem, posterior_scale(adj.result.solve), float(adj.result.solve.final_cost)

    used = objects.feature_object >= 0
    median = float(np.median(np.linalg.norm(features.centre_s[used], axis=1))) if np.any(used) else float("nan")
    out = CalibrationCheck(median)
    if first:
        problem, vf, cost = solve(first, False)
        out = replace(out, range_cost=cost)
        found = scanner_estimates(problem, vf)  # also holds what the configuration estimates: only what it left out
        if "estimate_range_calibration" in wanted:
            out = replace(out, range=found["range_calibration"], range_sigma=found["range_calibration_sigma"])
        if "estimate_channel_angles" in wanted:
            out = replace(out, channels=found["channel_angles"], channels_sigma=found["channel_angles_sigma"])
    model = first  # what the incidence solve holds beside the incidence bias (and the range cost's solve)
    if len(wanted) > len(first):  # the encoder error or the boresight, nested on the first solve
        problem, vf, cost = solve(wanted, False)
        found = scanner_estimates(problem, vf)
        if "estimate_encoder_error" in wanted:
            out = replace(out, encoder=found["encoder"], encoder_sigma=found["encoder_sigma"])
            c = features.centre_s[used]
            alpha = np.arctan2(c[:, 1], c[:, 2])
            out = replace(out, encoder_alpha=tuple(float(v) for v in np.percentile(alpha, [5, 95])) if alpha.size
                          else (float("nan"), float("nan")))
        if "estimate_boresight" in wanted:
            stated = boresight_matrix(nav.config.scanner.boresight_deg)
            out = replace(out, boresight=log_so3(stated.T @ problem.values("boresight")[0]),
                          boresight_sigma=block_sigma(problem, "boresight", vf)[0])
        if out._encoder_found() or out._boresight_found():  # the fuller model holds: read the first solve's from it
            model = wanted
            out = replace(out, range_cost=cost)
            if "estimate_range_calibration" in first:
                out = replace(out, range=found["range_calibration"], range_sigma=found["range_calibration_sigma"])
            if "estimate_channel_angles" in first:
                out = replace(out, channels=found["channel_angles"], channels_sigma=found["channel_angles_sigma"])
    if incidence:  # the range calibration held out: with it, the two trade along the GNSS error's height
        problem, vf, cost = solve({k: v for k, v in model.items() if k != "estimate_range_calibration"}, True)
        beam = features.centre_s[used] / np.linalg.norm(features.centre_s[used], axis=1)[:, None]
        g = incidence_term(beam, np.cross(features.axis1_s[used], features.axis2_s[used]))
        out = replace(out, incidence=float(problem.values(INCIDENCE_BLOCK)[0, 0]),
                      incidence_sigma=float(block_sigma(problem, INCIDENCE_BLOCK, vf)[0, 0]), incidence_cost=cost,
                      incidence_p95=float(np.percentile(g, 95)) if g.size else float("nan"))
    return out


def warn_calibration(check: CalibrationCheck | None) -> None:
    """Log the check's estimates, and each finding of ``check`` as a warning."""
    if check is None:
        return
    parts = []
    if check.range is not None:
        (r0, k), (s0, sk) = check.range, check.range_sigma
        parts.append(f"range offset {r0 * 1e3:+.1f} ± {s0 * 1e3:.1f} mm, scale {k * 1e6:+.1f} ± {sk * 1e6:.1f} ppm")
    if check.channels is not None and len(check.channels) > 1:
        z = np.abs(check.channels[1:]) / check.channels_sigma[1:]
        parts.append(f"channel angles up to {np.degrees(np.abs(check.channels[1:]).max()) * 1e3:.1f} mdeg "
                     f"({z.max():.1f} sigma)")
    if check.encoder is not None:
        top, where = check.encoder_extent()
        z = np.abs(check.encoder) / check.encoder_sigma
        parts.append(f"encoder error up to {np.degrees(top) * 1e3:.1f} mdeg at {np.degrees(where):+.0f} degrees "
                     f"({z.max():.1f} sigma)")
    if check.boresight is not None:
        z = np.abs(check.boresight) / check.boresight_sigma
        parts.append("boresight off the stated by " + "/".join(f"{v:+.1f}" for v in np.degrees(check.boresight) * 1e3)
                     + f" mdeg roll/pitch/yaw ({z.max():.1f} sigma)")
    if check.incidence is not None:
        parts.append(f"incidence bias {check.incidence * 1e3:+.1f} ± {check.incidence_sigma * 1e3:.1f} mm "
                     f"(1/cos(phi) - 1 up to {check.incidence_p95:.2f} at the features' 95th percentile)")
    log.info("scanner calibration check: %s", "; ".join(parts))
    for text in check.findings():
        log.warning(text)
