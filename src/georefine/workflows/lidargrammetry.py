"""Lidargrammetric co-matching and co-adjustment of a project (paper 004; docs/ARCHITECTURE.md §4.8).

:func:`run_coadjust` takes a project with photos (``project.yaml`` section ``photos``) and a
georeferenced point cloud (LAZ strips in the output CRS, e.g. ``georefine run`` output) and

1. renders lidargrams at the photos' approximate orientation -- one per photo and strip by
   default, so that each lidargram belongs to one trajectory (a strip's error is one smooth
   function, two strips' errors are not) -- at ``lidargram_scale`` of the photo resolution
   (the paper's point spacing is 2.5-3 GSD);
2. matches photo-photo and photo-lidargram pairs whose footprints overlap (SIFT by default,
   XFeat with ``method="xfeat"``), builds tracks and keeps those seen from two or more stations
   (a photo and the lidargram rendered at its pose are one station: no base between them);
3. adjusts the block as case 1, 2 or 3 (:mod:`georefine.lidargrammetry.bundle`), with the
   depth a lidargram shows at each tie keypoint as an observation (``use_depth``; off: the
   paper's image-only formulation);
4. writes the adjusted orientation of photos and lidargrams (``eop_photos.csv``,
   ``eop_lidargrams.csv``, output CRS), for cases 1 and 2 the refined point cloud
   (``points/``, same files and point order as the input, :mod:`.reintersect`), a match picture
   of one photo-lidargram pair (cf. paper Fig. 6) and ``metrics.json``.
"""

from __future__ import annotations

import logging
import shutil
import time as _time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from georefine.adjustment.observations.reprojection import ReprojectionObservation
from georefine.config import load_project
from georefine.errors import InputError
from georefine.evaluation.clouds import point_files
from georefine.geometry.camera import Camera
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io import metashape
from georefine.io.colmap import to_reconstruction, write_model
from georefine.io import photos as pio
from georefine.io.files import atomic_output, write_json
from georefine.io.las import LasWriter, PointCloud, iter_las_chunks
from georefine.lidargrammetry.bundle import (
    CASES,
    BlockImages,
    BundleResult,
    ControlData,
    coadjust,
    intersect_points,
    stations_per_point,
)
from georefine.lidargrammetry.matching import (
    Keypoints,
    LightGlueMatcher,
    PairMatches,
    Tracks,
    XFeatMatcher,
    build_tracks,
    detect_sift,
    draw_matches,
    match_pair,
    verify_pair,
)
from georefine.lidargrammetry.reintersect import feather_weights, reintersect
from georefine.lidargrammetry.render import Lidargram, render_lidargram
from georefine.progress import Progress, no_progress
from georefine.workflows.cache import StepCache, file_stamp
from georefine.workflows.project import output_folder

log = logging.getLogger(__name__)

__all__ = ["PhotoProject", "Cloud", "PAIR_KINDS", "load_photo_project", "read_cloud", "render_lidargrams",
           "make_matcher", "match_block", "run_match", "run_coadjust", "export_colmap"]


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


def load_photo_project(project_dir: str | Path) -> PhotoProject:
    """Read and check the photo files of a project (:func:`georefine.io.photos.check_photo_block`)."""
    root = Path(project_dir)
    cfg = load_project(root)
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


