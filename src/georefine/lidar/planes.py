"""Planar features of one view of the point cloud (docs/ARCHITECTURE.md §4.3 "Plane correspondence", §4.5 step 4).

A *view* is one strip × one scanner channel (nadir, forward, backward); features of different
views are matched later (:mod:`georefine.lidar.correspondences`) and become plane observations
of the adjustment (paper 000 §2, Eq. 5; Pöppl et al. 2023b, 2024).

Algorithm (per view, all points georeferenced in ``w`` with the current trajectory)

1. **Seeds.** The horizontal plane is divided into square cells of ``seed_spacing_m`` centred on
   the grid nodes ``(i s, j s)`` of ``w``; each cell column is cut into layers of
   ``seed_layer_m`` (``z`` from ``k h`` to ``(k + 1) h``). The seed of an occupied voxel is its
   point nearest to the node at the layer's mid-height. The layers give a facade one seed per
   layer instead of at most one per column (where the ground or the roof would usually win);
   on a roof or the ground a column holds one seed, except where the surface crosses a layer
   boundary: of two seeds of one column closer than ``radius_m`` the one farther from its node
   is dropped. The grid is anchored in ``w``, so the views of a strip seed the same places and
   their features' centres nearly coincide, which helps the matching.
2. **Neighbourhoods.** All points within ``radius_m`` (3-D ball) of a seed. A numba kernel
   looks them up in a voxel grid (cell = ``radius_m``, points sorted by voxel key, binary search
   of the 27 neighbour voxels) and accumulates the count, the first and second moments about
   the seed and the time range; memory is O(points + seeds), nothing per neighbour is stored.
3. **PCA.** ``C = S2/n - m m^T`` (moments about the seed, so sums stay small), eigenvalues
   ``l1 >= l2 >= l3`` and eigenvectors of all seeds at once (``np.linalg.eigh`` on the stack).
   ``axis1`` is the eigenvector of ``l1`` (largest in-plane spread), the normal that of ``l3``.
4. **Selection.** Keep a patch if ``n >= min_points``, roughness ``sqrt(l3) <= max_roughness_m``,
   linearity ``(l1 - l2)/l1 <= max_linearity`` (wires, edges, single scan lines),
   smaller in-plane extent ``2 sqrt(l2) >= min_extent_m`` and the point times span at most
   ``max_time_span_s`` (a view that sees a place twice would mix two poses).
5. **Orientation and frames.** The normal points towards the scanner at the mean time ``t_f``:
   ``n . (p_w_s(t_f) - c_w) > 0``; ``axis2 = n x axis1`` so that ``[axis1 axis2 n]`` is a
   right-handed orthonormal basis. With ``p_w_s = p_w_b + R_w_b p_b_s`` and
   ``R_w_s = R_w_b R_b_s`` at ``t_f``: ``c_s = R_w_s^T (c_w - p_w_s)``, ``k_s = R_w_s^T k_w``.

Feature uncertainty (weights of the plane observations, docs/ARCHITECTURE.md §4.3)

The per-point scatter normal to the plane is ``sigma_r = max(sqrt(n/(n-3)) roughness,
range_sigma_m)``: the roughness (RMS of the orthogonal residuals, corrected for the three
fitted parameters) measures ranging noise, surface texture and in-patch trajectory noise
together, and the ranging noise bounds it from below when few points make the estimate
small by chance. For a least-squares plane through ``n`` points with in-plane variances
``l1, l2`` (population, 1/n):

* ``sigma_d = sigma_r / sqrt(n)`` (offset of the plane at the centroid along the normal);
* ``sigma_slope = sigma_r / (sqrt(l2) sqrt(n))`` (slope along an in-plane axis with variance
  ``l``, ``sigma_r / sqrt(n l)``; the smaller spread ``l2`` is used for both slopes, which
  is conservative for the slope along ``axis1``).

Both are floored (``min_sigma_d_m``, ``min_sigma_slope_mdeg``): real surfaces are not exactly
planar over the slightly different patches that different views sample, and thousands of
features with sub-millimetre sigmas would otherwise outweigh GNSS and IMU.

Files: :func:`write_features` / :func:`read_features` use a CSV with a header (one feature
per row, columns in :data:`CSV_COLUMNS`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, fields

import numba
import numpy as np

from georefine.config import PlaneExtractionConfig
from georefine.errors import InputError
from georefine.io.files import (
    PathLike,
    atomic_output,
    data_lines,
    parse_float_rows,
    read_text_lines,
)

__all__ = [
    "CSV_COLUMNS",
    "FEATURES_VERSION",
    "PlanarFeatures",
    "PlaneExtractionConfig",
    "PoseFn",
    "extract_features",
    "extract_features_chunked",
    "read_features",
    "write_features",
]

FEATURES_VERSION = 2
"""Changes when :class:`PlanarFeatures` or their extraction change (part of the step cache's
keys); 2: the seed voxel (``seed_cell``)."""

PoseFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``pose_fn(t (M,)) -> (p_w_b (M,3), R_w_b (M,3,3))``: the trajectory used to georeference."""


