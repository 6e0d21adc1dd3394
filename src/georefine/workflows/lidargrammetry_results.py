"""Results of ``georefine match`` and ``georefine coadjust`` (docs/ARCHITECTURE.md §4.8).

:class:`MatchSummary` is what :func:`georefine.workflows.lidargrammetry.run_match` writes as
``summary.json``, :class:`CoadjustResult` what
:func:`georefine.workflows.lidargrammetry.run_coadjust` writes as ``metrics.json``. Each
``to_dict`` gives that file's JSON (keys in the file's order) and ``from_dict`` reads it back,
so a result and its file are one thing. Values the JSON writer turns into ``null`` (NaN) read
back as NaN.

The per-point files of ``georefine coadjust`` are typed the same way: :class:`PointResiduals`
(``point_residuals.csv``: each control and check point's error) and :class:`TieResiduals`
(``tie_residuals.csv``: each tie observation's image residual), each with its writer and reader.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from georefine.adjustment.statistics import SolveResult
from georefine.errors import InputError
from georefine.geometry import earth
from georefine.io.files import read_text_lines, write_csv
from georefine.lidargrammetry.bundle import CASES, BundleResult, PointStats

if TYPE_CHECKING:
    from georefine.workflows.photo_block import PhotoProject

__all__ = ["PairKindStats", "MatchSummary", "PairCount", "PhotoLidargramMatches", "TieReprojection",
           "ImagePrecision", "CheckPointPrecision", "Precision", "ColmapModel", "ReintersectionCounts",
           "CoadjustResult", "PointResiduals", "TieResiduals", "POINT_RESIDUAL_COLUMNS", "TIE_RESIDUAL_COLUMNS"]


def _float(value: Any) -> float:
    """A JSON number, ``null`` (NaN written by :func:`georefine.io.files.write_json`) as NaN."""
    return float("nan") if value is None else float(value)


def _stats(d: dict | None) -> PointStats | None:
    return None if d is None else PointStats.from_dict(d)


def _stats_dict(s: PointStats | None) -> dict | None:
    return None if s is None else s.to_dict()


# ---------------------------------------------------------------------------- match
@dataclass(frozen=True)
class PairKindStats:
    """Pairs of one kind (``photo-photo``, ``photo-lidargram``, ``lidargram-lidargram``) and their verified matches."""

    kind: str
    pairs: int
    pairs_with_matches: int
    median_verified: float
    mean_verified: float

    @classmethod
    def of_counts(cls, kind: str, verified: list[int]) -> PairKindStats:
        """From the verified matches of every pair of the kind tried (0 for a pair without)."""
        counts = np.asarray(verified, dtype=float)
        return cls(kind, len(counts), int(np.count_nonzero(counts)),
                   float(np.median(counts)) if len(counts) else 0.0, float(np.mean(counts)) if len(counts) else 0.0)

    def to_dict(self) -> dict:
        return {"pairs": self.pairs, "pairs_with_matches": self.pairs_with_matches,
                "median_verified": self.median_verified, "mean_verified": self.mean_verified}

    @classmethod
    def from_dict(cls, kind: str, d: dict) -> PairKindStats:
        return cls(kind, int(d["pairs"]), int(d["pairs_with_matches"]), _float(d["median_verified"]),
                   _float(d["mean_verified"]))


@dataclass(frozen=True)
class MatchSummary:
    """``summary.json`` of ``georefine match``: images, tracks and pairs per kind (in the order asked)."""

    method: str
    photos: int
    lidargrams: int
    tracks: int
    pair_kinds: tuple[PairKindStats, ...]
    timings_s: dict[str, float] = field(default_factory=dict)

    def kind(self, name: str) -> PairKindStats:
        """The record of pair kind ``name``; ``KeyError`` if it was not matched."""
        for k in self.pair_kinds:
            if k.kind == name:
                return k
        raise KeyError(name)

    def to_dict(self) -> dict:
        return {"method": self.method, "photos": self.photos, "lidargrams": self.lidargrams, "tracks": self.tracks,
                "pair_kinds": {k.kind: k.to_dict() for k in self.pair_kinds}, "timings_s": dict(self.timings_s)}

    @classmethod
    def from_dict(cls, d: dict) -> MatchSummary:
        return cls(str(d["method"]), int(d["photos"]), int(d["lidargrams"]), int(d["tracks"]),
                   tuple(PairKindStats.from_dict(k, v) for k, v in d["pair_kinds"].items()),
                   {k: _float(v) for k, v in d["timings_s"].items()})


# ---------------------------------------------------------------------------- coadjust
@dataclass(frozen=True)
class PairCount:
    """Verified matches of one photo-lidargram pair (image names)."""

    a: str
    b: str
    verified: int


@dataclass(frozen=True)
class PhotoLidargramMatches:
    """Photo-lidargram pairs tried and the median of their verified matches (``per_pair``: each pair, if kept)."""

    n_pairs: int
    median_verified: float
    per_pair: tuple[PairCount, ...] | None = None

    @classmethod
    def of_pairs(cls, per_pair: list[PairCount]) -> PhotoLidargramMatches:
        median = float(np.median([p.verified for p in per_pair])) if per_pair else 0.0
        return cls(len(per_pair), median, tuple(per_pair))

    def without_pairs(self) -> PhotoLidargramMatches:
        """The counts only (the demo's metrics)."""
        return PhotoLidargramMatches(self.n_pairs, self.median_verified, None)

    def to_dict(self) -> dict:
        d: dict = {"pairs": self.n_pairs, "median": self.median_verified}
        if self.per_pair is not None:
            d["per_pair"] = [{"a": p.a, "b": p.b, "verified": p.verified} for p in self.per_pair]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> PhotoLidargramMatches:
        per = d.get("per_pair")
        return cls(int(d["pairs"]), _float(d["median"]),
                   None if per is None else tuple(PairCount(str(p["a"]), str(p["b"]), int(p["verified"])) for p in per))


@dataclass(frozen=True)
class TieReprojection:
    """RMS reprojection error (px) of the inlier tie observations in photos and in lidargrams."""

    photos_px: float
    lidargrams_px: float

    def to_dict(self) -> dict:
        return {"photos": self.photos_px, "lidargrams": self.lidargrams_px}

    @classmethod
    def from_dict(cls, d: dict) -> TieReprojection:
        return cls(_float(d["photos"]), _float(d["lidargrams"]))


@dataclass(frozen=True)
class ImagePrecision:
    """Posterior precision of the free images of one kind: medians over the images."""

    images: int
    sigma_position_m_median: tuple[float, float, float]
    sigma_rotation_deg_median: tuple[float, float, float]

    def to_dict(self) -> dict:
        return {"images": self.images, "sigma_position_m_median": list(self.sigma_position_m_median),
                "sigma_rotation_deg_median": list(self.sigma_rotation_deg_median)}

    @classmethod
    def from_dict(cls, d: dict) -> ImagePrecision:
        return cls(int(d["images"]), tuple(_float(v) for v in d["sigma_position_m_median"]),  # type: ignore[arg-type]
                   tuple(_float(v) for v in d["sigma_rotation_deg_median"]))  # type: ignore[arg-type]


@dataclass(frozen=True)
class CheckPointPrecision:
    """Check points' posterior sigma beside their actual error; ``normalised_rms`` about 1 when honest."""

    n: int
    sigma_xyz_m_rms: tuple[float, float, float]
    error_xyz_m_rms: tuple[float, float, float]
    normalised_rms: float

    def to_dict(self) -> dict:
        return {"n": self.n, "sigma_xyz_m_rms": list(self.sigma_xyz_m_rms),
                "error_xyz_m_rms": list(self.error_xyz_m_rms), "normalised_rms": self.normalised_rms}

    @classmethod
    def from_dict(cls, d: dict) -> CheckPointPrecision:
        return cls(int(d["n"]), tuple(_float(v) for v in d["sigma_xyz_m_rms"]),  # type: ignore[arg-type]
                   tuple(_float(v) for v in d["error_xyz_m_rms"]), _float(d["normalised_rms"]))  # type: ignore[arg-type]


@dataclass(frozen=True)
class Precision:
    """Estimated precision of one adjustment (:mod:`georefine.lidargrammetry.bundle`); parts it could not give are None."""

    photos: ImagePrecision | None = None
    lidargrams: ImagePrecision | None = None
    check_points: CheckPointPrecision | None = None

    def to_dict(self) -> dict:
        return {k: v.to_dict() for k, v in (("photos", self.photos), ("lidargrams", self.lidargrams),
                                             ("check_points", self.check_points)) if v is not None}

    @classmethod
    def from_dict(cls, d: dict) -> Precision:
        return cls(*(None if d.get(k) is None else ImagePrecision.from_dict(d[k]) for k in ("photos", "lidargrams")),
                   None if d.get("check_points") is None else CheckPointPrecision.from_dict(d["check_points"]))


@dataclass(frozen=True)
class ColmapModel:
    """The COLMAP model written (:mod:`georefine.workflows.colmap_export`): its folder, the local
    frame it is in, the output CRS of its reference file, its size and its mean reprojection error
    (px, COLMAP's statistic: the mean over points of each point's mean error, as ``colmap
    model_analyzer`` reports it)."""

    folder: str
    frame: str
    origin_lat_deg: float
    origin_lon_deg: float
    origin_h_m: float
    crs: str = ""
    images: int = 0
    points: int = 0
    observations: int = 0
    mean_reprojection_error_px: float = float("nan")

    def to_dict(self) -> dict:
        return {"folder": self.folder, "frame": self.frame, "origin_lat_deg": self.origin_lat_deg,
                "origin_lon_deg": self.origin_lon_deg, "origin_h_m": self.origin_h_m, "crs": self.crs,
                "images": self.images, "points": self.points, "observations": self.observations,
                "mean_reprojection_error_px": self.mean_reprojection_error_px}

    @classmethod
    def from_dict(cls, d: dict) -> ColmapModel:
        return cls(str(d["folder"]), str(d["frame"]), _float(d["origin_lat_deg"]), _float(d["origin_lon_deg"]),
                   _float(d["origin_h_m"]), str(d["crs"]), int(d["images"]), int(d["points"]),
                   int(d["observations"]), _float(d["mean_reprojection_error_px"]))


@dataclass(frozen=True)
class ReintersectionCounts:
    """Points of the refined cloud by how they moved (:mod:`georefine.lidargrammetry.reintersect`)."""

    points: int
    multi_ray: int
    single_ray: int
    interpolated: int
    unchanged: int

    def to_dict(self) -> dict:
        return {"points": self.points, "multi_ray": self.multi_ray, "single_ray": self.single_ray,
                "interpolated": self.interpolated, "unchanged": self.unchanged}

    @classmethod
    def from_dict(cls, d: dict) -> ReintersectionCounts:
        return cls(*(int(d[k]) for k in ("points", "multi_ray", "single_ray", "interpolated", "unchanged")))


@dataclass(frozen=True)
class CoadjustResult:
    """``metrics.json`` of ``georefine coadjust`` (one case), and the adjustment behind it.

    ``adjustment`` and ``photo_block_adjustment`` are the solves' statistics
    (:class:`~georefine.adjustment.statistics.SolveResult`); the photo block's are there for case 1 only, the
    re-intersection for cases 1 and 2. ``bundle``: the adjusted poses and points (``None``
    when read back from a file).
    """

    case: int
    method: str
    use_depth: bool
    photos: int
    lidargrams: int
    tracks: int
    tie_observations: int
    photo_lidargram_matches: PhotoLidargramMatches
    control_points: PointStats | None
    check_points: PointStats | None
    tie_reprojection: TieReprojection
    adjustment: SolveResult
    precision: Precision
    tie_inlier_fraction: float
    colmap_model: ColmapModel
    photo_block_adjustment: SolveResult | None = None
    photo_block_precision: Precision | None = None
    reintersection: ReintersectionCounts | None = None
    timings_s: dict[str, float] = field(default_factory=dict)
    bundle: BundleResult | None = field(default=None, compare=False, repr=False)

    @property
    def description(self) -> str:
        return CASES[self.case]

    def to_dict(self) -> dict:
        d: dict = {"case": self.case, "description": self.description, "method": self.method,
                   "use_depth": self.use_depth, "photos": self.photos, "lidargrams": self.lidargrams,
                   "tracks": self.tracks, "tie_observations": self.tie_observations,
                   "photo_lidargram_matches": self.photo_lidargram_matches.to_dict(),
                   "control_points": _stats_dict(self.control_points), "check_points": _stats_dict(self.check_points),
                   "tie_reprojection_px": self.tie_reprojection.to_dict(), "adjustment": self.adjustment.to_dict()}
        if self.photo_block_adjustment is not None:
            d["photo_block_adjustment"] = self.photo_block_adjustment.to_dict()
        if self.photo_block_precision is not None:
            d["photo_block_precision"] = self.photo_block_precision.to_dict()
        d["precision"] = self.precision.to_dict()
        d["tie_inlier_fraction"] = self.tie_inlier_fraction
        d["colmap_model"] = self.colmap_model.to_dict()
        if self.reintersection is not None:
            d["reintersection"] = self.reintersection.to_dict()
        d["timings_s"] = dict(self.timings_s)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> CoadjustResult:
        pbp = d.get("photo_block_precision")
        ri = d.get("reintersection")
        pba = d.get("photo_block_adjustment")
        return cls(int(d["case"]), str(d["method"]), bool(d["use_depth"]), int(d["photos"]), int(d["lidargrams"]),
                   int(d["tracks"]), int(d["tie_observations"]),
                   PhotoLidargramMatches.from_dict(d["photo_lidargram_matches"]), _stats(d["control_points"]),
                   _stats(d["check_points"]), TieReprojection.from_dict(d["tie_reprojection_px"]),
                   SolveResult.from_dict(d["adjustment"]),
                   Precision.from_dict(d["precision"]), _float(d["tie_inlier_fraction"]),
                   ColmapModel.from_dict(d["colmap_model"]), None if pba is None else SolveResult.from_dict(pba),
                   None if pbp is None else Precision.from_dict(pbp),
                   None if ri is None else ReintersectionCounts.from_dict(ri),
                   {k: _float(v) for k, v in d["timings_s"].items()})


# ---------------------------------------------------------------------------- per-point files
POINT_RESIDUAL_COLUMNS = ("id", "role", "x", "y", "z", "dx_m", "dy_m", "dz_m", "dh_m", "d3_m", "rays",
                          "reprojection_px", "sigma_x_m", "sigma_y_m", "sigma_z_m")
"""Columns of ``point_residuals.csv`` (docs/ARCHITECTURE.md §4.8)."""

TIE_RESIDUAL_COLUMNS = ("image", "kind", "track", "u", "v", "du_px", "dv_px", "inlier")
"""Columns of ``tie_residuals.csv`` (docs/ARCHITECTURE.md §4.8)."""


def _cell(value: float, digits: int) -> str:
    """A number with ``digits`` decimals; empty for NaN (a spreadsheet shows an empty cell, not "nan")."""
    return "" if not np.isfinite(value) else f"{value:.{digits}f}"


def _table(path: Path, columns: tuple[str, ...]) -> tuple[dict[str, list[str]], np.ndarray]:
    """The columns ``columns`` of the CSV file ``path`` (header line first) and each row's line number.

    Raises
    ------
    InputError
        A missing column (named) or a row with another number of fields than the header.
    """
    lines = read_text_lines(path)
    if not lines:
        raise InputError("empty file", path=path, expected="a header line: " + ",".join(columns))
    header = next(csv.reader([lines[0]]))
    for c in columns:
        if c not in header:
            raise InputError("missing column", path=path, line=1, field=c, expected=",".join(columns))
    rows = list(csv.reader(io.StringIO("\n".join(lines[1:]))))
    out: dict[str, list[str]] = {c: [] for c in columns}
    idx = [header.index(c) for c in columns]
    numbers = []
    for k, r in enumerate(rows):
        if not r:
            continue
        if len(r) != len(header):
            raise InputError("wrong number of fields", path=path, line=k + 2, expected=str(len(header)),
                             found=str(len(r)))
        for c, i in zip(columns, idx):
            out[c].append(r[i])
        numbers.append(k + 2)
    return out, np.asarray(numbers, dtype=np.int64)


def _one_of(path: Path, table: dict[str, list[str]], lines: np.ndarray, name: str, choices: tuple[str, ...],
            what: str) -> None:
    """Raise naming the line and field where column ``name`` holds something else than ``choices``."""
    for k, text in enumerate(table[name]):
        if text not in choices:
            raise InputError(what, path=path, line=int(lines[k]), field=name, expected=" or ".join(choices),
                             found=text)


def _numbers(path: Path, table: dict[str, list[str]], lines: np.ndarray, name: str) -> np.ndarray:
    """Column ``name`` as floats, an empty cell as NaN; a bad cell raises naming its line and field."""
    out = np.full(len(lines), np.nan)
    for k, text in enumerate(table[name]):
        if text.strip():
            try:
                out[k] = float(text)
            except ValueError:
                raise InputError("not a number", path=path, line=int(lines[k]), field=name, found=text) from None
    return out


@dataclass(frozen=True)
class PointResiduals:
    """Each control and check point of one case: ``OUT/point_residuals.csv`` of ``georefine coadjust``.

    ``role``: as the case used the point (``control`` or ``check``; case 3 uses no control point,
    so all are ``check``). ``xyz``: the surveyed coordinates (output CRS, as ``gcp.csv``).
    ``error_m``: the point intersected from the adjusted photos minus its surveyed coordinates,
    along the output CRS's grid axes (east, north, height); NaN for a point measured in fewer than
    two photos. ``reprojection_px``: RMS of its image residuals with the adjusted photos.
    ``sigma_m``: its posterior standard deviation as a point of the adjustment the photos come from,
    along the same axes (NaN where that adjustment does not hold it: case 3). Rows are ordered
    worst first (3-D error descending; points not intersected last), so the file opens with the
    points to look at.
    """

    ids: tuple[str, ...]
    role: tuple[str, ...]
    xyz: np.ndarray  # (m, 3)
    error_m: np.ndarray  # (m, 3)
    rays: np.ndarray  # (m,) int
    reprojection_px: np.ndarray  # (m,)
    sigma_m: np.ndarray  # (m, 3)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def horizontal_m(self) -> np.ndarray:
        return np.hypot(self.error_m[:, 0], self.error_m[:, 1])

    @property
    def error_3d_m(self) -> np.ndarray:
        return np.linalg.norm(self.error_m, axis=1)

    @property
    def is_control(self) -> np.ndarray:
        return np.array([r == "control" for r in self.role], dtype=bool)

    def subset(self, keep: np.ndarray) -> PointResiduals:
        """The rows ``keep`` (a boolean mask or indices), in that order."""
        k = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep, dtype=np.int64)
        return PointResiduals(tuple(self.ids[i] for i in k), tuple(self.role[i] for i in k), self.xyz[k],
                              self.error_m[k], self.rays[k], self.reprojection_px[k], self.sigma_m[k])

    def worst_first(self) -> PointResiduals:
        """Sorted by 3-D error descending, points without an error last (stable: ties keep their order)."""
        d3 = self.error_3d_m
        return self.subset(np.argsort(np.where(np.isfinite(d3), -d3, np.inf), kind="stable"))

    @classmethod
    def of_bundle(cls, pp: PhotoProject, result: BundleResult, case: int) -> PointResiduals:
        """Each control and check point of ``pp`` after the adjustment ``result`` of case ``case``:
        the intersection from the adjusted photos minus the surveyed coordinates and the posterior
        sigma, both along the output CRS's grid axes (the covariance turned from ``w`` through the
        meridian convergence at the point), as ``point_residuals.csv`` holds them."""
        g = pp.gcps
        m = len(g)
        X = result.point_xyz_w
        ok = np.isfinite(X[:, 0]) if m else np.zeros(0, dtype=bool)
        error = np.full((m, 3), np.nan)
        sigma = np.full((m, 3), np.nan)
        if ok.any():
            error[ok] = pp.crs.from_w(pp.frame, X[ok]) - g.xyz[ok]
        if result.point_cov_w is not None and m:
            lat, lon, h = pp.crs.to_geodetic(g.xyz)
            R_enu_w = np.swapaxes(earth.R_e_enu(lat, lon), 1, 2) @ pp.frame.R_e_w
            R_grid_w = pp.crs.R_grid_enu(lat, lon, h) @ R_enu_w
            cov = R_grid_w @ result.point_cov_w @ np.swapaxes(R_grid_w, 1, 2)
            sigma = np.sqrt(np.einsum("kii->ki", cov))
        role = tuple("check" if case == 3 or not c else "control" for c in g.is_control)
        rays = result.point_rays if result.point_rays is not None else np.zeros(m, np.int64)
        re_px = result.point_reprojection_px if result.point_reprojection_px is not None else np.full(m, np.nan)
        return cls(tuple(g.ids), role, np.asarray(g.xyz, dtype=float).reshape(m, 3), error,
                   np.asarray(rays, dtype=np.int64), np.asarray(re_px, dtype=float), sigma)

    def write(self, path: Path, protect=()) -> None:
        """``path`` (CSV, :data:`POINT_RESIDUAL_COLUMNS`), written atomically, worst first."""
        r = self.worst_first()
        h, d3 = r.horizontal_m, r.error_3d_m
        write_csv(path, POINT_RESIDUAL_COLUMNS, (
            [pid, r.role[k], *(f"{v:.4f}" for v in r.xyz[k]), *(_cell(v, 4) for v in r.error_m[k]),
             _cell(h[k], 4), _cell(d3[k], 4), str(int(r.rays[k])), _cell(r.reprojection_px[k], 3),
             *(_cell(v, 4) for v in r.sigma_m[k])] for k, pid in enumerate(r.ids)), protect)

    @classmethod
    def read(cls, path: Path) -> PointResiduals:
        """Read :meth:`write`'s file.

        Raises
        ------
        InputError
            A missing column, a bad number or role (naming the line and field).
        """
        path = Path(path)
        t, lines = _table(path, POINT_RESIDUAL_COLUMNS)
        _one_of(path, t, lines, "role", ("control", "check"), "unknown role")

        def cols(*names: str) -> np.ndarray:
            return np.column_stack([_numbers(path, t, lines, c) for c in names]) if len(lines) \
                else np.zeros((0, len(names)))

        return cls(tuple(t["id"]), tuple(t["role"]), cols("x", "y", "z"), cols("dx_m", "dy_m", "dz_m"),
                   cols("rays")[:, 0].astype(np.int64), cols("reprojection_px")[:, 0],
                   cols("sigma_x_m", "sigma_y_m", "sigma_z_m"))


