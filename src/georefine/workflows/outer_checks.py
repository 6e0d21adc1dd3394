"""What the outer iterations of the G/I/L measure and warn about (docs/ARCHITECTURE.md §4.4).

The change of the trajectory from one outer iteration to the next (the convergence test), the
warning when the last allowed one still moved it, the warning when the planes pull the
trajectory off the GNSS, and the warning when the G/I's attitude sits further from the G/I/L's
than its stated sigma allows: a model that does not fit says so with its figures.
"""

from __future__ import annotations

import logging

import numpy as np

from georefine.adjustment.gnss_imu import GnssImuResult
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import log_so3, rph_from_R_n_b
from georefine.io.run_metrics import OuterIteration
from georefine.workflows.delivered import warn_delivered_pull
from georefine.workflows.gil import LidarAdjustment
from georefine.workflows.navigation import NavigationData

log = logging.getLogger(__name__)

__all__ = ["BORESIGHT_GI_SHARE", "BORESIGHT_SHARE", "GI_TILT_SIGMAS", "GNSS_PULL_RATIO", "boresight_separation",
           "gi_tilt", "outer_converged", "trajectory_change", "warn_boresight_separation", "warn_gi_tilt",
           "warn_plane_misfit", "warn_unconverged"]


def trajectory_change(a, b, *, statistic: str = "rms") -> tuple[float, float]:
    """Attitude (mdeg) and position (m) difference of two splines at ``a``'s knots.

    ``statistic="rms"`` (the outer-iteration criterion) or ``"max"``. The RMS, not the maximum:
    re-extracted and re-matched features differ a little from one outer iteration to the next,
    which moves single knots by a few mdeg without changing the trajectory as a whole.
    """
    t = a.grid.knot_times
    t = t[(t >= b.grid.t_start) & (t <= b.grid.t_end)]
    pa, Ra = a.pose(t)
    pb, Rb = b.pose(t)
    dth = np.linalg.norm(log_so3(np.swapaxes(Ra, 1, 2) @ Rb), axis=1)
    dp = np.linalg.norm(pa - pb, axis=1)
    if statistic == "max":
        return float(np.degrees(dth.max()) * 1e3), float(dp.max())
    if statistic != "rms":
        raise ValueError(f"statistic must be 'rms' or 'max', found {statistic!r}")
    return float(np.degrees(np.sqrt(np.mean(dth**2))) * 1e3), float(np.sqrt(np.mean(dp**2)))


def outer_converged(record: OuterIteration, lcfg) -> bool:
    """Whether an outer iteration changed the trajectory less than both thresholds."""
    return (record.attitude_change_mdeg < lcfg.convergence_attitude_mdeg
            and record.position_change_m < lcfg.convergence_position_m)


def warn_unconverged(records: list[OuterIteration], lcfg) -> None:
    """Warn, with the figures, when the last allowed outer iteration still moved the trajectory too much.

    A configuration of one outer iteration asked for no convergence test: its only change is the
    one from the G/I, which is what the LiDAR adds (a boresight calibration, as the demo's, uses
    one; the boresight's posterior sigma says how well it is known). That is logged, not warned.
    """
    last = records[-1]
    if outer_converged(last, lcfg):
        return
    if lcfg.outer_iterations == 1:
        log.info("one outer iteration (processing.lidar.outer_iterations: 1): no convergence test; it moved the "
                 "trajectory by %.2f mdeg and %.1f mm RMS from the G/I", last.attitude_change_mdeg,
                 last.position_change_m * 1e3)
        return
    log.warning(
        "the G/I/L outer iterations did not converge: after %d (processing.lidar.outer_iterations) the last one "
        "still moved the trajectory by %.2f mdeg and %.1f mm RMS (thresholds %.2f mdeg and %.1f mm; changes "
        "before it: %s); it used %s of %s features extracted (processing.lidar.max_features, max_features_per_minute)",
        len(records), last.attitude_change_mdeg, last.position_change_m * 1e3, lcfg.convergence_attitude_mdeg,
        lcfg.convergence_position_m * 1e3,
        ", ".join(f"{r.attitude_change_mdeg:.2f} mdeg" for r in records[:-1]) or "none",
        f"{last.features_used:,}", f"{last.features:,}",
    )


GNSS_PULL_RATIO = 2.0
"""Warn when the G/I/L adjustment's GNSS residuals (RMS in sigmas) exceed the G/I adjustment's by
this factor: the planes pull the trajectory off the GNSS, so LiDAR and navigation disagree about
something the model does not hold. Measured on ``corridor-tiny``: 1.04 in a clean run and with a
3 s time offset found and estimated; 6.1 with that offset left uncorrected, where the robust
sigma0 of the planes hardly moved (0.89 to 1.05: the matching keeps only the features that
agree locally, and the adjustment bends the trajectory to them)."""


