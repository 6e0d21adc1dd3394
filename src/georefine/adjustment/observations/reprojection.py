"""Image observations (docs/ARCHITECTURE.md §4.3, §4.8): reprojection of 3-D points into frame images.

``r = (project(camera_i, R_w_c[i]^T (X[k] - p_w_c[i])) - uv) / sigma_px`` for every observation
of point ``k`` in image ``i``. A camera is any object with ``project(x_c, jacobian=True)``
returning pixels and ``d uv / d x_c`` -- :class:`georefine.geometry.camera.Camera` in
practice; the adjustment layer does not import the lidargrammetry layer above it. With
``x_c = R^T (X - p)``: ``d x_c / d delta = [x_c]_x`` for ``R <- R Exp(delta)``,
``d x_c / d p = -R^T``, ``d x_c / d X = R^T``.
The blocks are the images' rotations (so3, right perturbation), their projection centres and the
points (all ``(n, 3)`` Euclidean); each may be held constant as a whole or per element, which is
how the co-adjustment cases fix photos or lidargrams (:mod:`georefine.lidargrammetry.bundle`).

A point at or behind an image (``z_c <= min_depth_m``) cannot be projected: its residual is a
large constant with no Jacobian, so that the robust loss (or the caller's outlier test) sees it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from georefine.adjustment.blocks import JacobianBlock, Linearization
from georefine.adjustment.robust import RobustLoss
from georefine.geometry.rotation import skew

__all__ = ["ReprojectionObservation", "DepthObservation", "BEHIND_RESIDUAL"]

BEHIND_RESIDUAL = 1e3
"""Whitened residual (per axis) of an observation whose point lies behind its image."""


@dataclass
class ReprojectionObservation:
    """Pixel observations ``uv`` of points ``point`` in images ``image``.

    Parameters
    ----------
    name
        Group name (statistics).
    cameras
        One camera per image (images of one camera share the object).
    image, point : (N,) int
        Image and point index of each observation.
    uv : (N, 2) px
    sigma_px : float or (N,)
    rotation_block, position_block, point_block
        Names of the blocks holding ``R_w_c`` (so3), ``p_w_c`` and ``X_w``.
    """

    name: str
    cameras: Sequence
    image: np.ndarray
    point: np.ndarray
    uv: np.ndarray
    sigma_px: float | np.ndarray = 1.0
    rotation_block: str = "image_rotation"
    position_block: str = "image_position"
    point_block: str = "points"
    loss: RobustLoss | None = None
    consumed_redundancy = 0.0  # degrees of freedom spent before the adjustment (ObservationGroup): none
    min_depth_m: float = 1e-3
    _by_camera: list = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.image = np.asarray(self.image, dtype=np.int64)
        self.point = np.asarray(self.point, dtype=np.int64)
        self.uv = np.asarray(self.uv, dtype=float).reshape(-1, 2)
        n = len(self.image)
        if self.point.shape != (n,) or self.uv.shape != (n, 2):
            raise ValueError(f"{self.name}: image {self.image.shape}, point {self.point.shape}, uv {self.uv.shape} differ")
        self.sigma_px = np.broadcast_to(np.asarray(self.sigma_px, dtype=float), (n,)).copy()
        if np.any(self.sigma_px <= 0):
            raise ValueError(f"{self.name}: sigma_px must be positive")
        if n and (self.image.min() < 0 or self.image.max() >= len(self.cameras)):
            raise ValueError(f"{self.name}: image index outside 0..{len(self.cameras) - 1}")
        distinct = list(dict.fromkeys(self.cameras))  # equal cameras are one (cameras are hashable values)
        cam_index = {c: k for k, c in enumerate(distinct)}
        of_image = np.array([cam_index[c] for c in self.cameras])
        self._by_camera = [(distinct[k], np.flatnonzero(of_image[self.image] == k)) for k in range(len(distinct))]

    def __len__(self) -> int:
        return len(self.image)

    def _camera_frame(self, values, idx):
        R, p, X = (np.asarray(values[b]) for b in (self.rotation_block, self.position_block, self.point_block))
        i, k = self.image[idx], self.point[idx]
        Ri = R[i]
        x_c = np.einsum("nji,nj->ni", Ri, X[k] - p[i])
        return Ri, x_c

    def predict(self, values: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Predicted pixel coordinates ``(N, 2)`` and whether each point is in front of its image."""
        uv = np.full_like(self.uv, np.nan)
        front = np.zeros(len(self), dtype=bool)
        for cam, idx in self._by_camera:
            _, x_c = self._camera_frame(values, idx)
            ok = x_c[:, 2] > self.min_depth_m
            front[idx] = ok
            uv[idx[ok]] = cam.project(x_c[ok])
        return uv, front

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        n = len(self)
        r = np.empty((n, 2))
        JR, Jp, JX = (np.zeros((n, 2, 3)) for _ in range(3))
        for cam, idx in self._by_camera:
            Ri, x_c = self._camera_frame(values, idx)
            ok = x_c[:, 2] > self.min_depth_m
            good = idx[ok]
            if jacobians:
                uv, J = cam.project(x_c[ok], jacobian=True)
                J = J / self.sigma_px[good, None, None]
                J_point = J @ np.swapaxes(Ri[ok], 1, 2)
                JR[good] = J @ skew(x_c[ok])
                Jp[good] = -J_point
                JX[good] = J_point
            else:
                uv = cam.project(x_c[ok])
            r[good] = (uv - self.uv[good]) / self.sigma_px[good, None]
            r[idx[~ok]] = BEHIND_RESIDUAL
        rows = np.arange(2 * n).reshape(n, 2)
        jac_blocks = []
        if jacobians:
            jac_blocks = [JacobianBlock(self.rotation_block, rows, self.image, JR),
                          JacobianBlock(self.position_block, rows, self.image, Jp),
                          JacobianBlock(self.point_block, rows, self.point, JX)]
        return Linearization(r.ravel(), jac_blocks, np.repeat(np.arange(n), 2))