def render_lidargrams(pp: PhotoProject, cloud: Cloud, *, scale: float = 0.5, per_strip: bool = True,
                      point_spacing_m: float | None = None, splat_scale: float = 2.0, min_coverage: float = 0.3,
                      progress: Progress = no_progress) -> list[tuple[Lidargram, int, int]]:
    """Lidargrams ``(lidargram, photo index, strip or -1)`` at the photos' approximate poses."""
    groups = [np.flatnonzero(cloud.strip == s) for s in range(len(cloud.files))] if per_strip else \
        [np.arange(len(cloud.xyz_w))]
    if point_spacing_m is None:  # from the density of the cloud: mean spacing of its strips together
        lo, hi = cloud.xyz_w[:, :2].min(axis=0), cloud.xyz_w[:, :2].max(axis=0)
        point_spacing_m = float(np.sqrt(np.prod(hi - lo) / len(cloud.xyz_w)))
    out = []
    total = len(groups) * len(pp.eop)
    for g, sel in enumerate(groups):
        for i in range(len(pp.eop)):
            progress("lidargrams", g * len(pp.eop) + i, total)
            lg = render_lidargram(cloud.xyz_w[sel], cloud.intensity[sel], pp.camera(i).scaled(scale), pp.R_w_c[i],
                                  pp.p_w_c[i], point_spacing_m=point_spacing_m, splat_scale=splat_scale,
                                  fill_holes=True)
            if np.mean(lg.ulpi >= 0) < min_coverage:
                continue
            lg = replace(lg, ulpi=np.where(lg.ulpi >= 0, sel[np.maximum(lg.ulpi, 0)], -1),
                         point_index=sel[lg.point_index])
            out.append((lg, i, g if per_strip else -1))
    progress("lidargrams", total, total)
    return out


@dataclass(frozen=True)
class BlockMatches:
    keypoints: list[Keypoints]
    pairs: list[PairMatches]
    tracks: Tracks


PAIR_KINDS = ("photo-photo", "photo-lidargram", "lidargram-lidargram")


def _check_pair_kinds(pair_kinds) -> None:
    bad = set(pair_kinds) - set(PAIR_KINDS)
    if bad or not pair_kinds:
        raise InputError("unknown pair kind", field="pairs", expected=", ".join(PAIR_KINDS),
                         found=", ".join(sorted(bad)) or "nothing")


def _pair_kind(is_lidargram: np.ndarray, a: int, b: int) -> str:
    la, lb = bool(is_lidargram[a]), bool(is_lidargram[b])
    return "lidargram-lidargram" if la and lb else "photo-lidargram" if la or lb else "photo-photo"


def _draw_best(pairs: list[PairMatches], is_lidargram: np.ndarray, images: list, keypoints: list[Keypoints],
               path: Path) -> None:
    """Picture of the pair with the most verified matches, a lidargram on the left (cf. paper Fig. 6)."""
    best = max(pairs, key=len, default=None)
    if best is None or not len(best):
        return
    a, b, ia, ib = best.a, best.b, best.ia, best.ib
    if is_lidargram[b] and not is_lidargram[a]:
        a, b, ia, ib = b, a, ib, ia
    draw_matches(images[a], images[b], keypoints[a].uv[ia], keypoints[b].uv[ib], path)


def make_matcher(method: str = "sift", *, lightglue_features: str = "disk", extractor_weights: Path | None = None,
                 lightglue_weights: Path | None = None, max_features: int = 6000):
    """``None`` for SIFT (OpenCV), else a matcher object with ``detect`` and ``match``."""
    if method == "sift":
        return None
    if method == "xfeat":
        return XFeatMatcher(max_features=max_features)
    if method == "lightglue":
        if extractor_weights is None or lightglue_weights is None:
            raise InputError("LightGlue needs local weight files", field="--extractor-weights/--lightglue-weights",
                             expected="the extractor's and LightGlue's .pth files (nothing is downloaded)")
        return LightGlueMatcher(lightglue_features, extractor_weights, lightglue_weights, max_features=max_features)
    raise InputError("unknown matching method", field="--method", expected="sift, xfeat or lightglue", found=method)


