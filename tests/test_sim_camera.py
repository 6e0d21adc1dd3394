"""The `block` scenario: photo block, rendered photos, control points, GNSS jamming."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from georefine.config import load_project
from georefine.geometry.camera import project_points
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io import photos
from georefine.io.gnss import read_pos
from georefine.sim.scenarios import simulate_project

SMALL = [
    "photos.camera.width_px=600", "photos.camera.height_px=400", "photos.camera.focal_px=800",
    "photos.gsd_m=0.4", "scanner.pulse_rate_hz=5000", "scanner.line_rate_hz=40",
]


@pytest.fixture(scope="module")
def block(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("block") / "p"
    simulate_project("block", out, seed=5, overrides=SMALL)
    return out


def _frame(project: Path):
    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    rp = truth["scenario"]["reference_point"]
    return LocalFrame.from_degrees(rp["lat_deg"], rp["lon_deg"], rp["h_m"]), OutputCRS(truth["scenario"]["output_epsg"])


def test_block_files_are_consistent_and_measurements_fit_the_true_orientation(block):
    cfg = load_project(block)
    assert cfg.photos is not None
    cams = photos.read_cameras(block / cfg.photos.cameras)
    eop = photos.read_eop(block / cfg.photos.eop, cams)
    gcps = photos.read_gcps(block / cfg.photos.gcp)
    pts = photos.read_image_points(block / cfg.photos.image_points)
    b = photos.PhotoBlock(cams, eop, gcps, pts, block / cfg.photos.folder)
    photos.check_photo_block(b, eop_path=block / cfg.photos.eop, gcp_path=block / cfg.photos.gcp,
                             image_points_path=block / cfg.photos.image_points)
    assert len(eop) == 14 and gcps.is_control.sum() == 6 and (~gcps.is_control).sum() == 12
    img = cv2.imread(str(block / cfg.photos.folder / eop.images[0]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (400, 600) and img.dtype == np.uint8 and img.std() > 10  # texture, not a flat image
    # True orientation and exact points reproduce the measurements to their noise (0.3 px).
    frame, crs = _frame(block)
    true_eop = photos.read_eop(block / "truth" / "photos_eop.csv", cams)
    true_gcp = photos.read_gcps(block / "truth" / "gcp.csv")
    R, p = photos.poses_in_w(true_eop, frame, crs)
    X = crs.to_w(frame, true_gcp.xyz)
    idx, gidx = true_eop.index(), {g: k for k, g in enumerate(true_gcp.ids)}
    i = np.array([idx[n] for n in pts.images])
    k = np.array([gidx[g] for g in pts.ids])
    uv, front = project_points(cams["camera"], X[k], R[i], p[i])
    err = uv - pts.uv
    assert front.all() and np.sqrt(np.mean(err**2)) < 0.5 and np.abs(err).max() < 1.5
    # The approximate orientation is off by its stated sigma (0.1 m, 0.02 deg), not more.
    d = np.linalg.norm(eop.xyz - true_eop.xyz, axis=1)
    assert 0.02 < np.sqrt(np.mean(d**2)) / np.sqrt(3) < 0.3


def test_gnss_is_jammed_from_the_first_pass_to_the_last(block):
    truth = yaml.safe_load((block / "truth" / "scenario.yaml").read_text())
    (a, b), = truth["gnss_outages_s"]
    first, last = truth["passes"][0], truth["passes"][-1]
    assert a == pytest.approx(first["t_start_s"] + 5.0) and b == pytest.approx(last["t_end_s"] - 5.0)
    pos = read_pos(block / "gnss" / "rover.pos")
    t = pos.time_gps - truth["t0_gps"]
    assert not np.any((t > a + 0.5) & (t < b - 0.5))  # no fix inside the outage
    assert np.any(t < first["t_start_s"] + 5.0) and np.any((t > b) & (t <= last["t_end_s"]))  # GNSS frames the strips
