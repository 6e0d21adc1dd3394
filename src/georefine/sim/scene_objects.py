"""Content of the simulated scene: what is in the world.

Builders that add the scene's objects to one triangle mesh in the mapping frame ``w``
(see :mod:`georefine.sim.scene` for the corridor layout and :func:`build_scene
<georefine.sim.scene.build_scene>`, which calls them with the seeded generator):

* :class:`Material` of a face and :class:`ReferenceSurface`, the surveyed slabs (both
  re-exported by :mod:`georefine.sim.scene`, their public home);
* small geometry helpers: face templates (hexahedra, buildings, sphere, cone), outward
  orientation of faces, instancing, square-section bars, and ``MeshBuilder``, which collects
  vertices, faces and face materials;
* the objects: reference-surface slabs, pylons and wires of the power line, gabled and
  flat-roofed buildings, vegetation (trees and shrubs).

The builders draw from the generator in a fixed order (the order :func:`build_scene
<georefine.sim.scene.build_scene>` calls them in); terrain heights, free-space tests and
road distances come in as callables, so this module does not depend on the terrain.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import trimesh

from georefine.errors import ConfigError


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


class MeshBuilder:
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


# ------------------------------------------------------------------------------- axis
class CorridorAxis:
    """The corridor's axis in ``w``: ``scene.axis_m`` (a polyline), by default ``x = 0`` from
    ``y = 0`` to ``length_m``. Its first and last segments extend without end, so that the
    distance across a straight axis is exactly ``x``."""

    def __init__(self, cfg):
        v = np.array(cfg.axis_m if cfg.axis_m is not None else [(0.0, 0.0), (0.0, cfg.length_m)], float)
        d = np.diff(v, axis=0)
        self.segment = np.linalg.norm(d, axis=1)
        self.u = d / self.segment[:, None]
        self.n = np.column_stack([self.u[:, 1], -self.u[:, 0]])  # to the right of the direction
        self.v, self.s0 = v, np.concatenate([[0.0], np.cumsum(self.segment)])
        self.total = float(self.s0[-1])

    def across(self, x, y):
        """Signed distance (m, positive to the right) of points from the nearest segment."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        best, off = None, None
        last = len(self.segment) - 1
        for k in range(last + 1):
            dx, dy = x - self.v[k, 0], y - self.v[k, 1]
            t = dx * self.u[k, 0] + dy * self.u[k, 1]
            o = dx * self.n[k, 0] + dy * self.n[k, 1]
            beyond = np.clip(t, -np.inf if k == 0 else 0.0, np.inf if k == last else self.segment[k]) - t
            dist = np.hypot(beyond, o)
            if best is None:
                best, off = dist, o
            else:
                closer = dist < best
                best, off = np.where(closer, dist, best), np.where(closer, o, off)
        return off

    def segment_of(self, s):
        return np.clip(np.searchsorted(self.s0, s, side="right") - 1, 0, len(self.segment) - 1)

    def at(self, s, offset=0.0):
        """Points (x, y) at arc length ``s`` and signed distance ``offset`` across."""
        k = self.segment_of(s)
        ds = np.asarray(s, float) - self.s0[k]
        x = self.v[k, 0] + ds * self.u[k, 0] + offset * self.n[k, 0]
        y = self.v[k, 1] + ds * self.u[k, 1] + offset * self.n[k, 1]
        return x, y

    def azimuth(self, s):
        """Grid azimuth (rad, clockwise from north) of the axis at ``s``."""
        k = self.segment_of(s)
        return np.arctan2(self.u[k, 0], self.u[k, 1])


# ---------------------------------------------------------------------------- objects
def add_reference_surfaces(cfg, rng, b, height, free, occupied):
    """Horizontal square slabs at ``len(reference_surfaces_per_site)`` sites."""
    L, s = cfg.length_m, cfg.reference_size_m
    n_sites, refs, k = len(cfg.reference_surfaces_per_site), [], 0
    axis = CorridorAxis(cfg)
    pylon_s = _pylon_s(cfg, axis.total) if cfg.power_line or cfg.layout == "corridor" else np.zeros(0)
    # An area spreads its sites over a lattice of cells covering the block, so that control
    # lies under every part of it; a corridor keeps them near the axis, along it.
    cols = max(1, int(np.ceil(np.sqrt(n_sites * cfg.width_m / L)))) if cfg.layout == "area" else 1
    rows = int(np.ceil(n_sites / cols))
    inner = cfg.width_m / 2 - 60.0
    for site, n_surf in enumerate(cfg.reference_surfaces_per_site):
        row, col = divmod(site, cols)
        for _ in range(200):  # site centre on open ground
            if cfg.layout == "area":
                y = L * (row + 0.5 + rng.uniform(-0.3, 0.3)) / rows
                x = -inner + 2 * inner * (col + 0.5 + rng.uniform(-0.3, 0.3)) / cols
                s_site = y
            else:  # near the axis
                s_site = axis.total * (site + 0.5 + rng.uniform(-0.25, 0.25)) / n_sites
                x, y = axis.at(s_site, rng.choice([-1.0, 1.0]) * rng.uniform(25.0, 90.0))
            if free(x, y, 8.0 * n_surf, 15.0) and np.all(np.abs(pylon_s - s_site) > 20):
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


