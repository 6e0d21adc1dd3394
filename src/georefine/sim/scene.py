"""Simulated world: a valley corridor as one triangle mesh in the mapping frame ``w``.

The scene is built directly in ``w`` (local east-north-up, metres). The corridor runs
north-south along the ``w`` y-axis, centred on ``x = 0``, from ``y = 0`` to
``y = length_m``; the terrain extends ``end_margin_m`` beyond both ends so that the
forward/backward views and the run-in find ground. Content (DESIGN.md §6):

* valley terrain: a regular grid (``grid_spacing_m``, two triangles per cell split along
  the south-west/north-east diagonal) of a valley floor with a gentle along-track slope,
  sides rising smoothly with distance from the axis, and a smooth random undulation
  (eight sinusoids, wavelengths 60-600 m);
* roads: one meandering main road along the valley and one straight cross road per
  settlement, flattened across their profile and marked with their own material;
* buildings in settlements (and a few scattered): boxes with vertical facades and gabled
  or flat roofs, aligned with the settlement's cross road or randomly oriented;
* a power line on the axis: lattice-like pylons (tapered legs, bracing, cross arms, peak)
  every ``pylon_spacing_m`` and five wires per span (hexagonal tubes, parabolic sag);
* vegetation: irregular ellipsoid crowns on trunks, cones on trunks, shrubs, partly in
  patches, kept out of the power-line clearance, roads, buildings and reference sites;
* reference surfaces: ``sum(reference_surfaces_per_site)`` horizontal square slabs
  (default 6 at 4 sites, paper 000 §3) raised ``reference_raise_m`` above the highest
  terrain under them. Each top is two triangles spanned by exactly the four surveyed
  corners, so it is exactly planar in ``w``.

Faces are wound counter-clockwise seen from outside (terrain normals point up); each face
has a :class:`Material`. :meth:`Scene.intersect` casts rays with Embree (embreex, float32)
on coordinates shifted by a scene offset and refines each range in float64 on the plane
of the hit triangle, so hit points lie on the triangle's plane to ~1e-9 m (and inside it
up to the float32 traversal, ~1e-4 m at the edges). :meth:`Scene.albedo`
is the seeded procedural texture followed by the LiDAR intensity and the camera.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from enum import IntEnum

import numba
import numpy as np
import trimesh
from pydantic import BaseModel, ConfigDict, Field, model_validator

from georefine.errors import ConfigError

log = logging.getLogger(__name__)

__all__ = ["Material", "SceneConfig", "ReferenceSurface", "Scene", "build_scene"]


class Material(IntEnum):
    """Material of a face (``Scene.face_material``, uint8)."""

    TERRAIN = 0  #: bare ground: grass and soil
    ROAD = 1  #: asphalt
    ROOF_TILE = 2  #: pitched roof of a gabled building
    ROOF_FLAT = 3  #: flat roof (gravel, membrane)
    FACADE = 4  #: vertical building walls and gables
    REFERENCE = 5  #: reference surface slab (bright paint)
    PYLON = 6  #: power-line pylon steel
    WIRE = 7  #: power-line conductor or earth wire
    VEGETATION = 8  #: tree crowns, trunks, shrubs


class SceneConfig(BaseModel):
    """Parameters of the simulated corridor (lengths in metres, ``w`` axes).

    The defaults give the ``corridor`` scene: 3 km x 800 m, which covers the swath of a
    100-degree scanner at 160 m above ground (+-190 m) with margin.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    length_m: float = Field(3000.0, gt=0, description="corridor length along +y from y=0")
    width_m: float = Field(800.0, ge=100, description="terrain width across the axis (x)")
    end_margin_m: float = Field(150.0, ge=0, description="terrain beyond both corridor ends")
    grid_spacing_m: float = Field(2.0, ge=0.25, le=20, description="terrain grid spacing")
    base_height_m: float = Field(0.0, description="valley floor height at y=0 (before undulation)")
    floor_slope_m_per_m: float = Field(0.01, ge=-0.2, le=0.2, description="along-track slope")
    floor_half_width_m: float = Field(150.0, ge=0, description="half width of the valley floor")
    side_rise_m: float = Field(
        80.0, ge=0, description="rise from the floor edge to the terrain edge (smoothstep)")
    undulation_m: float = Field(3.0, ge=0, description="RMS of the smooth random undulation")
    road_width_m: float = Field(7.0, gt=0, description="width of the roads")
    main_road_offset_m: float = Field(60.0, description="mean x of the main road")
    settlement_count: int = Field(3, ge=0, description="villages, each with a cross road")
    buildings_per_settlement: int = Field(14, ge=0, description="attempted; dropped if no room")
    settlement_radius_m: float = Field(80.0, gt=0)
    scattered_building_count: int = Field(6, ge=0, description="single buildings anywhere")
    flat_roof_fraction: float = Field(0.35, ge=0, le=1, description="others are gabled")
    power_line: bool = Field(True, description="pylons and wires on the axis")
    pylon_spacing_m: float = Field(300.0, gt=50, description="pylons centred on the corridor")
    pylon_height_m: float = Field(35.0, gt=10)
    wire_diameter_m: float = Field(0.03, gt=0, description="conductors and earth wire")
    wire_sag_m: float = Field(6.0, ge=0, description="sag at mid-span for a 300 m span")
    vegetation_per_ha: float = Field(12.0, ge=0, description="trees and shrubs per hectare")
    reference_surfaces_per_site: tuple[int, ...] = Field(
        (2, 1, 2, 1), description="surfaces at each site; sites spread evenly along y")
    reference_size_m: float = Field(5.0, gt=0.5, le=20, description="side of a square slab")
    reference_raise_m: float = Field(0.15, gt=0, le=1, description="top above highest ground")

    @model_validator(mode="after")
    def _check(self) -> "SceneConfig":
        if any(n < 1 for n in self.reference_surfaces_per_site):
            raise ValueError("reference_surfaces_per_site: every site needs >= 1 surface")
        if self.width_m / 2 < 40 + self.reference_size_m:
            raise ValueError("width_m too small for the reference sites (>= 100 m)")
        return self