_FLOAT_FIELDS = ("time", "roughness_m", "extent_m", "sigma_d_m", "sigma_slope_rad")
_VEC_FIELDS = ("centre_s", "axis1_s", "axis2_s", "normal_s", "centre_w", "normal_w")
_DTYPES = {"strip": np.int32, "channel": np.int16, "n_points": np.int32, "seed_cell": np.int64}


@dataclass(frozen=True)
class PlanarFeatures:
    """Planar features, a struct of arrays over F features (F = 0 allowed).

    Attributes
    ----------
    strip : (F,) int32
        Strip id (LAS ``point_source_id``).
    channel : (F,) int16
        Scanner channel (view) id.
    time : (F,) float64
        Mean point time ``t_f``, s relative to the dataset epoch.
    centre_s, axis1_s, axis2_s, normal_s : (F, 3) float64
        Centroid (m) and unit axes in the scanner frame ``s`` at ``t_f``; ``axis1`` along the
        largest in-plane spread, ``[axis1 axis2 normal]`` right-handed, normal towards the scanner.
    centre_w, normal_w : (F, 3) float64
        The same in ``w`` with the trajectory used for the extraction (for matching).
    n_points : (F,) int32
        Points in the patch.
    roughness_m : (F,) float64
        ``sqrt(l3)``, RMS of the orthogonal residuals of the fitted plane.
    extent_m : (F,) float64
        ``2 sqrt(l1)``: twice the standard deviation of the points along ``axis1`` (equals the
        radius for a fully covered disc).
    sigma_d_m, sigma_slope_rad : (F,) float64
        Standard deviations of the normal distance and of each of the two slopes (module
        docstring).
    seed_cell : (F, 3) int64
        The seed's voxel of the grid anchored in ``w`` (step 1 of the module docstring):
        ``rint(x / seed_spacing_m)``, ``rint(y / seed_spacing_m)``, ``floor(z / seed_layer_m)``.
        With ``strip`` and ``channel`` it names the feature across re-extractions with a slightly
        different trajectory (:func:`feature_keys`).
    """

    strip: np.ndarray
    channel: np.ndarray
    time: np.ndarray
    centre_s: np.ndarray
    axis1_s: np.ndarray
    axis2_s: np.ndarray
    normal_s: np.ndarray
    centre_w: np.ndarray
    normal_w: np.ndarray
    n_points: np.ndarray
    roughness_m: np.ndarray
    extent_m: np.ndarray
    sigma_d_m: np.ndarray
    sigma_slope_rad: np.ndarray
    seed_cell: np.ndarray

    def __post_init__(self) -> None:
        f = np.shape(self.time)[0] if np.ndim(self.time) == 1 else -1
        if f < 0:
            raise ValueError(f"time must be 1-D, got shape {np.shape(self.time)}")
        for fld in fields(self):
            name = fld.name
            dtype = _DTYPES.get(name, np.float64)
            arr = np.ascontiguousarray(getattr(self, name), dtype=dtype)
            want = (f, 3) if name in _VEC_FIELDS or name == "seed_cell" else (f,)
            if arr.shape != want:
                raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return int(self.time.shape[0])

    @staticmethod
    def empty() -> PlanarFeatures:
        """No features."""
        return PlanarFeatures(**{
            f.name: np.zeros((0, 3) if f.name in (*_VEC_FIELDS, "seed_cell") else (0,))
            for f in fields(PlanarFeatures)
        })

    @staticmethod
    def concatenate(parts: Sequence[PlanarFeatures]) -> PlanarFeatures:
        """Features of all ``parts`` in order (an empty sequence gives no features)."""
        parts = list(parts)
        if not parts:
            return PlanarFeatures.empty()
        return PlanarFeatures(**{
            f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(PlanarFeatures)
        })

    def select(self, index: np.ndarray) -> PlanarFeatures:
        """Subset by a boolean mask (F,) or an integer index array."""
        index = np.asarray(index)
        if index.dtype == bool and index.shape != (len(self),):
            raise ValueError(f"mask must have shape ({len(self)},), got {index.shape}")
        return PlanarFeatures(**{f.name: getattr(self, f.name)[index] for f in fields(self)})


