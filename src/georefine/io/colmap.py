"""COLMAP interchange (pycolmap): a block of images, tie points and observations as a model.

:func:`to_reconstruction` builds a ``pycolmap.Reconstruction`` from cameras, poses in ``w``
(``x_c = R_w_c^T (X - p_w_c)``, COLMAP's ``cam_from_world``) and tracks; :func:`write_model`
writes it as a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``) that
COLMAP opens, each point with its reprojection error and colour; :func:`write_reference_images`
writes the camera centres as the reference file of ``colmap model_aligner``; :func:`read_model`, :func:`poses_from_reconstruction` and
:func:`block_from_reconstruction` read one back (the last as Georefine cameras, poses and
observations, ready for :mod:`georefine.adjustment`).
:func:`colmap_bundle_adjustment` runs COLMAP's own bundle adjuster (Ceres) with chosen images
held fixed -- the reference the co-adjustment is checked against.

Cameras: ``OPENCV`` (fx, fy, cx, cy, k1, k2, p1, p2), or ``FULL_OPENCV`` when ``k3 != 0``;
read back also ``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL`` and ``RADIAL``.
COLMAP's pixel origin is ours (top-left pixel centre at (0.5, 0.5)), so pixels pass unchanged.
Image ids are 1-based in the order given; point ids follow the tracks' order.

A point's error (``points3D.txt``, column ``ERROR``) is COLMAP's: the mean over its track of
the image distances (px) between each observation and the point projected
(:func:`observation_errors`, with Georefine's camera model, which is COLMAP's ``OPENCV``), so
``colmap model_analyzer`` reports the mean reprojection error of the model as written
(:func:`mean_reprojection_error`) instead of the 0 of a model whose errors are unset (-1).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from georefine.geometry.camera import Camera, project_points
from georefine.io.files import PathLike, atomic_output

__all__ = ["to_reconstruction", "write_model", "write_reference_images", "read_model", "poses_from_reconstruction",
           "ColmapBlock", "block_from_reconstruction", "colmap_bundle_adjustment", "observation_errors",
           "point_errors", "mean_reprojection_error"]


def _colmap_camera(camera: Camera, camera_id: int):
    import pycolmap

    c = camera
    if c.k3 != 0.0:
        model, params = "FULL_OPENCV", [c.fx_px, c.fy_px, c.cx_px, c.cy_px, c.k1, c.k2, c.p1, c.p2, c.k3, 0, 0, 0]
    else:
        model, params = "OPENCV", [c.fx_px, c.fy_px, c.cx_px, c.cy_px, c.k1, c.k2, c.p1, c.p2]
    return pycolmap.Camera(model=model, width=c.width_px, height=c.height_px, params=params, camera_id=camera_id)


def observation_errors(cameras, R_w_c: np.ndarray, p_w_c: np.ndarray, obs_image: np.ndarray, obs_point: np.ndarray,
                       obs_uv: np.ndarray, points_w: np.ndarray) -> np.ndarray:
    """Image distance (px) between each observation and its point projected into its image."""
    obs_image, obs_point = np.asarray(obs_image), np.asarray(obs_point)
    uv = np.empty((len(obs_image), 2))
    for cam in set(cameras):
        sel = np.flatnonzero(np.array([c == cam for c in cameras])[obs_image])
        uv[sel] = project_points(cam, np.asarray(points_w, dtype=float)[obs_point[sel]], np.asarray(R_w_c)[obs_image[sel]],
                                 np.asarray(p_w_c)[obs_image[sel]])[0]
    return np.linalg.norm(uv - np.asarray(obs_uv, dtype=float), axis=1)


def point_errors(errors: np.ndarray, obs_point: np.ndarray, n_points: int) -> np.ndarray:
    """Each point's mean observation error (COLMAP's ``Point3D.error``); NaN for a point without observations."""
    n = np.bincount(obs_point, minlength=n_points)
    s = np.bincount(obs_point, weights=np.asarray(errors, dtype=float), minlength=n_points)
    with np.errstate(invalid="ignore", divide="ignore"):
        return s / n


def to_reconstruction(names, cameras, R_w_c: np.ndarray, p_w_c: np.ndarray, obs_image: np.ndarray,
                      obs_point: np.ndarray, obs_uv: np.ndarray, points_w: np.ndarray,
                      colors: np.ndarray | None = None):
    """A ``pycolmap.Reconstruction`` of the block (points with fewer than two observations are left out).

    Each point carries its reprojection error (:func:`point_errors` over the observations kept)
    and ``colors[k]`` (RGB, uint8) if given, else black.
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam_ids: dict[Camera, int] = {}
    for cam in cameras:
        if cam not in cam_ids:
            cam_ids[cam] = len(cam_ids) + 1
            rec.add_camera_with_trivial_rig(_colmap_camera(cam, cam_ids[cam]))
    obs_image, obs_point = np.asarray(obs_image), np.asarray(obs_point)
    counts = np.bincount(obs_point, minlength=len(points_w))
    keep = counts[obs_point] >= 2
    error = point_errors(observation_errors(cameras, R_w_c, p_w_c, obs_image[keep], obs_point[keep],
                                            np.asarray(obs_uv)[keep], points_w), obs_point[keep], len(points_w))
    slot = np.zeros(len(obs_image), dtype=np.int64)  # index of each observation among its image's points2D
    for i, name in enumerate(names):
        sel = np.flatnonzero((obs_image == i) & keep)
        slot[sel] = np.arange(sel.size)
        R_c_w = np.asarray(R_w_c[i]).T
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(Rotation.from_matrix(R_c_w).as_quat()), -R_c_w @ p_w_c[i])
        im = pycolmap.Image(name=str(name), camera_id=cam_ids[cameras[i]], image_id=i + 1)
        im.points2D = pycolmap.Point2DList([pycolmap.Point2D(np.asarray(u, dtype=float)) for u in obs_uv[sel]])
        rec.add_image_with_trivial_frame(im, pose)
    order = np.argsort(obs_point[keep], kind="stable")
    idx = np.flatnonzero(keep)[order]
    starts = np.flatnonzero(np.r_[True, np.diff(obs_point[idx]) != 0])
    black = np.zeros(3, dtype=np.uint8)
    for a, b in zip(starts, np.r_[starts[1:], idx.size]):
        track = pycolmap.Track()
        for o in idx[a:b]:
            track.add_element(int(obs_image[o]) + 1, int(slot[o]))
        k = obs_point[idx[a]]
        pid = rec.add_point3D(np.asarray(points_w[k], dtype=float), track,
                              black if colors is None else np.asarray(colors[k], dtype=np.uint8))
        rec.point3D(pid).error = float(error[k])
    return rec


