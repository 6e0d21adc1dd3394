"""Procedural albedo of the simulated scene: what the surfaces look like.

Seeded, deterministic texture evaluated per surface point by :meth:`Scene.albedo
<georefine.sim.scene.Scene.albedo>`: hashed lattice value noise and its multi-octave sum
(fbm), the road coordinates the asphalt markings need (nearest road centreline, signed
offset, along-road coordinate; ``roads`` is ``Scene.road_geometry``), and the numba kernel
that maps a point, its face normal and its :class:`~georefine.sim.scene.Material` to a
diffuse albedo in [0.05, 0.9].
"""

from __future__ import annotations

import numba
import numpy as np


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
def albedo_kernel(p, n, mat, seed, roads, out):
    """Albedo of surface points, written to ``out`` (N,).

    ``p`` (N, 3) points in ``w`` [m], ``n`` (N, 3) unit normals and ``mat`` (N,) uint8
    :class:`~georefine.sim.scene.Material` of their faces, ``seed`` the texture seed,
    ``roads`` the road geometry (``Scene.road_geometry``).
    """
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
