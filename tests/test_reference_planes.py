"""Reference-plane figures (paper 000, Table 1) against hand-computed values."""

import numpy as np
import pytest

from georefine.evaluation.reference_planes import (
    observe_reference_planes,
    reference_planes,
    summarise_observations,
)
from georefine.io.reference import ReferenceSurfaces


def _square(sid, centre, size=5.0, tilt=(0.0, 0.0)):
    cx, cy, cz = centre
    h = size / 2
    corners = np.array([[cx - h, cy - h], [cx + h, cy - h], [cx + h, cy + h], [cx - h, cy + h]])
    z = cz + tilt[0] * (corners[:, 0] - cx) + tilt[1] * (corners[:, 1] - cy)
    return [(sid, f"P{i}", *corners[i], z[i]) for i in range(4)]


def _surfaces():
    rows = _square("A", (100.0, 200.0, 50.0)) + _square("B", (300.0, 200.0, 60.0), tilt=(0.05, -0.02))
    sid, pid, x, y, z = zip(*rows)
    return ReferenceSurfaces(np.array(sid), np.array(pid), np.column_stack([x, y, z]))


def _points_on(rng, centre, tilt, offset, n=400, size=6.0, noise=0.0):
    """Points on (and beyond) a square surface, shifted vertically by ``offset``."""
    xy = rng.uniform(-size / 2, size / 2, size=(n, 2))
    z = centre[2] + tilt[0] * xy[:, 0] + tilt[1] * xy[:, 1] + offset + rng.normal(0, noise, n)
    return np.column_stack([xy[:, 0] + centre[0], xy[:, 1] + centre[1], z])


def test_planes_outline_and_inset():
    planes = reference_planes(_surfaces())
    a, b = planes
    assert a.surface_id == "A" and a.rms_survey_m < 1e-12 and a.normal[2] == pytest.approx(1.0)
    assert b.normal @ np.array([0.05, -0.02, -1.0]) == pytest.approx(-np.linalg.norm([0.05, -0.02, 1.0]))
    pts = np.array([[100.0, 200.0, 50.0], [102.4, 200.0, 50.0], [102.6, 200.0, 50.0], [101.0, 201.0, 50.0]])
    np.testing.assert_array_equal(a.inside(pts, 0.25), [True, False, False, True])
    np.testing.assert_array_equal(a.inside(pts, 0.0), [True, True, False, True])


def test_mean_rmse_and_avg_sd_of_known_offsets():
    rng = np.random.default_rng(4)
    planes = reference_planes(_surfaces())
    # Offsets (m) per (surface, strip, channel), chosen by hand.
    offsets = {("A", 1, 0): 0.010, ("A", 1, 1): 0.014, ("A", 2, 0): 0.006,
               ("B", 1, 0): -0.004, ("B", 2, 0): 0.000, ("B", 2, 2): 0.002}
    xyz, strip, chan = [], [], []
    for (sid, s, c), off in offsets.items():
        centre, tilt = ((100.0, 200.0, 50.0), (0.0, 0.0)) if sid == "A" else ((300.0, 200.0, 60.0), (0.05, -0.02))
        p = _points_on(rng, centre, tilt, off)
        # a slant plane shifted vertically by off is shifted by off * n_z along its normal
        xyz.append(p)
        strip.append(np.full(len(p), s))
        chan.append(np.full(len(p), c))
    wire = np.array([[100.0, 200.0, 55.0]] * 20)  # 5 m above the surface: not on it
    xyz.append(wire)
    strip.append(np.full(20, 1))
    chan.append(np.full(20, 0))
    obs = observe_reference_planes(np.vstack(xyz), np.concatenate(strip), np.concatenate(chan), planes)
    assert len(obs) == 6
    nz_b = 1.0 / np.linalg.norm([0.05, -0.02, 1.0])
    expect = {k: v * (nz_b if k[0] == "B" else 1.0) for k, v in offsets.items()}
    for o in obs:
        assert o.mean_m == pytest.approx(expect[(o.surface_id, o.strip, o.channel)], abs=1e-12)
    s = summarise_observations(obs)
    vals = np.array(list(expect.values()))
    assert s.n_observations == 6
    assert s.mean_m == pytest.approx(vals.mean(), abs=1e-12)
    assert s.rmse_m == pytest.approx(np.sqrt(np.mean(vals**2)), abs=1e-12)
    sd_a = np.std([0.010, 0.014, 0.006], ddof=1)
    sd_b = np.std(np.array([-0.004, 0.000, 0.002]) * nz_b, ddof=1)
    assert s.avg_sd_m == pytest.approx((sd_a + sd_b) / 2, abs=1e-12)
    assert [p["surface_id"] for p in s.per_surface] == ["A", "B"]