@dataclass(frozen=True)
class TieResiduals:
    """Each tie observation of one case: ``OUT/tie_residuals.csv`` of ``georefine coadjust``.

    ``residual_px``: the adjusted tie point projected into the image minus the measured keypoint
    (``du_px``, ``dv_px``; NaN where the point was not adjusted: seen from one station and
    without a lidargram depth); ``inlier``: within 3 loss scales (the observations the tie
    reprojection RMS of ``metrics.json`` is taken over).
    """

    images: tuple[str, ...]
    is_lidargram: np.ndarray  # (k,) bool
    track: np.ndarray  # (k,) int
    uv: np.ndarray  # (k, 2) measured, pixels (top-left pixel centre at (0.5, 0.5))
    residual_px: np.ndarray  # (k, 2)
    inlier: np.ndarray  # (k,) bool

    def __len__(self) -> int:
        return len(self.images)

    @property
    def norm_px(self) -> np.ndarray:
        return np.linalg.norm(self.residual_px, axis=1)

    def write(self, path: Path, protect=()) -> None:
        """``path`` (CSV, :data:`TIE_RESIDUAL_COLUMNS`), written atomically, in observation order."""
        write_csv(path, TIE_RESIDUAL_COLUMNS, (
            [name, "lidargram" if self.is_lidargram[k] else "photo", int(self.track[k]), f"{self.uv[k, 0]:.3f}",
             f"{self.uv[k, 1]:.3f}", _cell(self.residual_px[k, 0], 4), _cell(self.residual_px[k, 1], 4),
             int(bool(self.inlier[k]))] for k, name in enumerate(self.images)), protect)

    @classmethod
    def read(cls, path: Path) -> TieResiduals:
        """Read :meth:`write`'s file.

        Raises
        ------
        InputError
            A missing column, a bad number or kind (naming the line and field).
        """
        path = Path(path)
        t, lines = _table(path, TIE_RESIDUAL_COLUMNS)
        _one_of(path, t, lines, "kind", ("photo", "lidargram"), "unknown image kind")
        num = {c: _numbers(path, t, lines, c) for c in ("track", "u", "v", "du_px", "dv_px", "inlier")}
        return cls(tuple(t["image"]), np.array([k == "lidargram" for k in t["kind"]], dtype=bool),
                   num["track"].astype(np.int64), np.column_stack([num["u"], num["v"]]),
                   np.column_stack([num["du_px"], num["dv_px"]]), num["inlier"] == 1)
