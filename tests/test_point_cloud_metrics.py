"""Point-cloud metrics against hand-computed values: surface distance and strip discrepancy."""

import json
import shutil
import subprocess

import numpy as np
import pytest

from georefine.evaluation.point_cloud import strip_discrepancy, surface_distances
from georefine.evaluation.strip_difference_maps import map_figure, map_panels, write_png
from georefine.evaluation.strip_differences import (
    BAND_DESCRIPTION,
    StripDifferenceMap,
    cell_planes,
    crop,
    strip_differences,
    write_geotiff,
)


def _tilted(rng, n, slope, offset, extent=20.0):
    xy = rng.uniform(0.0, extent, size=(n, 2))
    z = offset + slope[0] * xy[:, 0] + slope[1] * xy[:, 1]
    return np.column_stack([xy, z])


def test_cell_planes_recover_height_at_the_cell_centre():
    rng = np.random.default_rng(1)
    pts = _tilted(rng, 20000, (0.1, -0.05), 3.0)
    planes = cell_planes(pts, 1.0, min_points=6)
    centre = (planes.cell_ij + 0.5) * 1.0
    expected = 3.0 + 0.1 * centre[:, 0] - 0.05 * centre[:, 1]
    np.testing.assert_allclose(planes.height_m, expected, atol=1e-9)
    assert planes.roughness_m.max() < 1e-9 and planes.n_points.sum() <= 20000


def test_strip_discrepancy_is_the_offset_between_tilted_strips():
    rng = np.random.default_rng(2)
    a = _tilted(rng, 20000, (0.1, 0.02), 0.0)
    b = _tilted(rng, 20000, (0.1, 0.02), 0.02)
    c = _tilted(rng, 20000, (0.1, 0.02), -0.01)
    out = strip_discrepancy([a, b, c], 1.0)
    assert out["cells"] == 18 * 18  # the cells on the edge of the strips' coverage are gated
    along_normal = 0.03 / np.sqrt(1.0 + 0.1**2 + 0.02**2)  # parallel planes 3 cm apart in height
    assert out["median_m"] == pytest.approx(along_normal, abs=1e-9) and out["p95_m"] == pytest.approx(along_normal, abs=1e-9)
    # A layer that does not fit a plane (5 cm noise) where the others do: not a planar surface in
    # every view, so the cells are gated; two layers without it give the map again.
    noisy = a + np.column_stack([np.zeros((20000, 2)), rng.normal(0, 0.05, 20000)])
    assert strip_discrepancy([noisy, b, c], 1.0)["cells"] == 0
    assert strip_discrepancy([b, c], 1.0)["median_m"] == pytest.approx(along_normal, abs=1e-9)


def test_surface_distance_is_the_offset_along_the_normal():
    rng = np.random.default_rng(3)
    truth = _tilted(rng, 30000, (0.0, 0.0), 0.0)
    shift = np.array([0.04, -0.03, 0.005])  # horizontal motion along a flat surface does not count
    d = surface_distances(truth + shift, truth, sample_step=10)
    s = d.summary()
    assert s["points"] == 3000
    assert s["mean_abs_distance_m"] == pytest.approx(0.005, abs=1e-9)
    assert s["mean_3d_error_m"] == pytest.approx(np.linalg.norm(shift), abs=1e-9)


