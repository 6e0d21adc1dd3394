"""COLMAP interchange (pycolmap): a block of images, tie points and observations as a model.

:func:`to_reconstruction` builds a ``pycolmap.Reconstruction`` from cameras, poses in ``w``
(``x_c = R_w_c^T (X - p_w_c)``, COLMAP's ``cam_from_world``) and tracks; :func:`write_model`
writes it as a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``) that
COLMAP opens; :func:`read_model` and :func:`poses_from_reconstruction` read one back.
:func:`colmap_bundle_adjustment` runs COLMAP's own bundle adjuster (Ceres) with chosen images
held fixed -- the reference the co-adjustment is checked against.

Cameras: ``OPENCV`` (fx, fy, cx, cy, k1, k2, p1, p2), or ``FULL_OPENCV`` when ``k3 != 0``.
COLMAP's pixel origin is ours (top-left pixel centre at (0.5, 0.5)), so pixels pass unchanged.
Image ids are 1-based in the order given; point ids follow the tracks' order.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from georefine.lidargrammetry.camera import Camera

__all__ = ["to_reconstruction", "write_model", "read_model", "poses_from_reconstruction", "colmap_bundle_adjustment"]


def _colmap_camera(camera: Camera, camera_id: int):
    import pycolmap

    c = camera
    if c.k3 != 0.0:
        model, params = "FULL_OPENCV", [c.fx_px, c.fy_px, c.cx_px, c.cy_px, c.k1, c.k2, c.p1, c.p2, c.k3, 0, 0, 0]
    else:
        model, params = "OPENCV", [c.fx_px, c.fy_px, c.cx_px, c.cy_px, c.k1, c.k2, c.p1, c.p2]
    return pycolmap.Camera(model=model, width=c.width_px, height=c.height_px, params=params, camera_id=camera_id)


def to_reconstruction(names, cameras, R_w_c: np.ndarray, p_w_c: np.ndarray, obs_image: np.ndarray,
                      obs_point: np.ndarray, obs_uv: np.ndarray, points_w: np.ndarray):
    """A ``pycolmap.Reconstruction`` of the block (points with fewer than two observations are left out)."""
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
    for a, b in zip(starts, np.r_[starts[1:], idx.size]):
        track = pycolmap.Track()
        for o in idx[a:b]:
            track.add_element(int(obs_image[o]) + 1, int(slot[o]))
        rec.add_point3D(np.asarray(points_w[obs_point[idx[a]]], dtype=float), track)
    return rec


def write_model(rec, folder: str | Path) -> Path:
    """Write a COLMAP text model into ``folder`` (created)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rec.write_text(str(folder))
    return folder


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