@dataclass(frozen=True, eq=False)
class ReferenceSurface:
    """A surveyed horizontal reference surface (paper 000 §3).

    Attributes
    ----------
    surface_id : str
        ``"RS01"`` ..., numbered site by site along +y.
    site_id : str
        ``"SITE1"`` ...; several surfaces can share a site.
    corners_w : ndarray (4, 3)
        Surveyed corners in ``w`` [m], counter-clockwise seen from above; exact.
    normal_w : ndarray (3,)
        Unit upward normal in ``w``.
    face_ids : ndarray (2,) int64
        The two mesh faces forming the top, spanned by corners 0-1-2 and 0-2-3.
    """

    surface_id: str
    site_id: str
    corners_w: np.ndarray
    normal_w: np.ndarray
    face_ids: np.ndarray


# ----------------------------------------------------------------------------- terrain
def _road_distance(roads, x, y):
    """Distance [m] to the nearest road centreline and the closest point on it.

    ``roads`` is ``Scene.road_geometry``: the main road, then straight cross roads.
    """
    x0, amp, k, ph, _ = roads[0]
    xc = x0 + amp * np.sin(k * y + ph)
    dist = np.abs(x - xc) / np.sqrt(1 + (amp * k * np.cos(k * y + ph)) ** 2)
    cx, cy = xc, np.asarray(y, dtype=float) * 1.0
    for c0, c1, u0, u1, _ in roads[1:]:
        s, d = (x - c0) * u0 + (y - c1) * u1, np.abs((x - c0) * u1 - (y - c1) * u0)
        closer = d < dist
        dist = np.where(closer, d, dist)
        cx, cy = np.where(closer, c0 + s * u0, cx), np.where(closer, c1 + s * u1, cy)
    return dist, cx, cy


def _valley_height(x, y, cfg: SceneConfig, waves: np.ndarray):
    """Analytic terrain height [m] before road flattening; waves (J, 4) = kx, ky, amp, phase."""
    half = cfg.width_m / 2
    span = max(half - cfg.floor_half_width_m, 1e-9)
    u = np.clip((np.abs(x) - cfg.floor_half_width_m) / span, 0.0, 1.0)
    z = cfg.base_height_m + cfg.floor_slope_m_per_m * y + cfg.side_rise_m * u * u * (3 - 2 * u)
    for kx, ky, amp, ph in waves:
        z = z + amp * np.sin(kx * x + ky * y + ph)
    return z


def _grid_height(gx, gy, gz, x, y):
    """Height of the triangulated grid (cells split a-b-c / a-c-d), clamped at its border."""
    u = np.clip((np.asarray(x, float) - gx[0]) / (gx[1] - gx[0]), 0, len(gx) - 1)
    v = np.clip((np.asarray(y, float) - gy[0]) / (gy[1] - gy[0]), 0, len(gy) - 1)
    i = np.minimum(np.floor(u).astype(np.int64), len(gx) - 2)
    j = np.minimum(np.floor(v).astype(np.int64), len(gy) - 2)
    fu, fv = u - i, v - j
    za, zb, zc, zd = gz[j, i], gz[j, i + 1], gz[j + 1, i + 1], gz[j + 1, i]
    lower = za + fu * (zb - za) + fv * (zc - zb)  # triangle a-b-c (fu >= fv)
    upper = za + fv * (zd - za) + fu * (zc - zd)  # triangle a-c-d
    return np.where(fu >= fv, lower, upper)


def _smoothstep(u):
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3 - 2 * u)


# -------------------------------------------------------------------------- primitives
_SQUARE = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])  # ccw from above
_WALLS = [[i, (i + 1) % 4, 4 + (i + 1) % 4] for i in range(4)]
_WALLS += [[i, 4 + (i + 1) % 4, 4 + i] for i in range(4)]
# hexahedron: bottom quad 0-3, top quad 4-7 (same order); faces 2, 3 are the top
_HEX_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7]] + _WALLS)
# buildings: vertices 0-3 bottom, 4-7 eave, 8-9 ridge ends (gabled only), local x along
# the length; _B_ORDER maps [footprint 0-3, ridge ends, footprint 0-3] to vertex order
_B_ORDER = {True: [0, 1, 2, 3, 4, 5, 6, 7], False: [0, 1, 2, 3, 6, 7, 8, 9, 4, 5]}
_B_FACES = {  # flat: True, gabled: False -> faces, materials
    True: (np.array(_WALLS + [[4, 5, 6], [4, 6, 7]]),
           np.array([Material.FACADE] * 8 + [Material.ROOF_FLAT] * 2)),
    False: (np.array(_WALLS + [[4, 7, 8], [5, 6, 9], [4, 5, 9], [4, 9, 8], [6, 7, 8], [6, 8, 9]]),
            np.array([Material.FACADE] * 10 + [Material.ROOF_TILE] * 4)),
}
_SPHERE = trimesh.creation.icosphere(subdivisions=1)  # 42 vertices, 80 faces
_CONE_F = np.array([[i, (i + 1) % 8, 8] for i in range(8)]  # 8-sided cone: ring, apex 8,
                   + [[(i + 1) % 8, i, 9] for i in range(8)])  # base centre 9