@dataclass
class DepthObservation:
    """Depth of points along the optical axis of images: ``r = (z_c(X[k]) - depth) / sigma_m``.

    A lidargram pixel shows a LiDAR point, so a keypoint in a lidargram observes the depth of
    the surface there as well as its direction: the range the scanner measured. With
    ``z_c = e3^T R^T (X - p)``: ``d z_c / d delta = e3^T [x_c]_x = (-y_c, x_c, 0)``,
    ``d z_c / d p = -e3^T R^T``, ``d z_c / d X = e3^T R^T``.
    """

    name: str
    image: np.ndarray
    point: np.ndarray
    depth_m: np.ndarray
    sigma_m: float | np.ndarray = 0.05
    rotation_block: str = "image_rotation"
    position_block: str = "image_position"
    point_block: str = "points"
    loss: RobustLoss | None = None
    consumed_redundancy = 0.0  # degrees of freedom spent before the adjustment (ObservationGroup): none

    def __post_init__(self) -> None:
        self.image = np.asarray(self.image, dtype=np.int64)
        self.point = np.asarray(self.point, dtype=np.int64)
        self.depth_m = np.asarray(self.depth_m, dtype=float)
        n = len(self.image)
        if self.point.shape != (n,) or self.depth_m.shape != (n,):
            raise ValueError(f"{self.name}: image, point and depth must have the same length")
        self.sigma_m = np.broadcast_to(np.asarray(self.sigma_m, dtype=float), (n,)).copy()
        if np.any(self.sigma_m <= 0):
            raise ValueError(f"{self.name}: sigma_m must be positive")

    def __len__(self) -> int:
        return len(self.image)

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        R, p, X = (np.asarray(values[b]) for b in (self.rotation_block, self.position_block, self.point_block))
        Ri = R[self.image]
        x_c = np.einsum("nji,nj->ni", Ri, X[self.point] - p[self.image])
        w = 1.0 / self.sigma_m
        r = (x_c[:, 2] - self.depth_m) * w
        n = len(self)
        jac = []
        if jacobians:
            rows = np.arange(n)[:, None]
            axis = Ri[:, :, 2] * w[:, None]  # e3^T R^T = third column of R
            JR = np.stack([-x_c[:, 1], x_c[:, 0], np.zeros(n)], axis=1) * w[:, None]
            jac = [JacobianBlock(self.rotation_block, rows, self.image, JR[:, None, :]),
                   JacobianBlock(self.position_block, rows, self.image, -axis[:, None, :]),
                   JacobianBlock(self.point_block, rows, self.point, axis[:, None, :])]
        return Linearization(r, jac, np.arange(n))