# --------------------------------------------------------------------------- kernels


@numba.njit(cache=True)
def _group_argmin(key_sorted: np.ndarray, d2_sorted: np.ndarray) -> np.ndarray:
    """Position of the smallest ``d2`` in each run of equal keys (keys sorted)."""
    n = key_sorted.shape[0]
    out = np.empty(n, np.int64)
    m = 0
    i = 0
    while i < n:
        best, j = i, i + 1
        while j < n and key_sorted[j] == key_sorted[i]:
            if d2_sorted[j] < d2_sorted[best]:
                best = j
            j += 1
        out[m] = best
        m += 1
        i = j
    return out[:m]


@numba.njit(cache=True, parallel=True)
def _ball_moments(pts, t, ukeys, starts, ends, lo, dims, cell, seeds, radius):
    """Count, moments about the seed (sum d, sum d d^T as xx yy zz xy xz yz) and time stats."""
    m = seeds.shape[0]
    count = np.zeros(m, np.int64)
    s1 = np.zeros((m, 3))
    s2 = np.zeros((m, 6))
    tsum = np.zeros(m)
    tmin = np.full(m, np.inf)
    tmax = np.full(m, -np.inf)
    r2 = radius * radius
    for k in numba.prange(m):
        cx, cy, cz = seeds[k, 0], seeds[k, 1], seeds[k, 2]
        ix = np.int64(np.floor(cx / cell)) - lo[0]
        iy = np.int64(np.floor(cy / cell)) - lo[1]
        iz = np.int64(np.floor(cz / cell)) - lo[2]
        n = 0
        a0 = a1 = a2 = b0 = b1 = b2 = b3 = b4 = b5 = ts = 0.0
        t0, t1 = np.inf, -np.inf
        for dx in range(-1, 2):
            jx = ix + dx
            if jx < 0 or jx >= dims[0]:
                continue
            for dy in range(-1, 2):
                jy = iy + dy
                if jy < 0 or jy >= dims[1]:
                    continue
                for dz in range(-1, 2):
                    jz = iz + dz
                    if jz < 0 or jz >= dims[2]:
                        continue
                    key = (jx * dims[1] + jy) * dims[2] + jz
                    pos = np.searchsorted(ukeys, key)
                    if pos >= ukeys.shape[0] or ukeys[pos] != key:
                        continue
                    for j in range(starts[pos], ends[pos]):
                        ux = pts[j, 0] - cx
                        uy = pts[j, 1] - cy
                        uz = pts[j, 2] - cz
                        if ux * ux + uy * uy + uz * uz > r2:
                            continue
                        n += 1
                        a0 += ux
                        a1 += uy
                        a2 += uz
                        b0 += ux * ux
                        b1 += uy * uy
                        b2 += uz * uz
                        b3 += ux * uy
                        b4 += ux * uz
                        b5 += uy * uz
                        ts += t[j]
                        t0 = min(t0, t[j])
                        t1 = max(t1, t[j])
        count[k] = n
        s1[k, 0], s1[k, 1], s1[k, 2] = a0, a1, a2
        s2[k, 0], s2[k, 1], s2[k, 2], s2[k, 3], s2[k, 4], s2[k, 5] = b0, b1, b2, b3, b4, b5
        tsum[k], tmin[k], tmax[k] = ts, t0, t1
    return count, s1, s2, tsum, tmin, tmax


