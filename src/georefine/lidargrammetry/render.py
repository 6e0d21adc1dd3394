"""Lidargrams: synthetic images of the point cloud that remember their points (docs/ARCHITECTURE.md §4.8, paper 004).

A *lidargram* is the LiDAR point cloud seen by a frame camera (:class:`~.camera.Camera`, full
Brown distortion) from a chosen pose ``(R_w_c, p_w_c)``. Every pixel remembers which point it
shows: the **ULPI** raster (unique LiDAR point identifier) holds the index of that point into the
input arrays, ``-1`` where the pixel is empty. Pixel convention as :mod:`georefine.geometry.camera`: ``(0, 0)`` is
the top-left *corner*, pixel ``(col, row)`` covers ``[col, col + 1) x [row, row + 1)``.

Rendering (:func:`render_lidargram`)

1. **Projection.** ``x_c = R_w_c^T (X_w - p_w_c)`` (element-wise, so that a point's numbers do
   not depend on the chunk it is in), kept if ``z_c > near_m`` and inside the field of view: its
   ideal normalised radius at most 5 % beyond that of the image border (widened by
   ``max_splat_px``). The last test stops points far outside the view from folding back into the
   image where the distortion polynomial turns over. Then ``(u, v)`` with the distortion.
2. **Splat.** A point covers the pixels whose centres lie within ``r_px`` of ``(u, v)`` in both
   axes (a square), always including the pixel that contains ``(u, v)``, with
   ``r_px = clip(splat_scale * 0.5 * point_spacing_m * fx / z_c, 0.5, max_splat_px)``: half the
   point spacing on the ground seen at depth ``z_c``. Points whose projection lies outside the
   image but whose splat reaches into it are drawn (``point_uv`` may lie up to ``max_splat_px``
   outside the image); the splats are clipped at the border.
3. **Z-buffer** (numba kernel, one pass over the cloud in chunks of ``chunk_size`` points; the
   buffer carries over between chunks): the point with the smallest ``z_c`` wins a pixel; at
   equal ``z_c`` the lower index wins, so the result does not depend on the order or chunking.
   Hence the pixel containing a shown point's projection shows that point unless a nearer
   point's splat covers it.
4. **Grey value.** Intensity of the shown points mapped linearly from its 2nd..98th percentile to
   0..255 (clipped); constant intensity gives 128. Empty pixels are 0.
5. **Hole filling** (optional, ``fill_holes``): an empty pixel with at least ``fill_min_neighbours``
   of its 8 neighbours shown takes the grey value and depth of its nearest shown neighbour (edge
   neighbours before diagonal ones, then the smaller depth). One pass over the original
   raster. **Only the image and the depth are filled; the ULPI raster stays -1 there**: no point
   is invented, so a measurement on a filled pixel has no LiDAR point.

Files (:func:`save_lidargram`, :func:`load_lidargram`): ``<name>.png`` (the 8-bit grey image) and
``<name>.npz`` (compressed: pose, camera parameters, depth, ULPI, ``point_index``, ``point_uv``,
point spacing), each written atomically.
"""

from __future__ import annotations

import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numba
import numpy as np
from scipy.spatial import cKDTree

from georefine.errors import InputError
from georefine.geometry.camera import Camera
from georefine.io.files import PathLike, atomic_output

__all__ = ["Lidargram", "LidargramCanvas", "estimate_point_spacing", "max_normalised_radius2", "render_lidargram",
           "save_lidargram", "load_lidargram"]

FORMAT_VERSION = 1
MAX_SPLAT_PX = 7
"""Default largest splat radius (px) of :func:`render_lidargram`."""
NEAR_M = 0.1
"""Default near limit (m) of :func:`render_lidargram`."""
_CAMERA_FIELDS = ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3", "p1", "p2")


