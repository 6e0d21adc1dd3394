"""The co-adjusted block as a COLMAP model that COLMAP uses as is (docs/ARCHITECTURE.md §4.8).

:func:`export_colmap` writes the folder ``OUT/colmap`` of ``georefine coadjust``:

* ``cameras.txt``, ``images.txt``, ``points3D.txt`` (and pycolmap's ``rigs.txt``,
  ``frames.txt``, which COLMAP 3.8 ignores): the adjusted photos and lidargrams and the tie
  points with their inlier observations, in the local east-north-up frame ``w``
  (:mod:`georefine.io.colmap`). Each point has its reprojection error (the mean over its track,
  so ``colmap model_analyzer`` reports the model's mean reprojection error) and a colour: the
  mean of the photos' pixels at its photo observations, or for a point seen in lidargrams only,
  the lidargrams' grey (the LiDAR intensity) at its observations.
* ``images/``: every image the model names, under that name -- the photos as hard links to the
  project's photo files (copies where the file system does not link them), the lidargrams as
  lossless 8-bit grey PNG -- so ``colmap image_undistorter --image_path OUT/colmap/images`` and
  Metashape (whose reference file ``metashape_cameras.csv`` uses the same names) find them.
* ``reference_images.txt``: ``NAME E N h`` per image, the adjusted camera centre in the output
  CRS (ellipsoidal height), the reference of ``colmap model_aligner --ref_is_gps 0``
  (:data:`MODEL_ALIGNER` is the command), which moves the model into the output CRS by a
  similarity (a few mm off the map projection over a block of a few hundred metres).
* ``georeference.json``: the frame -- origin (WGS84 latitude, longitude, ellipsoidal height),
  axes east-north-up -- and the output CRS, the way back from ``w`` without COLMAP.

The folder is written whole as ``colmap.partial`` and renamed.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io import photos as pio
from georefine.io.colmap import to_reconstruction, write_model, write_reference_images
from georefine.io.files import write_json
from georefine.lidargrammetry.bundle import BundleResult, stations_per_point
from georefine.workflows.lidargrammetry_results import ColmapModel

__all__ = ["IMAGES", "REFERENCE", "GEOREFERENCE", "MODEL_ALIGNER", "point_colours", "export_colmap"]

IMAGES = "images"
"""The model folder's image folder (``--image_path``)."""
REFERENCE = "reference_images.txt"
"""The model folder's reference file for ``colmap model_aligner`` (``--ref_images_path``)."""
GEOREFERENCE = "georeference.json"
"""The model folder's statement of its frame and the output CRS."""
MODEL_ALIGNER = ("colmap model_aligner --input_path {model} --output_path {out} "
                 "--ref_images_path {model}/" + REFERENCE + " --ref_is_gps 0 --alignment_type custom "
                 "--robust_alignment 1 --robust_alignment_max_error 1")
"""COLMAP 3.8's command that moves the model into the output CRS (``{out}`` must exist)."""