def _pylon_s(cfg, length_m):
    n = int(np.floor(length_m / cfg.pylon_spacing_m))
    return (length_m - n * cfg.pylon_spacing_m) / 2 + cfg.pylon_spacing_m * np.arange(n + 1)


def add_power_line(cfg, b, height):
    """Pylons on the axis (their arms across it) and five wires per span; returns the pylon foot points."""
    axis = CorridorAxis(cfg)
    H, ss = cfg.pylon_height_m, _pylon_s(cfg, axis.total)
    xs, ys = axis.at(ss)
    n_x, n_y = axis.n[axis.segment_of(ss)].T  # across each pylon
    u_x, u_y = axis.u[axis.segment_of(ss)].T
    z0 = height(xs, ys)
    a, top, bt = 0.09 * H, 0.85 * H, 0.025 * H
    arms = [(0.70 * H, 7.0), (0.82 * H, 5.0)]
    bars = []
    for x, y, nx_, ny_, ux, uy, zg in zip(xs, ys, n_x, n_y, u_x, u_y, z0):
        def place(p, q, z, x=x, y=y, nx_=nx_, ny_=ny_, ux=ux, uy=uy):  # p across, q along the axis
            p, q = np.asarray(p, float), np.asarray(q, float)
            return np.column_stack([x + p * nx_ + q * ux, y + p * ny_ + q * uy, np.broadcast_to(z, p.shape)])

        base = place(a * _SQUARE[:, 0], a * _SQUARE[:, 1], zg - 0.5)
        head = place(bt * _SQUARE[:, 0], bt * _SQUARE[:, 1], zg + top)
        bars.append(_bars(base, head, 0.18, 0.12))  # legs
        for f in (0.2, 0.4, 0.6):  # horizontal bracing between the legs
            lev = base + f * (head - base)
            bars.append(_bars(lev, np.roll(lev, -1, axis=0), 0.07, 0.07))
        for za, span in arms:
            bars.append(_bars(place([-span], [0.0], zg + za), place([span], [0.0], zg + za), 0.3, 0.3))
        bars.append(_bars(place([0.0], [0.0], zg + top), place([0.0], [0.0], zg + H), 1.3 * bt, 0.15))  # peak
    hexa = np.concatenate(bars)
    Vp, Fp = _convex(hexa, _HEX_FACES)
    b.add(Vp, Fp, Material.PYLON)
    # wires: attachment points at the arm ends and the peak, parabolic sag per span
    att = np.array([[-7.0, 0.70 * H - 0.3], [7.0, 0.70 * H - 0.3], [-5.0, 0.82 * H - 0.3],
                    [5.0, 0.82 * H - 0.3], [0.0, H]])
    r, ring = cfg.wire_diameter_m / 2, np.arange(6) * np.pi / 3
    for k in range(len(ss) - 1):
        span = ss[k + 1] - ss[k]
        S = max(8, int(np.ceil(span / 4.0))) + 1
        s = np.linspace(0, 1, S)
        A = np.column_stack([xs[k] + att[:, 0] * n_x[k], ys[k] + att[:, 0] * n_y[k], z0[k] + att[:, 1]])
        B = np.column_stack([xs[k + 1] + att[:, 0] * n_x[k + 1], ys[k + 1] + att[:, 0] * n_y[k + 1],
                             z0[k + 1] + att[:, 1]])
        P = A[:, None] + s[None, :, None] * (B - A)[:, None]
        P[..., 2] -= cfg.wire_sag_m * (span / 300.0) ** 2 * 4 * s * (1 - s)  # (5, S, 3)
        T = np.gradient(P, axis=1)
        T /= np.linalg.norm(T, axis=2, keepdims=True)
        N1 = np.cross(T, [n_x[k], n_y[k], 0.0])
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
    return np.column_stack([xs, ys, z0])


def add_buildings(cfg, rng, b, height, free, occupied, set_x, set_y, cross_ang):
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


def add_vegetation(cfg, rng, b, height, road_distance, occupied):
    """Trees (ellipsoid or cone crowns on trunks) and shrubs; returns the count.

    ``road_distance(x, y)`` gives the distance [m] to the nearest road centreline.
    """
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
    ok = (np.abs(CorridorAxis(cfg).across(x, y)) > 15) & (np.abs(x) < half - 3) & (y > y_lo + 3) & (y < y_hi - 3)
    ok &= road_distance(x, y) > cfg.road_width_m / 2 + 3  # road half width + 3 m
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