def warn_plane_misfit(gi: GnssImuResult, adj: LidarAdjustment, records: tuple[OuterIteration, ...],
                      nav: NavigationData | None = None) -> None:
    """Warn, with the figures, when the planes pull the trajectory off the GNSS (:data:`GNSS_PULL_RATIO`),
    or a delivered trajectory beyond its stated accuracy (:func:`~georefine.workflows.delivered.warn_delivered_pull`)."""
    if getattr(adj.result, "sbet_errors", None) is not None:
        if nav is not None:
            warn_delivered_pull(nav, adj.result, records)
        return
    try:
        before, after, planes = gi.solve.group("gnss"), adj.result.solve.group("gnss"), adj.result.solve.group("planes")
    except KeyError:
        return
    if not after.rms > GNSS_PULL_RATIO * before.rms:
        return
    log.warning(
        "the LiDAR planes pull the trajectory off the GNSS: GNSS residuals %.2f sigma RMS with the planes against "
        "%.2f without (warning above %.1fx); planes RMS %.1f sigma, %d of %d features down-weighted; outer "
        "iterations changed the trajectory by %s. The model does not fit: check scanner.time_offset_s "
        "(processing.lidar.time_offset), the boresight, the lever arms and the scanner channels",
        after.rms, before.rms, GNSS_PULL_RATIO, planes.rms, planes.n_downweighted, planes.n_observations,
        ", ".join(f"{r.attitude_change_mdeg:.2f}" for r in records) + " mdeg",
    )


GI_TILT_SIGMAS = 3.0
"""Warn when the G/I's roll, pitch or heading differs from the G/I/L's on average by more than this many
of the G/I's stated sigmas. The G/I/L is the more precise by a factor of 4-20, so the difference is
the G/I's own error, and a constant error beyond three sigmas is one the G/I's model does not hold.
Measured on ``corridor-tiny`` (seed 21), roll/pitch/heading: 0.67/0.51/0.50 sigma clean; with the IMU
triads misaligned by 0.5 mrad and the misalignment not stated, 3.2/5.6/0.2 (stated and estimated, the
G/I's sigma carries it: 1.05/0.23/0.37)."""


def _rph(spline, t: np.ndarray, frame: LocalFrame) -> np.ndarray:
    p_w, R_w_b = spline.pose(t)
    return rph_from_R_n_b(np.swapaxes(frame.R_w_n_at(p_w), 1, 2) @ R_w_b)


def gi_tilt(gi: GnssImuResult, gil: GnssImuResult, frame: LocalFrame) -> tuple[np.ndarray, np.ndarray] | None:
    """The mean roll, pitch and heading difference G/I - G/I/L (rad) at the G/I/L's sigma knots inside
    the G/I's span, and the RMS of the G/I's stated sigma there (rad); None without posterior sigma."""
    t = gil.sigma_time
    if t.size == 0 or gi.sigma_time.size == 0:
        return None
    t = t[(t >= gi.spline.grid.t_start) & (t <= gi.spline.grid.t_end)]
    if t.size == 0:
        return None
    d = _rph(gi.spline, t, frame) - _rph(gil.spline, t, frame)
    d[:, 2] = (d[:, 2] + np.pi) % (2.0 * np.pi) - np.pi
    sigma = np.column_stack([np.interp(t, gi.sigma_time, gi.sigma_rph_rad[:, i]) for i in range(3)])
    return d.mean(axis=0), np.sqrt(np.mean(sigma**2, axis=0))