def match_block(images: list[np.ndarray], cameras: list[Camera], station: np.ndarray, is_lidargram: np.ndarray,
                centres: np.ndarray, masks: list, *, method="sift", max_pair_distance_m: float = 150.0,
                pair_kinds: tuple[str, ...] = ("photo-photo", "photo-lidargram"),
                progress: Progress = no_progress) -> BlockMatches:
    """Keypoints of every image, verified matches of overlapping pairs of the kinds asked, tracks.

    ``method``: ``"sift"``, ``"xfeat"`` or a matcher object (:func:`make_matcher`). Pairs whose
    approximate centres are closer than ``max_pair_distance_m``; lidargram-lidargram pairs are
    left out by default (two lidargrams of one station have no base, two of one strip repeat the
    same trajectory error).
    """
    _check_pair_kinds(pair_kinds)
    clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8))
    enhanced = [clahe.apply(im) for im in images]
    matcher = make_matcher(method) if isinstance(method, str) else method
    n = len(images)
    if matcher is None:
        kps = [detect_sift(im, mask=m) for im, m in zip(enhanced, masks)]
    else:
        kps = []
        for k, im in enumerate(enhanced):
            progress("keypoints", k, n)
            kps.append(matcher.detect(im))
        progress("keypoints", n, n)
    pairs = [(a, b) for a in range(n) for b in range(a + 1, n)
             if _pair_kind(is_lidargram, a, b) in pair_kinds and np.linalg.norm(centres[a] - centres[b]) < max_pair_distance_m]
    out = []
    for k, (a, b) in enumerate(pairs):
        progress("matching", k, len(pairs))
        if matcher is None:
            m = match_pair(kps[a], kps[b], cameras[a], cameras[b], a, b, ratio=0.9, threshold_px=2.0)
        else:
            ia, ib = matcher.match(kps[a], kps[b], images[a].shape[::-1], images[b].shape[::-1])
            ok = verify_pair(kps[a].uv[ia], kps[b].uv[ib], cameras[a], cameras[b], threshold_px=2.0)
            ok = ok if ok.sum() >= 15 else np.zeros_like(ok)
            m = PairMatches(a, b, ia[ok], ib[ok], len(ia))
        out.append(m)
    progress("matching", len(pairs), len(pairs))
    return BlockMatches(kps, out, build_tracks(kps, out))


def _ties(lgs, imgs_R, imgs_p, cameras, station, matches: BlockMatches, cloud: Cloud, n_photos: int,
          max_initial_px: float = 15.0):
    """Tie observations, initial points (ULPI points, else photo intersections), lidargram depths."""
    tr = matches.tracks
    ntr = tr.n_tracks
    is_lg = tr.image >= n_photos
    acc, cnt = np.zeros((ntr, 3)), np.zeros(ntr)
    depth = np.full(len(tr), np.nan)
    for o in np.flatnonzero(is_lg):
        lg = lgs[tr.image[o] - n_photos][0]
        u = lg.ulpi_at(tr.uv[o][None])[0]
        if u >= 0:
            acc[tr.track[o]] += cloud.xyz_w[u]
            cnt[tr.track[o]] += 1
            c, r = np.floor(tr.uv[o]).astype(int)
            depth[o] = lg.depth[r, c]
    xyz0 = np.full((ntr, 3), np.nan)
    has = cnt > 0
    xyz0[has] = acc[has] / cnt[has, None]
    Xi, nr = intersect_points(cameras, imgs_R, imgs_p, tr.image[~is_lg], tr.track[~is_lg], tr.uv[~is_lg], ntr)
    fill = ~has & (nr >= 2)
    xyz0[fill] = Xi[fill]
    ok = np.isfinite(xyz0[:, 0])
    grp = ReprojectionObservation("init", cameras, tr.image, tr.track, tr.uv)
    uv, front = grp.predict({"image_rotation": imgs_R, "image_position": imgs_p,
                             "points": np.where(ok[:, None], xyz0, 0.0)})
    keep = ok[tr.track] & front & (np.linalg.norm(uv - tr.uv, axis=1) < max_initial_px)
    keep &= stations_per_point(tr.track[keep], station[tr.image[keep]], ntr)[tr.track] >= 2
    return keep, xyz0, depth


