"""WGS84 ellipsoid, normal gravity, Earth rate, geodetic <-> ECEF.

Constants are those of NIMA TR8350.2 (*Department of Defense World Geodetic System 1984*,
3rd ed., 2000), Tables 3.1-3.4. Normal gravity follows Somigliana's closed formula on the
ellipsoid (TR8350.2 Eq. 4-1) with the second-order height correction (Eq. 4-3); it is
directed along the ellipsoidal normal, downwards. It contains the centrifugal acceleration
of the rotating Earth, so in an Earth-fixed frame the specific force of a body at rest is
``-g``.

All functions are vectorised over leading axes; angles in radians, lengths in metres.
"""

from __future__ import annotations

import numpy as np

WGS84_A = 6378137.0
"""Semi-major axis (m)."""
WGS84_F = 1.0 / 298.257223563
"""Flattening."""
WGS84_B = WGS84_A * (1.0 - WGS84_F)
"""Semi-minor axis (m)."""
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
"""First eccentricity squared."""
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)
"""Second eccentricity squared."""
WGS84_GM = 3.986004418e14
"""Earth's gravitational constant including the atmosphere (m^3/s^2)."""
OMEGA_IE = 7.292115e-5
"""Earth rotation rate (rad/s)."""
GAMMA_E = 9.7803253359
"""Normal gravity at the equator (m/s^2)."""
SOMIGLIANA_K = 0.00193185265241
"""Somigliana's constant k = (b gamma_p) / (a gamma_e) - 1."""
GRAVITY_M = OMEGA_IE**2 * WGS84_A**2 * WGS84_B / WGS84_GM
"""m = omega^2 a^2 b / GM (0.00344978650684)."""

OMEGA_IE_E = np.array([0.0, 0.0, OMEGA_IE])
"""Earth rotation vector in ECEF (rad/s)."""


def radii_of_curvature(lat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Meridian radius ``M`` and prime-vertical radius ``N`` (m) at geodetic latitude ``lat``."""
    s2 = np.sin(lat) ** 2
    w = np.sqrt(1.0 - WGS84_E2 * s2)
    N = WGS84_A / w
    M = WGS84_A * (1.0 - WGS84_E2) / w**3
    return M, N


def geodetic_to_ecef(lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> np.ndarray:
    """ECEF position ``(..., 3)`` of geodetic latitude, longitude (rad) and ellipsoidal height (m)."""
    lat, lon, h = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (lat, lon, h)))
    _, N = radii_of_curvature(lat)
    cl = np.cos(lat)
    return np.stack(
        [
            (N + h) * cl * np.cos(lon),
            (N + h) * cl * np.sin(lon),
            (N * (1.0 - WGS84_E2) + h) * np.sin(lat),
        ],
        axis=-1,
    )


def ecef_to_geodetic(p_e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Geodetic latitude, longitude (rad) and ellipsoidal height (m) of ECEF points ``(..., 3)``.

    Bowring's parametric-latitude start followed by two fixed-point iterations: accurate to
    better than 1e-12 rad and 1e-8 m from the Earth's surface to aircraft heights.
    """
    p_e = np.asarray(p_e, dtype=float)
    x, y, z = p_e[..., 0], p_e[..., 1], p_e[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    theta = np.arctan2(z * WGS84_A, p * WGS84_B)
    lat = np.arctan2(
        z + WGS84_EP2 * WGS84_B * np.sin(theta) ** 3,
        p - WGS84_E2 * WGS84_A * np.cos(theta) ** 3,
    )
    for _ in range(2):
        s = np.sin(lat)
        N = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s * s)
        h = p * np.cos(lat) + z * s - WGS84_A * np.sqrt(1.0 - WGS84_E2 * s * s)
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * N / (N + h)))
    s = np.sin(lat)
    h = p * np.cos(lat) + z * s - WGS84_A * np.sqrt(1.0 - WGS84_E2 * s * s)
    return lat, lon, h


def R_e_n(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Rotation from local north-east-down to ECEF at ``(lat, lon)`` (rad). ``(..., 3, 3)``."""
    lat, lon = np.broadcast_arrays(np.asarray(lat, float), np.asarray(lon, float))
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    R = np.empty(lat.shape + (3, 3))  # columns: north, east, down
    R[..., 0, 0], R[..., 1, 0], R[..., 2, 0] = -sl * co, -sl * so, cl
    R[..., 0, 1], R[..., 1, 1], R[..., 2, 1] = -so, co, 0.0
    R[..., 0, 2], R[..., 1, 2], R[..., 2, 2] = -cl * co, -cl * so, -sl
    return R


def R_e_enu(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Rotation from local east-north-up to ECEF at ``(lat, lon)`` (rad). ``(..., 3, 3)``."""
    R = R_e_n(lat, lon)
    return np.stack([R[..., 1], R[..., 0], -R[..., 2]], axis=-1)


def normal_gravity(lat: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Magnitude of WGS84 normal gravity (m/s^2) at geodetic latitude (rad) and height (m).

    Somigliana on the ellipsoid, ``gamma0 = gamma_e (1 + k sin^2 lat) / sqrt(1 - e^2 sin^2 lat)``,
    then ``gamma = gamma0 (1 - 2/a (1 + f + m - 2 f sin^2 lat) h + 3 h^2 / a^2)``.
    """
    s2 = np.sin(lat) ** 2
    gamma0 = GAMMA_E * (1.0 + SOMIGLIANA_K * s2) / np.sqrt(1.0 - WGS84_E2 * s2)
    return gamma0 * (
        1.0
        - 2.0 / WGS84_A * (1.0 + WGS84_F + GRAVITY_M - 2.0 * WGS84_F * s2) * h
        + 3.0 * h * h / WGS84_A**2
    )


def gravity_e(p_e: np.ndarray) -> np.ndarray:
    """Normal gravity vector in ECEF (m/s^2) at ECEF positions ``(..., 3)``, along the downward normal."""
    lat, lon, h = ecef_to_geodetic(p_e)
    g = normal_gravity(lat, h)
    down = -np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)
    return g[..., None] * down


def transport_rate_n(lat: np.ndarray, h: np.ndarray, v_n: np.ndarray) -> np.ndarray:
    """Transport rate ``omega_en_n`` (rad/s) of the NED frame moving with velocity ``v_n`` (NED, m/s).

    ``omega_en_n = [v_E / (N + h), -v_N / (M + h), -v_E tan(lat) / (N + h)]``
    (Groves 2013, Eq. 5.44).
    """
    M, N = radii_of_curvature(lat)
    v_n = np.asarray(v_n, dtype=float)
    vN, vE = v_n[..., 0], v_n[..., 1]
    return np.stack([vE / (N + h), -vN / (M + h), -vE * np.tan(lat) / (N + h)], axis=-1)