def test_strip_difference_raster_png_and_geotiff(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    rng = np.random.default_rng(5)
    a = _tilted(rng, 20000, (0.1, 0.0), 0.0)
    b = _tilted(rng, 20000, (0.1, 0.0), 0.0)
    b[b[:, 0] >= 10.0, 2] += 0.05  # the eastern half of strip b lies 5 cm high
    m = strip_differences([a + [1000.0, 5000.0, 0.0], b + [1000.0, 5000.0, 0.0]], 1.0)
    assert m.spread_m.shape == (20, 20) and m.x0 == 1000.0 and m.y1 == 5020.0
    step = 0.05 / np.sqrt(1.0 + 0.1**2)  # along the normal of planes of slope 0.1
    inner = m.spread_m[1:-1, 1:-1]  # the outer ring is the edge of the strips' coverage: gated
    np.testing.assert_allclose(inner[:, :9], 0.0, atol=1e-9)
    np.testing.assert_allclose(inner[:, 9:], step, atol=1e-9)
    assert np.all(np.isnan(m.spread_m[[0, -1], :])) and np.all(np.isnan(m.spread_m[:, [0, -1]]))
    assert m.gating() == {"candidates": 400, "kept": 324, "rough": 0, "steep": 0, "edge": 76, "normals": 0}
    np.testing.assert_allclose(m.ungated_m[:, 10:], 0.05, atol=1e-9)  # the map before gating: vertical, all cells
    s = m.summary()
    assert s["cells"] == 324 and s["p95_m"] == pytest.approx(step)
    part = crop(m, (1012.0, 1015.5, 5001.0, 5003.0))  # whole cells covering the window
    assert part.spread_m.shape == (2, 4) and (part.x0, part.y1) == (1012.0, 5003.0)
    np.testing.assert_allclose(part.spread_m, step, atol=1e-9)
    assert part.gate.shape == part.ungated_m.shape == (2, 4)
    with pytest.raises(ValueError):
        crop(m, (0.0, 10.0, 0.0, 10.0))
    png = write_png(tmp_path / "map.png", m, epsg=25832)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # A long corridor's map: panels of at most 2.5 : 1 side by side, each at equal aspect, in mm, with
    # the cells beyond the colour scale counted and the sites inside a panel marked.
    assert map_panels(3300, 500)[0] == "rows" and [p.stop - p.start for p in map_panels(3300, 500)[1]] == [1100] * 3
    assert map_panels(200, 1200)[0] == "cols" and len(map_panels(200, 1200)[1]) == 3 and len(map_panels(90, 100)[1]) == 1
    rng = np.random.default_rng(4)
    long = StripDifferenceMap(rng.uniform(0.0, 0.12, (600, 100)), np.ones((600, 100), dtype=np.int32), 1000.0, 7000.0,
                              1.0, np.zeros((600, 100)), np.zeros((600, 100), dtype=np.int8))
    fig = map_figure(long, epsg=25832, sites=[("roof_a", 1050.0, 6800.0), ("far", 0.0, 0.0)])
    maps = [ax for ax in fig.axes if ax.images]
    assert len(maps) == 3 and all(ax.get_aspect() == 1.0 for ax in maps)
    assert sum(t.get_text() == "roof_a" for ax in maps for t in ax.texts) == 1  # the site outside is not drawn
    assert "cells above 100 mm in purple" in fig._suptitle.get_text() and fig.axes[-1].get_ylabel() == "difference [mm]"
    fonts = [t.get_fontsize() for ax in fig.axes for t in (*ax.get_xticklabels(), *ax.get_yticklabels(), *ax.texts)]
    assert min(fonts) >= 7
    tif = write_geotiff(tmp_path / "map.tif", m, 25832)
    with tifffile.TiffFile(tif) as t:
        page = t.pages[0]
        np.testing.assert_allclose(page.asarray(), m.spread_m.astype(np.float32))
        assert page.tags["ModelTiepointTag"].value[3:5] == (1000.0, 5020.0)
        keys = page.tags["GeoKeyDirectoryTag"].value
        assert 3072 in keys[4::4] and keys[keys.index(3072) + 3] == 25832
        assert page.tags["GDAL_NODATA"].value == "nan"
        xml = page.tags["GDAL_METADATA"].value
        assert 'role="description"' in xml and 'role="unittype">metre<' in xml


@pytest.mark.skipif(shutil.which("gdalinfo") is None or shutil.which("gdalsrsinfo") is None,
                    reason="GDAL command-line tools not installed")
def test_gdal_reads_the_geotiff_description_unit_nodata_crs_and_values(tmp_path):
    rng = np.random.default_rng(6)
    a = _tilted(rng, 20000, (0.1, 0.0), 0.0) + [700_000.0, 5_170_000.0, 0.0]
    b = a + [0.0, 0.0, 0.01]
    b[b[:, 1] >= 5_170_012.0, 2] += 0.03
    m = strip_differences([a, b], 1.0)
    tif = write_geotiff(tmp_path / "map.tif", m, 25832)
    info = json.loads(_run("gdalinfo", "-json", "-stats", str(tif)))
    band = info["bands"][0]
    assert band["description"] == BAND_DESCRIPTION
    assert band.get("unit") in ("metre", "m")
    assert band["type"] == "Float32" and band["noDataValue"] == "NaN"
    assert info["geoTransform"] == [m.x0, 1.0, 0.0, m.y1, 0.0, -1.0]
    v = m.spread_m.astype(np.float32).astype(float)
    stats = {k.removeprefix("STATISTICS_"): float(x) for k, x in band["metadata"][""].items()}
    assert stats["MINIMUM"] == pytest.approx(np.nanmin(v), rel=1e-6)
    assert stats["MAXIMUM"] == pytest.approx(np.nanmax(v), rel=1e-6)
    assert stats["MEAN"] == pytest.approx(np.nanmean(v), rel=1e-6)
    assert stats["STDDEV"] == pytest.approx(np.nanstd(v), rel=1e-5)
    assert stats["VALID_PERCENT"] == pytest.approx(100.0 * np.mean(np.isfinite(v)), abs=0.01)
    assert _run("gdalsrsinfo", "-e", str(tif)).split()[0] == "EPSG:25832"
    if shutil.which("projinfo"):
        wkt = tmp_path / "crs.wkt"
        wkt.write_text(_run("gdalsrsinfo", "-o", "wkt2", str(tif)))
        assert "EPSG:25832: 100 %" in _run("projinfo", "--identify", "-o", "PROJ", f"@{wkt}")


def _run(*args: str) -> str:
    return subprocess.run(args, capture_output=True, text=True, check=True).stdout