@dataclass(frozen=True)
class _Block:
    """Photos and the lidargrams rendered at their stations, as one list of images."""

    lgs: list
    n_photos: int
    cameras: list
    station: np.ndarray  # (n,) photo index each image was taken or rendered at
    is_lidargram: np.ndarray
    R0: np.ndarray
    p0: np.ndarray
    images: list
    masks: list
    names: tuple


def _open(project_dir, out, points) -> tuple[PhotoProject, Path, Cloud]:
    """The photo project, the output folder (outside the project; created once the inputs read) and the cloud."""
    pp = load_photo_project(project_dir)
    out = output_folder(out, pp.root)
    cloud = read_cloud([Path(p) for p in points], pp)
    out.mkdir(parents=True, exist_ok=True)
    return pp, out, cloud


def _block_images(pp: PhotoProject, cloud: Cloud, scale: float, progress: Progress) -> _Block:
    lgs = render_lidargrams(pp, cloud, scale=scale, progress=progress)
    n = len(pp.eop)
    photos = [cv2.imread(str(pp.folder / name), cv2.IMREAD_GRAYSCALE) for name in pp.eop.images]
    for name, img in zip(pp.eop.images, photos):
        if img is None:
            raise InputError("image does not open", path=pp.folder / name, expected="an image file OpenCV reads")
    station = np.array(list(range(n)) + [i for _, i, _ in lgs], dtype=np.int64)
    names = tuple(pp.eop.images) + tuple(f"LG_{Path(cloud.files[s]).stem if s >= 0 else 'all'}_{pp.eop.images[i]}"
                                         for _, i, s in lgs)
    return _Block(lgs, n, [pp.camera(i) for i in range(n)] + [lg.camera for lg, _, _ in lgs], station,
                  np.r_[np.zeros(n, bool), np.ones(len(lgs), bool)], pp.R_w_c[station], pp.p_w_c[station],
                  photos + [lg.image for lg, _, _ in lgs], [None] * n + [np.isfinite(lg.depth) for lg, _, _ in lgs],
                  names)