def _rgb(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` 8-bit RGB of a grey, BGR or BGRA image as OpenCV decodes it."""
    im = np.asarray(image)
    if im.dtype == np.uint16:
        im = (im >> 8).astype(np.uint8)
    if im.ndim == 2:
        return np.repeat(im[:, :, None], 3, axis=2)
    return im[:, :, 2::-1] if im.shape[2] >= 3 else np.repeat(im[:, :, :1], 3, axis=2)


def point_colours(images: Sequence[np.ndarray], is_photo: np.ndarray, obs_image: np.ndarray, obs_point: np.ndarray,
                  obs_uv: np.ndarray, n_points: int) -> np.ndarray:
    """``(n_points, 3)`` uint8 RGB: the mean pixel at a point's photo observations, at its other
    observations if it has none in a photo (black without any).

    ``images``: per image, ``(H, W)`` grey or ``(H, W, 3)`` RGB; the pixel of an observation is
    the one whose area holds it (top-left pixel centre at (0.5, 0.5), docs/ARCHITECTURE.md §2).
    """
    obs_image, obs_point = np.asarray(obs_image, dtype=np.int64), np.asarray(obs_point, dtype=np.int64)
    rgb = np.zeros((len(obs_image), 3))
    for i in np.unique(obs_image):
        sel = np.flatnonzero(obs_image == i)
        im = images[i] if images[i].ndim == 3 else images[i][:, :, None]
        c = np.clip(np.floor(obs_uv[sel, 0]).astype(np.int64), 0, im.shape[1] - 1)
        r = np.clip(np.floor(obs_uv[sel, 1]).astype(np.int64), 0, im.shape[0] - 1)
        rgb[sel] = im[r, c].reshape(len(sel), -1)
    photo = np.asarray(is_photo, dtype=bool)[obs_image]
    has_photo = np.bincount(obs_point, weights=photo, minlength=n_points) > 0
    w = np.where(has_photo[obs_point], photo, True).astype(float)
    n = np.bincount(obs_point, weights=w, minlength=n_points)
    out = np.zeros((n_points, 3))
    for k in range(3):
        s = np.bincount(obs_point, weights=w * rgb[:, k], minlength=n_points)
        out[:, k] = np.divide(s, n, out=np.zeros(n_points), where=n > 0)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _place_photo(source: Path, target: Path) -> None:
    """``target`` the same file as ``source``: a hard link, else a copy."""
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(source, target)
    except OSError:
        shutil.copyfile(source, target)


def _write_images(folder: Path, names, images: Sequence[Path | np.ndarray]) -> list[np.ndarray]:
    """Each image into ``folder`` under its name (a photo file placed, a lidargram encoded as PNG);
    the images as RGB for the colours."""
    pixels = []
    for name, image in zip(names, images):
        target = folder / name
        if isinstance(image, np.ndarray):
            if target.suffix.lower() != ".png":
                raise ValueError(f"a rendered image is written as PNG: {name!r} must end with .png")
            target.parent.mkdir(parents=True, exist_ok=True)
            ok, encoded = cv2.imencode(".png", image)
            if not ok:
                raise ValueError(f"image {name!r} does not encode as PNG")
            target.write_bytes(encoded.tobytes())
            pixels.append(_rgb(image))
        else:
            _place_photo(Path(image), target)
            pixels.append(_rgb(pio.read_photo(target, grey=False)))
    return pixels


def export_colmap(folder: Path, names, cameras, result: BundleResult, obs_image: np.ndarray, obs_point: np.ndarray,
                  obs_uv: np.ndarray, station: np.ndarray | None = None, *, images: Sequence[Path | np.ndarray],
                  frame: LocalFrame, crs: OutputCRS) -> ColmapModel:
    """The adjusted block as the COLMAP model folder of the module docstring; returns what was written.

    Photos and lidargrams with their adjusted poses, the tie points and their inlier
    observations seen from two stations or more (``station``: of each image; without a base a
    track's depth is free in a tie-only adjustment); control points are left out (COLMAP has no
    coordinate observations). ``images``: per image of ``names``, the photo's file (placed in
    ``images/``) or the rendered lidargram (written as PNG; its name ends with ``.png``).
    ``frame``: the local frame ``w`` of the poses; ``crs``: the output CRS of the reference file.
    """
    folder = Path(folder)
    if len(images) != len(names):
        raise ValueError(f"{len(images)} images for {len(names)} names")
    inl = result.tie_inlier.copy() if result.tie_inlier is not None else np.ones(len(obs_image), bool)
    if station is not None and inl.any():  # tracks still seen from two stations
        inl &= stations_per_point(obs_point[inl], station[obs_image[inl]], int(obs_point.max()) + 1)[obs_point] >= 2
    tmp = folder.with_name(folder.name + ".partial")  # written whole, then renamed
    if tmp.exists():
        shutil.rmtree(tmp)
    pixels = _write_images(tmp / IMAGES, names, images)
    points_w = np.nan_to_num(result.tie_points_w)
    is_photo = np.array([not isinstance(im, np.ndarray) for im in images])
    colours = point_colours(pixels, is_photo, obs_image[inl], obs_point[inl], obs_uv[inl], len(points_w))
    rec = to_reconstruction(names, cameras, result.R_w_c, result.p_w_c, obs_image[inl], obs_point[inl], obs_uv[inl],
                            points_w, colors=colours)
    write_model(rec, tmp)
    write_reference_images(tmp / REFERENCE, names, crs.from_w(frame, result.p_w_c))
    model = ColmapModel(folder.name, "local east-north-up", float(np.degrees(frame.lat0_rad)),
                        float(np.degrees(frame.lon0_rad)), frame.h0_m, f"EPSG:{crs.epsg}", rec.num_images(),
                        rec.num_points3D(), rec.compute_num_observations(),
                        float(rec.compute_mean_reprojection_error()) if rec.num_points3D() else float("nan"))
    write_json(tmp / GEOREFERENCE, {
        "frame": model.frame, "axes": "x east, y north, z up (metres) at the origin",
        "origin_lat_deg": model.origin_lat_deg, "origin_lon_deg": model.origin_lon_deg,
        "origin_h_m": model.origin_h_m, "origin_datum": "WGS84 (EPSG:4979), ellipsoidal height",
        "crs": model.crs, "reference_images": REFERENCE, "reference_columns": "image E N h (output CRS, metres)",
        "images": IMAGES, "model_aligner": MODEL_ALIGNER.format(model=".", out="aligned"),
    })
    if folder.exists():
        shutil.rmtree(folder)
    tmp.rename(folder)
    return model