# --------------------------------------------------------------------------- extraction


def _seed_cells(points_w: np.ndarray, cfg: PlaneExtractionConfig) -> np.ndarray:
    """(n, 3) int64 voxel of the seed grid anchored in ``w`` that holds each point (step 1)."""
    ixy = np.rint(points_w[:, :2] / cfg.seed_spacing_m).astype(np.int64)
    iz = np.floor(points_w[:, 2] / cfg.seed_layer_m).astype(np.int64)
    return np.column_stack([ixy, iz])


def _select_seeds(points_w: np.ndarray, cfg: PlaneExtractionConfig) -> np.ndarray:
    """Indices of the seed points (step 1 of the module docstring), sorted by voxel."""
    s, h = cfg.seed_spacing_m, cfg.seed_layer_m
    ijk = _seed_cells(points_w, cfg)
    d = points_w - np.column_stack([ijk[:, :2] * s, (ijk[:, 2] + 0.5) * h])
    d2 = np.einsum("ij,ij->i", d, d)
    ijk -= ijk.min(axis=0)
    dims = ijk.max(axis=0) + 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.argsort(key)
    seeds = order[_group_argmin(key[order], d2[order])]
    # Two seeds of one column closer than the radius share most of their points: keep the one
    # nearer to its node.
    col = key[seeds] // dims[2]
    p = points_w[seeds]
    close = (col[1:] == col[:-1]) & (np.linalg.norm(p[1:] - p[:-1], axis=1) < cfg.radius_m)
    drop = np.zeros(seeds.size, bool)
    i = np.flatnonzero(close)
    farther_is_upper = d2[seeds[i + 1]] >= d2[seeds[i]]
    drop[np.where(farther_is_upper, i + 1, i)] = True
    return seeds[~drop]


def _neighbourhood_moments(points_w, time, seed_xyz, radius):
    """Per-seed ball statistics via the voxel grid (step 2)."""
    ijk = np.floor(points_w / radius).astype(np.int64)
    lo = ijk.min(axis=0)
    ijk -= lo
    dims = ijk.max(axis=0) + 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.argsort(key)
    skey = key[order]
    starts = np.flatnonzero(np.r_[True, skey[1:] != skey[:-1]])
    ukeys = skey[starts]
    ends = np.append(starts[1:], skey.size)
    return _ball_moments(
        np.ascontiguousarray(points_w[order]), np.ascontiguousarray(time[order]), ukeys,
        starts.astype(np.int64), ends.astype(np.int64), lo, dims, float(radius),
        np.ascontiguousarray(seed_xyz), float(radius),
    )


def _check_inputs(points_w, time, p_b_s, R_b_s):
    """Arrays as float64 with checked shapes; non-finite points or times are an error."""
    points_w = np.asarray(points_w, dtype=np.float64)
    time = np.asarray(time, dtype=np.float64)
    if points_w.ndim != 2 or points_w.shape[1] != 3 or time.shape != (points_w.shape[0],):
        raise ValueError(f"points_w must be (N,3) and time (N,), got {points_w.shape} and {time.shape}")
    p_b_s = np.asarray(p_b_s, dtype=np.float64)
    R_b_s = np.asarray(R_b_s, dtype=np.float64)
    if p_b_s.shape != (3,) or R_b_s.shape != (3, 3):
        raise ValueError(f"p_b_s must be (3,) and R_b_s (3,3), got {p_b_s.shape} and {R_b_s.shape}")
    if not (np.all(np.isfinite(points_w)) and np.all(np.isfinite(time))):
        raise ValueError("points_w and time must be finite")
    return points_w, time, p_b_s, R_b_s