def run_match(project_dir: str | Path, points: list[str | Path], out: str | Path, *, method: str = "sift",
              matcher=None, pair_kinds: tuple[str, ...] = ("photo-photo", "photo-lidargram"),
              lidargram_scale: float = 0.5, max_pair_distance_m: float = 150.0,
              progress: Progress = no_progress) -> dict:
    """Render the lidargrams, match the pairs of the kinds asked and write the matches.

    Writes into ``out``: ``lidargrams/`` (PNG and ULPI npz of each lidargram matched),
    ``pairs.csv`` (``image_a,image_b,kind,putative,verified`` for every pair tried),
    ``matches.csv`` (``image_a,image_b,u_a,v_a,u_b,v_b``: the verified matches, pixels with the
    top-left pixel centre at (0.5, 0.5)), ``tracks.csv`` (``track,image,u,v``), a match picture
    per pair kind (``matches_<kind>.png``, the pair with most matches) and ``summary.json``
    (pairs and verified matches per kind). Returns the summary.
    """
    from georefine.lidargrammetry.render import save_lidargram

    _check_pair_kinds(pair_kinds)  # before anything is written
    timings: dict[str, float] = {}
    t = _time.perf_counter()
    pp, out, cloud = _open(project_dir, out, points)
    blk = _block_images(pp, cloud, lidargram_scale, progress)
    (out / "lidargrams").mkdir(exist_ok=True)
    for (lg, _, _), name in zip(blk.lgs, blk.names[blk.n_photos:]):
        save_lidargram(lg, out / "lidargrams", Path(name).stem)
    timings["lidargrams"] = _time.perf_counter() - t
    t = _time.perf_counter()
    m = match_block(blk.images, blk.cameras, blk.station, blk.is_lidargram, blk.p0[:, :2], blk.masks,
                    method=method if matcher is None else matcher, max_pair_distance_m=max_pair_distance_m,
                    pair_kinds=pair_kinds, progress=progress)
    timings["matching"] = _time.perf_counter() - t
    names, lg = blk.names, blk.is_lidargram

    def kind(p: PairMatches) -> str:
        return _pair_kind(lg, p.a, p.b)

    with atomic_output(out / "pairs.csv") as fh:
        fh.write("image_a,image_b,kind,putative,verified\n")
        for p in m.pairs:
            fh.write(f"{names[p.a]},{names[p.b]},{kind(p)},{p.n_putative},{len(p)}\n")
    with atomic_output(out / "matches.csv") as fh:
        fh.write("image_a,image_b,u_a,v_a,u_b,v_b\n")
        for p in m.pairs:
            ua, ub = m.keypoints[p.a].uv[p.ia], m.keypoints[p.b].uv[p.ib]
            for (x0, y0), (x1, y1) in zip(ua, ub):
                fh.write(f"{names[p.a]},{names[p.b]},{x0:.3f},{y0:.3f},{x1:.3f},{y1:.3f}\n")
    tr = m.tracks
    with atomic_output(out / "tracks.csv") as fh:
        fh.write("track,image,u,v\n")
        for k in range(len(tr)):
            fh.write(f"{tr.track[k]},{names[tr.image[k]]},{tr.uv[k, 0]:.3f},{tr.uv[k, 1]:.3f}\n")
    summary: dict = {"method": method if matcher is None else repr(matcher), "photos": blk.n_photos,
                     "lidargrams": len(blk.lgs), "tracks": tr.n_tracks, "pair_kinds": {}, "timings_s": timings}
    for k in pair_kinds:
        ps = [p for p in m.pairs if kind(p) == k]
        counts = np.array([len(p) for p in ps])
        summary["pair_kinds"][k] = {"pairs": len(ps), "pairs_with_matches": int(np.count_nonzero(counts)),
                                    "median_verified": float(np.median(counts)) if ps else 0.0,
                                    "mean_verified": float(np.mean(counts)) if ps else 0.0}
        _draw_best(ps, lg, blk.images, m.keypoints, out / f"matches_{k.replace('-', '_')}.png")
    write_json(out / "summary.json", summary)
    return summary