def _orient(V, F, centre):
    """Flip faces whose normal points towards ``centre`` (K*, 3), per face."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    n = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", n, (a + b + c) / 3 - centre) < 0
    F = F.copy()
    F[flip] = F[flip][:, [0, 2, 1]]
    return F


def _instances(V, F):
    """Stack per-instance vertices (K, nv, 3) with a shared face template (nf, 3)."""
    K, nv = V.shape[:2]
    faces = (F[None] + (np.arange(K) * nv)[:, None, None]).reshape(-1, 3)
    return V.reshape(-1, 3), faces


def _convex(V, F):
    """Instances of convex/star-shaped bodies (K, nv, 3) oriented outward."""
    Vf, Ff = _instances(V, F)
    centre = np.repeat(V.mean(axis=1), len(F), axis=0)
    return Vf, _orient(Vf, Ff, centre)


def _bars(p0, p1, w0, w1):
    """Square-section bars (K hexahedra) from p0 to p1 with half widths w0, w1 [m]."""
    p0, p1 = np.atleast_2d(p0), np.atleast_2d(p1)
    e = p1 - p0
    e = e / np.linalg.norm(e, axis=1, keepdims=True)
    helper = np.where(np.abs(e[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(e, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(e, u)
    ring = _SQUARE[None, :, 0:1] * u[:, None] + _SQUARE[None, :, 1:2] * v[:, None]  # (K, 4, 3)
    w0 = np.broadcast_to(np.asarray(w0, float), len(p0))[:, None, None]
    w1 = np.broadcast_to(np.asarray(w1, float), len(p0))[:, None, None]
    return np.concatenate([p0[:, None] + w0 * ring, p1[:, None] + w1 * ring], axis=1)


class _Builder:
    """Collects vertices, faces and face materials of the scene parts."""

    def __init__(self):
        self.V, self.F, self.M, self.n_v, self.n_f = [], [], [], 0, 0

    def add(self, V, F, material) -> int:
        """Append a part; returns the index of its first face. material: int or (nf,)."""
        first = self.n_f
        self.V.append(np.asarray(V, float))
        self.F.append(np.asarray(F, np.int64) + self.n_v)
        self.M.append(np.broadcast_to(np.asarray(material, np.uint8), (len(F),)))
        self.n_v += len(V)
        self.n_f += len(F)
        return first

    def build(self):
        return np.concatenate(self.V), np.concatenate(self.F), np.concatenate(self.M)


# ---------------------------------------------------------------------------- texture
@numba.njit(cache=True)
def _hash(ix, iy, iz, seed):
    h = (ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791) ^ seed
    h = h & 0xFFFFFFFF
    h = ((h ^ (h >> 16)) * 0x45D9F3B) & 0xFFFFFFFF
    h = ((h ^ (h >> 16)) * 0x45D9F3B) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF) / 16777216.0


@numba.njit(cache=True)
def _value_noise(x, y, z, seed):
    fx, fy, fz = np.floor(x), np.floor(y), np.floor(z)
    ix, iy, iz = np.int64(fx), np.int64(fy), np.int64(fz)
    ux, uy, uz = x - fx, y - fy, z - fz
    ux, uy, uz = ux * ux * (3 - 2 * ux), uy * uy * (3 - 2 * uy), uz * uz * (3 - 2 * uz)
    acc = 0.0
    for dz in range(2):
        wz = uz if dz else 1 - uz
        for dy in range(2):
            wy = uy if dy else 1 - uy
            for dx in range(2):
                wx = ux if dx else 1 - ux
                acc += wx * wy * wz * _hash(ix + dx, iy + dy, iz + dz, seed)
    return acc


@numba.njit(cache=True)
def _fbm(x, y, z, wavelength, octaves, seed):
    """Multi-octave value noise in [0, 1] at the given base wavelength [m]."""
    acc, amp, norm, f = 0.0, 1.0, 0.0, 1.0 / wavelength
    for o in range(octaves):
        acc += amp * _value_noise(x * f, y * f, z * f, seed + 1013 * o)
        norm += amp
        amp *= 0.5
        f *= 2.0
    return acc / norm


@numba.njit(cache=True)
def _road_coords(x, y, roads):
    """Distance to the nearest road centreline, signed offset and along-road coordinate."""
    x0, amp, k, ph, hw = roads[0]
    q = np.sqrt(1 + (amp * k * np.cos(k * y + ph)) ** 2)
    off, along = (x - x0 - amp * np.sin(k * y + ph)) / q, y
    for r in range(1, roads.shape[0]):
        rx, ry = x - roads[r, 0], y - roads[r, 1]
        o = rx * roads[r, 3] - ry * roads[r, 2]
        if abs(o) < abs(off):
            off, along = o, rx * roads[r, 2] + ry * roads[r, 3]
    return abs(off), off, along, hw


@numba.njit(cache=True)
def _albedo_kernel(p, n, mat, seed, roads, out):
    for i in range(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        m = mat[i]
        if m <= 1:  # terrain or road: decided per point, so road edges are crisp
            dist, off, along, hw = _road_coords(x, y, roads)
            m = 1 if dist < hw else 0
        speck = _hash(np.int64(np.floor(x * 5)), np.int64(np.floor(y * 5)),
                      np.int64(np.floor(z * 5)), seed + 7)  # 0.2 m cells
        nh = np.sqrt(n[i, 0] ** 2 + n[i, 1] ** 2)
        u = (-n[i, 1] * x + n[i, 0] * y) / nh if nh > 1e-6 else x  # along a wall / roof
        if m == 0:  # grass and soil patches, clumps, speckle
            mix = _fbm(x, y, 0.0, 40.0, 4, seed)
            a = 0.17 + 0.22 * min(max((mix - 0.35) * 3.0, 0.0), 1.0)
            a += 0.10 * (_fbm(x, y, 0.0, 1.5, 3, seed + 11) - 0.5) + 0.05 * (speck - 0.5)
        elif m == 1:  # asphalt with patches, dashed centre line and edge lines
            a = 0.09 + 0.05 * _fbm(x, y, 0.0, 6.0, 3, seed + 21) + 0.03 * speck
            if abs(off) < 0.075 and along / 9.0 - np.floor(along / 9.0) < 1.0 / 3.0:
                a = 0.75
            elif hw - 0.45 < dist < hw - 0.3:
                a = 0.7
        elif m == 2:  # tiles: rows at constant height, joints, per-tile shade
            a = 0.16 + 0.10 * _fbm(x, y, z, 10.0, 2, seed + 31)
            a += 0.06 * _hash(np.int64(np.floor(u / 0.3)), np.int64(np.floor(z / 0.12)), 0,
                              seed + 33)
            if z / 0.12 - np.floor(z / 0.12) < 0.2:
                a -= 0.06
        elif m == 3:  # gravel / membrane
            a = 0.30 + 0.15 * _fbm(x, y, 0.0, 6.0, 3, seed + 41) + 0.04 * (speck - 0.5)
        elif m == 4:  # plaster with dark windows on a 3 m grid
            a = 0.45 + 0.30 * _fbm(x, y, z, 30.0, 2, seed + 51) + 0.03 * (speck - 0.5)
            fu, fz = u / 3.0 - np.floor(u / 3.0), z / 3.0 - np.floor(z / 3.0)
            if 0.3 < fu < 0.7 and 0.35 < fz < 0.75:
                a = 0.10 + 0.04 * speck
        elif m == 5:  # bright paint
            a = 0.84 + 0.02 * (speck - 0.5)
        elif m == 6:  # galvanised steel
            a = 0.28 + 0.08 * _fbm(x, y, z, 2.0, 2, seed + 61)
        elif m == 7:  # weathered aluminium conductor
            a = 0.20
        else:  # foliage
            a = 0.10 + 0.12 * _fbm(x, y, z, 0.8, 3, seed + 81)
            a += 0.05 * _fbm(x, y, z, 20.0, 1, seed + 83)
        out[i] = min(max(a, 0.05), 0.9)


@numba.njit(cache=True, nogil=True)
def _refine_hits(o, d, prim, v0, normal, max_range, range_out, face_out):
    """Range along d to the plane of the hit face (float64); misses get inf and -1."""
    for i in range(o.shape[0]):
        f = prim[i]
        range_out[i], face_out[i] = np.inf, -1
        if f < 0:
            continue
        den = normal[f, 0] * d[i, 0] + normal[f, 1] * d[i, 1] + normal[f, 2] * d[i, 2]
        num = (normal[f, 0] * (v0[f, 0] - o[i, 0]) + normal[f, 1] * (v0[f, 1] - o[i, 1])
               + normal[f, 2] * (v0[f, 2] - o[i, 2]))
        if den != 0.0:
            t = num / den
            if 0.0 < t <= max_range:
                range_out[i], face_out[i] = t, f


# ------------------------------------------------------------------------------ scene
@dataclass(frozen=True, eq=False)
class Scene:
    """The simulated world in ``w``; build it with :func:`build_scene`.

    Attributes
    ----------
    mesh : trimesh.Trimesh
        All surfaces, vertices in ``w`` [m] (not processed: face order is fixed).
    face_material : ndarray (M,) uint8
        :class:`Material` of each face.
    reference_surfaces : tuple of ReferenceSurface
        The surveyed reference surfaces, ordered along +y.
    axis_w : ndarray (K, 3)
        Corridor axis for the flight planner: ``x = 0``, ``y`` from 0 to ``length_m``
        every 10 m, ``z`` = bare terrain height [m].
    pylon_bases_w : ndarray (P, 3)
        Pylon foot points on the terrain [m].
    config : SceneConfig
    texture_seed : int
        Seed of the procedural albedo (drawn from the build generator).
    grid_x, grid_y : ndarray (nx,), (ny,)
        Terrain grid coordinates [m]; ``grid_z`` (ny, nx) the vertex heights [m].
    road_geometry : ndarray (1 + K, 5)
        Road centrelines: main road ``[x0, amp, k, phase, half_width]`` with
        ``x = x0 + amp sin(k y + phase)``, then cross roads ``[cx, cy, ux, uy, half_width]``
        (a point and a unit direction). Road faces are those whose centroid lies on a
        road; the albedo decides asphalt per point, so road edges look crisp.
    """

    mesh: trimesh.Trimesh
    face_material: np.ndarray
    reference_surfaces: tuple
    axis_w: np.ndarray
    pylon_bases_w: np.ndarray
    config: SceneConfig
    texture_seed: int
    grid_x: np.ndarray
    grid_y: np.ndarray
    grid_z: np.ndarray
    road_geometry: np.ndarray
    _cache: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self):
        if self.face_material.shape != (len(self.mesh.faces),):
            raise ValueError("face_material must have one entry per face")
        tri = np.asarray(self.mesh.vertices, float)[np.asarray(self.mesh.faces)]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        self._cache["v0"] = tri[:, 0].copy()
        self._cache["normal"] = n / np.where(norm > 0, norm, 1.0)
        lo, hi = tri.reshape(-1, 3).min(axis=0), tri.reshape(-1, 3).max(axis=0)
        self._cache["offset"] = np.round((lo + hi) / 2)
        self._cache["lock"] = threading.Lock()

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_cache"] = {}
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self.__post_init__()

    # ------------------------------------------------------------------ geometry queries
    def terrain_height(self, x, y):
        """Bare terrain height [m] at ``w`` coordinates x, y [m] (any equal shapes).

        Exactly the triangulated terrain surface (piecewise linear); positions outside the
        grid are clamped to its border. Buildings, vegetation etc. are not included.
        """
        return _grid_height(self.grid_x, self.grid_y, self.grid_z, x, y)

    def surface_normal(self, face_id):
        """Unit outward normals (N, 3) in ``w`` of faces ``face_id`` (N,); NaN for -1."""
        face_id = np.asarray(face_id, np.int64)
        n = self._cache["normal"][np.maximum(face_id, 0)]
        return np.where((face_id >= 0)[..., None], n, np.nan)

    def _embree(self):
        with self._cache["lock"]:
            if "embree" not in self._cache:
                from embreex import rtcore_scene
                from embreex.mesh_construction import TriangleMesh

                t0 = time.perf_counter()
                emb = rtcore_scene.EmbreeScene()
                # float32 inside Embree: coordinates relative to the scene centre
                vertices = np.asarray(self.mesh.vertices) - self._cache["offset"]
                TriangleMesh(scene=emb, vertices=vertices.astype(np.float32),
                             indices=np.asarray(self.mesh.faces, np.int32))
                emb.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))  # commit (BVH)
                self._cache["embree"] = emb
                log.debug("Embree BVH built in %.2f s", time.perf_counter() - t0)
            return self._cache["embree"]

    def intersect(self, origins_w, directions_w, max_range_m=np.inf, n_threads=None):
        """First hit of rays with the scene.

        Parameters
        ----------
        origins_w : ndarray (N, 3)
            Ray origins in ``w`` [m].
        directions_w : ndarray (N, 3)
            Ray directions in ``w`` (normalised here).
        max_range_m : float
            Hits farther than this are misses.
        n_threads : int, optional
            Threads for Embree (it releases the GIL); default ``min(cpu_count, 4)``.

        Returns
        -------
        range_m : ndarray (N,) float64
            Distance from the origin along the unit direction [m], ``inf`` for misses.
            Refined in float64 on the plane of the hit triangle.
        face_id : ndarray (N,) int64
            Index of the hit face, -1 for misses.
        """
        o = np.ascontiguousarray(origins_w, np.float64).reshape(-1, 3)
        d = np.ascontiguousarray(directions_w, np.float64).reshape(-1, 3)
        if o.shape != d.shape:
            raise ValueError(f"origins {o.shape} and directions {d.shape} differ")
        emb, n = self._embree(), len(o)
        range_m, face_id = np.empty(n), np.empty(n, np.int64)
        tfar = None if not np.isfinite(max_range_m) else float(max_range_m) + 1.0
        v0, normal, offset = self._cache["v0"], self._cache["normal"], self._cache["offset"]

        def work(a, b):  # Embree and the numba kernel release the GIL
            d_unit = d[a:b] / np.linalg.norm(d[a:b], axis=1, keepdims=True)
            prim = emb.run((o[a:b] - offset).astype(np.float32), d_unit.astype(np.float32),
                           dists=tfar)
            _refine_hits(o[a:b], d_unit, prim, v0, normal, float(max_range_m), range_m[a:b],
                         face_id[a:b])

        n_threads = n_threads or min(os.cpu_count() or 1, 4)
        n_parts = max(1, min(n_threads, n // 20_000))
        if n_parts == 1:
            work(0, n)
        else:
            cuts = np.linspace(0, n, n_parts + 1).astype(int)
            with ThreadPoolExecutor(n_parts) as pool:
                list(pool.map(work, cuts[:-1], cuts[1:]))
        return range_m, face_id

    def albedo(self, points_w, face_ids):
        """Procedural diffuse albedo in [0.05, 0.9] of surface points.

        Material base value (:class:`Material`) modulated by seeded multi-octave value
        noise (wavelengths 0.8-40 m) and small-scale patterns (0.2 m speckle, roof-tile
        rows, facade windows) so that rendered images have texture for matching.
        Deterministic given the scene seed.

        Parameters
        ----------
        points_w : ndarray (N, 3)
            Points on the surface in ``w`` [m].
        face_ids : ndarray (N,)
            Faces the points lie on (>= 0).
        """
        p = np.ascontiguousarray(points_w, np.float64).reshape(-1, 3)
        f = np.asarray(face_ids, np.int64).reshape(-1)
        if len(f) != len(p) or (len(f) and f.min() < 0):
            raise ValueError("albedo needs one valid face id (>= 0) per point")
        out = np.empty(len(p))
        _albedo_kernel(p, np.ascontiguousarray(self._cache["normal"][f]),
                       np.ascontiguousarray(self.face_material[f]), self.texture_seed,
                       self.road_geometry, out)
        return out


# ------------------------------------------------------------------------------ build
def build_scene(cfg: SceneConfig, rng: np.random.Generator) -> Scene:
    """Build the seeded corridor scene (see the module docstring).

    Parameters
    ----------
    cfg : SceneConfig
    rng : numpy.random.Generator
        The only source of randomness: equal seeds give identical scenes.
    """
    t0 = time.perf_counter()
    L, half = cfg.length_m, cfg.width_m / 2
    lam = np.exp(rng.uniform(np.log(60.0), np.log(600.0), 8))
    ang = rng.uniform(0, 2 * np.pi, 8)
    amp = lam / np.sqrt(np.sum(lam**2) / 2) * cfg.undulation_m  # RMS of the sum = undulation_m
    waves = np.column_stack([2 * np.pi / lam * np.cos(ang), 2 * np.pi / lam * np.sin(ang),
                             amp, rng.uniform(0, 2 * np.pi, 8)])

    # settlements and roads (cross road through each settlement centre)
    n_set = cfg.settlement_count
    set_y = np.sort(rng.uniform(0.1, 0.9, n_set)) * L if n_set else np.zeros(0)
    set_x = rng.choice([-1.0, 1.0], n_set) * rng.uniform(50.0, np.clip(half - 60, 60, 130), n_set)
    cross_ang = rng.uniform(-np.pi / 6, np.pi / 6, n_set)
    hw = cfg.road_width_m / 2  # main road x = x0 + 15 sin(2 pi y / 900 m + phase)
    main = [cfg.main_road_offset_m, 15.0, 2 * np.pi / 900.0, rng.uniform(0, 2 * np.pi), hw]
    roads = np.vstack([main, np.column_stack([set_x, set_y, np.cos(cross_ang), np.sin(cross_ang),
                                              np.full(n_set, hw)])])

    # terrain grid: analytic valley, then roads flattened across their profile
    nx = int(round(cfg.width_m / cfg.grid_spacing_m)) + 1
    ny = int(round((L + 2 * cfg.end_margin_m) / cfg.grid_spacing_m)) + 1
    gx = np.linspace(-half, half, nx)
    gy = np.linspace(-cfg.end_margin_m, L + cfg.end_margin_m, ny)
    X, Y = np.meshgrid(gx, gy)
    Z = _valley_height(X, Y, cfg, waves)
    dist, cx, cy = _road_distance(roads, X, Y)
    w = 1 - _smoothstep((dist - hw) / 4.0)
    Z = Z + w * (_valley_height(cx, cy, cfg, waves) - Z)
    ii = (np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
    F_t = np.concatenate([np.column_stack([ii, ii + 1, ii + nx + 1]),
                          np.column_stack([ii, ii + nx + 1, ii + nx])])
    V_t = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    cen = V_t[F_t].mean(axis=1)
    on_road = _road_distance(roads, cen[:, 0], cen[:, 1])[0] < hw
    b = _Builder()
    b.add(V_t, F_t, np.where(on_road, Material.ROAD, Material.TERRAIN))

    def height(x, y):
        return _grid_height(gx, gy, Z, x, y)

    occupied = []  # (x, y, radius) of placed objects, for spacing

    def free(x, y, r, clear):
        if abs(x) + r > half - 5 or abs(x) - r < clear:
            return False
        if _road_distance(roads, np.array([x]), np.array([y]))[0][0] < hw + r + 2:
            return False
        return all(np.hypot(x - ox, y - oy) > r + orr + 3 for ox, oy, orr in occupied)

    refs = _reference_surfaces(cfg, rng, b, height, free, occupied)
    pylons = _power_line(cfg, b, height) if cfg.power_line else np.zeros((0, 3))
    n_b = _buildings(cfg, rng, b, height, free, occupied, set_x, set_y, cross_ang)
    n_v = _vegetation(cfg, rng, b, height, roads, occupied)

    V, F, M = b.build()
    mesh = trimesh.Trimesh(vertices=V, faces=F, process=False, validate=False)
    ay = np.linspace(0, L, int(np.ceil(L / 10.0)) + 1)
    axis = np.column_stack([np.zeros_like(ay), ay, height(np.zeros_like(ay), ay)])
    scene = Scene(mesh, M, tuple(refs), axis, pylons, cfg, int(rng.integers(1, 2**31 - 1)),
                  gx, gy, Z, roads)
    log.info("scene built in %.2f s: %d triangles, %d buildings, %d vegetation objects, "
             "%d pylons, %d reference surfaces", time.perf_counter() - t0, len(F), n_b, n_v,
             len(pylons), len(refs))
    return scene


def _reference_surfaces(cfg, rng, b, height, free, occupied):
    """Horizontal square slabs at ``len(reference_surfaces_per_site)`` sites."""
    L, s = cfg.length_m, cfg.reference_size_m
    n_sites, refs, k = len(cfg.reference_surfaces_per_site), [], 0
    pylon_y = _pylon_y(cfg)
    for site, n_surf in enumerate(cfg.reference_surfaces_per_site):
        for _ in range(200):  # site centre on open ground near the axis
            y = L * (site + 0.5 + rng.uniform(-0.25, 0.25)) / n_sites
            x = rng.choice([-1.0, 1.0]) * rng.uniform(25.0, 90.0)
            if free(x, y, 8.0 * n_surf, 15.0) and np.all(np.abs(pylon_y - y) > 20):
                break
        else:
            raise ConfigError(f"no free place for reference site {site + 1}; enlarge the scene",
                              field="reference_surfaces_per_site")
        for j in range(n_surf):
            for _ in range(100):
                cx, cy = x, y
                if j > 0:
                    dist, ang = rng.uniform(8, 14), rng.uniform(0, 2 * np.pi)
                    cx, cy = x + dist * np.cos(ang), y + dist * np.sin(ang)
                if free(cx, cy, s * 0.75, 15.0):
                    break
            else:
                raise ConfigError(f"no free place for a surface at reference site {site + 1}",
                                  field="reference_surfaces_per_site")
            yaw = rng.uniform(0, np.pi / 2)
            c, sn = np.cos(yaw), np.sin(yaw)
            loc = _SQUARE * s / 2
            xy = np.column_stack([cx + c * loc[:, 0] - sn * loc[:, 1],
                                  cy + sn * loc[:, 0] + c * loc[:, 1]])
            g = np.linspace(0, 1, 11)
            uu, vv = np.meshgrid(g, g)
            fx = xy[0, 0] + uu * (xy[1, 0] - xy[0, 0]) + vv * (xy[3, 0] - xy[0, 0])
            fy = xy[0, 1] + uu * (xy[1, 1] - xy[0, 1]) + vv * (xy[3, 1] - xy[0, 1])
            ground = height(fx, fy)
            top = float(np.round(ground.max() + cfg.reference_raise_m, 3))
            corners = np.column_stack([xy, np.full(4, top)])
            hexa = np.concatenate([np.column_stack([xy, np.full(4, ground.min() - 0.3)]), corners])
            F = _orient(hexa, _HEX_FACES, hexa.mean(axis=0)[None])
            first = b.add(hexa, F, Material.REFERENCE)
            k += 1
            refs.append(ReferenceSurface(f"RS{k:02d}", f"SITE{site + 1}", corners,
                                         np.array([0.0, 0.0, 1.0]), first + np.array([2, 3])))
            occupied.append((cx, cy, s * 0.75))
    return refs


def _pylon_y(cfg):
    n = int(np.floor(cfg.length_m / cfg.pylon_spacing_m))
    return (cfg.length_m - n * cfg.pylon_spacing_m) / 2 + cfg.pylon_spacing_m * np.arange(n + 1)


def _power_line(cfg, b, height):
    """Pylons on the axis and five wires per span; returns the pylon foot points."""
    H, ys = cfg.pylon_height_m, _pylon_y(cfg)
    z0 = height(np.zeros_like(ys), ys)
    a, top, bt = 0.09 * H, 0.85 * H, 0.025 * H
    arms = [(0.70 * H, 7.0), (0.82 * H, 5.0)]
    bars = []
    for y, zg in zip(ys, z0):
        base = np.column_stack([a * _SQUARE, np.full(4, zg - 0.5)]) + [0, y, 0]
        head = np.column_stack([bt * _SQUARE, np.full(4, zg + top)]) + [0, y, 0]
        bars.append(_bars(base, head, 0.18, 0.12))  # legs
        for f in (0.2, 0.4, 0.6):  # horizontal bracing between the legs
            lev = base + f * (head - base)
            bars.append(_bars(lev, np.roll(lev, -1, axis=0), 0.07, 0.07))
        for za, span in arms:
            bars.append(_bars([[-span, y, zg + za]], [[span, y, zg + za]], 0.3, 0.3))
        bars.append(_bars([[0, y, zg + top]], [[0, y, zg + H]], 1.3 * bt, 0.15))  # peak
    hexa = np.concatenate(bars)
    Vp, Fp = _convex(hexa, _HEX_FACES)
    b.add(Vp, Fp, Material.PYLON)
    # wires: attachment points at the arm ends and the peak, parabolic sag per span
    att = np.array([[-7.0, 0.70 * H - 0.3], [7.0, 0.70 * H - 0.3], [-5.0, 0.82 * H - 0.3],
                    [5.0, 0.82 * H - 0.3], [0.0, H]])
    r, ring = cfg.wire_diameter_m / 2, np.arange(6) * np.pi / 3
    for k in range(len(ys) - 1):
        span = ys[k + 1] - ys[k]
        S = max(8, int(np.ceil(span / 4.0))) + 1
        s = np.linspace(0, 1, S)
        A = np.column_stack([att[:, 0], np.full(5, ys[k]), z0[k] + att[:, 1]])
        B = np.column_stack([att[:, 0], np.full(5, ys[k + 1]), z0[k + 1] + att[:, 1]])
        P = A[:, None] + s[None, :, None] * (B - A)[:, None]
        P[..., 2] -= cfg.wire_sag_m * (span / 300.0) ** 2 * 4 * s * (1 - s)  # (5, S, 3)
        T = np.gradient(P, axis=1)
        T /= np.linalg.norm(T, axis=2, keepdims=True)
        N1 = np.cross(T, [1.0, 0.0, 0.0])
        N1 /= np.linalg.norm(N1, axis=2, keepdims=True)
        N2 = np.cross(T, N1)
        Vw = (P[:, :, None] + r * (np.cos(ring)[:, None] * N1[:, :, None]
                                   + np.sin(ring)[:, None] * N2[:, :, None])).reshape(-1, 3)
        q = np.arange(S - 1)[:, None] * 6 + np.arange(6)[None, :]
        q1 = np.arange(S - 1)[:, None] * 6 + (np.arange(6)[None, :] + 1) % 6
        quad = np.concatenate([np.stack([q, q1, q1 + 6], -1), np.stack([q, q1 + 6, q + 6], -1)],
                              axis=1).reshape(-1, 3)
        Fw = (quad[None] + (np.arange(5) * S * 6)[:, None, None]).reshape(-1, 3)
        ring_centre = P.reshape(-1, 3)[Fw[:, 0] // 6]  # of each face's first vertex
        b.add(Vw, _orient(Vw, Fw, ring_centre), Material.WIRE)
    return np.column_stack([np.zeros_like(ys), ys, z0])


def _buildings(cfg, rng, b, height, free, occupied, set_x, set_y, cross_ang):
    """Gabled and flat-roofed buildings in settlements and scattered; returns the count."""
    specs = []  # centre x, y, yaw, length, width, eave, ridge (0 = flat)
    todo = [(sx, sy, ca, cfg.settlement_radius_m) for sx, sy, ca in zip(set_x, set_y, cross_ang)
            for _ in range(cfg.buildings_per_settlement)]
    todo += [(None, None, None, None)] * cfg.scattered_building_count
    for sx, sy, ca, rad in todo:
        flat = rng.random() < cfg.flat_roof_fraction
        length, width = rng.uniform(10, 24), rng.uniform(7, 13)
        eave = rng.uniform(5, 12) if flat else rng.uniform(3.5, 8)
        ridge = 0.0 if flat else width / 2 * np.tan(np.radians(rng.uniform(25, 45)))
        r = 0.5 * np.hypot(length, width)
        for _ in range(30):
            if sx is None:
                x, y = rng.uniform(-cfg.width_m / 2, cfg.width_m / 2), rng.uniform(0, cfg.length_m)
                yaw = rng.uniform(0, np.pi)
            else:
                ang, rr = rng.uniform(0, 2 * np.pi), rad * np.sqrt(rng.random())
                x, y = sx + rr * np.cos(ang), sy + rr * np.sin(ang)
                if rng.random() < 0.6:  # aligned with the settlement's cross road
                    yaw = ca + rng.choice([0, np.pi / 2]) + rng.normal(0, 0.05)
                else:
                    yaw = rng.uniform(0, np.pi)
            if 0 <= y <= cfg.length_m and free(x, y, r, 22.0):
                occupied.append((x, y, r))
                specs.append((x, y, yaw, length, width, eave, ridge))
                break
    if not specs:
        return 0
    S = np.array(specs)
    for flat in (True, False):
        sel = S[(S[:, 6] == 0) == flat]
        if not len(sel):
            continue
        x, y, yaw, ln, wd, eave, ridge = sel.T
        lx, ly = _SQUARE[None, :, 0] * ln[:, None] / 2, _SQUARE[None, :, 1] * wd[:, None] / 2
        if not flat:
            lx = np.concatenate([lx, ln[:, None] / 2 * [[-1, 1]]], axis=1)
            ly = np.concatenate([ly, np.zeros((len(sel), 2))], axis=1)
        c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        gx, gy = x[:, None] + c * lx - s * ly, y[:, None] + s * lx + c * ly
        ground = height(gx[:, :4], gy[:, :4])
        zb, ze = ground.min(axis=1) - 1.0, ground.max(axis=1) + eave
        z = np.concatenate([np.repeat(zb[:, None], 4, 1), np.repeat(ze[:, None], 4, 1)], axis=1)
        if not flat:
            z = np.concatenate([z, np.repeat((ze + ridge)[:, None], 2, 1)], axis=1)
        V = np.stack([np.concatenate([gx, gx[:, :4]], 1)[:, _B_ORDER[flat]],
                      np.concatenate([gy, gy[:, :4]], 1)[:, _B_ORDER[flat]], z], axis=-1)
        F, mat = _B_FACES[flat]
        Vb, Fb = _convex(V, F)
        b.add(Vb, Fb, np.tile(mat, len(sel)))
    return len(S)



def _vegetation(cfg, rng, b, height, roads, occupied):
    """Trees (ellipsoid or cone crowns on trunks) and shrubs; returns the count."""
    half = cfg.width_m / 2
    y_lo, y_hi = -cfg.end_margin_m, cfg.length_m + cfg.end_margin_m
    n = int(round(cfg.vegetation_per_ha * cfg.width_m * (y_hi - y_lo) / 1e4))
    if n == 0:
        return 0
    m = 3 * n  # candidates: 60 % in patches, 40 % uniform
    n_patch = max(1, int(np.ceil(n / 250)))
    pc = np.column_stack([rng.uniform(-half, half, n_patch), rng.uniform(y_lo, y_hi, n_patch)])
    k = rng.integers(0, n_patch, m)
    cand = np.where((rng.random(m) < 0.6)[:, None], pc[k] + rng.normal(0, 35.0, (m, 2)),
                    np.column_stack([rng.uniform(-half, half, m), rng.uniform(y_lo, y_hi, m)]))
    x, y = cand.T
    ok = (np.abs(x) > 15) & (np.abs(x) < half - 3) & (y > y_lo + 3) & (y < y_hi - 3)
    ok &= _road_distance(roads, x, y)[0] > roads[0, 4] + 3
    if occupied:
        occ = np.array(occupied)
        gap = np.hypot(x[:, None] - occ[:, 0], y[:, None] - occ[:, 1]) - occ[:, 2]
        ok &= np.all(gap > 4, axis=1)
    x, y = x[ok][:n], y[ok][:n]
    n = len(x)
    g = height(x, y)
    kind = rng.choice(3, n, p=[0.45, 0.3, 0.25])  # deciduous, conifer, shrub
    h = np.where(kind == 0, rng.uniform(6, 16, n), np.where(kind == 1, rng.uniform(8, 22, n),
                                                             rng.uniform(0.8, 2.0, n)))
    tree = kind < 2
    ht = np.where(kind == 0, 0.4, 0.25)[tree] * h[tree]
    trunks = _bars(np.column_stack([x[tree], y[tree], g[tree] - 0.3]),
                   np.column_stack([x[tree], y[tree], g[tree] + ht]), 0.15, 0.12)
    Vt, Ft = _convex(trunks, _HEX_FACES)
    b.add(Vt, Ft, Material.VEGETATION)
    ell = kind != 1  # ellipsoid crowns and shrubs
    rh = np.where(kind == 0, rng.uniform(0.25, 0.4, n) * h, rng.uniform(0.8, 2.0, n))[ell]
    rv = np.where(kind == 0, 0.35 * h, 0.5 * h)[ell]
    zc = np.where(kind == 0, g + 0.65 * h, g + 0.3 * h)[ell]
    sv = np.asarray(_SPHERE.vertices)
    jit = rng.uniform(0.8, 1.2, (ell.sum(), len(sv), 1))
    psi = rng.uniform(0, 2 * np.pi, ell.sum())[:, None]
    lx, ly = sv[None, :, 0] * rh[:, None], sv[None, :, 1] * rh[:, None] * 0.85
    Ve = jit * np.stack([np.cos(psi) * lx - np.sin(psi) * ly, np.sin(psi) * lx + np.cos(psi) * ly,
                         sv[None, :, 2] * rv[:, None]], -1)
    centre = np.column_stack([x[ell], y[ell], zc])
    Ve, Fe = _instances(Ve + centre[:, None], np.asarray(_SPHERE.faces))
    b.add(Ve, _orient(Ve, Fe, np.repeat(centre, len(_SPHERE.faces), 0)), Material.VEGETATION)
    con = kind == 1
    nc = con.sum()
    rb = rng.uniform(0.2, 0.3, nc) * h[con] * rng.uniform(0.85, 1.15, (8, nc))
    th = np.arange(8) * np.pi / 4 + rng.uniform(0, np.pi / 4, nc)[:, None]
    zb = g[con] + 0.2 * h[con]
    ringv = np.stack([x[con][:, None] + rb.T * np.cos(th), y[con][:, None] + rb.T * np.sin(th),
                      np.repeat(zb[:, None], 8, 1)], -1)
    apex = np.column_stack([x[con], y[con], g[con] + h[con]])[:, None]
    centre = np.column_stack([x[con], y[con], zb])[:, None]
    Vc, Fc = _convex(np.concatenate([ringv, apex, centre], axis=1), _CONE_F)
    b.add(Vc, Fc, Material.VEGETATION)
    return n