def _write_strip(path, xyz, strip, channel, epsg=25832):
    import laspy
    from pyproj import CRS

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.floor(xyz.min(axis=0))
    header.add_crs(CRS.from_epsg(epsg))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.point_source_id = np.full(len(xyz), strip, dtype=np.uint16)
    las.scanner_channel = channel.astype(np.uint8)
    las.write(path)


def test_evaluate_commands_on_laz_files(tmp_path):
    import json

    from typer.testing import CliRunner

    from georefine.cli import app
    from georefine.io.reference import write_reference_surfaces

    rng = np.random.default_rng(6)
    surfaces = _surfaces()
    write_reference_surfaces(tmp_path / "surfaces.csv", surfaces)
    offsets = {(1, 0): 0.004, (1, 1): 0.008, (2, 0): -0.002}  # per strip, channel; same on both surfaces
    pts = {1: [], 2: []}
    chans = {1: [], 2: []}
    for (s, c), off in offsets.items():
        for centre, tilt in (((100.0, 200.0, 50.0), (0.0, 0.0)), ((300.0, 200.0, 60.0), (0.05, -0.02))):
            p = _points_on(rng, centre, tilt, off, n=12000, size=20.0)
            pts[s].append(p)
            chans[s].append(np.full(len(p), c))
    for s in (1, 2):
        _write_strip(tmp_path / f"strip_{s}.laz", np.vstack(pts[s]), s, np.concatenate(chans[s]))
    run = CliRunner().invoke(app, ["evaluate", "reference-planes", str(tmp_path), "--reference",
                                   str(tmp_path / "surfaces.csv"), "--out", str(tmp_path / "ev")])
    assert run.exit_code == 0, run.output
    rep = json.loads((tmp_path / "ev" / "reference_planes.json").read_text())
    nz_b = 1.0 / np.linalg.norm([0.05, -0.02, 1.0])
    vals = np.array([0.004, 0.008, -0.002, 0.004 * nz_b, 0.008 * nz_b, -0.002 * nz_b])
    assert rep["n_observations"] == 6
    assert rep["mean_m"] == pytest.approx(vals.mean(), abs=2e-4)  # 0.1 mm coordinate resolution
    assert rep["rmse_m"] == pytest.approx(np.sqrt(np.mean(vals**2)), abs=2e-4)
    sd = (np.std(vals[:3], ddof=1) + np.std(vals[3:], ddof=1)) / 2
    assert rep["avg_sd_m"] == pytest.approx(sd, abs=2e-4)
    assert "AVG-SD" in run.output

    run = CliRunner().invoke(app, ["evaluate", "strip-differences", str(tmp_path / "strip_1.laz"),
                                   str(tmp_path / "strip_2.laz"), "--out", str(tmp_path / "sd")])
    assert run.exit_code == 0, run.output
    rep = json.loads((tmp_path / "sd" / "strip_differences.json").read_text())
    # The layers are shifted vertically by +4, +8 and -2 mm on both surfaces: spread 10 mm.
    assert rep["cells"] > 200 and rep["median_m"] == pytest.approx(0.010, abs=3e-4)
    assert rep["epsg"] == 25832 and len(rep["layers"]) == 3
    for name in ("strip_differences.png", "strip_differences.tif", "strip_pairs.png"):
        assert (tmp_path / "sd" / name).is_file()
    # The pair from the same read: strip 1's centre (+4 and +8 mm: +6) against strip 2's -2 mm, along
    # the normal (n_z 0.9986 on the tilted surface): 8 mm, strip 2 below.
    import csv

    with open(tmp_path / "sd" / "strip_pairs.csv", newline="") as f:
        (pair,) = list(csv.DictReader(f))
    assert (pair["strip_a"], pair["strip_b"]) == ("1", "2") and int(pair["cells"]) > 200
    assert float(pair["median_mm"]) == pytest.approx(8.0, abs=0.3)
    assert float(pair["signed_median_mm"]) == pytest.approx(-8.0, abs=0.3)
    assert "strip pairs: 1 of 1 overlap on planar cells" in run.output
    bad = CliRunner().invoke(app, ["evaluate", "strip-differences", str(tmp_path / "missing")])
    assert bad.exit_code == 2 and "missing" in bad.output
