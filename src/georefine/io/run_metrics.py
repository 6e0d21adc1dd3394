"""``metrics.json`` of a ``georefine run``: the typed record and its JSON form (docs/ARCHITECTURE.md §4.5).

The run (:mod:`georefine.workflows.lidar`) writes this file; the evaluation
(:mod:`georefine.workflows.evaluate`) reads the strips and their time spans from it and the
report (:mod:`georefine.evaluation.report`) its outer iterations, timings and resumed steps.
The report sits in ``evaluation``, a layer below ``workflows`` (docs/ARCHITECTURE.md §1), so
the record cannot live beside the workflow that fills it: it lives here, with the other file
formats, where the writer and every reader can import it. It is plain data (no numpy, no
estimation), as a file format should be.

:meth:`WorkflowMetrics.to_dict` gives exactly the JSON the run writes (keys, order, values);
:meth:`WorkflowMetrics.from_dict` reads it back, so ``from_dict(d).to_dict() == d``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["OuterIteration", "PassPrecision", "PointsWritten", "WorkflowMetrics"]


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
        at most ``processing.lidar.max_features``).
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