def warn_gi_tilt(gi: GnssImuResult, adj: LidarAdjustment, frame: LocalFrame, who: str = "") -> None:
    """Warn, with the figures, when the G/I's attitude differs from the G/I/L's on average by more than
    :data:`GI_TILT_SIGMAS` of the G/I's stated sigma: GNSS and IMU alone see a tilt or heading that the
    planes do not, which the G/I's model does not hold (an unmodelled IMU misalignment, a wrong GNSS lever
    arm), or the planes see through a boresight the G/I/L holds at a wrong value. Either way one of the two
    states sigmas its data contradict. ``who`` leads the message (``"flight 2: "`` where several flights are
    adjusted together, each with its own IMU and G/I)."""
    if getattr(adj.result, "sbet_errors", None) is not None or gi.imu_errors is None:
        return
    found = gi_tilt(gi, adj.result, frame)
    if found is None:
        return
    mean, sigma = found
    ratio = np.abs(mean) / np.maximum(sigma, 1e-12)
    if not np.any(ratio > GI_TILT_SIGMAS):
        return
    names = ("roll", "pitch", "heading")
    log.warning(
        "%sthe G/I attitude differs from the G/I/L's on average by %s, %s its stated sigma (%s; warning above %.0f): "
        "GNSS and IMU alone see an attitude the planes do not, and the G/I's sigmas do not hold it. An IMU whose "
        "triads are misaligned (imu.errors.gyro_misalignment_mrad, acc_misalignment_mrad with "
        "processing.trajectory.estimate_misalignment) or a wrong gnss.lever_arm_m does this; the G/I/L "
        "holds its attitude to the planes, but the same misfit can reach it. So does a scanner boresight off the "
        "stated one where the G/I/L does not estimate it (scanner.boresight_deg, processing.lidar.estimate_boresight; "
        "the scanner calibration check tests it): then the G/I/L's attitude is the one that is off",
        who, ", ".join(f"{n} {np.degrees(m) * 1e3:+.2f} mdeg" for n, m in zip(names, mean)),
        "/".join(f"{r:.1f}" for r in ratio) + " times",
        "/".join(f"{np.degrees(s) * 1e3:.2f}" for s in sigma) + " mdeg", GI_TILT_SIGMAS,
    )


BORESIGHT_SHARE = 0.5
"""Warn when an estimated boresight's sigma about a body axis is at least this share of the G/I/L's stated attitude
sigma about it (RMS over the flight): at least a quarter of the trajectory's variance there is then the boresight's,
one turn the planes cannot tell from a turn of every strip. Measured with two passes along one line: ``corridor``
(seed 42, the encoder error's case) roll / pitch / heading 0.76 / 0.76 / 1.00; ``corridor-tiny`` (seed 4, a 50 mdeg
roll error estimated) roll 0.74, heading 0.91; ``two-flights-tiny`` (seed 42, both flights' boresight one) 0.60 /
0.55 / 0.77, where the boresight's roll (1.93 mdeg) is the G/I's per pass (4.18) over the four passes' square root:
unseparated, and clear of this threshold where half the variance (0.71) would not be."""
BORESIGHT_GI_SHARE = 0.2
"""... and at least this share of the G/I's stated attitude sigma: the planes know the boresight no better than a
fifth of what GNSS and IMU know of each epoch (``corridor`` 0.59 / 0.60 / 0.45; ``corridor-tiny`` roll 0.66,
heading 0.49; ``two-flights-tiny`` 0.46 / 0.42 / 0.35). A boresight that strips at several headings and
cross strips separate sits far below it, and then a small sigma of the trajectory is no fault."""


def boresight_separation(gi, adj) -> np.ndarray | None:
    """(3, 3): per body axis (roll, pitch, heading) the boresight's sigma, the G/I/L's stated attitude sigma and the
    G/I's (RMS over their sigma epochs; rad), or None where the boresight is not estimated or there is no
    posterior. ``gi`` and ``adj`` are one flight's results or the sequences of several flights' (one boresight;
    the sigmas of all their epochs pooled)."""
    gis = tuple(gi) if isinstance(gi, (list, tuple)) else (gi,)
    adjs = tuple(adj) if isinstance(adj, (list, tuple)) else (adj,)
    body = getattr(adjs[0], "boresight_body_sigma_mdeg", None)
    if body is None or any(a.result.sigma_time.size == 0 for a in adjs) or any(g.sigma_time.size == 0 for g in gis):
        return None
    gil = np.sqrt(np.mean(np.vstack([a.result.sigma_rph_rad for a in adjs])**2, axis=0))
    gi_sigma = np.sqrt(np.mean(np.vstack([g.sigma_rph_rad for g in gis])**2, axis=0))
    return np.column_stack([np.radians(np.asarray(body, dtype=float) * 1e-3), gil, gi_sigma])