def extract_features(
    points_w: np.ndarray,
    time: np.ndarray,
    strip: int,
    channel: int,
    pose_fn: PoseFn,
    p_b_s: np.ndarray,
    R_b_s: np.ndarray,
    cfg: PlaneExtractionConfig | None = None,
    *,
    own_time: tuple[float, float] = (-np.inf, np.inf),
) -> PlanarFeatures:
    """Extract planar features of one view (strip × channel); algorithm in the module docstring.

    Parameters
    ----------
    points_w : (N, 3) float64
        Points of the view in ``w`` (m), georeferenced with ``pose_fn``.
    time : (N,) float64
        Point times, s relative to the dataset epoch (any order).
    strip, channel : int
        Ids stored with every feature.
    pose_fn : callable
        ``pose_fn(t (M,)) -> (p_w_b (M,3), R_w_b (M,3,3))``, the trajectory that georeferenced
        the points; evaluated at the features' mean times.
    p_b_s : (3,) float64
        Scanner origin in the body frame (m).
    R_b_s : (3, 3) float64
        Boresight, ``s`` to ``b``.
    cfg : PlaneExtractionConfig, optional
        Defaults if omitted.
    own_time : (t0, t1)
        Keep only the features whose seed point's time is in ``[t0, t1)``: a time tile of a
        strip, given with the points up to ``2 max_time_span_s`` beyond both ends, yields
        exactly the features the whole view would give there (see :func:`extract_features_chunked`).

    Returns
    -------
    PlanarFeatures
        In the order of their seed voxels (x, then y, then z of the seed grid).
    """
    return _extract(points_w, time, strip, channel, pose_fn, p_b_s, R_b_s, cfg, *own_time)


def _extract(points_w, time, strip, channel, pose_fn, p_b_s, R_b_s, cfg, own_t0, own_t1):
    """:func:`extract_features` keeping only seeds with ``own_t0 <= time < own_t1``."""
    cfg = cfg or PlaneExtractionConfig()
    points_w, time, p_b_s, R_b_s = _check_inputs(points_w, time, p_b_s, R_b_s)
    if points_w.shape[0] < cfg.min_points:
        return PlanarFeatures.empty()
    seeds = _select_seeds(points_w, cfg)
    seeds = seeds[(time[seeds] >= own_t0) & (time[seeds] < own_t1)]
    if seeds.size == 0:
        return PlanarFeatures.empty()
    t_ref = float(time.min())
    seed_xyz = points_w[seeds]
    n, s1, s2, tsum, tmin, tmax = _neighbourhood_moments(points_w, time - t_ref, seed_xyz, cfg.radius_m)
    ok = (n >= cfg.min_points) & (tmax - tmin <= cfg.max_time_span_s)
    n, s1, s2, tsum, seed_xyz = n[ok], s1[ok], s2[ok], tsum[ok], seed_xyz[ok]
    seed_cell = _seed_cells(seed_xyz, cfg)

    # Step 3: PCA of all candidate patches at once.
    nf = n.astype(np.float64)
    mean = s1 / nf[:, None]
    xx, yy, zz, xy, xz, yz = (s2 / nf[:, None]).T
    C = np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2)
    C -= mean[:, :, None] * mean[:, None, :]
    lam, V = np.linalg.eigh(C)  # ascending: l3, l2, l1
    lam = np.maximum(lam, 0.0)
    l3, l2, l1 = lam[:, 0], lam[:, 1], lam[:, 2]
    roughness = np.sqrt(l3)
    with np.errstate(invalid="ignore", divide="ignore"):
        linearity = np.where(l1 > 0, (l1 - l2) / l1, 1.0)
    keep = (
        (roughness <= cfg.max_roughness_m)
        & (linearity <= cfg.max_linearity)
        & (2.0 * np.sqrt(l2) >= cfg.min_extent_m)
        & (l2 > 0)
    )
    if not np.any(keep):
        return PlanarFeatures.empty()
    n, nf, l1, l2, roughness = n[keep], nf[keep], l1[keep], l2[keep], roughness[keep]
    centre_w = seed_xyz[keep] + mean[keep]
    normal_w = V[keep, :, 0]
    axis1_w = V[keep, :, 2]
    t_f = tsum[keep] / nf + t_ref

    # Step 5: orientation towards the scanner, then the scanner frame at t_f.
    p_w_b, R_w_b = pose_fn(t_f)
    R_w_s = np.asarray(R_w_b) @ R_b_s
    p_w_s = np.asarray(p_w_b) + np.einsum("nij,j->ni", np.asarray(R_w_b), p_b_s)
    flip = np.einsum("ni,ni->n", normal_w, p_w_s - centre_w) < 0
    normal_w[flip] *= -1.0
    axis2_w = np.cross(normal_w, axis1_w)

    def to_s(v):
        return np.einsum("nji,nj->ni", R_w_s, v)

    sigma_r = np.maximum(roughness * np.sqrt(nf / (nf - 3.0)), cfg.range_sigma_m)
    sigma_d = np.maximum(sigma_r / np.sqrt(nf), cfg.min_sigma_d_m)
    sigma_slope = np.maximum(sigma_r / np.sqrt(l2 * nf), np.radians(cfg.min_sigma_slope_mdeg * 1e-3))
    f = nf.size
    return PlanarFeatures(
        strip=np.full(f, strip), channel=np.full(f, channel), time=t_f,
        centre_s=to_s(centre_w - p_w_s), axis1_s=to_s(axis1_w), axis2_s=to_s(axis2_w),
        normal_s=to_s(normal_w), centre_w=centre_w, normal_w=normal_w, n_points=n,
        roughness_m=roughness, extent_m=2.0 * np.sqrt(l1), sigma_d_m=sigma_d, sigma_slope_rad=sigma_slope,
        seed_cell=seed_cell[keep],
    )