def run_coadjust(project_dir: str | Path, points: list[str | Path], out: str | Path, case: int, *,
                 method: str = "sift", matcher=None, use_depth: bool = True, lidargram_scale: float = 0.5,
                 lidargram_sigma_position_m: float = 1.0,
                 lidargram_sigma_rotation_deg: float | tuple[float, float, float] = (0.01, 0.01, 0.1),
                 cache_dir: str | Path | None = None, feather: bool = True,
                 progress: Progress = no_progress) -> tuple[BundleResult, dict]:
    """Steps 1-4 of the module docstring; returns the adjustment and the metrics written.

    ``matcher``: a matcher object (:func:`make_matcher`) instead of ``method``'s default one.
    ``cache_dir``: a step cache (:class:`georefine.workflows.cache.StepCache`) for the matches,
    keyed by the photos, the point files, the matcher and the lidargram scale: cases 1 and 2
    of one cloud match once.

    A lidargram's a-priori pose is the one it was rendered from, with the accuracy of the
    LiDAR trajectory: ``lidargram_sigma_position_m`` and ``lidargram_sigma_rotation_deg`` (one
    value, or three about the camera axes x, y, z). The default (0.01, 0.01, 0.1) deg is that of
    an INS without GNSS for minutes: gravity keeps roll and pitch, heading drifts. On the
    jammed ``block`` the rigid corrections fitted to the truth turn by 0.03-0.12 deg about the
    vertical and by at most 0.025 deg about the horizontal axes; a 0.01 deg prior on all three
    held the heading back (refined cloud 0.41x the jammed cloud's error, 0.32x with this one).
    """
    if case not in CASES:
        raise InputError("unknown case", field="--case", expected="1, 2 or 3", found=str(case))
    timings: dict[str, float] = {}
    t = _time.perf_counter()
    pp, out, cloud = _open(project_dir, out, points)
    timings["read"] = _time.perf_counter() - t
    t = _time.perf_counter()
    blk = _block_images(pp, cloud, lidargram_scale, progress)
    timings["lidargrams"] = _time.perf_counter() - t
    lgs, n, cameras, station, is_lg, R0, p0, images = (blk.lgs, blk.n_photos, blk.cameras, blk.station,
                                                       blk.is_lidargram, blk.R0, blk.p0, blk.images)
    t = _time.perf_counter()
    cache = StepCache(Path(cache_dir)) if cache_dir is not None else None
    key = StepCache.key("coadjust-matches", [file_stamp(pp.folder / x, pp.root) for x in pp.eop.images],
                        [file_stamp(f) for f in cloud.files], method if matcher is None else repr(matcher),
                        lidargram_scale, len(lgs))
    matches = cache.load("matches", key) if cache is not None else None
    if matches is None:
        matches = match_block(images, cameras, station, is_lg, p0[:, :2], blk.masks,
                              method=method if matcher is None else matcher, progress=progress)
        if cache is not None:
            cache.store("matches", key, matches)
    timings["matching"] = _time.perf_counter() - t
    keep, xyz0, depth = _ties(lgs, R0, p0, cameras, station, matches, cloud, n)
    tr = matches.tracks
    sig_p = np.r_[pp.eop.sigma_xyz if pp.eop.sigma_xyz is not None else np.full((n, 3), 0.1),
                  np.full((len(lgs), 3), lidargram_sigma_position_m)]
    sig_r = np.radians(np.r_[pp.eop.sigma_opk_deg if pp.eop.sigma_opk_deg is not None else np.full((n, 3), 0.02),
                             np.broadcast_to(np.asarray(lidargram_sigma_rotation_deg, dtype=float), (len(lgs), 3))])
    names = blk.names
    block = BlockImages(names, tuple(cameras), is_lg, R0, p0, sig_p, sig_r, station)
    idx = pp.eop.index()
    gi = {g: k for k, g in enumerate(pp.gcps.ids)}
    ip = pp.image_points
    control = ControlData(pp.gcps.ids, pp.crs.to_w(pp.frame, pp.gcps.xyz) if len(pp.gcps) else np.zeros((0, 3)),
                          pp.gcps.sigma, pp.gcps.is_control, np.array([idx[x] for x in ip.images], dtype=np.int64),
                          np.array([gi[x] for x in ip.ids], dtype=np.int64), ip.uv)
    t = _time.perf_counter()
    result = coadjust(block, tr.image[keep], tr.track[keep], tr.uv[keep], xyz0, control, case,
                      tie_depth_m=depth[keep] if use_depth else None)
    timings["coadjustment"] = _time.perf_counter() - t
    # Products.
    eop_ph = pio.eop_from_w(pp.eop.images, result.R_w_c[:n], result.p_w_c[:n], pp.frame, pp.crs, pp.eop.cameras)
    pio.write_eop(out / "eop_photos.csv", eop_ph)
    eop_lg = pio.eop_from_w(names[n:], result.R_w_c[n:], result.p_w_c[n:], pp.frame, pp.crs, "lidargram")
    pio.write_eop(out / "eop_lidargrams.csv", eop_lg)
    # The same for Metashape's Import Reference (paper 004's workflow continues there).
    both = pio.ExteriorOrientation(eop_ph.images + eop_lg.images, np.r_[eop_ph.xyz, eop_lg.xyz],
                                   np.r_[eop_ph.opk_deg, eop_lg.opk_deg], eop_ph.cameras + eop_lg.cameras)
    metashape.write_cameras(out / "metashape_cameras.csv", both, crs_name=f"EPSG:{pp.crs.epsg}")
    if len(pp.gcps):
        metashape.write_markers(out / "metashape_markers.csv", pp.gcps, crs_name=f"EPSG:{pp.crs.epsg}")
    photo_lg = [m for m in matches.pairs if is_lg[m.a] != is_lg[m.b]]
    pair_counts = [(names[m.a], names[m.b], len(m)) for m in photo_lg]
    _draw_best(photo_lg, is_lg, images, matches.keypoints, out / "matches_lidargram_photo.png")
    t = _time.perf_counter()
    export_colmap(out / "colmap", names, cameras, result, tr.image[keep], tr.track[keep], tr.uv[keep], station)
    timings["colmap_export"] = _time.perf_counter() - t
    metrics = {"case": case, "description": CASES[case], "method": method if matcher is None else repr(matcher),
               "use_depth": use_depth,
               "photos": n, "lidargrams": len(lgs), "tracks": int(np.unique(tr.track[keep]).size),
               "tie_observations": int(keep.sum()),
               "photo_lidargram_matches": {"pairs": len(pair_counts),
                                           "median": float(np.median([c for *_, c in pair_counts])) if pair_counts else 0.0,
                                           "per_pair": [{"a": a, "b": b, "verified": c} for a, b, c in pair_counts]},
               **result.to_dict(),
               "colmap_model": {"folder": "colmap", "frame": "local east-north-up",
                                "origin_lat_deg": float(np.degrees(pp.frame.lat0_rad)),
                                "origin_lon_deg": float(np.degrees(pp.frame.lon0_rad)),
                                "origin_h_m": pp.frame.h0_m}}
    if case in (1, 2):
        t = _time.perf_counter()
        w = [feather_weights(lg.point_uv, lg.camera.width_px, lg.camera.height_px) for lg, _, _ in lgs] \
            if feather else None
        ref = reintersect(cloud.xyz_w, cloud.strip, [lg.point_index for lg, _, _ in lgs], R0[n:], p0[n:],
                          result.R_w_c[n:], result.p_w_c[n:], weights=w)
        _write_cloud(cloud, pp, ref.xyz_w, ref.n_lidargrams, out / "points")
        metrics["reintersection"] = ref.summary()
        timings["reintersection"] = _time.perf_counter() - t
    metrics["timings_s"] = timings
    write_json(out / "metrics.json", metrics)
    return result, metrics


