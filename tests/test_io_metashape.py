"""Metashape reference files: cameras and markers round-trip, and bad files name line and field."""

from __future__ import annotations

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.io import metashape
from georefine.io.photos import ControlPoints, ExteriorOrientation


def _eop(sigma: bool) -> ExteriorOrientation:
    rng = np.random.default_rng(8)
    xyz = rng.uniform([650000, 5120000, 900], [651000, 5121000, 1000], (3, 3))
    opk = rng.normal(0, [0.5, 0.5, 60], (3, 3))
    s = (np.full((3, 3), 0.1), np.full((3, 3), 0.02)) if sigma else (None, None)
    return ExteriorOrientation(("a.jpg", "b.jpg", "LG_strip_1_a.jpg"), xyz, opk, ("camera",) * 3, *s)


@pytest.mark.parametrize("sigma", [True, False])
def test_cameras_round_trip(tmp_path, sigma):
    eop = _eop(sigma)
    metashape.write_cameras(tmp_path / "c.csv", eop, crs_name="EPSG:25832")
    text = (tmp_path / "c.csv").read_text().splitlines()
    assert text[0].startswith("# Cameras (3), EPSG:25832") and text[1] == "#" + ",".join(metashape.CAMERA_COLUMNS)
    back = metashape.read_cameras(tmp_path / "c.csv")
    assert back.images == eop.images
    np.testing.assert_allclose(back.xyz, eop.xyz, atol=1e-4)
    np.testing.assert_allclose(back.opk_deg, eop.opk_deg, atol=1e-8)
    assert (back.sigma_xyz is None) == (not sigma)


def test_markers_round_trip_with_check_points_disabled(tmp_path):
    g = ControlPoints(("G1", "C1"), np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]), np.array([[0.01, 0.01, 0.02]] * 2),
                      ("control", "check"))
    metashape.write_markers(tmp_path / "m.csv", g)
    assert (tmp_path / "m.csv").read_text().splitlines()[2].endswith(",1")
    back = metashape.read_markers(tmp_path / "m.csv")
    assert back.ids == g.ids and back.role == ("control", "check")
    np.testing.assert_allclose(back.xyz, g.xyz)
    np.testing.assert_allclose(back.sigma, g.sigma)


def test_markers_without_accuracy_columns_take_the_default(tmp_path):
    (tmp_path / "m.csv").write_text("#Label,X/Easting,Y/Northing,Z/Altitude,Enabled\nP1,1,2,3,0\n")
    back = metashape.read_markers(tmp_path / "m.csv", default_sigma_m=(0.02, 0.02, 0.03))
    assert back.role == ("check",) and back.sigma.tolist() == [[0.02, 0.02, 0.03]]


@pytest.mark.parametrize("text, message, line, field", [
    ("#Label,X/Easting,Y/Northing,Z/Altitude,Omega,Phi,Kappa\nA,1,2,3,0,0,x\n", "bad number", 2, "Kappa"),
    ("#Label,X/Easting,Y/Northing,Z/Altitude,Omega,Phi,Kappa\nA,1,2,3,0,0\n", "wrong number of fields", 2, None),
    ("#Label,X,Y,Z,Omega,Phi,Kappa\nA,1,2,3,0,0,0\n", "wrong columns", 1, None),
    ("#Label,X/Easting,Y/Northing,Z/Altitude,Omega,Phi,Kappa,Enabled\nA,1,2,3,0,0,0,yes\n", "bad flag", 2, "Enabled"),
    ("# Cameras (0)\n", "no column line", None, None),
])
def test_bad_camera_files_are_named(tmp_path, text, message, line, field):
    (tmp_path / "c.csv").write_text(text)
    with pytest.raises(InputError, match=message) as err:
        metashape.read_cameras(tmp_path / "c.csv")
    msg = str(err.value)
    assert "c.csv" in msg and (line is None or f"line {line}" in msg) and (field is None or field in msg)
