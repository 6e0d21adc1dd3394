"""``metrics.json`` of a ``georefine run`` and every ``adjustment.json``: the typed records and their JSON form.

``metrics.json`` (docs/ARCHITECTURE.md §4.5) is :class:`WorkflowMetrics`; ``adjustment.json``
(its schema in the products table of §4.5) is :class:`AdjustmentReport`, one schema for whichever
adjustment wrote it: ``georefine trajectory`` (the filter alone or the G/I adjustment), ``run``'s
``gi/`` and ``gil/`` (raw GNSS/IMU or a delivered trajectory) and ``hybrid/``.

The run (:mod:`georefine.workflows.lidar`) writes ``metrics.json``; the evaluation
(:mod:`georefine.workflows.evaluate`) reads the strips and their time spans from it and the
report (:mod:`georefine.evaluation.report`) its outer iterations, timings and resumed steps.
The report sits in ``evaluation``, a layer below ``workflows`` (docs/ARCHITECTURE.md §1), so
the record cannot live beside the workflow that fills it: it lives here, with the other file
formats, where the writer and every reader can import it. It is plain data (no numpy, no
estimation), as a file format should be.

:meth:`WorkflowMetrics.to_dict` gives exactly the JSON the run writes (keys, order, values);
:meth:`WorkflowMetrics.from_dict` reads it back, so ``from_dict(d).to_dict() == d``.
:func:`write_adjustment_report` and :func:`read_adjustment_report` write and read
``adjustment.json``; the reader checks every field it types and raises
:class:`~georefine.errors.InputError` naming the file, the field and what was expected.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from georefine.errors import InputError
from georefine.io.files import write_json

__all__ = ["AdjustmentReport", "FilterSummary", "FrameOrigin", "LidarTimeOffset", "OuterIteration", "PassPrecision",
           "PointsWritten", "SOLUTIONS", "WorkflowMetrics", "read_adjustment_report", "write_adjustment_report"]


@dataclass(frozen=True)
class OuterIteration:
    """One outer iteration (steps 3-5 of paper 000) of the G/I/L adjustment.

    Attributes
    ----------
    iteration
        1-based number of the outer iteration.
    features, objects
        Planar features extracted in all views and planar objects matched from them.
    features_used, objects_used
        Features and objects that entered the adjustment (matched, inside the trajectory span,
        within ``processing.lidar.max_features`` and ``max_features_per_minute``).
    attitude_change_mdeg, position_change_m
        RMS change of the trajectory at the knots against the iteration's start (the
        convergence criterion).
    points_outside_trajectory
        Points of all strips outside the trajectory's span (left out of the features).
    views
        Features extracted per view, ``strip{id}_{channel name}``, in the order extracted.
    knot_interval_s
        Knot interval of the iteration's trajectory (coarser in a first iteration with
        ``processing.lidar.first_knot_interval_s``); None in files written before it was recorded.
    time_offset_start_s, time_offset_prior_s, time_offset_s
        LiDAR time offset (s, added to the strips' time stamps) that the iteration's features
        used, the centre of its prior (``scanner.time_offset_s`` or the search's result) and the
        iteration's estimate (the start value when not estimated); None in older files.
    time_offset_search
        The first iteration's search for the offset (:class:`~georefine.lidar.time_offset.TimeOffsetSearch`
        as a dict), None when not searched.
    """

    iteration: int
    features: int
    objects: int
    features_used: int
    objects_used: int
    attitude_change_mdeg: float
    position_change_m: float
    points_outside_trajectory: int
    views: dict[str, int] = field(default_factory=dict)
    knot_interval_s: float | None = None
    time_offset_start_s: float | None = None
    time_offset_prior_s: float | None = None
    time_offset_s: float | None = None
    time_offset_search: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "iteration": self.iteration, "features": self.features, "objects": self.objects,
            "features_used": self.features_used, "objects_used": self.objects_used,
            "attitude_change_mdeg": self.attitude_change_mdeg, "position_change_m": self.position_change_m,
            "points_outside_trajectory": self.points_outside_trajectory, "views": dict(self.views),
            "knot_interval_s": self.knot_interval_s, "time_offset_start_s": self.time_offset_start_s,
            "time_offset_prior_s": self.time_offset_prior_s, "time_offset_s": self.time_offset_s,
            "time_offset_search": self.time_offset_search,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> OuterIteration:
        return cls(
            int(d["iteration"]), int(d["features"]), int(d["objects"]), int(d["features_used"]),
            int(d["objects_used"]), float(d["attitude_change_mdeg"]), float(d["position_change_m"]),
            int(d["points_outside_trajectory"]), {str(k): int(v) for k, v in d["views"].items()},
            None if d.get("knot_interval_s") is None else float(d["knot_interval_s"]),
            *(None if d.get(k) is None else float(d[k])
              for k in ("time_offset_start_s", "time_offset_prior_s", "time_offset_s")),
            d.get("time_offset_search"),
        )


@dataclass(frozen=True)
class PointsWritten:
    """One strip of the final point cloud (step 6): ``points/<file>``."""

    strip: int
    file: str
    points: int
    outside_trajectory: int

    def to_dict(self) -> dict[str, Any]:
        return {"strip": self.strip, "file": self.file, "points": self.points,
                "outside_trajectory": self.outside_trajectory}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PointsWritten:
        return cls(int(d["strip"]), str(d["file"]), int(d["points"]), int(d["outside_trajectory"]))


@dataclass(frozen=True)
class PassPrecision:
    """The posterior attitude sigma during one strip, G/I and G/I/L: what the planes added.

    ``gi_sigma_mdeg`` and ``gil_sigma_mdeg`` are the RMS of the roll, pitch and yaw sigma over the
    strip's time span (:func:`georefine.workflows.precision.pass_precision`).
    """

    strip: int
    gi_sigma_mdeg: tuple[float, float, float]
    gil_sigma_mdeg: tuple[float, float, float]

    def to_dict(self) -> dict[str, Any]:
        return {"strip": self.strip, "gi_sigma_mdeg": list(self.gi_sigma_mdeg),
                "gil_sigma_mdeg": list(self.gil_sigma_mdeg)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PassPrecision:
        def sigmas(key: str) -> tuple[float, float, float]:  # NaN (no posterior) is null in JSON
            return tuple(float("nan") if v is None else float(v) for v in d[key])  # type: ignore[return-value]

        return cls(int(d["strip"]), sigmas("gi_sigma_mdeg"), sigmas("gil_sigma_mdeg"))


@dataclass(frozen=True)
class WorkflowMetrics:
    """What ``georefine run`` records in ``metrics.json``.

    Attributes
    ----------
    t0_gps
        Dataset epoch (GPS s): in-memory times are relative to it.
    strips
        Strip ids (``point_source_id``) the run used, in the order of the project's files.
    strip_time_gps
        First and last point time (GPS s) per strip id.
    outer_iterations
        The outer iterations of the G/I/L adjustment (empty without LiDAR).
    points
        The strips written in the output CRS (empty without the final point clouds).
    resumed
        Steps loaded from the step cache instead of computed, in the order loaded.
    timings_s
        Wall time (s) per step, in the order run; a step's time excludes the steps timed
        inside it (the filter is not part of ``gi_adjustment``).
    pass_precision
        Per strip, the posterior attitude sigma of G/I and G/I/L (empty without LiDAR).
    """

    t0_gps: float
    strips: tuple[int, ...]
    strip_time_gps: dict[int, tuple[float, float]]
    outer_iterations: tuple[OuterIteration, ...] = ()
    points: tuple[PointsWritten, ...] = ()
    resumed: tuple[str, ...] = ()
    timings_s: dict[str, float] = field(default_factory=dict)
    pass_precision: tuple[PassPrecision, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of ``metrics.json`` (strip ids as string keys, as JSON requires)."""
        return {
            "t0_gps": self.t0_gps,
            "strips": list(self.strips),
            "strip_time_gps": {str(k): [t0, t1] for k, (t0, t1) in self.strip_time_gps.items()},
            "outer_iterations": [it.to_dict() for it in self.outer_iterations],
            "points": [p.to_dict() for p in self.points],
            "resumed": list(self.resumed),
            "timings_s": dict(self.timings_s),
            "pass_precision": [p.to_dict() for p in self.pass_precision],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> WorkflowMetrics:
        return cls(
            t0_gps=float(d["t0_gps"]),
            strips=tuple(int(s) for s in d["strips"]),
            strip_time_gps={int(k): (float(v[0]), float(v[1])) for k, v in d["strip_time_gps"].items()},
            outer_iterations=tuple(OuterIteration.from_dict(it) for it in d.get("outer_iterations", [])),
            points=tuple(PointsWritten.from_dict(p) for p in d.get("points", [])),
            resumed=tuple(str(s) for s in d.get("resumed", [])),
            timings_s={str(k): float(v) for k, v in d.get("timings_s", {}).items()},
            pass_precision=tuple(PassPrecision.from_dict(p) for p in d.get("pass_precision", [])),
        )

    @classmethod
    def read(cls, path: str | Path) -> WorkflowMetrics:
        """Read ``metrics.json`` (a file path) written by a run."""
        return cls.from_dict(json.loads(Path(path).read_text(encoding="utf-8")))


# ---------------------------------------------------------------------------- adjustment.json
SOLUTIONS = ("filter", "G/I", "G/I/L", "hybrid")
"""What an ``adjustment.json`` reports (:attr:`AdjustmentReport.solution`): ``georefine trajectory
--filter-only``'s filter, the G/I adjustment (or, on a delivered trajectory, that trajectory
adjusted alone), the G/I/L adjustment, the hybrid adjustment."""


@dataclass(frozen=True)
class LidarTimeOffset:
    """The LiDAR time offset (s, added to the strips' time stamps) of an adjustment with LiDAR.

    Attributes
    ----------
    configured_s
        ``scanner.time_offset_s`` of the configuration.
    estimate_s
        The offset the adjustment ends with: its estimate, or the one its features used when it
        does not estimate one.
    sigma_ms
        Posterior 1-sigma of the estimate (ms); None where not estimated or without a posterior.
    gnss_sigma_ms
        The sigma that GNSS errors lasting a pass add (ms), which the adjustment's does not hold
        (:func:`~georefine.workflows.time_offset.gnss_offset_sigma`); None where not estimated or
        unknown.
    prior_s
        Centre of the estimate's prior (the configured offset or the search's result); None
        where there is no prior.
    held
        Why an offset that the configuration estimates was held where it started, or None.
    """

    configured_s: float
    estimate_s: float
    sigma_ms: float | None = None
    gnss_sigma_ms: float | None = None
    prior_s: float | None = None
    held: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"configured_s": self.configured_s, "estimate_s": self.estimate_s, "sigma_ms": self.sigma_ms,
                "gnss_sigma_ms": self.gnss_sigma_ms, "prior_s": self.prior_s, "held": self.held}


@dataclass(frozen=True)
class FrameOrigin:
    """The origin of the local east-north-up frame ``w`` the report's times and vectors refer to."""

    lat_deg: float
    lon_deg: float
    h_m: float

    @classmethod
    def of(cls, frame: Any) -> FrameOrigin:
        """Of a :class:`~georefine.geometry.frames.LocalFrame` (``lat0_rad``, ``lon0_rad``, ``h0_m``)."""
        return cls(math.degrees(frame.lat0_rad), math.degrees(frame.lon0_rad), float(frame.h0_m))

    def to_dict(self) -> dict[str, Any]:
        return {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "h_m": self.h_m}


@dataclass(frozen=True)
class FilterSummary:
    """The initialisation filter of ``georefine trajectory``: GNSS updates applied and rejected,
    and when the alignment ended (s from ``t0_gps``; None when the filter does not say)."""

    gnss_updates: int
    gnss_rejected: int
    alignment_time_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"gnss_updates": self.gnss_updates, "gnss_rejected": self.gnss_rejected,
                "alignment_time_s": self.alignment_time_s}


