"""The mapping frame ``w`` (local tangent plane, ENU) and the output CRS.

``w`` is ECEF rotated and shifted to east-north-up at a reference point (docs/ARCHITECTURE.md §4.1):
``p_e = p_e_w + R_e_w p_w``. It is fixed to the Earth, so the Earth rate and normal gravity
are the only extra terms of the physics written in it:

``omega_ie_w = R_e_w^T [0, 0, omega_ie]``, ``g_w(p_w) = R_e_w^T g_e(p_e_w + R_e_w p_w)``.

The output CRS (e.g. ETRS89 / UTM 32N, EPSG:25832) is reached through pyproj from
geodetic WGS84 coordinates with ellipsoidal heights (EPSG:4979); heights stay ellipsoidal
(the projected CRS is promoted to 3D with ``CRS.to_3d()``). Only the final point clouds may
carry gravity-related heights instead, ``H = h - N`` from a geoid grid (:class:`GeoidHeights`,
``crs.geoid_grid`` and ``crs.vertical_epsg`` in ``project.yaml``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numba
import numpy as np

from georefine.geometry import earth


@dataclass(frozen=True)
class LocalFrame:
    """East-north-up frame ``w`` at geodetic ``lat0_rad, lon0_rad, h0_m``."""

    lat0_rad: float
    lon0_rad: float
    h0_m: float

    @classmethod
    def from_degrees(cls, lat0_deg: float, lon0_deg: float, h0_m: float) -> "LocalFrame":
        return cls(float(np.radians(lat0_deg)), float(np.radians(lon0_deg)), float(h0_m))

    @cached_property
    def R_e_w(self) -> np.ndarray:
        """Rotation ENU at the reference point -> ECEF, ``(3, 3)``."""
        return earth.R_e_enu(self.lat0_rad, self.lon0_rad)

    @cached_property
    def p_e_w(self) -> np.ndarray:
        """ECEF position of the origin of ``w`` (m)."""
        return earth.geodetic_to_ecef(self.lat0_rad, self.lon0_rad, self.h0_m)

    @cached_property
    def omega_ie_w(self) -> np.ndarray:
        """Earth rate in ``w`` (rad/s)."""
        return self.R_e_w.T @ earth.OMEGA_IE_E

    def to_ecef(self, p_w: np.ndarray) -> np.ndarray:
        """``p_e = p_e_w + R_e_w p_w`` for ``(..., 3)`` positions (m)."""
        # einsum, not BLAS: an (N, 3) x (3, 3) product through BLAS is slow and fights task threads
        return np.einsum("ij,...j->...i", self.R_e_w, np.asarray(p_w, dtype=float)) + self.p_e_w

    def from_ecef(self, p_e: np.ndarray) -> np.ndarray:
        """``p_w = R_e_w^T (p_e - p_e_w)``."""
        return np.einsum("ji,...j->...i", self.R_e_w, np.asarray(p_e, dtype=float) - self.p_e_w)

    def to_geodetic(self, p_w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Latitude, longitude (rad) and ellipsoidal height (m) of ``w`` positions."""
        return earth.ecef_to_geodetic(self.to_ecef(p_w))

    def from_geodetic(self, lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> np.ndarray:
        """``w`` positions of geodetic coordinates (rad, rad, m)."""
        return self.from_ecef(earth.geodetic_to_ecef(lat, lon, h))

    def gravity_w(self, p_w: np.ndarray) -> np.ndarray:
        """Normal gravity vector in ``w`` (m/s^2) at ``w`` positions ``(..., 3)``."""
        return earth.gravity_e(self.to_ecef(p_w)) @ self.R_e_w

    def R_w_n(self, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        """Rotation from the local NED frame at ``(lat, lon)`` to ``w``: ``R_e_w^T R_e_n``."""
        return self.R_e_w.T @ earth.R_e_n(lat, lon)

    def up_w(self, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        """Unit ellipsoid normals (local up) in ``w`` at geodetic ``(lat, lon)`` (rad), ``(..., 3)``."""
        lat, lon = np.asarray(lat, dtype=float), np.asarray(lon, dtype=float)
        cl = np.cos(lat)
        up_e = np.stack([cl * np.cos(lon), cl * np.sin(lon), np.sin(lat)], axis=-1)
        return np.einsum("ji,...j->...i", self.R_e_w, up_e)

    def R_w_n_at(self, p_w: np.ndarray) -> np.ndarray:
        """Rotation from the local NED frame at ``w`` positions ``(..., 3)`` to ``w``."""
        lat, lon, _ = self.to_geodetic(p_w)
        return self.R_w_n(lat, lon)

    def rph_from_R_w_b(self, p_w: np.ndarray, R_w_b: np.ndarray) -> np.ndarray:
        """NED roll, pitch, heading (rad) of body attitudes ``R_w_b`` at positions ``p_w``."""
        from georefine.geometry.rotation import rph_from_R_n_b

        R_n_w = np.swapaxes(self.R_w_n_at(p_w), -1, -2)
        return rph_from_R_n_b(R_n_w @ R_w_b)

    def R_w_b_from_rph(self, p_w: np.ndarray, rph: np.ndarray) -> np.ndarray:
        """Body attitudes ``R_w_b = R_w_n R_n_b`` from NED roll, pitch, heading (rad) at positions ``p_w``."""
        p_w, rph = np.broadcast_arrays(np.asarray(p_w, dtype=float), np.asarray(rph, dtype=float))
        shape = p_w.shape[:-1]
        lat, lon, _ = self.to_geodetic(p_w)
        out = np.empty((int(np.prod(shape, dtype=np.int64)), 3, 3))
        _R_w_b_kernel(np.ravel(lat), np.ravel(lon), np.ascontiguousarray(rph.reshape(-1, 3)), self.R_e_w, out)
        return out.reshape(shape + (3, 3))


@dataclass(frozen=True)
class OutputCRS:
    """Transformations between geodetic WGS84 (ellipsoidal heights) and an output CRS.

    Parameters
    ----------
    epsg
        EPSG code of the output CRS (e.g. 25832, ETRS89 / UTM zone 32N). A 2D projected CRS
        is promoted to 3D, so heights pass through as ellipsoidal heights. Note that the
        datum shift WGS84 -> ETRS89 is treated as identity (PROJ's default, ~0.5 m in 2025;
        the simulator and the pipeline use the same transformation, so results are
        consistent).
    """

    epsg: int
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def _transformers(self):
        if not self._cache:
            from pyproj import CRS, Transformer

            target = CRS.from_epsg(self.epsg)
            if not target.is_geographic and len(target.axis_info) == 2:
                target = target.to_3d()
            geodetic = CRS.from_epsg(4979)
            self._cache["crs"] = target
            self._cache["fwd"] = Transformer.from_crs(geodetic, target, always_xy=True)
            self._cache["inv"] = Transformer.from_crs(target, geodetic, always_xy=True)
        return self._cache

    @property
    def crs(self):
        """The (3D) ``pyproj.CRS`` of the output."""
        return self._transformers()["crs"]

    def from_geodetic(self, lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Output-CRS coordinates ``(..., 3)`` (easting, northing, ellipsoidal height) of geodetic (rad)."""
        t = self._transformers()["fwd"]
        x, y, z = t.transform(np.degrees(lon), np.degrees(lat), np.asarray(h, dtype=float))
        return np.stack([np.asarray(x), np.asarray(y), np.asarray(z)], axis=-1)

    def to_geodetic(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Geodetic latitude, longitude (rad) and ellipsoidal height (m) of output-CRS points."""
        xyz = np.asarray(xyz, dtype=float)
        t = self._transformers()["inv"]
        lon, lat, h = t.transform(xyz[..., 0], xyz[..., 1], xyz[..., 2])
        return np.radians(np.asarray(lat)), np.radians(np.asarray(lon)), np.asarray(h)

    def from_w(self, frame: LocalFrame, p_w: np.ndarray) -> np.ndarray:
        """Output-CRS coordinates of ``w`` positions."""
        return self.from_geodetic(*frame.to_geodetic(p_w))

    def to_w(self, frame: LocalFrame, xyz: np.ndarray) -> np.ndarray:
        """``w`` positions of output-CRS coordinates."""
        return frame.from_geodetic(*self.to_geodetic(xyz))

    def R_grid_enu(self, lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Rotations ``(n, 3, 3)`` from local east-north-up to the CRS's grid east-north-up.

        The grid is conformal, so true north maps to a direction rotated by the meridian convergence
        about the vertical; it is measured here by mapping a step of 1e-7 rad north through the CRS
        (no sign convention to get wrong). Identity for a geographic CRS.
        """
        from georefine.geometry.rotation import rot_z

        lat, lon, h = (np.atleast_1d(np.asarray(a, dtype=float)) for a in (lat, lon, h))
        if self.crs.is_geographic:
            return np.broadcast_to(np.eye(3), (len(lat), 3, 3)).copy()
        a = self.from_geodetic(lat, lon, h)
        b = self.from_geodetic(lat + 1e-7, lon, h)
        gamma = np.arctan2(b[:, 0] - a[:, 0], b[:, 1] - a[:, 1])  # true north's azimuth on the grid
        return rot_z(-gamma)  # ENU: a positive z rotation turns north (y) towards -x; true north -> azimuth gamma


@numba.njit(cache=True, nogil=True)
def _R_w_b_kernel(lat, lon, rph, R_e_w, out):  # pragma: no cover - compiled
    """``out[n] = R_e_w^T R_e_n(lat, lon) Rz(heading) Ry(pitch) Rx(roll)``, written out per point.

    Per-pulse attitudes of the simulator pass through here (30 M per ``corridor``); the numpy
    form needs two batched 3x3 products and half a dozen (N, 3, 3) temporaries.
    """
    A = np.empty((3, 3))
    B = np.empty((3, 3))
    for n in range(lat.shape[0]):
        sl, cl, so, co = np.sin(lat[n]), np.cos(lat[n]), np.sin(lon[n]), np.cos(lon[n])
        # R_e_n: columns north, east, down.
        A[0, 0], A[1, 0], A[2, 0] = -sl * co, -sl * so, cl
        A[0, 1], A[1, 1], A[2, 1] = -so, co, 0.0
        A[0, 2], A[1, 2], A[2, 2] = -cl * co, -cl * so, -sl
        sr, cr = np.sin(rph[n, 0]), np.cos(rph[n, 0])
        sp, cp = np.sin(rph[n, 1]), np.cos(rph[n, 1])
        sh, ch = np.sin(rph[n, 2]), np.cos(rph[n, 2])
        B[0, 0], B[0, 1], B[0, 2] = cp * ch, sr * sp * ch - cr * sh, cr * sp * ch + sr * sh
        B[1, 0], B[1, 1], B[1, 2] = cp * sh, sr * sp * sh + cr * ch, cr * sp * sh - sr * ch
        B[2, 0], B[2, 1], B[2, 2] = -sp, sr * cp, cr * cp
        for i in range(3):
            r0 = R_e_w[0, i] * A[0, 0] + R_e_w[1, i] * A[1, 0] + R_e_w[2, i] * A[2, 0]
            r1 = R_e_w[0, i] * A[0, 1] + R_e_w[1, i] * A[1, 1] + R_e_w[2, i] * A[2, 1]
            r2 = R_e_w[0, i] * A[0, 2] + R_e_w[1, i] * A[1, 2] + R_e_w[2, i] * A[2, 2]
            for j in range(3):
                out[n, i, j] = r0 * B[0, j] + r1 * B[1, j] + r2 * B[2, j]


@dataclass(frozen=True)
class GeoidHeights:
    """Gravity-related heights ``H = h - N(lat, lon)`` from a geoid grid, through PROJ.

    Parameters
    ----------
    grid
        Absolute path of the grid PROJ reads (GeoTIFF or GTX): the geoid undulation ``N`` in
        metres above the ellipsoid of the output CRS's datum, on a latitude/longitude grid.
    vertical_epsg
        EPSG code of the vertical CRS the grid realises (e.g. 7837 DHHN2016 height, 5703 NAVD88
        height): the vertical part of the compound CRS the final point clouds are written in.

    Notes
    -----
    The conversion is PROJ's ``vgridshift`` (bilinear interpolation in the grid), with the
    multiplier stated rather than left to its default: PROJ applies ``z_out = z_in + multiplier *
    grid value`` in the forward direction, so ``+multiplier=-1`` goes from ellipsoidal to
    gravity-related heights (-1 is also PROJ's default, kept from the PROJ.4 ``+geoidgrids``
    convention; tests/test_geoid.py checks the sign against a grid of known undulations).
    Everything inside Georefine stays ellipsoidal; only the heights written into the final
    point clouds pass through here (docs/ARCHITECTURE.md §3, "Sensor configuration").

    A point where the grid gives no value (outside it, or on its no-data cells) makes PROJ
    return ``inf``; that is an :class:`~georefine.errors.InputError` naming the grid and
    ``crs.geoid_grid``, never a height written as it is.
    """

    grid: str
    vertical_epsg: int
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def _transformer(self):
        if "t" not in self._cache:
            from pyproj import Transformer

            g = str(self.grid)
            g = f'"{g}"' if any(c.isspace() for c in g) else g  # a PROJ string value with blanks is quoted
            # Longitude and latitude in radians (``transform(..., radians=True)``), heights in metres.
            self._cache["t"] = Transformer.from_pipeline(f"+proj=pipeline +step +proj=vgridshift +grids={g} +multiplier=-1")
        return self._cache["t"]

    def check(self) -> None:
        """Raise ``ValueError`` (PROJ's reason) if PROJ cannot open the grid."""
        from pyproj.exceptions import ProjError

        try:
            self._transformer()
        except ProjError as exc:
            reason = str(exc).split("(Internal Proj Error: ")[-1].rstrip(")") or str(exc)
            raise ValueError(f"PROJ cannot use it as a vertical grid: {reason}") from None

    def vertical_crs(self):
        """The ``pyproj.CRS`` of ``vertical_epsg``."""
        from pyproj import CRS

        return CRS.from_epsg(int(self.vertical_epsg))

    def compound_crs(self, output: OutputCRS):
        """The compound ``pyproj.CRS`` of the final point clouds: the output CRS's horizontal CRS
        (its EPSG definition, 2-D) + the vertical CRS, e.g. EPSG:25832+7837."""
        from pyproj import CRS
        from pyproj.crs import CompoundCRS

        horizontal, vertical = CRS.from_epsg(int(output.epsg)), self.vertical_crs()
        if len(horizontal.axis_info) == 3:
            horizontal = horizontal.to_2d()
        return CompoundCRS(f"{horizontal.name} + {vertical.name}", [horizontal, vertical])

    def _shift(self, lat, lon, z, direction: str, what: str) -> np.ndarray:
        lat, lon = np.asarray(lat, dtype=float), np.asarray(lon, dtype=float)
        z = np.asarray(z, dtype=float)
        if z.size == 0:
            return z.copy()
        _, _, out = self._transformer().transform(lon, lat, z, radians=True, direction=direction)
        out = np.asarray(out, dtype=float)
        bad = ~np.isfinite(out)
        if np.any(bad):
            from georefine.errors import InputError

            k = int(np.argmax(bad.ravel()))
            lat_d, lon_d = np.degrees(np.broadcast_to(lat, z.shape).ravel()[k]), np.degrees(
                np.broadcast_to(lon, z.shape).ravel()[k])
            raise InputError(
                f"the geoid grid gives no undulation for {int(bad.sum()):,} of {z.size:,} {what}", path=self.grid,
                field="crs.geoid_grid", expected="a grid that covers every point",
                found=f"the first at latitude {lat_d:.6f} deg, longitude {lon_d:.6f} deg")
        return out

    def orthometric(self, lat: np.ndarray, lon: np.ndarray, h: np.ndarray, *, what: str = "points") -> np.ndarray:
        """``H = h - N(lat, lon)`` (m) of geodetic points (rad; ``h`` ellipsoidal, m).

        Raises :class:`~georefine.errors.InputError` where the grid has no value; ``what`` names
        the points in that message (e.g. ``"points of strip_1.laz"``)."""
        return self._shift(lat, lon, h, "FORWARD", what)

    def ellipsoidal(self, lat: np.ndarray, lon: np.ndarray, H: np.ndarray, *, what: str = "points") -> np.ndarray:
        """``h = H + N(lat, lon)`` (m): the inverse of :meth:`orthometric`."""
        return self._shift(lat, lon, H, "INVERSE", what)

    def orthometric_xyz(self, output: OutputCRS, xyz: np.ndarray, *, what: str = "points") -> np.ndarray:
        """Output-CRS points ``(n, 3)`` with ellipsoidal heights, their heights made gravity-related."""
        xyz = np.array(xyz, dtype=float)
        lat, lon, h = output.to_geodetic(xyz)
        xyz[..., 2] = self.orthometric(lat, lon, h, what=what)
        return xyz

    def ellipsoidal_xyz(self, output: OutputCRS, xyz: np.ndarray, *, what: str = "points") -> np.ndarray:
        """Output-CRS points ``(n, 3)`` with gravity-related heights, their heights made ellipsoidal.

        The horizontal coordinates do not depend on the height (a projected CRS's easting and
        northing, or latitude and longitude), so they give ``N`` directly."""
        xyz = np.array(xyz, dtype=float)
        lat, lon, H = output.to_geodetic(xyz)
        xyz[..., 2] = self.ellipsoidal(lat, lon, H, what=what)
        return xyz