def extract_features_chunked(
    chunks: Iterable[tuple[np.ndarray, np.ndarray]],
    strip: int,
    channel: int,
    pose_fn: PoseFn,
    p_b_s: np.ndarray,
    R_b_s: np.ndarray,
    cfg: PlaneExtractionConfig | None = None,
    window_s: float = 30.0,
    margin_s: float | None = None,
) -> PlanarFeatures:
    """Extract the features of one view streamed as time-ordered chunks, in bounded memory.

    The view is processed in time windows of ``window_s``. A window owns the seeds whose point
    time lies in it and sees the points up to ``margin_s`` (default ``2 max_time_span_s``)
    beyond both ends, so every accepted patch is complete. The result equals
    :func:`extract_features` on the whole view (up to feature order) when the points of each
    seed voxel were acquired within ``margin_s``, which holds along straight strips. Memory
    holds ``window_s + 2 margin_s`` of points.

    Parameters
    ----------
    chunks : iterable of (time (n,), points_w (n, 3))
        The view's points in non-decreasing time (s relative to the dataset epoch; ``w``, m).
    window_s, margin_s : float
        Window length and margin, s.

    Other parameters as :func:`extract_features`.
    """
    cfg = cfg or PlaneExtractionConfig()
    margin = 2.0 * cfg.max_time_span_s if margin_s is None else float(margin_s)
    if window_s <= 0 or margin < 0:
        raise ValueError(f"window_s must be > 0 and margin_s >= 0, got {window_s}, {margin}")
    parts: list[PlanarFeatures] = []
    buf_t, buf_p = np.zeros(0), np.zeros((0, 3))
    core0 = None

    def run(t0: float, t1: float) -> None:  # the window [t0, t1) with its margins
        sel = (buf_t >= t0 - margin) & (buf_t < t1 + margin)
        parts.append(_extract(buf_p[sel], buf_t[sel], strip, channel, pose_fn, p_b_s, R_b_s, cfg, t0, t1))

    for t, p in chunks:
        t = np.asarray(t, dtype=np.float64)
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        if t.size == 0:
            continue
        if np.any(np.diff(t) < 0) or (buf_t.size and t[0] < buf_t[-1]):
            raise ValueError("chunks must be in non-decreasing time")
        buf_t, buf_p = np.concatenate([buf_t, t]), np.concatenate([buf_p, p])
        core0 = float(buf_t[0]) if core0 is None else core0
        while buf_t[-1] >= core0 + window_s + margin:
            run(core0, core0 + window_s)
            core0 += window_s
            keep = buf_t >= core0 - margin
            buf_t, buf_p = buf_t[keep], buf_p[keep]
    if core0 is not None:
        run(core0, np.inf)
    return PlanarFeatures.concatenate(parts)