@dataclass(frozen=True)
class AdjustmentReport:
    """What an adjustment records in ``adjustment.json``: one schema for every writer, the
    sections a writer does not have None (``null`` in the file).

    Attributes
    ----------
    solution
        One of :data:`SOLUTIONS`.
    t0_gps
        Dataset epoch (GPS s): the sections' times are seconds from it.
    timings_s
        Wall time (s) per part of the adjustment (the trajectory command: per step, the
        adjustment's parts as ``adjustment_<part>``).
    adjustment
        The solve's statistics,
        :meth:`SolveResult.to_dict() <georefine.adjustment.statistics.SolveResult.to_dict>`
        (termination, iterations, cost, redundancy, variance factor, per observation group,
        timings, variance components); :meth:`SolveResult.from_dict
        <georefine.adjustment.statistics.SolveResult.from_dict>` makes it the typed value again
        (this layer is below the estimation, which owns that type). None for the filter alone.
    imu_errors
        The estimated IMU errors with their sigma,
        :meth:`~georefine.adjustment.gnss_imu.ImuErrorEstimate.to_dict`; None without raw IMU data.
    sbet_errors
        On a delivered trajectory, its estimated error per knot with sigma
        (:meth:`~georefine.adjustment.trajectory_prior.SbetErrorEstimate.to_dict`); else None.
    gnss_error
        The estimated correlated GNSS error (``gnss.correlated_error``) and the offsets of the segments
        without a fixed solution (``gnss.float_offset``),
        :meth:`~georefine.adjustment.gnss_imu.GnssErrorEstimate.to_dict`; else None.
    boresight_deg, boresight_sigma_mdeg
        The estimated boresight roll/pitch/yaw (deg) and its posterior 1-sigma (mdeg; NaN, null
        in the file, where unknown); None where the boresight was not estimated. The hybrid
        adjustment takes the sigma from the posterior it computes for the trajectory.
    lidar_time_offset
        :class:`LidarTimeOffset` of an adjustment with LiDAR (G/I/L, hybrid); None otherwise.
    range_calibration
        The scanner's estimated range offset and scale error (``offset_m``, ``offset_sigma_m``,
        ``scale_ppm``, ``scale_sigma_ppm``; ``processing.lidar.estimate_range_calibration``); else None.
    channel_angles
        Each scanner channel's estimated facet-tilt and scan-angle error (lists by channel:
        ``tilt_mdeg``, ``tilt_sigma_mdeg``, ``scan_angle_mdeg``, ``scan_angle_sigma_mdeg``;
        ``processing.lidar.estimate_channel_angles``); else None.
    encoder_error
        The scan-angle encoder's estimated error (``terms_mdeg``, ``terms_sigma_mdeg``: the coefficients of the
        Legendre terms ``P_1 .. P_4`` of ``alpha / half_width_deg``; ``half_width_deg``;
        ``processing.lidar.estimate_encoder_error``); else None.
    project
        The project folder (absolute).
    frame
        :class:`FrameOrigin` of the local frame ``w`` (the GNSS error's east/north/up).
    filter
        :class:`FilterSummary` of ``georefine trajectory``; None where the adjustment started
        from a cached filter.
    """

    solution: str
    t0_gps: float
    timings_s: dict[str, float] = field(default_factory=dict)
    adjustment: dict[str, Any] | None = None
    imu_errors: dict[str, Any] | None = None
    sbet_errors: dict[str, Any] | None = None
    gnss_error: dict[str, Any] | None = None
    boresight_deg: tuple[float, float, float] | None = None
    boresight_sigma_mdeg: tuple[float, float, float] | None = None
    lidar_time_offset: LidarTimeOffset | None = None
    project: str | None = None
    frame: FrameOrigin | None = None
    filter: FilterSummary | None = None
    range_calibration: dict[str, Any] | None = None
    channel_angles: dict[str, Any] | None = None
    encoder_error: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.solution not in SOLUTIONS:
            raise ValueError(f"solution must be one of {SOLUTIONS}, got {self.solution!r}")

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of ``adjustment.json``: every key, null where a section is absent."""
        def triple(v: tuple[float, float, float] | None) -> list[float] | None:
            return None if v is None else [float(x) for x in v]

        return {
            "solution": self.solution, "project": self.project,
            "frame": None if self.frame is None else self.frame.to_dict(),
            "t0_gps": self.t0_gps, "timings_s": dict(self.timings_s),
            "filter": None if self.filter is None else self.filter.to_dict(),
            "adjustment": self.adjustment, "imu_errors": self.imu_errors, "sbet_errors": self.sbet_errors,
            "gnss_error": self.gnss_error, "boresight_deg": triple(self.boresight_deg),
            "boresight_sigma_mdeg": triple(self.boresight_sigma_mdeg),
            "lidar_time_offset": None if self.lidar_time_offset is None else self.lidar_time_offset.to_dict(),
            "range_calibration": self.range_calibration, "channel_angles": self.channel_angles,
            "encoder_error": self.encoder_error,
        }

    @classmethod
    def from_dict(cls, d: Any, path: str | Path | None = None) -> AdjustmentReport:
        """The report of the JSON object ``d``; :class:`InputError` naming ``path``, the field and
        what was expected where a field is missing or of another type. A section missing from
        the object reads as None."""
        top = _JsonObject(d, path)
        offset = top.section("lidar_time_offset")
        frame = top.section("frame")
        filt = top.section("filter")
        solve = top.section("adjustment")
        return cls(
            solution=top.choice("solution", SOLUTIONS),
            t0_gps=top.number("t0_gps"),
            timings_s=top.numbers("timings_s"),
            adjustment=None if solve is None else _solve_statistics(solve),
            imu_errors=top.mapping("imu_errors"),
            sbet_errors=top.mapping("sbet_errors"),
            gnss_error=top.mapping("gnss_error"),
            boresight_deg=top.triple("boresight_deg"),
            boresight_sigma_mdeg=top.triple("boresight_sigma_mdeg"),
            lidar_time_offset=None if offset is None else LidarTimeOffset(
                offset.number("configured_s"), offset.number("estimate_s"), offset.number("sigma_ms", True),
                offset.number("gnss_sigma_ms", True), offset.number("prior_s", True), offset.string("held", True)),
            project=top.string("project", True),
            frame=None if frame is None else FrameOrigin(frame.number("lat_deg"), frame.number("lon_deg"),
                                                          frame.number("h_m")),
            filter=None if filt is None else FilterSummary(filt.integer("gnss_updates"), filt.integer("gnss_rejected"),
                                                            filt.number("alignment_time_s", True)),
            range_calibration=top.mapping("range_calibration"),
            channel_angles=top.mapping("channel_angles"),
            encoder_error=top.mapping("encoder_error"),
        )


def write_adjustment_report(path: str | Path, report: AdjustmentReport) -> None:
    """``adjustment.json`` at ``path`` (atomically; NaN as null)."""
    write_json(Path(path), report.to_dict())


def read_adjustment_report(path: str | Path) -> AdjustmentReport:
    """The :class:`AdjustmentReport` of the ``adjustment.json`` at ``path``.

    Raises
    ------
    InputError
        Not JSON, or a field missing or of another type than the schema's (named, with what was
        expected).
    """
    path = Path(path)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError("not a JSON file", path=path, line=exc.lineno, expected="an adjustment report (JSON object)",
                         found=exc.msg) from None
    return AdjustmentReport.from_dict(d, path)


_SOLVE_INTEGERS = ("iterations", "successful_iterations", "n_unknowns", "n_observations", "n_residuals", "redundancy")
_SOLVE_NUMBERS = ("initial_cost", "final_cost", "final_lambda", "variance_factor", "sigma0")  # null: not finite
_GROUP_INTEGERS = ("n_observations", "n_residuals", "n_downweighted")
_GROUP_NUMBERS = ("rms", "cost", "cost_share", "variance_factor")
_COMPONENT_NUMBERS = ("redundancy", "redundancy_sd", "sum_wr2", "factor", "scale")


def _solve_statistics(o: _JsonObject) -> dict[str, Any]:
    """The ``adjustment`` section checked against ``SolveResult.to_dict``'s form, as read."""
    o.string("termination")
    o.string("backend")
    o.boolean("converged")
    for k in _SOLVE_INTEGERS:
        o.integer(k)
    for k in _SOLVE_NUMBERS:
        o.number(k, True)
    o.section("timings", required=True)
    o.array("cost_history")
    for k, g in enumerate(o.array("groups")):
        group = o.item("groups", k, g)
        group.string("name")
        group.string("robust_loss", True)
        for name in _GROUP_INTEGERS:
            group.integer(name)
        for name in _GROUP_NUMBERS:
            group.number(name, True)
    for k, c in enumerate(o.array("variance_components", True) or ()):
        component = o.item("variance_components", k, c)
        component.array("groups")
        component.integer("n_residuals")
        for name in _COMPONENT_NUMBERS:
            component.number(name, True)
    return dict(o.d)


