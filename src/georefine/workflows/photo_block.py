"""The photo block of a project and its LiDAR cloud, read for lidargrammetry (paper 004; docs/ARCHITECTURE.md §4.8).

:func:`load_photo_project` reads and checks the photo files a project names (``photos``
section), :func:`read_cloud` indexes a georeferenced cloud for block reads in the block's local frame ``w``,
:func:`render_lidargrams` renders a lidargram per photo (and strip) at the photo's approximate
pose, :func:`write_cloud` writes a refined cloud back in the input's files and point order.
None of them holds the cloud: each task reads the blocks it needs (:mod:`georefine.workflows.cloud_index`).
:func:`lidargrammetry_settings` resolves the ``processing.lidargrammetry`` settings.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
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
from georefine.geometry.camera import Camera
from georefine.geometry.frames import GeoidHeights, LocalFrame, OutputCRS
from georefine.io import photos as pio
from georefine.io.las import PointCloud, point_files, read_las_range
from georefine.io.las_encode import EncodedPoints, ExtraDim, LasLayout, encode_points
from georefine.io.las_writer import LasWriter, offset_near
from georefine.lidargrammetry.reintersect import Reintersector
from georefine.lidargrammetry.render import MAX_SPLAT_PX, NEAR_M, Lidargram, LidargramCanvas, max_normalised_radius2
from georefine.progress import Progress, no_progress
from georefine.tasks import TaskRunner
from georefine.workflows.cloud_index import INDEX_RANGE_POINTS, RENDER_PART_POINTS, CloudIndex, index_cloud

__all__ = ["SECTION", "LIDARGRAMS_DIM", "PhotoProject", "CloudIndex", "lidargrammetry_settings", "load_photo_project", "read_cloud",
           "render_lidargrams", "render_in_cloud", "write_cloud"]

SECTION = "processing.lidargrammetry"
"""Where the settings are in ``project.yaml`` (errors name ``SECTION.field``)."""

LIDARGRAMS_DIM = ExtraDim("lidargrams", "i2", "lidargrams that showed the point", no_data=-1)
"""Extra dimension of the refined cloud: 1, 2, ... lidargrams, 0 interpolated, -1 (no data) unchanged."""


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
    warnings: tuple[str, ...] = ()
    heights: GeoidHeights | None = None  # the refined cloud's gravity-related heights (crs.geoid_grid)

    def camera(self, i: int) -> Camera:
        return self.cameras[self.eop.cameras[i]]

    def read_photos(self, progress: Progress = no_progress) -> list[np.ndarray]:
        """Every photo decoded in grey, each checked complete and of its camera's size
        (:func:`georefine.io.photos.read_photo`); about 10 ms per 10-megapixel JPEG."""
        photos = []
        for i, name in enumerate(self.eop.images):
            photos.append(pio.read_photo(self.folder / name, self.camera(i)))
            progress("read photos", i + 1, len(self.eop))
        return photos


def lidargrammetry_settings(config: ProjectConfig, overrides: Mapping[str, Any] | None = None) -> LidargrammetryConfig:
    """``processing.lidargrammetry`` of a project with ``overrides`` (field name to value) applied.

    Raises
    ------
    ConfigError
        An unknown field or a bad value; names ``processing.lidargrammetry.<field>``.
    """
    return override_fields(config.processing.lidargrammetry, overrides or {}, name=SECTION)  # type: ignore[return-value]


def load_photo_project(project_dir: str | Path, config: ProjectConfig | None = None, *,
                       frame: LocalFrame | None = None) -> PhotoProject:
    """Read and check the photo files of a project (:func:`georefine.io.photos.check_photo_block`).

    ``config``: the project's configuration if already loaded (else ``project.yaml`` is read).
    ``frame``: the mapping frame of the poses (default: one at the block's centre, at the
    control points' median height).
    The images themselves are read where they are used, and by ``georefine check``
    (:meth:`PhotoProject.read_photos`); the block's warnings are in ``warnings``.
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
    warnings = pio.check_photo_block(block, eop_path=root / ph.eop, gcp_path=root / (ph.gcp or "gcp.csv"),
                                     image_points_path=root / (ph.image_points or "image_points.csv"))
    crs = OutputCRS(cfg.crs.output_epsg)
    if frame is None:
        lat, lon, _ = crs.to_geodetic(eop.xyz.mean(axis=0))
        h0 = float(np.median(gcps.xyz[:, 2])) if gcps is not None and len(gcps) else 0.0
        frame = LocalFrame(float(lat), float(lon), h0)
    R, p = pio.poses_in_w(eop, frame, crs)
    empty = pio.ImagePoints((), (), np.zeros((0, 2)), np.zeros(0, np.int64))
    gc = gcps if gcps is not None else pio.ControlPoints((), np.zeros((0, 3)), np.zeros((0, 3)), ())
    return PhotoProject(root, frame, crs, cameras, eop, gc, pts or empty, root / ph.folder, R, p, tuple(warnings),
                        cfg.crs.geoid(root))


def read_cloud(paths: list[Path], pp: PhotoProject, *, runner: TaskRunner | None = None,
               progress: Progress = no_progress) -> CloudIndex:
    """Georeferenced LAZ/LAS strips (output CRS), indexed for block reads in ``w``
    (:mod:`georefine.workflows.cloud_index`; the points are not held). Strips with the
    gravity-related heights of the project's geoid grid are read back to ellipsoidal heights."""
    return index_cloud(point_files([Path(p) for p in paths]), pp.frame, pp.crs, runner=runner, progress=progress,
                       heights=pp.heights)


def render_lidargrams(pp: PhotoProject, cloud: CloudIndex, settings: LidargrammetryConfig | None = None, *,
                      progress: Progress = no_progress, runner: TaskRunner | None = None
                      ) -> list[tuple[Lidargram, int, int]]:
    """Lidargrams ``(lidargram, photo index, strip or -1)`` at the photos' approximate poses.

    ``settings``: ``lidargram_scale``, ``per_strip``, ``point_spacing_m``, ``splat_scale``,
    ``fill_holes`` and ``min_coverage`` (defaults of :class:`~georefine.config.LidargrammetryConfig` if None).
    ``runner``: where the lidargrams are rendered, one task per photo and strip
    (:mod:`georefine.tasks`; default in this process). Each task reads the blocks of the cloud
    in its view (:meth:`CloudIndex.blocks_in_view`); the lidargrams come back in the order of
    strips and photos whatever the scheduler, and are those of the whole cloud rendered at once.
    """
    st = settings or LidargrammetryConfig()
    per_strip = st.per_strip
    point_spacing_m = st.point_spacing_m
    if point_spacing_m is None:  # from the density of the cloud: mean spacing of its strips together
        point_spacing_m = cloud.point_spacing_m()
    runner = runner or TaskRunner("sync")
    index = runner.share(cloud)
    strips = range(len(cloud.files)) if per_strip else [-1]
    tasks = [(index, s, pp.camera(i).scaled(st.lidargram_scale), pp.R_w_c[i], pp.p_w_c[i], point_spacing_m,
              st.splat_scale, st.fill_holes, st.min_coverage) for s in strips for i in range(len(pp.eop))]
    out = []
    for k, lg in enumerate(runner.map(render_in_cloud, tasks, label="lidargrams", progress=progress)):
        if lg is not None:
            g, i = divmod(k, len(pp.eop))
            out.append((lg, i, g if per_strip else -1))
    return out


def render_in_cloud(cloud: CloudIndex, strip: int, camera: Camera, R_w_c: np.ndarray, p_w_c: np.ndarray,
                    point_spacing_m: float, splat_scale: float, fill_holes: bool, min_coverage: float
                    ) -> Lidargram | None:
    """One lidargram task: the points of strip ``strip`` (-1: all) in the view of a pose, read
    a few blocks at a time and drawn with their identifiers in the cloud
    (:class:`~georefine.lidargrammetry.render.LidargramCanvas`); ``None`` when less than
    ``min_coverage`` of its pixels show a point."""
    blocks = cloud.blocks_in_view(camera, R_w_c, p_w_c, max_normalised_radius2(camera, float(MAX_SPLAT_PX)), NEAR_M)
    if strip >= 0:
        blocks = blocks[cloud.block_file[blocks] == strip]
    canvas = LidargramCanvas(camera, R_w_c, p_w_c, point_spacing_m=point_spacing_m, splat_scale=splat_scale,
                             max_splat_px=MAX_SPLAT_PX, near_m=NEAR_M)
    for xyz, intensity, ids in cloud.iter_read(blocks, RENDER_PART_POINTS):  # memory: a part, not the view
        canvas.add(xyz, intensity, ids)
    lg = canvas.finish(fill_holes=fill_holes)
    if not lg.point_index.size or np.mean(lg.ulpi >= 0) < min_coverage:
        return None
    return lg


def write_cloud(cloud: CloudIndex, refine: Reintersector, folder: Path, *, protect: Sequence[Path] = (),
                runner: TaskRunner | None = None, progress: Progress = no_progress) -> dict[str, int]:
    """The refined strips, same file names and point order as the input (output CRS), streamed.

    Every point is moved by ``refine`` (:class:`~georefine.lidargrammetry.reintersect.Reintersector`)
    in tasks of :data:`~georefine.workflows.cloud_index.INDEX_RANGE_POINTS` records that read their
    range, move it and compress it (:func:`georefine.io.las_encode.encode_points`); this process
    writes the chunks in order. Extra dimension ``lidargrams`` (:data:`LIDARGRAMS_DIM`): how
    many lidargrams showed the point (0: interpolated from its neighbours, -1, the no-data value:
    outside every lidargram, unchanged). The scan angles are the input's (a move of centimetres
    turns a beam by far less than the LAS step of 0.006 degrees), and so is each file's source ID.
    Heights are ellipsoidal, or with the project's geoid grid (``cloud.heights``) gravity-related
    in the compound CRS, converted in each task (a point outside the grid is an error).
    Returns how many points were moved which way (as :meth:`Reintersection.summary`).
    """
    folder.mkdir(parents=True, exist_ok=True)
    runner = runner or TaskRunner("sync")
    shared = runner.share((cloud, refine))
    file_crs = cloud.crs.crs if cloud.heights is None else cloud.heights.compound_crs(cloud.crs)
    counts = np.zeros(4, np.int64)
    for k, f in enumerate(cloud.files):
        with LasWriter(folder / (f.stem + ".laz"), scale=0.001, offset=offset_near(cloud.file_centre[k]),
                       crs=file_crs, protect=[*protect, f], extra_dims=[LIDARGRAMS_DIM]) as w:
            layout = w.layout_for()
            n = int(cloud.file_start[k + 1] - cloud.file_start[k])
            tasks = [(shared, k, a, min(a + INDEX_RANGE_POINTS, n), layout) for a in range(0, n, INDEX_RANGE_POINTS)]
            for enc, c in runner.map(_refine_range, tasks, label=f"refined {f.stem}", progress=progress):
                w.write_encoded(enc)
                counts += c
    return {"points": int(counts.sum()), "multi_ray": int(counts[2]), "single_ray": int(counts[1]),
            "interpolated": int(counts[0]), "unchanged": int(counts[3])}


def _refine_range(shared: tuple[CloudIndex, Reintersector], strip: int, start: int, stop: int, layout: LasLayout
                  ) -> tuple[EncodedPoints, np.ndarray]:
    """One re-intersection task: records ``start..stop`` of a strip moved, encoded, and their
    counts (interpolated, single-ray, multi-ray, unchanged)."""
    cloud, refine = shared
    c = read_las_range(cloud.files[strip], start, stop)
    ids = cloud.file_start[strip] + np.arange(start, stop, dtype=np.int64)
    xyz_w, n = refine.refine(cloud.to_w(strip, c.xyz), ids, np.full(len(ids), strip))
    xyz = cloud.crs.from_w(cloud.frame, xyz_w)
    if cloud.heights is not None:  # the refined cloud is a final product: gravity-related heights
        xyz = cloud.heights.orthometric_xyz(cloud.crs, xyz, what=f"points of {cloud.files[strip].name}")
    out = PointCloud(c.time_gps, xyz, c.intensity, c.scanner_channel,
                     c.point_source_id, c.return_number, c.number_of_returns,
                     {"lidargrams": n.astype(np.float64)}, scan_angle_deg=c.scan_angle_deg)
    counts = np.array([np.count_nonzero(n == 0), np.count_nonzero(n == 1), np.count_nonzero(n >= 2),
                       np.count_nonzero(n < 0)], np.int64)
    return encode_points(out, layout), counts
