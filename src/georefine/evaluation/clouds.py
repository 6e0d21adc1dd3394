"""Point-cloud evaluation of georeferenced strips (LAZ in the output CRS) and its files.

Reads the strips a run wrote (``points/strip_N.laz``, or any LAS/LAZ with ``point_source_id``
and ``scanner_channel``), in chunks, keeping only what each metric needs, and writes:

* ``reference_planes.json`` and ``reference_planes.csv``: the observations of the reference
  surfaces per strip x channel and paper 000's Table 1 figures
  (:mod:`georefine.evaluation.reference_planes`);
* ``strip_differences.json``, ``strip_differences.png`` and ``strip_differences.tif``: the Fig. 7
  raster over the layers strip x channel (:mod:`georefine.evaluation.strip_differences`).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np

from georefine.errors import InputError
from georefine.evaluation.reference_planes import (
    PlaneObservation,
    ReferencePlaneSummary,
    observe_reference_planes,
    reference_planes,
    summarise_observations,
)
from georefine.evaluation.strip_differences import (
    StripDifferenceMap,
    crop,
    strip_differences,
    write_geotiff,
    write_png,
)
from georefine.io.files import atomic_output, write_json
from georefine.io.reference import read_reference_surfaces

__all__ = ["Layer", "point_files", "read_layers", "evaluate_reference_planes", "evaluate_strip_differences", "epsg_of"]

_CHUNK = 5_000_000


def point_files(paths: list[Path]) -> list[Path]:
    """LAS/LAZ files named directly or found in the named folders (sorted)."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out += sorted(q for q in p.iterdir() if q.suffix.lower() in (".las", ".laz"))
        elif p.is_file():
            out.append(p)
        else:
            raise InputError("no such file or folder", path=p)
    if not out:
        raise InputError("no LAS/LAZ files", path=", ".join(map(str, paths)), expected="georeferenced strips")
    return out


def epsg_of(path: Path) -> int | None:
    """EPSG code of a LAS/LAZ file's CRS (WKT in the header), if it has one."""
    with laspy.open(path) as f:
        crs = f.header.parse_crs()
    if crs is None:
        return None
    # The strips carry the projected CRS with ellipsoidal heights (3-D), which has no EPSG code
    # of its own: the horizontal CRS has.
    return crs.to_epsg() or crs.to_2d().to_epsg()


@dataclass(frozen=True)
class Layer:
    """The points of one strip x scanner channel."""

    strip: int
    channel: int
    xyz: np.ndarray


def _chunks(path: Path):
    try:
        with laspy.open(path) as f:
            for pts in f.chunk_iterator(_CHUNK):
                yield (np.column_stack([pts.x, pts.y, pts.z]), np.asarray(pts.point_source_id),
                       np.asarray(pts.scanner_channel))
    except (laspy.errors.LaspyException, OSError, ValueError) as exc:
        raise InputError(f"cannot read the point cloud ({exc})", path=path) from exc


def read_layers(files: list[Path], keep=None) -> list[Layer]:
    """Points per strip x channel; ``keep(xyz) -> mask`` thins them while reading."""
    parts: dict[tuple[int, int], list[np.ndarray]] = {}
    for f in files:
        for xyz, sid, ch in _chunks(f):
            if keep is not None:
                m = keep(xyz)
                xyz, sid, ch = xyz[m], sid[m], ch[m]
            code = sid.astype(np.int64) * 256 + ch
            for k in np.unique(code):
                parts.setdefault((int(k // 256), int(k % 256)), []).append(xyz[code == k])
    return [Layer(s, c, np.concatenate(v)) for (s, c), v in sorted(parts.items())]


def evaluate_reference_planes(
    files: list[Path], reference_csv: Path, out: Path | None = None, *, inset_m: float = 0.25,
    max_distance_m: float = 0.3, min_points: int = 10, layers: list[Layer] | None = None,
) -> tuple[list[PlaneObservation], ReferencePlaneSummary]:
    """Observations of the reference surfaces and the Table 1 figures (written to ``out``).

    ``layers``: points already read (:func:`read_layers`); else ``files`` are read, keeping only
    the points near the surfaces.
    """
    planes = reference_planes(read_reference_surfaces(reference_csv))
    lo = np.min([p.centre - 10.0 for p in planes], axis=0)
    hi = np.max([p.centre + 10.0 for p in planes], axis=0)

    def near(xyz):
        return np.all((xyz >= lo) & (xyz <= hi), axis=1)

    if layers is None:
        layers = read_layers(files, keep=near)
    else:
        layers = [Layer(la.strip, la.channel, la.xyz[near(la.xyz)]) for la in layers]
    xyz = np.concatenate([la.xyz for la in layers]) if layers else np.zeros((0, 3))
    sid = np.concatenate([np.full(len(la.xyz), la.strip) for la in layers]) if layers else np.zeros(0, int)
    ch = np.concatenate([np.full(len(la.xyz), la.channel) for la in layers]) if layers else np.zeros(0, int)
    obs = observe_reference_planes(xyz, sid, ch, planes, inset_m=inset_m, max_distance_m=max_distance_m,
                                   min_points=min_points)
    obs.sort(key=lambda o: (o.surface_id, o.strip, o.channel))
    summary = summarise_observations(obs)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "reference_planes.json", {
            **summary.to_dict(), "inset_m": inset_m, "max_distance_m": max_distance_m,
            "observations": [o.__dict__ for o in obs], "files": [str(f) for f in files],
        })
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["surface_id", "strip", "channel", "n_points", "mean_mm", "sd_points_mm"])
        for o in obs:
            w.writerow([o.surface_id, o.strip, o.channel, o.n_points, f"{o.mean_m * 1e3:.2f}", f"{o.sd_points_m * 1e3:.2f}"])
        with atomic_output(out / "reference_planes.csv", "w") as fh:
            fh.write(buf.getvalue())
    return obs, summary


def evaluate_strip_differences(
    files: list[Path], out: Path | None = None, *, cell_size_m: float = 1.0, min_points: int = 6,
    max_roughness_m: float = 0.03, title: str = "", layers: list[Layer] | None = None,
    zoom: tuple[float, float, float, float] | None = None,
) -> StripDifferenceMap:
    """The strip-difference raster over all strip x channel layers (files written to ``out``).

    ``zoom``: ``(xmin, xmax, ymin, ymax)`` of an additional detail map,
    ``strip_differences_zoom.png`` (as paper 000's Fig. 7 shows a semi-urban area).
    """
    layers = read_layers(files) if layers is None else layers
    m = strip_differences([layer.xyz for layer in layers], cell_size_m, min_points, max_roughness_m)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        epsg = epsg_of(files[0])
        write_json(out / "strip_differences.json", {
            **m.summary(), "cell_size_m": cell_size_m, "min_points": min_points, "max_roughness_m": max_roughness_m,
            "layers": [{"strip": la.strip, "channel": la.channel, "points": int(len(la.xyz))} for la in layers],
            "x0": m.x0, "y1": m.y1, "epsg": epsg,
        })
        write_png(out / "strip_differences.png", m, title=title, epsg=epsg)
        if zoom is not None:
            write_png(out / "strip_differences_zoom.png", crop(m, zoom), title=title + " (detail)", epsg=epsg)
        if epsg is not None:
            write_geotiff(out / "strip_differences.tif", m, epsg)
    return m
