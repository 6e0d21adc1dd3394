"""A georeferenced cloud read block by block for lidargrammetry (docs/ARCHITECTURE.md §4.8).

Lidargrammetry needs the cloud in three places: every lidargram renders the points in its view,
the tie points take the coordinates of the points the lidargrams show, and the re-intersection
moves every point. None of them needs the whole cloud at once, so the cloud is never held: it is
indexed once (:func:`index_cloud`) and read back in blocks.

* **Blocks.** Each strip (LAS/LAZ file) is cut into blocks of :data:`BLOCK_POINTS` consecutive
  records, the LAZ chunk size, so a block is read by one seek through the chunk table
  (:func:`georefine.io.las.read_las_range`). The index keeps each block's bounding box in the
  block's local frame ``w``: 48 bytes per 50,000 points.
* **Point identifiers.** A point is its record number in the files taken in order
  (:attr:`CloudIndex.file_start`): the identifier the lidargram's ULPI raster holds, the same
  as for a cloud read whole, so the lidargrams and the refined cloud do not depend on the blocks.
* **A lidargram's blocks** (:meth:`CloudIndex.blocks_in_view`): those whose box may reach into
  the camera's field of view, tested conservatively on the projected box corners; the renderer
  applies its own exact test to their points.

Memory is that of one block range per task (a lidargram's view, a re-intersection range), not
of the cloud.

Every point is read into ``w`` with ellipsoidal heights. A strip with gravity-related heights
(a run's final cloud with ``crs.geoid_grid``: its header states ``crs.vertical_epsg``) is read
back with the project's grid, ``h = H + N`` (:attr:`CloudIndex.file_orthometric`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.errors import InputError
from georefine.geometry.camera import Camera
from georefine.geometry.frames import GeoidHeights, LocalFrame, OutputCRS
from georefine.io.las import read_las_info, read_las_range, vertical_epsg_of
from georefine.io.las_encode import LAZ_CHUNK_POINTS
from georefine.progress import Progress, no_progress
from georefine.tasks import TaskRunner

__all__ = ["BLOCK_POINTS", "INDEX_RANGE_POINTS", "RENDER_PART_POINTS", "CloudIndex", "index_cloud"]

BLOCK_POINTS = LAZ_CHUNK_POINTS
"""Records per block: one LAZ chunk, read by one seek."""

INDEX_RANGE_POINTS = 20 * BLOCK_POINTS
"""Records one indexing or re-intersection task reads at a time (1 M: about 0.2 GB of temporaries)."""

RENDER_PART_POINTS = 10 * BLOCK_POINTS
"""Records a lidargram task draws at a time. Measured on the 800 kHz `block` (28 lidargrams of
about 15 M points in view each, `threads`): 500,000 records peak at 2.09 GB and take 139 s,
2 M at 2.57 GB and 155 s."""


@dataclass(frozen=True, eq=False)
class CloudIndex:
    """Where the blocks of a cloud's strips are (module docstring). B blocks, F files.

    Attributes
    ----------
    files : the strips in order
    frame, crs : the local frame ``w`` the boxes are in and the files' output CRS
    file_start : (F + 1,) int64
        Identifier of each file's first point; the last entry is the number of points.
    block_start, block_stop : (B,) int64
        Identifiers of each block's first point and of the one after its last.
    block_file : (B,) int64
    lo, hi : (B, 3) float64, m
        Bounding box of each block's points in ``w``.
    file_centre : (F, 3) float64
        Centre of each file's header bounds (output CRS), from which refined files take their offset.
    heights : the project's geoid grid (``crs.geoid_grid``), or ``None``
    file_orthometric : (F,) bool
        Which files hold gravity-related heights of ``heights`` (read back to ellipsoidal ones).
    """

    files: tuple[Path, ...]
    frame: LocalFrame
    crs: OutputCRS
    file_start: np.ndarray
    block_start: np.ndarray
    block_stop: np.ndarray
    block_file: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    file_centre: np.ndarray
    heights: GeoidHeights | None = None
    file_orthometric: tuple[bool, ...] = ()

    def to_w(self, file: int, xyz: np.ndarray) -> np.ndarray:
        """``w`` positions of points of file ``file`` (output CRS, as stored in it)."""
        return _to_w(self.files[file], xyz, self.frame, self.crs,
                     self.heights if file < len(self.file_orthometric) and self.file_orthometric[file] else None)

    @property
    def n_points(self) -> int:
        return int(self.file_start[-1])

    def strip_of(self, index: np.ndarray) -> np.ndarray:
        """File of each point identifier."""
        return (np.searchsorted(self.file_start, index, side="right") - 1).astype(np.int64)

    def point_spacing_m(self) -> float:
        """Mean horizontal point spacing: the square root of the cloud's XY box area per point."""
        if not self.n_points:
            return float("nan")
        lo, hi = self.lo[:, :2].min(axis=0), self.hi[:, :2].max(axis=0)
        return float(np.sqrt(np.prod(hi - lo) / self.n_points))

    def blocks_in_view(self, camera: Camera, R_w_c: np.ndarray, p_w_c: np.ndarray, max_normalised_radius2: float,
                       near_m: float) -> np.ndarray:
        """Blocks that may hold a point with ``z_c > near_m`` and ideal normalised radius² at most
        ``max_normalised_radius2`` (the renderer's view test; ``inf``: no radius limit).

        A box wholly in front of the camera projects inside the bounding rectangle of its
        projected corners (perspective keeps convexity), so a box whose rectangle misses the
        square of that radius holds no such point. A box reaching behind the camera is kept
        unless it lies wholly at or behind ``near_m``.
        """
        corners = np.stack([np.where(np.array([(c >> i) & 1 for i in range(3)], bool), self.hi, self.lo)
                            for c in range(8)], axis=1)  # (B, 8, 3)
        d = corners - np.asarray(p_w_c, float)
        x_c = d @ np.asarray(R_w_c, float)  # (B, 8, 3): R^T d per corner
        z = x_c[..., 2]
        reaches = (z > near_m).any(axis=1)
        ahead = (z > 0).all(axis=1)
        keep = reaches.copy()
        if np.isfinite(max_normalised_radius2):
            r = np.sqrt(max_normalised_radius2) * (1 + 1e-9)
            with np.errstate(divide="ignore", invalid="ignore"):
                xn, yn = x_c[..., 0] / z, x_c[..., 1] / z
            miss = np.zeros(len(z), bool)
            miss[ahead] = ((xn[ahead].min(axis=1) > r) | (xn[ahead].max(axis=1) < -r)
                           | (yn[ahead].min(axis=1) > r) | (yn[ahead].max(axis=1) < -r))
            keep &= ~miss
        return np.flatnonzero(keep)

    def iter_read(self, blocks: np.ndarray, max_points: int = INDEX_RANGE_POINTS
                  ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """``(xyz_w, intensity, identifiers)`` of the points of ``blocks`` in parts of at most
        ``max_points`` records (whole blocks, at least one), in identifier order: consecutive
        blocks of a file are read as one record range."""
        blocks = np.unique(np.asarray(blocks, dtype=np.int64))
        for f, start, stop in self._runs(blocks):
            step = max(BLOCK_POINTS, max_points // BLOCK_POINTS * BLOCK_POINTS)
            for a in range(start, stop, step):
                b = min(a + step, stop)
                c = read_las_range(self.files[f], a, b)
                yield (self.to_w(f, c.xyz), np.asarray(c.intensity),
                       self.file_start[f] + np.arange(a, b, dtype=np.int64))

    def gather(self, index: np.ndarray, max_points: int = INDEX_RANGE_POINTS) -> np.ndarray:
        """``w`` coordinates of the points ``index`` (sorted, distinct), reading their blocks
        about ``max_points`` records at a time."""
        index = np.asarray(index, dtype=np.int64)
        out = np.zeros((len(index), 3))
        if not len(index):
            return out
        if np.any(np.diff(index) <= 0) or index[0] < 0 or index[-1] >= self.n_points:
            raise ValueError("point identifiers must be sorted, distinct and within the cloud")
        blk = np.searchsorted(self.block_start, index, side="right") - 1
        for xyz, _, ids in self.iter_read(np.unique(blk), max_points):  # a part: consecutive records
            sel = slice(int(np.searchsorted(index, ids[0])), int(np.searchsorted(index, ids[-1], side="right")))
            out[sel] = xyz[index[sel] - ids[0]]
        return out

    def _runs(self, blocks: np.ndarray):
        """``(file, start record, stop record)`` of each run of consecutive blocks in a file."""
        if not len(blocks):
            return
        cut = np.flatnonzero((np.diff(blocks) != 1) | (np.diff(self.block_file[blocks]) != 0)) + 1
        for run in np.split(blocks, cut):
            f = int(self.block_file[run[0]])
            yield f, int(self.block_start[run[0]] - self.file_start[f]), int(self.block_stop[run[-1]]
                                                                            - self.file_start[f])


def _to_w(path: Path, xyz: np.ndarray, frame: LocalFrame, crs: OutputCRS, orthometric: GeoidHeights | None
          ) -> np.ndarray:
    """``w`` positions of a file's points; ``orthometric``: the grid their gravity-related heights come from."""
    if orthometric is not None:
        xyz = orthometric.ellipsoidal_xyz(crs, xyz, what=f"points of {Path(path).name}")
    return crs.to_w(frame, xyz)


def _index_range(path: Path, start: int, stop: int, frame: LocalFrame, crs: OutputCRS,
                 orthometric: GeoidHeights | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One indexing task: ``w`` bounding boxes of the blocks of records ``start..stop`` of a file."""
    c = read_las_range(path, start, stop)
    xyz = _to_w(path, c.xyz, frame, crs, orthometric)
    cut = np.arange(0, len(xyz), BLOCK_POINTS)
    return np.minimum.reduceat(xyz, cut, axis=0), np.maximum.reduceat(xyz, cut, axis=0)


def index_cloud(files: list[Path], frame: LocalFrame, crs: OutputCRS, *, runner: TaskRunner | None = None,
                progress: Progress = no_progress, heights: GeoidHeights | None = None) -> CloudIndex:
    """Index georeferenced strips (output CRS) for block reads in ``frame``: one pass over the points,
    as tasks of :data:`INDEX_RANGE_POINTS` records on ``runner`` (default in this process).
    ``heights``: the project's geoid grid; files whose header states its vertical CRS are read
    back to ellipsoidal heights.

    Raises
    ------
    InputError
        A file that does not open or is corrupt (named, with the record range); a cloud without
        points; a file with gravity-related heights of another vertical CRS than ``heights``
        (which could not be read back to ellipsoidal ones).
    """
    files = [Path(f) for f in files]
    infos = [read_las_info(f) for f in files]
    vertical = [vertical_epsg_of(f) for f in files]
    for f, v in zip(files, vertical):
        if v is not None and (heights is None or v != int(heights.vertical_epsg)):
            raise InputError(
                "the points have gravity-related heights, which lidargrammetry reads back to ellipsoidal ones only "
                "with the project's geoid grid", path=f, field="crs.vertical_epsg",
                expected=f"EPSG:{v} with crs.geoid_grid in project.yaml, or ellipsoidal heights",
                found="no geoid grid" if heights is None else f"EPSG:{heights.vertical_epsg}")
    orthometric = tuple(v is not None for v in vertical)
    counts = np.array([i.point_count for i in infos], dtype=np.int64)
    if not counts.sum():
        raise InputError("the point cloud has no points", path=", ".join(map(str, files)),
                         expected="georeferenced strips with points")
    file_start = np.r_[0, np.cumsum(counts)].astype(np.int64)
    starts, stops, owner = [], [], []
    for f, n in enumerate(counts):
        s = np.arange(0, n, BLOCK_POINTS, dtype=np.int64)
        starts.append(file_start[f] + s)
        stops.append(file_start[f] + np.minimum(s + BLOCK_POINTS, n))
        owner.append(np.full(len(s), f, dtype=np.int64))
    tasks = [(files[f], a, min(a + INDEX_RANGE_POINTS, int(n)), frame, crs, heights if orthometric[f] else None)
             for f, n in enumerate(counts) for a in range(0, int(n), INDEX_RANGE_POINTS)]
    runner = runner or TaskRunner("sync")
    parts = list(runner.map(_index_range, tasks, label="indexing the cloud", progress=progress))
    lo = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 3))
    hi = np.concatenate([p[1] for p in parts]) if parts else np.zeros((0, 3))
    centre = np.array([0.5 * (i.mins + i.maxs) for i in infos]).reshape(-1, 3)
    return CloudIndex(tuple(files), frame, crs, file_start, np.concatenate(starts), np.concatenate(stops),
                      np.concatenate(owner), lo, hi, centre, heights, orthometric)