def write_model(rec, folder: str | Path) -> Path:
    """Write a COLMAP text model into ``folder`` (created)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rec.write_text(str(folder))
    return folder


def write_reference_images(path: PathLike, names, xyz: np.ndarray) -> None:
    """``colmap model_aligner``'s reference file (``--ref_images_path``, ``--ref_is_gps 0``): a line
    ``NAME X Y Z`` per image, its camera centre in a Cartesian or projected CRS (mm)."""
    if any(" " in str(n) for n in names):
        raise ValueError("image names with spaces cannot be written to a COLMAP reference file")
    with atomic_output(path) as fh:
        for name, (x, y, z) in zip(names, np.asarray(xyz, dtype=float)):
            fh.write(f"{name} {x:.4f} {y:.4f} {z:.4f}\n")


def read_model(folder: str | Path):
    import pycolmap

    return pycolmap.Reconstruction(str(folder))


def poses_from_reconstruction(rec, names) -> tuple[np.ndarray, np.ndarray]:
    """``(R_w_c, p_w_c)`` of the images called ``names`` in a reconstruction."""
    R, p = np.empty((len(names), 3, 3)), np.empty((len(names), 3))
    for k, name in enumerate(names):
        im = rec.find_image_with_name(str(name))
        if im is None:
            raise KeyError(f"image {name!r} not in the COLMAP model")
        m = np.asarray(im.cam_from_world().matrix())
        R[k] = m[:, :3].T
        p[k] = -m[:, :3].T @ m[:, 3]
    return R, p


def _camera_from_colmap(cam) -> Camera:
    model, q = cam.model.name, [float(v) for v in cam.params]
    w, h = int(cam.width), int(cam.height)
    if model == "SIMPLE_PINHOLE":
        return Camera(w, h, q[0], q[0], q[1], q[2], name=f"colmap{cam.camera_id}")
    if model == "PINHOLE":
        return Camera(w, h, q[0], q[1], q[2], q[3], name=f"colmap{cam.camera_id}")
    if model == "SIMPLE_RADIAL":
        return Camera(w, h, q[0], q[0], q[1], q[2], k1=q[3], name=f"colmap{cam.camera_id}")
    if model == "RADIAL":
        return Camera(w, h, q[0], q[0], q[1], q[2], k1=q[3], k2=q[4], name=f"colmap{cam.camera_id}")
    if model in ("OPENCV", "FULL_OPENCV"):
        if model == "FULL_OPENCV" and any(q[9:12]):
            raise ValueError(f"COLMAP camera {cam.camera_id}: FULL_OPENCV with k4-k6 (rational model) is not supported")
        return Camera(w, h, q[0], q[1], q[2], q[3], k1=q[4], k2=q[5], p1=q[6], p2=q[7],
                      k3=q[8] if model == "FULL_OPENCV" else 0.0, name=f"colmap{cam.camera_id}")
    raise ValueError(f"COLMAP camera {cam.camera_id}: model {model} is not supported "
                     "(SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV)")


@dataclass(frozen=True)
class ColmapBlock:
    """A COLMAP model as Georefine arrays: images in image-id order, points in point-id order."""

    names: tuple[str, ...]
    cameras: tuple[Camera, ...]
    R_w_c: np.ndarray  # (n, 3, 3)
    p_w_c: np.ndarray  # (n, 3)
    obs_image: np.ndarray  # (k,) index into names
    obs_point: np.ndarray  # (k,) index into points_w
    obs_uv: np.ndarray  # (k, 2)
    points_w: np.ndarray  # (m, 3)
    point_ids: np.ndarray  # (m,) COLMAP point3D ids


def block_from_reconstruction(rec) -> ColmapBlock:
    """Cameras, poses, tracks and 3-D points of a reconstruction (registered images only)."""
    image_ids = sorted(rec.reg_image_ids())
    at = {iid: k for k, iid in enumerate(image_ids)}
    cams = {cid: _camera_from_colmap(rec.camera(cid)) for cid in rec.cameras}
    names = tuple(rec.image(i).name for i in image_ids)
    R, p = poses_from_reconstruction(rec, names)
    point_ids = np.array(sorted(rec.points3D), dtype=np.int64)
    row = {pid: k for k, pid in enumerate(point_ids)}
    img, pt, uv = [], [], []
    for pid in point_ids:
        for el in rec.points3D[pid].track.elements:
            img.append(at[el.image_id])
            pt.append(row[pid])
            uv.append(rec.image(el.image_id).points2D[el.point2D_idx].xy)
    X = np.array([rec.points3D[pid].xyz for pid in point_ids], dtype=float).reshape(-1, 3)
    return ColmapBlock(names, tuple(cams[rec.image(i).camera_id] for i in image_ids), R, p,
                       np.array(img, dtype=np.int64), np.array(pt, dtype=np.int64),
                       np.array(uv, dtype=float).reshape(-1, 2), X, point_ids)


def mean_reprojection_error(errors: np.ndarray, obs_point: np.ndarray) -> float:
    """COLMAP's statistic: the mean over 3-D points of each point's mean reprojection error (px).

    (The mean over observations weighs long tracks more; on a block with tracks of 2-10
    observations the two differ by a few per cent.)
    """
    errors, obs_point = np.asarray(errors, dtype=float), np.asarray(obs_point)
    n = np.bincount(obs_point)
    s = np.bincount(obs_point, weights=errors)
    return float(np.mean(s[n > 0] / n[n > 0]))


def colmap_bundle_adjustment(rec, fixed_images=(), max_iterations: int = 100) -> float:
    """COLMAP's bundle adjustment in place (points and free poses; intrinsics fixed); mean reprojection error (px)."""
    import pycolmap

    config = pycolmap.BundleAdjustmentConfig()
    fixed = {int(i) + 1 for i in fixed_images}
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
        if image_id in fixed:
            config.set_constant_rig_from_world_pose(rec.image(image_id).frame_id)
    for camera_id in rec.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    options = pycolmap.BundleAdjustmentOptions()
    options.ceres.solver_options.max_num_iterations = max_iterations
    adjuster = pycolmap.create_default_bundle_adjuster(options, config, rec)
    adjuster.solve()
    rec.update_point_3d_errors()
    return float(rec.compute_mean_reprojection_error())
