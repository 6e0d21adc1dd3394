"""The figures of a run's evaluation, typed: ``RUN/evaluation/summary.json`` (docs/ARCHITECTURE.md §5).

:func:`georefine.workflows.evaluate.evaluate_run` computes them, :mod:`georefine.evaluation.report`
and the command line show them. The report is built from files and sits in ``evaluation``, a
layer below ``workflows`` (docs/ARCHITECTURE.md §1); the types live here, beside the metrics
they summarise (trajectory differences, reference planes, strip differences, strip pairs), so that the
workflow that fills them and the report that reads them both import them downward.

Each type's ``to_dict`` gives exactly the JSON written today (keys, order, values) and
``from_dict`` reads it back: ``from_dict(d).to_dict() == d`` for a ``d`` read from the file.
Figures that are undefined (an empty raster, a surface seen once) are NaN when computed and
``None`` when read back (the files store NaN as ``null``); both are shown as "–".
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from georefine.adjustment.accuracy_standards import PositionalAccuracy
from georefine.evaluation.calibration import BoresightFigures, ImuErrorFigures
from georefine.evaluation.coverage import CoverageMap
from georefine.evaluation.reference_planes import ReferencePlaneSummary
from georefine.evaluation.strip_differences import StripDifferenceMap
from georefine.evaluation.strip_pairs import StripPairDifferences

__all__ = [
    "ANGLES",
    "TrajectoryFigures",
    "SolutionFigures",
    "SurfaceFigures",
    "ReferencePlaneFigures",
    "CoverageFigures",
    "StripDifferenceFigures",
    "StripPairFigures",
    "CloudEvaluation",
    "EvaluationPlots",
    "RunEvaluation",
]

ANGLES = ("roll", "pitch", "yaw")


def _num(x: Any) -> float | None:
    """A figure read from JSON: ``null`` (NaN when written) stays ``None``."""
    return None if x is None else float(x)


@dataclass(frozen=True)
class TrajectoryFigures:
    """RMSE of a trajectory against the reference (paper 000, Fig. 9), over one time span."""

    roll_rmse_mdeg: float | None
    pitch_rmse_mdeg: float | None
    yaw_rmse_mdeg: float | None
    position_3d_rmse_m: float | None

    def rmse_mdeg(self, angle: str) -> float | None:
        """RMSE of ``angle`` (``roll``, ``pitch`` or ``yaw``) in mdeg."""
        if angle not in ANGLES:
            raise ValueError(f"angle must be one of {ANGLES}, found {angle!r}")
        return getattr(self, f"{angle}_rmse_mdeg")

    @classmethod
    def from_stats(cls, stats: dict[str, float]) -> TrajectoryFigures:
        """From :attr:`georefine.evaluation.trajectory.TrajectoryComparison.stats`."""
        return cls(stats["roll_rmse_mdeg"], stats["pitch_rmse_mdeg"], stats["yaw_rmse_mdeg"], stats["3d_rmse_m"])

    def to_dict(self) -> dict[str, Any]:
        return {"roll_rmse_mdeg": self.roll_rmse_mdeg, "pitch_rmse_mdeg": self.pitch_rmse_mdeg,
                "yaw_rmse_mdeg": self.yaw_rmse_mdeg, "3d_rmse_m": self.position_3d_rmse_m}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrajectoryFigures:
        return cls(_num(d["roll_rmse_mdeg"]), _num(d["pitch_rmse_mdeg"]), _num(d["yaw_rmse_mdeg"]),
                   _num(d["3d_rmse_m"]))


@dataclass(frozen=True)
class SolutionFigures:
    """One trajectory solution during each strip (by strip id) and during all strips together."""

    strips: dict[int, TrajectoryFigures]
    overall: TrajectoryFigures

    def to_dict(self) -> dict[str, Any]:
        return {"strips": {str(k): v.to_dict() for k, v in self.strips.items()}, "all": self.overall.to_dict()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SolutionFigures:
        return cls({int(k): TrajectoryFigures.from_dict(v) for k, v in d["strips"].items()},
                   TrajectoryFigures.from_dict(d["all"]))


@dataclass(frozen=True)
class SurfaceFigures:
    """One reference surface over its observations (a row of paper 000's Table 1)."""

    surface_id: str
    observations: int
    mean_m: float | None
    sd_m: float | None
    rmse_m: float | None

    def to_dict(self) -> dict[str, Any]:
        return {"surface_id": self.surface_id, "observations": self.observations, "mean_m": self.mean_m,
                "sd_m": self.sd_m, "rmse_m": self.rmse_m}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SurfaceFigures:
        return cls(str(d["surface_id"]), int(d["observations"]), _num(d["mean_m"]), _num(d["sd_m"]),
                   _num(d["rmse_m"]))


@dataclass(frozen=True)
class ReferencePlaneFigures:
    """Mean, RMSE and AVG-SD over all observations of the reference surfaces (Table 1), and per surface."""

    mean_m: float | None
    rmse_m: float | None
    avg_sd_m: float | None
    n_observations: int
    surfaces: tuple[SurfaceFigures, ...] = ()
    asprs_vertical: PositionalAccuracy | None = None  # the level surfaces as vertical check points

    @classmethod
    def from_summary(cls, s: ReferencePlaneSummary) -> ReferencePlaneFigures:
        return cls(s.mean_m, s.rmse_m, s.avg_sd_m, s.n_observations,
                   tuple(SurfaceFigures(**row) for row in s.per_surface), s.vertical)

    def to_dict(self) -> dict[str, Any]:
        out = {"mean_m": self.mean_m, "rmse_m": self.rmse_m, "avg_sd_m": self.avg_sd_m,
               "n_observations": self.n_observations, "surfaces": [s.to_dict() for s in self.surfaces]}
        if self.asprs_vertical is not None:
            out["asprs_vertical"] = self.asprs_vertical.to_dict()
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ReferencePlaneFigures:
        vertical = d.get("asprs_vertical")
        return cls(_num(d["mean_m"]), _num(d["rmse_m"]), _num(d["avg_sd_m"]), int(d["n_observations"]),
                   tuple(SurfaceFigures.from_dict(s) for s in d.get("surfaces", [])),
                   None if vertical is None else PositionalAccuracy.from_dict(vertical))


@dataclass(frozen=True)
class StripDifferenceFigures:
    """The strip-difference raster's figures (Fig. 7) and its maps (paths relative to ``RUN/evaluation``)."""

    cells: int
    median_m: float | None
    p95_m: float | None
    mean_m: float | None
    map: str
    zoom_map: str | None = None
    gated: dict[str, int] | None = None  # StripDifferenceMap.gating(): candidates, kept, cells gated per reason

    @classmethod
    def from_map(cls, m: StripDifferenceMap, map: str, zoom_map: str | None = None) -> StripDifferenceFigures:
        s = m.summary()
        return cls(s["cells"], s["median_m"], s["p95_m"], s["mean_m"], map, zoom_map, m.gating())

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"cells": self.cells, "median_m": self.median_m, "p95_m": self.p95_m,
                             "mean_m": self.mean_m, "map": self.map}
        if self.zoom_map is not None:
            d["zoom_map"] = self.zoom_map
        if self.gated is not None:
            d["gated"] = dict(self.gated)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StripDifferenceFigures:
        gated = d.get("gated")
        return cls(int(d["cells"]), _num(d["median_m"]), _num(d["p95_m"]), _num(d["mean_m"]), str(d["map"]),
                   d.get("zoom_map"), None if gated is None else {str(k): int(v) for k, v in gated.items()})