def export_colmap(folder: Path, names, cameras, result: BundleResult, obs_image: np.ndarray, obs_point: np.ndarray,
                  obs_uv: np.ndarray, station: np.ndarray | None = None) -> Path:
    """The adjusted block as a COLMAP text model in the local frame ``w`` (:mod:`georefine.io.colmap`).

    Photos and lidargrams with their adjusted poses, the tie points and their inlier
    observations seen from two stations or more (``station``: of each image; without a base a
    track's depth is free in a tie-only adjustment); control points are left out (COLMAP has no
    coordinate observations). Returns ``folder``.
    """

    inl = result.tie_inlier.copy() if result.tie_inlier is not None else np.ones(len(obs_image), bool)
    if station is not None and inl.any():  # tracks still seen from two stations
        inl &= stations_per_point(obs_point[inl], station[obs_image[inl]], int(obs_point.max()) + 1)[obs_point] >= 2
    rec = to_reconstruction(names, cameras, result.R_w_c, result.p_w_c, obs_image[inl], obs_point[inl], obs_uv[inl],
                            np.nan_to_num(result.tie_points_w))
    tmp = folder.with_name(folder.name + ".partial")  # written whole, then renamed
    if tmp.exists():
        shutil.rmtree(tmp)
    write_model(rec, tmp)
    if folder.exists():
        shutil.rmtree(folder)
    tmp.rename(folder)
    return folder


def _write_cloud(cloud: Cloud, pp: PhotoProject, xyz_w: np.ndarray, n_lidargrams: np.ndarray, folder: Path) -> None:
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