def _json_type(v: Any) -> str:
    """The JSON type of a decoded value, for an error message."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, (int, float)):
        return f"the number {v}"
    if isinstance(v, str):
        return f"the string {v[:40]!r}"
    return "an array" if isinstance(v, list) else "an object"


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


class _JsonObject:
    """One object of ``adjustment.json`` (``name``: its dotted place in the file), whose fields
    are read with their type checked; a field that is missing or of another type raises
    :class:`InputError` naming the file, the field and what was expected. ``optional`` fields
    read as None when missing or null."""

    def __init__(self, d: Any, path: str | Path | None, name: str = "") -> None:
        if not isinstance(d, dict):
            raise InputError("not a JSON object", path=path, field=name or None, expected="an object",
                             found=_json_type(d))
        self.d, self.path, self.name = d, path, name

    def _get(self, key: str, ok, expected: str, optional: bool) -> Any:
        field_name = f"{self.name}.{key}" if self.name else key
        v = self.d.get(key)
        if v is None:
            if optional:
                return None
            raise InputError("missing field" if key not in self.d else "null where a value is required",
                             path=self.path, field=field_name, expected=expected)
        if not ok(v):
            raise InputError("wrong type", path=self.path, field=field_name, expected=expected, found=_json_type(v))
        return v

    def number(self, key: str, optional: bool = False) -> Any:
        return self._get(key, _is_number, "a number" + (" or null" if optional else ""), optional)

    def integer(self, key: str) -> int:
        return self._get(key, lambda v: isinstance(v, int) and not isinstance(v, bool), "an integer", False)

    def boolean(self, key: str) -> bool:
        return self._get(key, lambda v: isinstance(v, bool), "true or false", False)

    def string(self, key: str, optional: bool = False) -> Any:
        return self._get(key, lambda v: isinstance(v, str), "a string" + (" or null" if optional else ""), optional)

    def choice(self, key: str, choices: tuple[str, ...]) -> str:
        return self._get(key, lambda v: v in choices, "one of " + ", ".join(choices), False)

    def array(self, key: str, optional: bool = False) -> Any:
        return self._get(key, lambda v: isinstance(v, list), "an array" + (" or null" if optional else ""), optional)

    def mapping(self, key: str) -> dict[str, Any] | None:
        """An object field (optional) as the dict read."""
        return self._get(key, lambda v: isinstance(v, dict), "an object or null", True)

    def section(self, key: str, required: bool = False) -> _JsonObject | None:
        """An object field as a :class:`_JsonObject` (None when optional and absent)."""
        v = self._get(key, lambda v: isinstance(v, dict), "an object" + ("" if required else " or null"), not required)
        return None if v is None else _JsonObject(v, self.path, f"{self.name}.{key}" if self.name else key)

    def item(self, key: str, k: int, v: Any) -> _JsonObject:
        """Entry ``k`` (``v``) of the array field ``key`` as an object."""
        return _JsonObject(v, self.path, f"{self.name}.{key}[{k}]" if self.name else f"{key}[{k}]")

    def numbers(self, key: str) -> dict[str, float]:
        """An object of numbers (required)."""
        v = self._get(key, lambda v: isinstance(v, dict) and all(_is_number(x) for x in v.values()),
                      "an object of numbers", False)
        return {str(k): x for k, x in v.items()}

    def triple(self, key: str) -> tuple[float, float, float] | None:
        """Three numbers (null read as NaN), or None when the field is absent or null."""
        v = self._get(key, lambda v: isinstance(v, list) and len(v) == 3 and all(x is None or _is_number(x) for x in v),
                      "three numbers or null", True)
        if v is None:
            return None
        return tuple(math.nan if x is None else float(x) for x in v)  # type: ignore[return-value]