@dataclass(frozen=True)
class StripPairFigures:
    """The strip-pair differences of a point cloud (:mod:`georefine.evaluation.strip_pairs`) and their
    files (paths relative to ``RUN/evaluation``): ``strip_pairs.csv`` and the matrix of the medians."""

    pairs: StripPairDifferences
    csv: str
    matrix: str

    def to_dict(self) -> dict[str, Any]:
        return {"csv": self.csv, "matrix": self.matrix, **self.pairs.to_dict()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StripPairFigures:
        return cls(StripPairDifferences.from_dict(d), str(d["csv"]), str(d["matrix"]))


@dataclass(frozen=True)
class CoverageFigures:
    """Point density and strip overlap of a point cloud (:class:`~georefine.evaluation.coverage.CoverageMap`)
    and their maps (paths relative to ``RUN/evaluation``)."""

    area_km2: float
    density_median_per_m2: float | None
    density_p5_per_m2: float | None
    overlap_share: float | None  # share of the covered area seen from two strips or more
    max_strips: int
    density_map: str
    overlap_map: str

    @classmethod
    def from_map(cls, m: CoverageMap, density_map: str, overlap_map: str) -> CoverageFigures:
        s = m.summary()
        return cls(s["area_km2"], _num(s["density_median_per_m2"]), _num(s["density_p5_per_m2"]),
                   _num(s["overlap_share"]), int(s["max_strips"]), density_map, overlap_map)

    def to_dict(self) -> dict[str, Any]:
        return {"area_km2": self.area_km2, "density_median_per_m2": self.density_median_per_m2,
                "density_p5_per_m2": self.density_p5_per_m2, "overlap_share": self.overlap_share,
                "max_strips": self.max_strips, "density_map": self.density_map, "overlap_map": self.overlap_map}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CoverageFigures:
        return cls(float(d["area_km2"]), _num(d["density_median_per_m2"]), _num(d["density_p5_per_m2"]),
                   _num(d["overlap_share"]), int(d["max_strips"]), str(d["density_map"]), str(d["overlap_map"]))


@dataclass(frozen=True)
class CloudEvaluation:
    """One point cloud of a run (G/I or G/I/L): reference planes (when the project has them), strip
    differences, coverage and the strip-pair differences."""

    strip_differences: StripDifferenceFigures
    reference_planes: ReferencePlaneFigures | None = None
    coverage: CoverageFigures | None = None
    strip_pairs: StripPairFigures | None = None

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {}
        if self.reference_planes is not None:
            d["reference_planes"] = self.reference_planes.to_dict()
        d["strip_differences"] = self.strip_differences.to_dict()
        if self.coverage is not None:
            d["coverage"] = self.coverage.to_dict()
        if self.strip_pairs is not None:
            d["strip_pairs"] = self.strip_pairs.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CloudEvaluation:
        rp, cov, pairs = d.get("reference_planes"), d.get("coverage"), d.get("strip_pairs")
        return cls(StripDifferenceFigures.from_dict(d["strip_differences"]),
                   None if rp is None else ReferencePlaneFigures.from_dict(rp),
                   None if cov is None else CoverageFigures.from_dict(cov),
                   None if pairs is None else StripPairFigures.from_dict(pairs))


@dataclass(frozen=True)
class EvaluationPlots:
    """File names of the trajectory-difference plots in ``RUN/evaluation``."""

    attitude: str
    position: str

    def to_dict(self) -> dict[str, Any]:
        return {"attitude": self.attitude, "position": self.position}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EvaluationPlots:
        return cls(str(d["attitude"]), str(d["position"]))


@dataclass(frozen=True)
class RunEvaluation:
    """Everything ``RUN/evaluation/summary.json`` holds.

    Attributes
    ----------
    reference
        What the trajectories are compared with: ``"truth"`` or ``"full G/I/L"``.
    trajectory
        Per solution label (``"G/I"``, ``"G/I/L"``, ``"G/I/L single pass (strip N)"``).
    plots
        The trajectory plots, when any trajectory was compared.
    reference_planes, strip_differences
        Per point cloud label (``"G/I"``, ``"G/I/L"``).
    imu_errors, imu_errors_plot, boresight
        Where the project has a simulated truth: the adjustments' IMU errors against it per
        solution (``"G/I"``, ``"G/I/L"``), their plot's file name, and the estimated boresight
        against it (:mod:`georefine.evaluation.calibration`).
    overview_plot, coverage
        The flight on a map; per point cloud label, its point density and strip overlap.
    strip_pairs
        Per point cloud label, the differences of every pair of strips (G/I before the LiDAR
        adjustment, G/I/L after it); absent from summaries written before they were computed.
    """

    reference: str
    trajectory: dict[str, SolutionFigures] = field(default_factory=dict)
    plots: EvaluationPlots | None = None
    reference_planes: dict[str, ReferencePlaneFigures] = field(default_factory=dict)
    strip_differences: dict[str, StripDifferenceFigures] = field(default_factory=dict)
    imu_errors: dict[str, ImuErrorFigures] = field(default_factory=dict)
    imu_errors_plot: str | None = None
    boresight: BoresightFigures | None = None
    overview_plot: str | None = None  # the flight on a map (evaluation.plots.plot_overview)
    coverage: dict[str, CoverageFigures] = field(default_factory=dict)  # per point cloud label
    strip_pairs: dict[str, StripPairFigures] = field(default_factory=dict)  # per point cloud label

    SINGLE_PASS = "G/I/L single pass"
    """Start of the single-pass solution's label."""

    @property
    def single_pass(self) -> SolutionFigures | None:
        """The single-pass G/I/L solution, if the evaluation has one."""
        return next((v for k, v in self.trajectory.items() if k.startswith(self.SINGLE_PASS)), None)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"reference": self.reference,
                             "trajectory": {k: v.to_dict() for k, v in self.trajectory.items()}}
        if self.plots is not None:
            d["plots"] = self.plots.to_dict()
        d["reference_planes"] = {k: v.to_dict() for k, v in self.reference_planes.items()}
        d["strip_differences"] = {k: v.to_dict() for k, v in self.strip_differences.items()}
        if self.imu_errors:
            d["imu_errors"] = {k: v.to_dict() for k, v in self.imu_errors.items()}
        if self.imu_errors_plot is not None:
            d["imu_errors_plot"] = self.imu_errors_plot
        if self.boresight is not None:
            d["boresight"] = self.boresight.to_dict()
        if self.overview_plot is not None:
            d["overview_plot"] = self.overview_plot
        if self.coverage:
            d["coverage"] = {k: v.to_dict() for k, v in self.coverage.items()}
        if self.strip_pairs:
            d["strip_pairs"] = {k: v.to_dict() for k, v in self.strip_pairs.items()}
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RunEvaluation:
        plots = d.get("plots")
        return cls(
            reference=str(d["reference"]),
            trajectory={k: SolutionFigures.from_dict(v) for k, v in d.get("trajectory", {}).items()},
            plots=None if plots is None else EvaluationPlots.from_dict(plots),
            reference_planes={k: ReferencePlaneFigures.from_dict(v) for k, v in d.get("reference_planes", {}).items()},
            strip_differences={k: StripDifferenceFigures.from_dict(v)
                               for k, v in d.get("strip_differences", {}).items()},
            imu_errors={k: ImuErrorFigures.from_dict(v) for k, v in d.get("imu_errors", {}).items()},
            imu_errors_plot=d.get("imu_errors_plot"),
            boresight=None if d.get("boresight") is None else BoresightFigures.from_dict(d["boresight"]),
            overview_plot=d.get("overview_plot"),
            coverage={k: CoverageFigures.from_dict(v) for k, v in d.get("coverage", {}).items()},
            strip_pairs={k: StripPairFigures.from_dict(v) for k, v in d.get("strip_pairs", {}).items()},
        )

    @classmethod
    def read(cls, path: str | Path) -> RunEvaluation:
        """Read ``summary.json`` (a file path) written by the evaluation."""
        return cls.from_dict(json.loads(Path(path).read_text(encoding="utf-8")))