def warn_boresight_separation(gi, adj) -> None:
    """Warn, with the figures, where the flight's strips do not separate the estimated boresight from the
    trajectory's attitude (:data:`BORESIGHT_SHARE`, :data:`BORESIGHT_GI_SHARE`): two passes along one line see
    a roll of the scanner as a roll of each pass, known absolutely only as well as the G/I knows them; what the
    G/I/L states about that angle is then the boresight's sigma, and its accuracy no better. The direction is
    not observable from this flight; the stated sigmas hold it (docs/ARCHITECTURE.md §4.4). ``gi``, ``adj``: as
    :func:`boresight_separation` takes them."""
    sep = boresight_separation(gi, adj)
    if sep is None:
        return
    share, gi_share = sep[:, 0] / np.maximum(sep[:, 1], 1e-15), sep[:, 0] / np.maximum(sep[:, 2], 1e-15)
    weak = (share >= BORESIGHT_SHARE) & (gi_share >= BORESIGHT_GI_SHARE)
    if not np.any(weak):
        return
    names = ("roll", "pitch", "heading")
    mdeg = np.degrees(sep) * 1e3
    log.warning(
        "the strips do not separate the boresight from the trajectory's attitude in %s: the boresight is known to "
        "%s, %s of the G/I/L's stated sigma and %s of the G/I's (warning from %.1f and %.1f of them). The "
        "planes see a turn of the scanner as a turn of every strip (two passes along one line see a scanner roll "
        "only beside each pass's roll, which GNSS and IMU know to the G/I's sigma), so the G/I/L's attitude there is "
        "only as good as this boresight, and its stated sigmas say so. Strips at other headings and cross strips, "
        "several flights sharing the boresight, or a boresight calibrated on such a flight and held "
        "(scanner.boresight_deg, processing.lidar.estimate_boresight: false) narrow it. A scan-angle encoder's "
        "mean error and a scan-angle error common to every channel are a boresight roll",
        ", ".join(n for n, w in zip(names, weak) if w),
        ", ".join(f"{n} ± {mdeg[i, 0]:.2f} mdeg" for i, n in enumerate(names) if weak[i]),
        "/".join(f"{share[i]:.2f}" for i in range(3) if weak[i]),
        "/".join(f"{gi_share[i]:.2f} ({mdeg[i, 2]:.2f} mdeg)" for i in range(3) if weak[i]),
        BORESIGHT_SHARE, BORESIGHT_GI_SHARE,
    )


GNSS_ERROR_FIT_LIMIT = 1.5
"""Warn when the G/I/L's correlated-GNSS-error prior fits worse than this per row (``sum w r^2 / n``). The
expected value of a group's ``sum w r^2`` is its redundancy, at most its number of rows, so a mean above 1 is
misfit whatever the share of the redundancy the group holds; with 100 or more knots its spread is below 0.15.
Measured on ``corridor`` (seed 42): 0.22-0.28 clean and with each error stated, 0.27-0.46 with an IMU
misalignment, a temperature drift or a range error left unstated; 2.38 with 2/4 cm of multipath correlated over
20 s, 5.67 with a float segment taken as fixes, 13.0 with a wrong fix not searched for, 3.83 with the channel
angles left out (``corridor-tiny``: 0.14 with range and channels estimated, 3.20 with neither)."""


def warn_gnss_error_misfit(adj: LidarAdjustment, who: str = "the G/I/L") -> None:
    """Warn, with the figures, when the G/I/L's correlated GNSS error moves faster or further than its prior
    (``gnss.correlated_error``) allows: the planes see GNSS errors the model does not hold (multipath, a wrong
    fix or float solution below what the search finds, a ``.pos`` file whose sigmas are too small). The stated
    position and attitude sigmas then lean optimistic. ``who`` names the solution (a flight's, where several
    flights are adjusted together: each has its own GNSS errors and groups)."""
    solve = getattr(adj.result, "solve", None)
    groups = {g.name: g for g in getattr(solve, "groups", ())}
    group = groups.get("gnss_error_prior")
    if group is not None and group.variance_factor > GNSS_ERROR_FIT_LIMIT:
        multipath = "gnss_multipath_prior" in groups
        log.warning(
            "%s's correlated GNSS error fits its prior at %.2f per row (warning above %.1f; expected at most 1): "
            "the planes pull it faster or further than gnss.correlated_error allows, and the stated position and "
            "attitude sigmas lean optimistic. GNSS errors the model does not hold do this (%s, a wrong fix or float "
            "segment the file does not flag, sigmas in the .pos file too small; the G/I/L's estimate is in "
            "gil/adjustment.json, gnss_error), and so does a LiDAR model that does not fit (then other warnings name it)",
            who, group.variance_factor, GNSS_ERROR_FIT_LIMIT,
            "multipath beyond the stated gnss.multipath" if multipath
            else "multipath, which gnss.multipath models where it is stated",
        )
    group = groups.get("gnss_multipath_prior")
    if group is not None and group.variance_factor > GNSS_ERROR_FIT_LIMIT:
        log.warning(
            "%s's multipath fits its prior at %.2f per row (warning above %.1f; expected at most 1): the planes "
            "pull it faster or further than gnss.multipath allows (its sigmas or correlation time understate it), and "
            "the stated position and attitude sigmas lean optimistic", who, group.variance_factor, GNSS_ERROR_FIT_LIMIT,
        )
