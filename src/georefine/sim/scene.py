"""Simulated world: a valley corridor as one triangle mesh in the mapping frame ``w``.

The scene is built directly in ``w`` (local east-north-up, metres). The corridor runs
north-south along the ``w`` y-axis, centred on ``x = 0``, from ``y = 0`` to
``y = length_m``; the terrain extends ``end_margin_m`` beyond both ends so that the
forward/backward views and the run-in find ground. Content (docs/ARCHITECTURE.md §6):

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

This module holds the public API (:class:`Material`, :class:`SceneConfig`,
:class:`ReferenceSurface`, :class:`Scene`, :func:`build_scene`) and the terrain (valley
height, road flattening, grid). The builders of the other scene content (buildings,
power line, vegetation, reference slabs; :class:`Material` and :class:`ReferenceSurface`
are defined there and re-exported here) are in :mod:`georefine.sim.scene_objects`; the
procedural albedo kernel is in :mod:`georefine.sim.texture`.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

import numba
import numpy as np
import trimesh
from pydantic import BaseModel, ConfigDict, Field, model_validator

from georefine.sim.scene_objects import (
    CorridorAxis,
    Material,
    MeshBuilder,
    ReferenceSurface,
    add_buildings,
    add_power_line,
    add_reference_surfaces,
    add_vegetation,
)
from georefine.sim.texture import albedo_kernel

log = logging.getLogger(__name__)

__all__ = ["Material", "SceneConfig", "ReferenceSurface", "Scene", "build_scene"]


class SceneConfig(BaseModel):
    """Parameters of the simulated corridor (lengths in metres, ``w`` axes).

    The defaults give the ``corridor`` scene: 3 km x 800 m, which covers the swath of a
    100-degree scanner at 160 m above ground (+-190 m) with margin.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    layout: Literal["corridor", "area"] = Field(
        "corridor", description="corridor: settlements and reference sites near the axis x = 0; area: spread over "
        "the whole width (a block of parallel strips)")
    length_m: float = Field(3000.0, gt=0, description="corridor length along +y from y=0")
    axis_m: tuple[tuple[float, float], ...] | None = Field(
        None, description="the corridor's axis as a polyline in w (x, y), with bends; default x = 0 from y = 0 to "
        "length_m. The valley, the power line, the villages and the reference sites follow it.")
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
        if self.axis_m is not None:
            v = np.asarray(self.axis_m, float)
            if len(v) < 2 or np.any(np.linalg.norm(np.diff(v, axis=0), axis=1) < 1.0):
                raise ValueError("axis_m needs at least two vertices at least 1 m apart")
            if np.any(np.abs(v[:, 0]) > self.width_m / 2 - 100.0) or np.any((v[:, 1] < 0) | (v[:, 1] > self.length_m)):
                raise ValueError(f"axis_m must lie within x ±{self.width_m / 2 - 100:.0f} m (width_m / 2 - 100) and "
                                 f"y 0-{self.length_m:.0f} m (length_m)")
        return self


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
    u = np.clip((np.abs(CorridorAxis(cfg).across(x, y)) - cfg.floor_half_width_m) / span, 0.0, 1.0)
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


# ------------------------------------------------------------------------ ray casting
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
        albedo_kernel(p, np.ascontiguousarray(self._cache["normal"][f]),
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
    axis = CorridorAxis(cfg)
    if cfg.layout == "area":  # villages anywhere in the block, clear of its border
        set_y = np.sort(rng.uniform(0.1, 0.9, n_set)) * L if n_set else np.zeros(0)
        set_x = rng.uniform(-1.0, 1.0, n_set) * max(half - cfg.settlement_radius_m - 40.0, 50.0)
        cross_ang = rng.uniform(-np.pi / 6, np.pi / 6, n_set)
    else:  # beside the axis, their cross roads across it
        set_s = np.sort(rng.uniform(0.1, 0.9, n_set)) * axis.total if n_set else np.zeros(0)
        set_x, set_y = axis.at(set_s, rng.choice([-1.0, 1.0], n_set) * rng.uniform(
            50.0, np.clip(half - 60, 60, 130), n_set))
        cross_ang = rng.uniform(-np.pi / 6, np.pi / 6, n_set) - axis.azimuth(set_s)
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
    b = MeshBuilder()
    b.add(V_t, F_t, np.where(on_road, Material.ROAD, Material.TERRAIN))

    def height(x, y):
        return _grid_height(gx, gy, Z, x, y)

    occupied = []  # (x, y, radius) of placed objects, for spacing

    def free(x, y, r, clear):
        if abs(x) + r > half - 5 or abs(axis.across(x, y)) - r < clear:
            return False
        if _road_distance(roads, np.array([x]), np.array([y]))[0][0] < hw + r + 2:
            return False
        return all(np.hypot(x - ox, y - oy) > r + orr + 3 for ox, oy, orr in occupied)

    refs = add_reference_surfaces(cfg, rng, b, height, free, occupied)
    pylons = add_power_line(cfg, b, height) if cfg.power_line else np.zeros((0, 3))
    n_b = add_buildings(cfg, rng, b, height, free, occupied, set_x, set_y, cross_ang)
    n_v = add_vegetation(cfg, rng, b, height, lambda x, y: _road_distance(roads, x, y)[0],
                      occupied)

    V, F, M = b.build()
    mesh = trimesh.Trimesh(vertices=V, faces=F, process=False, validate=False)
    ay = np.linspace(0, axis.total, int(np.ceil(axis.total / 10.0)) + 1)
    ax, ay = axis.at(ay)
    scene = Scene(mesh, M, tuple(refs), np.column_stack([ax, ay, height(ax, ay)]), pylons, cfg, int(rng.integers(1, 2**31 - 1)),
                  gx, gy, Z, roads)
    log.info("scene built in %.2f s: %d triangles, %d buildings, %d vegetation objects, "
             "%d pylons, %d reference surfaces", time.perf_counter() - t0, len(F), n_b, n_v,
             len(pylons), len(refs))
    return scene
