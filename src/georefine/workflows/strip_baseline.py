"""The classical strip adjustment of a run, as a baseline beside the G/I/L (docs/ARCHITECTURE.md §4.5, §5).

The strip-adjustment tools in common use correct each strip by a rotation and translation (or a
low-order polynomial in time) estimated from correspondences between overlapping strips
(:mod:`georefine.lidar.strip_adjustment`). Run from the same planar features and objects as the
first G/I/L adjustment -- those extracted and matched under the G/I trajectory (§4.5 steps 3-4)
-- and applied to that trajectory within every strip's time span, it gives a trajectory that the
evaluation compares with the truth exactly as it compares the G/I and the G/I/L (§5): what the
trajectory-level adjustment gains over the strip-level one.

:func:`strip_baseline` takes what a run has (features, objects, the preliminary trajectory, the
strips' spans, the priors); :func:`run_strip_baseline` takes them as the run holds them (the
navigation data, the G/I result, the features and objects of the first outer iteration, the
strips), the priors from the G/I's posterior sigmas (:func:`gi_strip_priors`) and the robust loss
from ``processing.lidar.plane_loss``; :func:`write_strip_baseline` writes the corrected
trajectory as an SBET and the corrections as JSON.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.adjustment.gnss_imu import GnssImuResult
from georefine.adjustment.robust import RobustLoss, make_loss
from georefine.errors import GeorefineError, InputError
from georefine.geometry.frames import OutputCRS
from georefine.io.files import write_json
from georefine.lidar.correspondences import PlanarObjects
from georefine.lidar.planes import PlanarFeatures
from georefine.lidar.strip_adjustment import (
    StripCorrections,
    StripPriors,
    adjust_strips,
    apply_strip_corrections,
)
from georefine.trajectory.sampled import Trajectory
from georefine.workflows.cache import StepCache
from georefine.workflows.navigation import NavigationData, imu_rate_trajectory
from georefine.workflows.products import write_sbet_product
from georefine.workflows.strips import StripFile

log = logging.getLogger(__name__)

__all__ = [
    "StripBaseline",
    "stage_strip_baseline",
    "gi_strip_priors",
    "run_strip_baseline",
    "strip_baseline",
    "strip_spans",
    "write_strip_baseline",
]


@dataclass(frozen=True, eq=False)
class StripBaseline:
    """The strip adjustment of a run: the corrections, the corrected trajectory and what they came from.

    Attributes
    ----------
    corrections
        Per strip (:class:`~georefine.lidar.strip_adjustment.StripCorrections`).
    trajectory
        The preliminary trajectory with every strip's correction applied inside its span.
    priors
        The datum the corrections were estimated with.
    spans
        Strip id -> ``(t0, t1)``, s relative to the dataset epoch, where the corrections apply.
    """

    corrections: StripCorrections
    trajectory: Trajectory
    priors: StripPriors
    spans: dict[int, tuple[float, float]]

    def summary(self) -> str:
        """A few lines for logs: the correction of every strip and the fit."""
        c = self.corrections
        mdeg = np.degrees(1.0) * 1e3
        lines = [f"strip adjustment (order {c.order}): {len(c)} strips, {c.objects_used} objects, variance factor "
                 f"{c.variance_factor:.3g}"]
        for k, sid in enumerate(c.strip.tolist()):
            lines.append(f"  strip {sid}: rotation {np.array2string(c.omega_rad[k] * mdeg, precision=2)} mdeg "
                         f"(± {np.array2string(c.sigma_omega_rad[k] * mdeg, precision=2)}), translation "
                         f"{np.array2string(c.translation_m[k] * 1e3, precision=1)} mm "
                         f"(± {np.array2string(c.sigma_translation_m[k] * 1e3, precision=1)}), "
                         f"{int(c.n_features[k])} features")
        if c.misfit is not None:
            lines.append(f"  {c.misfit}")
        return "\n".join(lines)


def strip_spans(strips: Sequence[StripFile]) -> dict[int, tuple[float, float]]:
    """Strip id -> time span ``(t_first, t_last)`` (s from the epoch, navigation time at the
    strips' time offset)."""
    return {int(s.strip_id): (float(s.t_first), float(s.t_last)) for s in strips}


def gi_strip_priors(gi: GnssImuResult, spans: Mapping[int, tuple[float, float]], order: int = 0,
                    trajectory: Trajectory | None = None) -> StripPriors:
    """The priors of the strip corrections from the G/I's posterior sigmas over the strips' spans.

    Rotation: about east and north the RMS of the roll and pitch sigmas (on a strip either one
    is about a horizontal axis, which way depending on the heading), about up the heading sigma;
    translation: the position sigma per axis of ``w``; RMS over the posterior's times inside the
    spans. For ``order`` 1 the drift sigmas are these over half the mean strip duration: the
    drift may reach one sigma at either end of a strip.

    With ``trajectory`` each rotation sigma is also at most the position sigma over the RMS lever
    of the strip's trajectory positions about that axis (the shortest strip's): a strip turned
    rigidly about its centre moves its trajectory's ends, which the GNSS holds to its position
    sigma, while the G/I's heading sigma describes a turn of the body about its own position (on
    ``corridor-tiny`` the G/I states 33 mdeg of heading; a strip turned by that about its centre
    moves its ends by 17 cm; the bound is 4.4 mdeg there).

    Raises
    ------
    InputError
        No posterior sigma in ``gi``, or none of its times inside the spans.
    """
    t = np.asarray(gi.sigma_time, dtype=float)
    if t.size == 0:
        raise InputError("the G/I result has no posterior sigma to take the strip priors from",
                         field="sigma_time", expected="a G/I with its posterior", found="none")
    inside = np.zeros(t.size, bool)
    for t0, t1 in spans.values():
        inside |= (t >= t0) & (t <= t1)
    if not inside.any():
        raise InputError("no posterior sigma of the G/I inside the strips' time spans", field="spans",
                         expected=f"spans within [{t[0]:.1f}, {t[-1]:.1f}] s", found=str(dict(spans)))
    rph = np.asarray(gi.sigma_rph_rad, dtype=float)[inside]
    pos = np.asarray(gi.sigma_position_m, dtype=float)[inside]
    horizontal = float(np.sqrt(np.mean(0.5 * (rph[:, 0] ** 2 + rph[:, 1] ** 2))))
    rotation = np.array([horizontal, horizontal, float(np.sqrt(np.mean(rph[:, 2] ** 2)))])
    translation = np.sqrt(np.mean(pos**2, axis=0))
    if trajectory is not None:
        lever = _levers(trajectory, spans)
        bound = float(np.sqrt(np.mean(translation**2))) / np.where(lever > 0, lever, 1.0)
        rotation = np.where(lever > 0, np.minimum(rotation, bound), rotation)
    if order == 0:
        return StripPriors(rotation, translation)
    half = 0.5 * float(np.mean([t1 - t0 for t0, t1 in spans.values()]))
    if not half > 0:
        raise InputError("the strips' time spans are empty", field="spans", expected="t1 > t0", found=str(dict(spans)))
    return StripPriors(rotation, translation, rotation / half, translation / half)


def _levers(trajectory: Trajectory, spans: Mapping[int, tuple[float, float]]) -> np.ndarray:
    """(3,) RMS lever (m) of the trajectory positions about the east, north and up axes through
    their mean, the smallest over the strips (the loosest bound): ``sqrt(mean |e_k x (p - mean)|^2)``;
    0 where no strip has positions off the axis (no bound)."""
    out = np.full(3, np.inf)
    for t0, t1 in spans.values():
        p = trajectory.p_w_b[(trajectory.time >= t0) & (trajectory.time <= t1)]
        if p.shape[0] < 2:
            continue
        d2 = np.mean((p - p.mean(axis=0)) ** 2, axis=0)
        out = np.minimum(out, np.sqrt([d2[1] + d2[2], d2[0] + d2[2], d2[0] + d2[1]]))
    return np.where(np.isfinite(out), out, 0.0)


def strip_baseline(
    features: PlanarFeatures,
    objects: PlanarObjects,
    trajectory: Trajectory,
    spans: Mapping[int, tuple[float, float]],
    priors: StripPriors | None,
    *,
    order: int = 0,
    loss: RobustLoss | None = None,
    min_strips_per_object: int = 2,
) -> StripBaseline:
    """The strip corrections from ``features`` and ``objects``, applied to ``trajectory``.

    Parameters
    ----------
    features, objects
        Planar features georeferenced with ``trajectory`` and their matching into objects.
    trajectory
        The preliminary trajectory (e.g. the G/I at the IMU samples, ``imu_rate_trajectory``).
    spans
        Strip id -> ``(t0, t1)`` (s from the epoch) where each strip's correction applies.
    priors
        The datum (:func:`gi_strip_priors`); required.
    order, loss, min_strips_per_object
        As :func:`~georefine.lidar.strip_adjustment.adjust_strips`.

    Raises
    ------
    InputError
        No priors, or what :func:`~georefine.lidar.strip_adjustment.adjust_strips` and
        :func:`~georefine.lidar.strip_adjustment.apply_strip_corrections` refuse.
    """
    corrections = adjust_strips(features, objects, priors, order=order, loss=loss,
                                min_strips_per_object=min_strips_per_object)
    spans = {int(k): (float(a), float(b)) for k, (a, b) in spans.items()}
    corrected = apply_strip_corrections(trajectory, corrections, spans)
    baseline = StripBaseline(corrections, corrected, priors, spans)
    log.info("%s", baseline.summary())
    return baseline


def run_strip_baseline(
    nav: NavigationData,
    gi: GnssImuResult,
    features: PlanarFeatures,
    objects: PlanarObjects,
    strips: Sequence[StripFile],
    *,
    order: int = 0,
    priors: StripPriors | None = None,
) -> StripBaseline:
    """:func:`strip_baseline` as a run holds its inputs.

    ``features`` and ``objects`` must be those extracted under the G/I trajectory (the first
    outer iteration's, ``features_and_objects(nav, gi, ...)`` of :mod:`georefine.workflows.lidar`),
    ``strips`` at the time offset they were extracted at. The trajectory is the G/I at the IMU
    samples, the priors those of :func:`gi_strip_priors` (bounded by the trajectory's levers) unless given, the robust loss the plane
    observations' (``processing.lidar.plane_loss``, ``plane_loss_scale``).
    """
    spans = strip_spans(strips)
    lcfg = nav.config.processing.lidar
    trajectory = imu_rate_trajectory(nav, gi)
    return strip_baseline(features, objects, trajectory, spans,
                          gi_strip_priors(gi, spans, order, trajectory) if priors is None else priors, order=order,
                          loss=make_loss(lcfg.plane_loss, lcfg.plane_loss_scale))


def write_strip_baseline(out: Path, nav: NavigationData, baseline: StripBaseline, crs: OutputCRS) -> None:
    """``out/trajectory.sbet`` (with its companion ``trajectory.sbet.json``: the corrected trajectory
    at its samples; body rates and specific force left zero, the evaluation reads poses only) and
    ``out/strip_corrections.json`` (:meth:`StripCorrections.to_dict`, with the spans and priors)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    traj = baseline.trajectory
    if traj.v_w_b is None:
        raise InputError("the corrected trajectory has no velocity for the SBET", field="v_w_b")
    write_sbet_product(out / "trajectory.sbet", nav.frame, nav.t0_gps, traj.time, traj.p_w_b, traj.v_w_b,
                       traj.R_w_b, output_epsg=crs.epsg)
    p = baseline.priors
    priors = {"rotation_mdeg": _mdeg(p.rotation_rad), "translation_m": _listed(p.translation_m),
              "rotation_rate_mdeg_per_s": _mdeg(p.rotation_rate_rad_per_s),
              "translation_rate_m_per_s": _listed(p.translation_rate_m_per_s)}
    spans = {str(k): [a + nav.t0_gps, b + nav.t0_gps] for k, (a, b) in baseline.spans.items()}
    write_json(out / "strip_corrections.json",
               {**baseline.corrections.to_dict(), "t0_gps": nav.t0_gps, "spans_gps": spans, "priors": priors})


def _listed(v) -> list[float] | None:
    return None if v is None else [float(x) for x in np.asarray(v)]


def _mdeg(v) -> list[float] | None:
    return None if v is None else [float(x) for x in np.degrees(np.asarray(v)) * 1e3]


def stage_strip_baseline(steps, nav: NavigationData, gi: GnssImuResult, strips: Sequence[StripFile], key: str,
                         planes: tuple[PlanarFeatures | None, PlanarObjects | None], offset_s: float, out: Path,
                         crs: OutputCRS, recompute, progress=None) -> StripBaseline | None:
    """The run's baseline stage (:func:`georefine.workflows.lidar.run_workflow`, after its first outer
    iteration): :func:`run_strip_baseline` from that iteration's ``planes`` (features and objects,
    extracted and matched under the G/I trajectory at the time offset ``offset_s``), cached by the
    step runner ``steps`` under the iteration's ``key``, written to ``out`` (:func:`write_strip_baseline`).

    ``recompute(strips)`` gives the features and objects again when the iteration came from the
    cache. A project of one strip has no baseline; an adjustment that cannot be made (no object
    seen by two strips) is logged and left out, not the run.
    """
    if len(strips) < 2:
        return None
    shifted = [s.shifted(offset_s) for s in strips]
    report = progress or (lambda *a: None)

    def compute() -> StripBaseline:
        features, objects = planes
        if features is None:  # the iteration came from the cache: its planes again (deterministic)
            features, objects = recompute(shifted)
        return run_strip_baseline(nav, gi, features, objects, shifted, order=0)

    report("strip adjustment (baseline)", 0, 1)
    try:
        baseline = steps.cached("strip_baseline", StepCache.key("strip_baseline", key), compute,
                                timing="strip_baseline")
    except GeorefineError as exc:
        log.warning("no strip-adjustment baseline: %s", exc)
        return None
    finally:
        report("strip adjustment (baseline)", 1, 1)
    write_strip_baseline(out, nav, baseline, crs)
    return baseline