@dataclass(frozen=True, eq=False)
class Lidargram:
    """A rendered lidargram (module docstring). H, W = ``camera.height_px, camera.width_px``.

    Attributes
    ----------
    camera : Camera
    R_w_c : (3, 3) float64
    p_w_c : (3,) float64, m
        Pose: ``x_c = R_w_c^T (X_w - p_w_c)``.
    image : (H, W) uint8
        Grey value from intensity; 0 where empty.
    depth : (H, W) float32, m
        ``z_c`` of the shown point (or of the fill value); NaN where empty.
    ulpi : (H, W) int64
        Index of the shown point into the rendered arrays; -1 where empty (also on filled pixels).
    point_index : (M,) int64
        The distinct points shown anywhere, sorted ascending.
    point_uv : (M, 2) float64, px
        Exact sub-pixel projection ``(u, v)`` of each of those points.
    point_spacing_m : float
        Point spacing used to size the splats (NaN if unknown).
    """

    camera: Camera
    R_w_c: np.ndarray
    p_w_c: np.ndarray
    image: np.ndarray
    depth: np.ndarray
    ulpi: np.ndarray
    point_index: np.ndarray
    point_uv: np.ndarray
    point_spacing_m: float = float("nan")

    def __post_init__(self) -> None:
        problem = _shape_problem(self.camera, {k: getattr(self, k) for k in _ARRAY_SPECS})
        if problem is not None:
            field, expected, found = problem
            raise ValueError(f"{field} must be {expected}, got {found}")

    @property
    def shown_mask(self) -> np.ndarray:
        """(H, W) bool: the pixel shows a LiDAR point (``ulpi >= 0``)."""
        return self.ulpi >= 0

    @property
    def filled_mask(self) -> np.ndarray:
        """(H, W) bool: the pixel was filled by hole filling (has a depth but no ULPI)."""
        return (self.ulpi < 0) & np.isfinite(self.depth)

    def uv_of(self, index: np.ndarray) -> np.ndarray:
        """Exact projections ``(K, 2)`` (px) of points given by index ``(K,)``; NaN for points not shown."""
        index = np.asarray(index, dtype=np.int64).reshape(-1)
        out = np.full((index.size, 2), np.nan)
        if self.point_index.size:
            pos = np.minimum(np.searchsorted(self.point_index, index), self.point_index.size - 1)
            ok = self.point_index[pos] == index
            out[ok] = self.point_uv[pos[ok]]
        return out

    def ulpi_at(self, uv: np.ndarray) -> np.ndarray:
        """ULPI ``(K,)`` of the pixels containing the positions ``uv (K, 2)`` (px); -1 outside or empty."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        h, w = self.ulpi.shape
        ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        out = np.full(uv.shape[0], -1, np.int64)
        out[ok] = self.ulpi[row[ok].astype(np.int64), col[ok].astype(np.int64)]
        return out


# field -> (dtype, shape with "H", "W", "M" placeholders)
_ARRAY_SPECS = {
    "R_w_c": (np.float64, (3, 3)), "p_w_c": (np.float64, (3,)), "image": (np.uint8, ("H", "W")),
    "depth": (np.float32, ("H", "W")), "ulpi": (np.int64, ("H", "W")),
    "point_index": (np.int64, ("M",)), "point_uv": (np.float64, ("M", 2)),
}


def _shape_problem(camera: Camera, arrays: dict) -> tuple[str, str, str] | None:
    """``(field, expected, found)`` of the first array with a wrong dtype or shape, else None."""
    sizes = {"H": camera.height_px, "W": camera.width_px, "M": np.shape(arrays["point_index"])[0]
             if np.ndim(arrays["point_index"]) == 1 else -1}
    for name, (dtype, spec) in _ARRAY_SPECS.items():
        a = arrays[name]
        want = tuple(sizes.get(s, s) for s in spec)
        if not isinstance(a, np.ndarray) or a.dtype != dtype or a.shape != want:
            found = f"{a.dtype} {a.shape}" if isinstance(a, np.ndarray) else type(a).__name__
            return name, f"{np.dtype(dtype).name} {want}", found
    return None


# --------------------------------------------------------------------------- kernels


@numba.njit(cache=True, nogil=True)  # lidargram tasks on threads run their z-buffers side by side
def _splat(u, v, z, r, idx, zbuf, ulpi):
    """Draw square splats into the z-buffer (in place): smaller ``z`` wins, then the lower index."""
    h, w = zbuf.shape
    for k in range(u.shape[0]):
        uk, vk, zk, rk, ik = u[k], v[k], z[k], r[k], idx[k]
        iu, iv = np.int64(np.floor(uk)), np.int64(np.floor(vk))
        c0 = max(min(np.int64(np.ceil(uk - rk - 0.5)), iu), 0)
        c1 = min(max(np.int64(np.floor(uk + rk - 0.5)), iu), w - 1)
        r0 = max(min(np.int64(np.ceil(vk - rk - 0.5)), iv), 0)
        r1 = min(max(np.int64(np.floor(vk + rk - 0.5)), iv), h - 1)
        for row in range(r0, r1 + 1):
            for col in range(c0, c1 + 1):
                zb = zbuf[row, col]
                if zk < zb or (zk == zb and ik < ulpi[row, col]):
                    zbuf[row, col] = zk
                    ulpi[row, col] = ik


@numba.njit(cache=True, nogil=True)
def _fill_holes(depth, image, ulpi, min_neighbours):
    """Filled copies of ``depth`` and ``image``: empty pixels with enough shown neighbours (docstring step 5)."""
    h, w = ulpi.shape
    out_d, out_i = depth.copy(), image.copy()
    drs = (-1, 1, 0, 0, -1, -1, 1, 1)
    dcs = (0, 0, -1, 1, -1, 1, -1, 1)
    for row in range(h):
        for col in range(w):
            if ulpi[row, col] >= 0:
                continue
            count, best, best_rank, best_z = 0, -1, 2, np.inf
            for k in range(8):
                rr, cc = row + drs[k], col + dcs[k]
                if rr < 0 or rr >= h or cc < 0 or cc >= w or ulpi[rr, cc] < 0:
                    continue
                count += 1
                rank = 0 if k < 4 else 1
                if rank < best_rank or (rank == best_rank and depth[rr, cc] < best_z):
                    best, best_rank, best_z = k, rank, depth[rr, cc]
            if count >= min_neighbours:
                out_d[row, col] = depth[row + drs[best], col + dcs[best]]
                out_i[row, col] = image[row + drs[best], col + dcs[best]]
    return out_d, out_i


# --------------------------------------------------------------------------- rendering


def estimate_point_spacing(points_w: np.ndarray, sample_size: int = 10_000, seed: int = 0) -> float:
    """Typical horizontal point spacing (m): median XY distance of a random sample to its nearest neighbour.

    The k-d tree holds all points (about 1 s per 5 M points); callers rendering many lidargrams of
    one cloud should estimate once and pass ``point_spacing_m``. Coincident points (distance 0)
    are ignored. NaN for fewer than two distinct positions.
    """
    xy = np.asarray(points_w, dtype=float)[:, :2]
    if xy.shape[0] < 2:
        return float("nan")
    rng = np.random.default_rng(seed)
    sample = xy[rng.choice(xy.shape[0], size=min(sample_size, xy.shape[0]), replace=False)]
    dist, _ = cKDTree(xy, balanced_tree=False, compact_nodes=False).query(sample, k=2)
    dist = dist[:, 1][dist[:, 1] > 0.0]
    return float(np.median(dist)) if dist.size else float("nan")


def _camera_coords(X_w: np.ndarray, R_w_c: np.ndarray, p_w_c: np.ndarray) -> np.ndarray:
    """``x_c = R_w_c^T (X_w - p_w_c)`` ``(N, 3)`` element-wise (no BLAS: the same bits for any N)."""
    d = [X_w[:, i] - p_w_c[i] for i in range(3)]
    return np.stack([d[0] * R_w_c[0, k] + d[1] * R_w_c[1, k] + d[2] * R_w_c[2, k] for k in range(3)], axis=1)


def max_normalised_radius2(camera: Camera, margin_px: float) -> float:
    """Largest squared ideal normalised radius on the image border widened by ``margin_px``, plus 5 %:
    the view test of :func:`render_lidargram` (``inf`` where the distortion does not invert)."""
    w, h, m = camera.width_px, camera.height_px, margin_px
    s = np.linspace(0.0, 1.0, 65)
    border = np.concatenate([np.stack([-m + s * (w + 2 * m), np.full_like(s, y)], 1) for y in (-m, h + m)]
                            + [np.stack([np.full_like(s, x), -m + s * (h + 2 * m)], 1) for x in (-m, w + m)])
    xn = camera.normalised(border)
    xd = (border - [camera.cx_px, camera.cy_px]) / [camera.fx_px, camera.fy_px]
    if not np.allclose(camera.distort(xn), xd, atol=1e-9):  # distortion not invertible there: no limit
        return float("inf")
    return float(np.max(np.sum(xn * xn, axis=1))) * 1.05**2


class LidargramCanvas:
    """A lidargram rendered from points given in parts (:func:`render_lidargram` in steps).

    :meth:`add` draws a part of the cloud into the z-buffer, each point with its identifier
    (``ids``, ascending within a part; e.g. its record number in the cloud), and keeps, per
    pixel, the coordinates and intensity of the point it shows; :meth:`finish` makes the
    lidargram. The result does not depend on how the cloud is cut into parts, so a cloud can be
    rendered without being held: memory is the rasters and one part. Parameters as
    :func:`render_lidargram` (``point_spacing_m`` is required here).
    """

    def __init__(self, camera: Camera, R_w_c: np.ndarray, p_w_c: np.ndarray, *, point_spacing_m: float,
                 splat_scale: float = 1.0, max_splat_px: int = MAX_SPLAT_PX, near_m: float = NEAR_M,
                 chunk_size: int = 5_000_000) -> None:
        R = np.array(R_w_c, dtype=np.float64)
        p = np.array(p_w_c, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3) or p.shape != (3,) or chunk_size < 1 or max_splat_px < 0.5 or splat_scale < 0:
            raise ValueError("need R_w_c (3, 3), p_w_c (3,), chunk_size >= 1, max_splat_px >= 0.5, splat_scale >= 0")
        self.camera, self.R, self.p = camera, R, p
        self.spacing = float(point_spacing_m)
        self.radius_factor = (splat_scale * 0.5 * self.spacing * camera.fx_px
                              if np.isfinite(self.spacing) and self.spacing > 0 else 0.0)
        self.max_splat_px, self.near_m, self.chunk_size = max_splat_px, float(near_m), int(chunk_size)
        self.rn2_max = max_normalised_radius2(camera, float(max_splat_px))
        h, w = camera.height_px, camera.width_px
        self.zbuf = np.full((h, w), np.inf)
        self.ulpi = np.full((h, w), -1, np.int64)
        self.xyz = np.zeros((h, w, 3))  # the shown point's coordinates and intensity
        self.intensity = np.zeros((h, w))

    def add(self, points_w: np.ndarray, intensity: np.ndarray, ids: np.ndarray) -> None:
        """Draw points ``(N, 3)`` with their intensities ``(N,)`` and identifiers ``(N,)`` (ascending)."""
        cam, R, p = self.camera, self.R, self.p
        h, w = cam.height_px, cam.width_px
        for start in range(0, len(ids), self.chunk_size):
            stop = start + self.chunk_size
            x_c = _camera_coords(np.asarray(points_w[start:stop], dtype=np.float64), R, p)
            z = x_c[:, 2]
            keep = np.flatnonzero(z > self.near_m)
            x_c, z = x_c[keep], z[keep]
            rn2 = (x_c[:, 0] * x_c[:, 0] + x_c[:, 1] * x_c[:, 1]) / (z * z)
            fov = rn2 <= self.rn2_max
            keep, x_c, z = keep[fov], x_c[fov], z[fov]
            uv = cam.project(x_c)
            r = np.clip(self.radius_factor / z, 0.5, self.max_splat_px)
            inside = (uv[:, 0] > -r - 1) & (uv[:, 0] < w + r + 1) & (uv[:, 1] > -r - 1) & (uv[:, 1] < h + r + 1)
            local = keep[inside] + start
            before = self.ulpi.copy()
            _splat(uv[inside, 0], uv[inside, 1], z[inside], r[inside], np.asarray(ids[local], dtype=np.int64),
                   self.zbuf, self.ulpi)
            won = self.ulpi != before  # pixels a point of this chunk now shows
            if won.any():
                at = local[np.searchsorted(ids[local], self.ulpi[won])]
                self.xyz[won] = points_w[at]
                self.intensity[won] = intensity[at]

    def finish(self, *, fill_holes: bool = False, fill_min_neighbours: int = 5) -> Lidargram:
        """The lidargram of the points drawn (module docstring, steps 3-5)."""
        cam, h, w = self.camera, self.camera.height_px, self.camera.width_px
        shown = self.ulpi >= 0
        point_index, first = np.unique(self.ulpi[shown], return_index=True)
        point_uv = cam.project(_camera_coords(self.xyz[shown][first], self.R, self.p))
        depth = np.where(shown, self.zbuf, np.nan).astype(np.float32)
        image = np.zeros((h, w), np.uint8)
        if point_index.size:
            values = self.intensity[shown][first]
            lo, hi = np.percentile(values, [2.0, 98.0])
            grey = (np.clip((self.intensity[shown] - lo) / (hi - lo), 0.0, 1.0) * 255.0 + 0.5 if hi > lo
                    else np.full(int(shown.sum()), 128.0))
            image[shown] = grey.astype(np.uint8)
        if fill_holes:
            depth, image = _fill_holes(depth, image, self.ulpi, int(fill_min_neighbours))
        return Lidargram(cam, self.R, self.p, image, depth, self.ulpi.copy(), point_index.astype(np.int64),
                         point_uv, self.spacing)


def render_lidargram(
    points_w: np.ndarray,
    intensity: np.ndarray,
    camera: Camera,
    R_w_c: np.ndarray,
    p_w_c: np.ndarray,
    *,
    point_spacing_m: float | None = None,
    splat_scale: float = 1.0,
    max_splat_px: int = MAX_SPLAT_PX,
    fill_holes: bool = False,
    fill_min_neighbours: int = 5,
    near_m: float = NEAR_M,
    chunk_size: int = 5_000_000,
) -> Lidargram:
    """Render the point cloud seen from pose ``(R_w_c, p_w_c)`` (module docstring).

    Parameters
    ----------
    points_w : (N, 3) float64, m
        Points in ``w``; the ULPI raster indexes this array.
    intensity : (N,) numeric
        Grey value source (any unit; normalised robustly).
    camera, R_w_c (3, 3), p_w_c (3,) m
        Interior orientation and pose: ``x_c = R_w_c^T (X_w - p_w_c)``.
    point_spacing_m
        Horizontal point spacing (m) sizing the splats; default :func:`estimate_point_spacing`.
    splat_scale
        Factor on the splat radius (1: splats of neighbouring points just touch).
    max_splat_px
        Largest splat radius (px); the smallest is 0.5 px (the point's own pixel).
    fill_holes, fill_min_neighbours
        Fill empty pixels with at least this many of 8 neighbours shown (image and depth only).
    near_m
        Points with ``z_c <= near_m`` (m) are not drawn.
    chunk_size
        Points projected at a time (bounds the temporaries; the result does not depend on it).

    A cloud too large to hold is rendered part by part with :class:`LidargramCanvas`.
    """
    points_w = np.asarray(points_w)
    intensity = np.asarray(intensity).reshape(-1)
    n = points_w.shape[0] if points_w.ndim == 2 else -1
    if points_w.ndim != 2 or points_w.shape[1] != 3 or intensity.shape != (n,):
        raise ValueError(f"points_w must be (N, 3) and intensity (N,), got {points_w.shape} and {intensity.shape}")
    if point_spacing_m is None:
        point_spacing_m = estimate_point_spacing(points_w)
    canvas = LidargramCanvas(camera, R_w_c, p_w_c, point_spacing_m=point_spacing_m, splat_scale=splat_scale,
                             max_splat_px=max_splat_px, near_m=near_m, chunk_size=chunk_size)
    canvas.add(points_w, intensity, np.arange(n, dtype=np.int64))
    return canvas.finish(fill_holes=fill_holes, fill_min_neighbours=fill_min_neighbours)


# --------------------------------------------------------------------------- files


def _paths(folder: PathLike, name: str) -> tuple[Path, Path]:
    return Path(folder) / f"{name}.png", Path(folder) / f"{name}.npz"


def save_lidargram(lg: Lidargram, folder: PathLike, name: str) -> tuple[Path, Path]:
    """Write ``<folder>/<name>.png`` and ``<folder>/<name>.npz`` atomically; returns both paths.

    The ULPI raster is stored as int32 when the indices fit (it is int64 again after loading).
    """
    png, npz = _paths(folder, name)
    ok, encoded = cv2.imencode(".png", lg.image)
    if not ok:
        raise ValueError(f"cannot encode lidargram {name} as PNG")
    small = lg.ulpi.size == 0 or lg.ulpi.max() < np.iinfo(np.int32).max
    with atomic_output(png, "wb") as fh:
        fh.write(encoded.tobytes())
    with atomic_output(npz, "wb") as fh:
        np.savez_compressed(
            fh, format_version=np.int64(FORMAT_VERSION),
            camera=np.array([getattr(lg.camera, f) for f in _CAMERA_FIELDS], dtype=np.float64),
            R_w_c=lg.R_w_c, p_w_c=lg.p_w_c, depth=lg.depth, ulpi=lg.ulpi.astype(np.int32) if small else lg.ulpi,
            point_index=lg.point_index, point_uv=lg.point_uv, point_spacing_m=np.float64(lg.point_spacing_m))
    return png, npz


def load_lidargram(folder: PathLike, name: str, camera: Camera) -> Lidargram:
    """Read a lidargram written by :func:`save_lidargram`, rendered with ``camera``.

    Raises
    ------
    InputError
        A missing or unreadable file, a missing array, a wrong shape or dtype, or a camera
        different from the one the lidargram was rendered with.
    """
    png, npz = _paths(folder, name)
    for path in (png, npz):
        if not path.is_file():
            raise InputError("file not found", path=path)
    image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError("cannot read the lidargram image", path=png, expected="an 8-bit grey PNG")
    arrays = {"image": image}
    try:
        with np.load(npz, allow_pickle=False) as data:
            files = set(data.files)
            for key in ("format_version", "camera", "point_spacing_m", *(k for k in _ARRAY_SPECS if k != "image")):
                if key in files:
                    arrays[key] = data[key]
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise InputError(f"not a readable lidargram file ({type(exc).__name__}: {exc})", path=npz,
                         expected="a .npz written by save_lidargram") from exc
    missing = [k for k in ("format_version", "camera", "point_spacing_m", *_ARRAY_SPECS) if k not in arrays]
    if missing:
        raise InputError("missing array", path=npz, field=missing[0])
    version = arrays.pop("format_version")
    if version.shape != () or int(version) != FORMAT_VERSION:
        raise InputError("unsupported format", path=npz, field="format_version",
                         expected=str(FORMAT_VERSION), found=str(version))
    stored = arrays.pop("camera")
    want = np.array([getattr(camera, f) for f in _CAMERA_FIELDS], dtype=np.float64)
    if stored.shape != want.shape or not np.allclose(stored, want, rtol=1e-12, atol=1e-12):
        raise InputError("rendered with a different camera", path=npz, field="camera",
                         expected=str(want.tolist()), found=str(stored.tolist()))
    spacing = arrays.pop("point_spacing_m")
    if spacing.shape != () or spacing.dtype != np.float64:
        raise InputError("bad point spacing", path=npz, field="point_spacing_m", expected="a float64 scalar",
                         found=f"{spacing.dtype} {spacing.shape}")
    if arrays["ulpi"].dtype == np.int32:
        arrays["ulpi"] = arrays["ulpi"].astype(np.int64)
    problem = _shape_problem(camera, arrays)
    if problem is not None:
        field, expected, found = problem
        raise InputError("wrong shape or type", path=png if field == "image" else npz, field=field,
                         expected=expected, found=found)
    pi, ul = arrays["point_index"], arrays["ulpi"]
    if (pi.size and (pi[0] < 0 or np.any(np.diff(pi) <= 0))) or (ul.size and ul.min() < -1):
        raise InputError("invalid point indices", path=npz, field="point_index",
                         expected="sorted distinct indices >= 0 and ulpi >= -1")
    return Lidargram(camera=camera, point_spacing_m=float(spacing), **arrays)
