"""The photo block of a project and its LiDAR cloud, read for lidargrammetry (paper 004; docs/ARCHITECTURE.md §4.8).

:func:`load_photo_project` reads and checks the photo files a project names (``photos``
section), :func:`read_cloud` a georeferenced cloud into the block's local frame ``w``,
:func:`render_lidargrams` renders a lidargram per photo (and strip) at the photo's approximate
pose, :func:`write_cloud` writes a refined cloud back in the input's files and point order.
:func:`lidargrammetry_settings` resolves the ``processing.lidargrammetry`` settings.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from georefine.config import (
    LidargrammetryConfig,
    ProjectConfig,
    load_project,
    override_fields,
)
from georefine.errors import InputError
from georefine.evaluation.clouds import point_files
from georefine.geometry.camera import Camera
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io import photos as pio
from georefine.io.las import PointCloud, iter_las_chunks
from georefine.io.las_writer import LasWriter
from georefine.lidargrammetry.render import Lidargram, render_lidargram
from georefine.progress import Progress, no_progress
from georefine.tasks import TaskRunner

__all__ = ["SECTION", "PhotoProject", "Cloud", "lidargrammetry_settings", "load_photo_project", "read_cloud",
           "render_lidargrams", "render_in_cloud", "write_cloud"]

SECTION = "processing.lidargrammetry"
"""Where the settings are in ``project.yaml`` (errors name ``SECTION.field``)."""


@dataclass(frozen=True)
class PhotoProject:
    """The photo block of a project, checked, with approximate poses in a local frame ``w``."""

    root: Path
    frame: LocalFrame
    crs: OutputCRS
    cameras: dict[str, Camera]
    eop: pio.ExteriorOrientation
    gcps: pio.ControlPoints
    image_points: pio.ImagePoints
    folder: Path
    R_w_c: np.ndarray
    p_w_c: np.ndarray

    def camera(self, i: int) -> Camera:
        return self.cameras[self.eop.cameras[i]]


@dataclass(frozen=True)
class Cloud:
    """A georeferenced point cloud in ``w``, strip by strip (files kept for writing back)."""

    files: tuple[Path, ...]
    xyz_w: np.ndarray
    intensity: np.ndarray
    strip: np.ndarray  # (N,) index into files


def lidargrammetry_settings(config: ProjectConfig, overrides: Mapping[str, Any] | None = None) -> LidargrammetryConfig:
    """``processing.lidargrammetry`` of a project with ``overrides`` (field name to value) applied.

    Raises
    ------
    ConfigError
        An unknown field or a bad value; names ``processing.lidargrammetry.<field>``.
    """
    return override_fields(config.processing.lidargrammetry, overrides or {}, name=SECTION)  # type: ignore[return-value]


def load_photo_project(project_dir: str | Path, config: ProjectConfig | None = None) -> PhotoProject:
    """Read and check the photo files of a project (:func:`georefine.io.photos.check_photo_block`).

    ``config``: the project's configuration if already loaded (else ``project.yaml`` is read).
    """
    root = Path(project_dir)
    cfg = load_project(root) if config is None else config
    ph = cfg.photos
    if ph is None:
        raise InputError("the project has no photos", path=root / "project.yaml", field="photos",
                         expected="a photos section (folder, cameras, eop, gcp, image_points)")
    cameras = pio.read_cameras(root / ph.cameras)
    eop = pio.read_eop(root / ph.eop, cameras)
    gcps = pio.read_gcps(root / ph.gcp) if ph.gcp else None
    pts = pio.read_image_points(root / ph.image_points) if ph.image_points else None
    block = pio.PhotoBlock(cameras, eop, gcps, pts, root / ph.folder)
    pio.check_photo_block(block, eop_path=root / ph.eop, gcp_path=root / (ph.gcp or "gcp.csv"),
                          image_points_path=root / (ph.image_points or "image_points.csv"))
    crs = OutputCRS(cfg.crs.output_epsg)
    lat, lon, _ = crs.to_geodetic(eop.xyz.mean(axis=0))
    h0 = float(np.median(gcps.xyz[:, 2])) if gcps is not None and len(gcps) else 0.0
    frame = LocalFrame(float(lat), float(lon), h0)
    R, p = pio.poses_in_w(eop, frame, crs)
    empty = pio.ImagePoints((), (), np.zeros((0, 2)), np.zeros(0, np.int64))
    gc = gcps if gcps is not None else pio.ControlPoints((), np.zeros((0, 3)), np.zeros((0, 3)), ())
    return PhotoProject(root, frame, crs, cameras, eop, gc, pts or empty, root / ph.folder, R, p)


def read_cloud(paths: list[Path], pp: PhotoProject) -> Cloud:
    """Georeferenced LAZ/LAS strips (output CRS) into ``w``."""
    files = point_files([Path(p) for p in paths])
    xyz, inten, strip = [], [], []
    for k, f in enumerate(files):
        for c in iter_las_chunks(f, 5_000_000):
            xyz.append(pp.crs.to_w(pp.frame, c.xyz))
            inten.append(np.asarray(c.intensity, dtype=float))
            strip.append(np.full(len(c.xyz), k, dtype=np.int32))
    return Cloud(tuple(files), np.concatenate(xyz), np.concatenate(inten), np.concatenate(strip))


def render_lidargrams(pp: PhotoProject, cloud: Cloud, settings: LidargrammetryConfig | None = None, *,
                      progress: Progress = no_progress, runner: TaskRunner | None = None
                      ) -> list[tuple[Lidargram, int, int]]:
    """Lidargrams ``(lidargram, photo index, strip or -1)`` at the photos' approximate poses.

    ``settings``: ``lidargram_scale``, ``per_strip``, ``point_spacing_m``, ``splat_scale``,
    ``fill_holes`` and ``min_coverage`` (defaults of :class:`~georefine.config.LidargrammetryConfig` if None).
    ``runner``: where the lidargrams are rendered, one task per photo and strip
    (:mod:`georefine.tasks`; default in this process). The cloud goes to each worker once; the
    lidargrams come back in the order of strips and photos whatever the scheduler.
    """
    st = settings or LidargrammetryConfig()
    per_strip, point_spacing_m = st.per_strip, st.point_spacing_m
    groups = [np.flatnonzero(cloud.strip == s) for s in range(len(cloud.files))] if per_strip else \
        [np.arange(len(cloud.xyz_w))]
    if point_spacing_m is None:  # from the density of the cloud: mean spacing of its strips together
        lo, hi = cloud.xyz_w[:, :2].min(axis=0), cloud.xyz_w[:, :2].max(axis=0)
        point_spacing_m = float(np.sqrt(np.prod(hi - lo) / len(cloud.xyz_w)))
    runner = runner or TaskRunner("sync")
    xyz, intensity = runner.share(cloud.xyz_w), runner.share(cloud.intensity)
    tasks = []
    for sel in groups:
        shared_sel = runner.share(sel)
        for i in range(len(pp.eop)):
            tasks.append((xyz, intensity, shared_sel, pp.camera(i).scaled(st.lidargram_scale), pp.R_w_c[i],
                          pp.p_w_c[i], point_spacing_m, st.splat_scale, st.fill_holes, st.min_coverage))
    out = []
    for k, lg in enumerate(runner.map(render_in_cloud, tasks, label="lidargrams", progress=progress)):
        if lg is not None:
            g, i = divmod(k, len(pp.eop))
            out.append((lg, i, g if per_strip else -1))
    return out


def render_in_cloud(xyz_w: np.ndarray, intensity: np.ndarray, sel: np.ndarray, camera: Camera, R_w_c: np.ndarray,
                    p_w_c: np.ndarray, point_spacing_m: float, splat_scale: float, fill_holes: bool,
                    min_coverage: float) -> Lidargram | None:
    """One lidargram task: the points ``sel`` of the cloud rendered at a pose, its indices into the
    whole cloud; ``None`` when less than ``min_coverage`` of its pixels show a point."""
    lg = render_lidargram(xyz_w[sel], intensity[sel], camera, R_w_c, p_w_c, point_spacing_m=point_spacing_m,
                          splat_scale=splat_scale, fill_holes=fill_holes)
    if np.mean(lg.ulpi >= 0) < min_coverage:
        return None
    return replace(lg, ulpi=np.where(lg.ulpi >= 0, sel[np.maximum(lg.ulpi, 0)], -1), point_index=sel[lg.point_index])


def write_cloud(cloud: Cloud, pp: PhotoProject, xyz_w: np.ndarray, n_lidargrams: np.ndarray, folder: Path) -> None:
    """The refined strips, same files and point order as the input (output CRS).

    Extra dimension ``lidargrams``: how many lidargrams showed the point (0: interpolated from
    its neighbours, -1: outside every lidargram, unchanged).
    """
    folder.mkdir(parents=True, exist_ok=True)
    for k, f in enumerate(cloud.files):
        sel = np.flatnonzero(cloud.strip == k)
        xyz = pp.crs.from_w(pp.frame, xyz_w[sel])
        done = 0
        count = n_lidargrams[sel].astype(np.float64)
        with LasWriter(folder / (f.stem + ".laz"), scale=0.001, crs=pp.crs.crs, protect=[pp.root, f],
                       extra_dims=["lidargrams"]) as w:
            for c in iter_las_chunks(f, 5_000_000, extra_dims=()):
                m = len(c.xyz)
                w.write(PointCloud(c.time_gps, xyz[done:done + m], c.intensity, c.scanner_channel, c.point_source_id,
                                   c.return_number, c.number_of_returns, {"lidargrams": count[done:done + m]}))
                done += m
