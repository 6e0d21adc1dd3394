"""The output CRS of a project (``crs`` in ``project.yaml``): EPSG codes checked against PROJ,
the optional reference point, and the geoid grid that gives the final point clouds
gravity-related heights (docs/ARCHITECTURE.md §3, "Sensor configuration")."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import Field, field_validator, model_validator

from georefine.config.base import StrictModel
from georefine.errors import ConfigError

if TYPE_CHECKING:
    from georefine.geometry.frames import GeoidHeights

__all__ = ["GEOID_GRID_SUFFIXES", "CrsConfig", "ReferencePoint", "check_output_epsg", "check_vertical_epsg"]


class ReferencePoint(StrictModel):
    """Origin of the mapping frame ``w`` (east-north-up). Default: the first GNSS fix."""

    lat_deg: float = Field(ge=-90.0, le=90.0)
    lon_deg: float = Field(ge=-180.0, le=180.0)
    h_m: float


def check_output_epsg(code: int) -> int:
    """``code`` if PROJ knows it as a horizontal (projected or geographic) CRS reachable from WGS84.

    Checked when a configuration is read, so that ``georefine check`` refuses a code that would
    otherwise fail when the first trajectory or point is written.
    """
    from pyproj import CRS, Transformer
    from pyproj.exceptions import CRSError, ProjError

    try:
        crs = CRS.from_epsg(int(code))
    except CRSError:
        raise ValueError(f"EPSG:{code} is not a coordinate reference system PROJ knows") from None
    if not (crs.is_projected or crs.is_geographic):
        raise ValueError(f"EPSG:{code} ({crs.name}) is not a projected or geographic CRS")
    try:
        Transformer.from_crs(CRS.from_epsg(4979), crs, always_xy=True)
    except ProjError as exc:
        raise ValueError(f"EPSG:{code} ({crs.name}) cannot be reached from WGS84: {exc}") from None
    return int(code)


def check_vertical_epsg(code: int) -> int:
    """``code`` if EPSG defines it as a vertical CRS (gravity-related heights, e.g. 7837 DHHN2016 height)."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        crs = CRS.from_epsg(int(code))
    except CRSError:
        raise ValueError(f"EPSG:{code} is not a coordinate reference system PROJ knows") from None
    if crs.is_compound or not crs.is_vertical:
        raise ValueError(f"EPSG:{code} ({crs.name}) is a {crs.type_name}, not a vertical CRS "
                         f"(e.g. 7837 DHHN2016 height, 5703 NAVD88 height)")
    return int(code)


GEOID_GRID_SUFFIXES = (".tif", ".tiff", ".gtx")
"""The geoid grid formats PROJ reads for ``crs.geoid_grid``: GeoTIFF and NOAA GTX."""


class CrsConfig(StrictModel):
    """The output CRS (docs/ARCHITECTURE.md §3, "Sensor configuration").

    Every height Georefine computes and writes is ellipsoidal, except, when ``geoid_grid`` and
    ``vertical_epsg`` are given, the heights of the final point clouds (``run``'s ``points/``,
    ``georeference``, ``coadjust``'s refined cloud): those are gravity-related, ``H = h - N``
    with the undulation ``N`` of the grid, and the files state the compound CRS
    ``output_epsg`` + ``vertical_epsg`` (:class:`georefine.geometry.frames.GeoidHeights`).
    """

    output_epsg: int = Field(
        25832, description="EPSG code of the output CRS (horizontal); heights are ellipsoidal unless geoid_grid "
        "and vertical_epsg are given, which make the final point clouds' heights gravity-related.")
    reference_point: ReferencePoint | None = None
    geoid_grid: str | None = Field(
        None, description="Geoid grid (GeoTIFF .tif or GTX .gtx, undulation N in metres above the ellipsoid) "
        "relative to the project folder: the final point clouds get heights H = h - N in vertical_epsg.")
    vertical_epsg: int | None = Field(
        None, description="EPSG code of the vertical CRS geoid_grid realises (e.g. 7837 DHHN2016 height, "
        "5703 NAVD88 height); with geoid_grid, or neither.")

    @field_validator("output_epsg")
    @classmethod
    def _known_epsg(cls, v: int) -> int:
        return check_output_epsg(v)

    @field_validator("vertical_epsg")
    @classmethod
    def _vertical_epsg(cls, v: int | None) -> int | None:
        return None if v is None else check_vertical_epsg(v)

    @field_validator("geoid_grid")
    @classmethod
    def _grid_format(cls, v: str | None) -> str | None:
        if v is not None and Path(v).suffix.lower() not in GEOID_GRID_SUFFIXES:
            raise ValueError(f"a geoid grid PROJ reads: {', '.join(GEOID_GRID_SUFFIXES)} (GeoTIFF or GTX), not {v!r}")
        return v

    @model_validator(mode="after")
    def _both_or_neither(self) -> "CrsConfig":
        if (self.geoid_grid is None) != (self.vertical_epsg is None):
            given, missing = (("geoid_grid", "vertical_epsg") if self.vertical_epsg is None
                              else ("vertical_epsg", "geoid_grid"))
            raise ValueError(f"{given} is given without {missing}: gravity-related heights need both "
                             f"(the grid and the vertical CRS it realises), ellipsoidal heights neither")
        return self

    def geoid(self, project_dir: str | Path) -> "GeoidHeights | None":
        """The final point clouds' height conversion (``None``: ellipsoidal heights), the grid
        resolved against ``project_dir`` and opened by PROJ.

        Raises
        ------
        ConfigError
            The grid does not exist or PROJ cannot read it; names the file and ``crs.geoid_grid``.
        """
        from georefine.geometry.frames import GeoidHeights

        if self.geoid_grid is None or self.vertical_epsg is None:
            return None
        path = (Path(project_dir) / self.geoid_grid).absolute()
        expected = f"a geoid grid ({', '.join(GEOID_GRID_SUFFIXES)}) relative to the project folder {project_dir}"
        if not path.is_file():
            raise ConfigError("no such geoid grid file", path=path, field="crs.geoid_grid", expected=expected,
                              found=repr(self.geoid_grid))
        heights = GeoidHeights(str(path), int(self.vertical_epsg))
        try:
            heights.check()
        except ValueError as exc:
            raise ConfigError(str(exc), path=path, field="crs.geoid_grid", expected=expected) from None
        return heights