# --------------------------------------------------------------------------- files

CSV_COLUMNS: tuple[str, ...] = (
    "strip", "channel", "time", "n_points",
    *(f"{v}_{a}" for v in _VEC_FIELDS for a in "xyz"),
    *_FLOAT_FIELDS[1:],
    "seed_cell_i", "seed_cell_j", "seed_cell_k",
)
"""Header of the features CSV: ids, mean time (s rel. epoch), point count, the vectors of
:class:`PlanarFeatures` by component (``centre_s_x`` ...), roughness, extent and sigmas, then
the seed voxel (``seed_cell``)."""

_INT_COLUMNS = ("strip", "channel", "n_points", "seed_cell_i", "seed_cell_j", "seed_cell_k")

_CSV_FORMAT = {"time": "%.6f", "roughness_m": "%.7f", "extent_m": "%.5f", "sigma_d_m": "%.4e",
               "sigma_slope_rad": "%.4e", **dict.fromkeys(_INT_COLUMNS, "%d")}


def _column_format(name: str) -> str:
    if name in _CSV_FORMAT:
        return _CSV_FORMAT[name]
    # Centres to the micrometre, unit vectors to 1e-12 (sub-nanoradian).
    return "%.6f" if name.startswith("centre") else "%.12f"


def write_features(path: PathLike, features: PlanarFeatures, protect: Iterable[PathLike] = ()) -> None:
    """Write features as CSV (header :data:`CSV_COLUMNS`), atomically.

    Parameters
    ----------
    path
        Destination file; written under a temporary name and renamed when complete.
    features
        The features (any number, including none).
    protect
        Input files/folders that must not be overwritten.
    """
    f = features
    table = [f.strip, f.channel, f.time, f.n_points, *(getattr(f, v)[:, i] for v in _VEC_FIELDS for i in range(3)),
             *(getattr(f, name) for name in _FLOAT_FIELDS[1:]), *f.seed_cell.T]
    fmt = ",".join(_column_format(c) for c in CSV_COLUMNS)
    with atomic_output(path, "w", protect=protect) as fh:
        fh.write(",".join(CSV_COLUMNS) + "\n")
        if len(f):
            data = np.empty(len(f), dtype=[(c, a.dtype) for c, a in zip(CSV_COLUMNS, table)])
            for c, a in zip(CSV_COLUMNS, table):
                data[c] = a
            np.savetxt(fh, data, fmt=fmt, delimiter=",")


def read_features(path: PathLike) -> PlanarFeatures:
    """Read a features CSV written by :func:`write_features` (columns in any order).

    Raises
    ------
    InputError
        With the file, line and column when the header or a value is wrong.
    """
    lines = read_text_lines(path)
    if not lines:
        raise InputError("empty file", path=path, expected="a header line: " + ",".join(CSV_COLUMNS))
    header = [c.strip() for c in lines[0].split(",")]
    missing = [c for c in CSV_COLUMNS if c not in header]
    extra = [c for c in header if c not in CSV_COLUMNS]
    if missing or extra or len(set(header)) != len(header):
        raise InputError("wrong header", path=path, line=1, expected=",".join(CSV_COLUMNS),
                         found=f"missing {missing}, unknown {extra}" if missing or extra else "repeated columns")
    rows, numbers = data_lines(lines, 1)
    values = parse_float_rows(path, rows, numbers, header, delimiter=",")
    col = {c: values[:, header.index(c)] for c in CSV_COLUMNS}
    for c in _INT_COLUMNS:
        bad = np.flatnonzero(col[c] != np.round(col[c]))
        if bad.size:
            raise InputError("not an integer", path=path, line=int(numbers[bad[0]]), field=c,
                             expected="an integer", found=repr(col[c][bad[0]]))
    kw = {name: col[name] for name in ("strip", "channel", "time", "n_points", *_FLOAT_FIELDS[1:])}
    kw.update({v: np.column_stack([col[f"{v}_{a}"] for a in "xyz"]) for v in _VEC_FIELDS})
    kw["seed_cell"] = np.column_stack([np.round(col[f"seed_cell_{a}"]) for a in "ijk"])
    return PlanarFeatures(**kw)
