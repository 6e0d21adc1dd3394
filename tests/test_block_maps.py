"""The block demo's surveyor view: per-point residual files, the layout map, the error vectors,
the residual histograms and the report's sections (small synthetic inputs; the demo itself runs
in tests/test_coadjust.py)."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.quiver import Quiver
from matplotlib.text import Text

from georefine.demo.block import BlockCase, BlockDemoMetrics, BlockDemoResult, _write_report, point_table_rows
from georefine.errors import InputError
from georefine.evaluation.block_maps import (
    BlockLayout,
    PointPanel,
    ResidualHistogram,
    draw_block_layout,
    draw_point_vectors,
    draw_residual_histograms,
    ground_footprint,
    plot_block_layout,
    plot_point_vectors,
    plot_residual_histograms,
    sparse_labels,
    vector_scale,
)
from georefine.evaluation.coadjust import CloudErrorSummary
from georefine.geometry.camera import Camera, R_w_c_from_opk
from georefine.lidargrammetry.bundle import PointStats, coadjust
from georefine.workflows.lidargrammetry_results import (
    POINT_RESIDUAL_COLUMNS,
    TIE_RESIDUAL_COLUMNS,
    PhotoLidargramMatches,
    PointResiduals,
    Precision,
    TieReprojection,
    TieResiduals,
)
from test_bundle import _block

CAM = Camera(3000, 2000, 4000.0, 4000.0, 1500.0, 1000.0, name="camera")
NADIR = np.diag([1.0, -1.0, -1.0])  # camera x east, y south, z down: looking straight down


def _residuals(seed: int, m: int = 8, outlier: bool = True) -> PointResiduals:
    """``m`` points around (500000, 5400000): centimetre errors, one point 1.5 m off (``outlier``),
    one measured in a single photo (no error), every third a control point."""
    rng = np.random.default_rng(seed)
    xyz = np.column_stack([500000 + rng.uniform(0, 300, m), 5400000 + rng.uniform(0, 400, m), rng.uniform(600, 610, m)])
    err = rng.normal(0, 0.03, (m, 3))
    if outlier:
        err[1] = [1.2, -0.9, 0.4]
    err[2] = np.nan
    rays = np.full(m, 3)
    rays[2] = 1
    return PointResiduals(tuple(f"P{k:02d}" for k in range(m)),
                          tuple("control" if k % 3 == 0 else "check" for k in range(m)), xyz, err, rays,
                          np.where(np.isnan(err[:, 0]), np.nan, rng.uniform(0.1, 0.5, m)),
                          np.where(np.arange(m)[:, None] % 2 == 0, 0.02, np.nan) * np.ones((m, 3)))


def _layout(seed: int) -> BlockLayout:
    rng = np.random.default_rng(seed)
    photo_xy = np.column_stack([np.repeat([500050.0, 500250.0], 4), np.tile(5400000 + np.arange(4) * 120.0, 2)])
    fp = [np.array([[x - 90, y - 60], [x + 90, y - 60], [x + 90, y + 60], [x - 90, y + 60]]) for x, y in photo_xy]
    r = _residuals(seed)
    return BlockLayout("ETRS89 / UTM zone 32N (EPSG:25832)", tuple(f"IMG_{k:03d}.jpg" for k in range(8)), photo_xy,
                       fp, r.ids, r.xyz[:, :2], r.is_control, tuple(f"LG_strip_{s}_{k}.png" for s in (1, 2)
                                                                        for k in range(8)),
                       np.concatenate([photo_xy, photo_xy]) + rng.normal(0, 0.5, (16, 2)), fp + fp,
                       ("strip_1",) * 8 + ("strip_2",) * 8, 605.0)


def _font_sizes(fig) -> list[float]:
    return [t.get_fontsize() for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()]


# ---------------------------------------------------------------------------- files
def test_point_residuals_file_is_worst_first_and_reads_back(tmp_path):
    r = _residuals(1)
    path = tmp_path / "point_residuals.csv"
    r.write(path)
    lines = path.read_text().splitlines()
    assert tuple(lines[0].split(",")) == POINT_RESIDUAL_COLUMNS
    back = PointResiduals.read(path)
    d3 = back.error_3d_m
    assert back.ids[0] == "P01" and np.all(np.diff(d3[np.isfinite(d3)]) <= 0)  # the 1.5 m point on top
    assert back.ids[-1] == "P02" and lines[-1].split(",")[5] == ""  # not intersected: last, empty cells
    order = [r.ids.index(i) for i in back.ids]
    np.testing.assert_allclose(back.error_m, r.error_m[order], atol=5e-5)
    np.testing.assert_allclose(back.xyz, r.xyz[order], atol=5e-5)
    np.testing.assert_array_equal(back.rays, r.rays[order])
    assert back.role == tuple(r.role[i] for i in order)
    np.testing.assert_allclose(back.horizontal_m[0], np.hypot(1.2, 0.9), atol=1e-4)
    np.testing.assert_array_equal(np.isnan(back.sigma_m), np.isnan(r.sigma_m[order]))


def test_a_point_id_with_a_comma_is_quoted_and_reads_back(tmp_path):
    r = _residuals(3)
    r = PointResiduals(("GCP 7, roof",) + r.ids[1:], r.role, r.xyz, r.error_m, r.rays, r.reprojection_px, r.sigma_m)
    path = tmp_path / "point_residuals.csv"
    r.write(path)
    assert '"GCP 7, roof"' in path.read_text()
    assert "GCP 7, roof" in PointResiduals.read(path).ids


def test_residual_files_name_the_bad_line_and_field(tmp_path):
    path = tmp_path / "point_residuals.csv"
    _residuals(2).write(path)
    lines = path.read_text().splitlines()
    lines[3] = lines[3].replace(",check,", ",checkpoint,").replace(",control,", ",checkpoint,")
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as exc:
        PointResiduals.read(path)
    assert exc.value.line == 4 and exc.value.field == "role"
    path.write_text("id,role,x\nA,check,1\n")
    with pytest.raises(InputError) as exc:
        PointResiduals.read(path)
    assert exc.value.field == "y"


def test_tie_residuals_file_reads_back(tmp_path):
    rng = np.random.default_rng(3)
    k = 50
    res = rng.normal(0, 0.5, (k, 2))
    res[4] = np.nan
    t = TieResiduals(tuple(f"I{i % 5}" for i in range(k)), np.arange(k) % 2 == 1, np.arange(k) // 2,
                     rng.uniform(0, 3000, (k, 2)), res, np.abs(res[:, 0]) < 1.0)
    path = tmp_path / "tie_residuals.csv"
    t.write(path)
    assert tuple(path.read_text().splitlines()[0].split(",")) == TIE_RESIDUAL_COLUMNS
    back = TieResiduals.read(path)
    assert back.images == t.images and len(back) == k
    np.testing.assert_array_equal(back.is_lidargram, t.is_lidargram)
    np.testing.assert_array_equal(back.inlier, t.inlier)
    np.testing.assert_allclose(back.residual_px, t.residual_px, atol=5e-5)  # NaN where NaN
    assert np.isnan(back.norm_px[4])


def test_the_adjustment_gives_each_points_residual_rays_and_sigma():
    images, img, pt, uv, xyz0, depth, control, _ = _block(23)
    r = coadjust(images, img, pt, uv, xyz0, control, 1, tie_depth_m=depth)
    m = len(control.ids)
    assert r.point_rays.shape == (m,) and np.all(r.point_rays == np.bincount(control.point, minlength=m))
    ok = r.point_rays >= 2
    assert np.all(r.point_reprojection_px[ok] < 1.5) and np.all(np.isnan(r.point_reprojection_px[~ok]))
    # The check points' RE of the statistics is the RMS over their measurements.
    chk = ~control.is_control & ok
    n = r.point_rays[chk]
    assert np.sqrt(np.sum(n * r.point_reprojection_px[chk] ** 2) / n.sum()) == pytest.approx(r.check.reprojection_px)
    # Case 1: the check points' sigmas are the photo block's (whose photos they are intersected from).
    assert r.point_cov_w.shape == (m, 3, 3)
    sig = np.sqrt(np.einsum("kii->ki", r.point_cov_w[~control.is_control]))
    np.testing.assert_allclose(np.sqrt(np.mean(sig**2, axis=0)),
                               r.extra["photo_block_precision"]["check_points"]["sigma_xyz_m_rms"], rtol=1e-9)
    assert r.tie_residual_px.shape == (len(img), 2)
    inl = r.tie_inlier & ~images.is_lidargram[img]
    rms = np.sqrt(np.mean(np.sum(r.tie_residual_px[inl] ** 2, axis=1)))
    assert rms == pytest.approx(r.tie_reprojection_px["photos"])
    r3 = coadjust(images, img, pt, uv, xyz0, control, 3, tie_depth_m=depth)
    assert r3.point_cov_w is None  # the points are not in case 3's block


# ---------------------------------------------------------------------------- maps
def test_ground_footprint_of_a_nadir_camera():
    fp = ground_footprint(CAM, NADIR, np.array([10.0, 20.0, 400.0]), 0.0)
    # 400 m above the plane: 3000 px x 400 / 4000 = 300 m east-west, 200 m north-south.
    np.testing.assert_allclose(fp.min(axis=0), [10 - 150, 20 - 100], atol=1e-6)
    np.testing.assert_allclose(fp.max(axis=0), [10 + 150 - 0.1, 20 + 100], atol=0.2)
    part = ground_footprint(CAM, NADIR, np.array([0.0, 0.0, 400.0]), 0.0, (1500.0, 0.0, 3000.0, 2000.0))
    assert part[:, 0].min() == pytest.approx(0.0, abs=1e-6)  # the right half of the image: east of the centre
    tilted = R_w_c_from_opk(0.0, np.radians(89.0), 0.0)
    assert len(ground_footprint(CAM, tilted, np.array([0.0, 0.0, 400.0]), 0.0)) < 24  # rays above the horizon left out


def test_sparse_labels_keep_their_distance():
    xy = np.column_stack([np.arange(10.0), np.zeros(10)])
    np.testing.assert_array_equal(sparse_labels(xy, 2.5), [0, 3, 6, 9])


def test_layout_map_shows_every_station_and_point_at_equal_aspect(tmp_path):
    layout = _layout(4)
    fig = draw_block_layout(layout, title="layout")
    maps = fig.axes
    assert len(maps) == 2 and all(ax.get_aspect() == 1.0 for ax in maps)
    assert "EPSG:25832" in maps[0].get_xlabel()
    sizes = [len(c.get_offsets()) for c in maps[0].collections if hasattr(c, "get_offsets")]
    assert 8 in sizes and sum(layout.point_is_control) in sizes and sum(~layout.point_is_control) in sizes
    assert min(_font_sizes(fig)) >= 8
    assert fig.legends and not maps[0].get_legend()  # the legend is the figure's, below the maps
    import matplotlib.pyplot as plt

    plt.close(fig)
    path = plot_block_layout(layout, tmp_path / "layout.png")
    from PIL import Image

    with Image.open(path) as im:
        assert im.size[0] >= 1000  # 11 in at 110 dpi


def test_point_vectors_draw_an_arrow_per_point_and_clip_the_outlier(tmp_path):
    panels = []
    for case in (1, 2, 3):
        r = _residuals(10 + case, outlier=case == 2)
        panels.append(PointPanel(f"case {case}", r.ids, r.xyz[:, :2], r.error_m, r.is_control))
    layout = _layout(5)
    fig = draw_point_vectors(panels, layout.crs_name, context=layout)
    maps = [ax for ax in fig.axes if not hasattr(ax, "_colorbar")]
    assert len(maps) == 3 and all(ax.get_aspect() == 1.0 for ax in maps)
    for k, (ax, p) in enumerate(zip(maps, panels)):
        arrows = sum(len(q.U) for q in ax.findobj(Quiver))
        finite = int(np.all(np.isfinite(p.error_m), axis=1).sum())
        assert arrows == finite + (1 if k == 0 else 0)  # the scale arrow in the first panel
        markers = sum(len(c.get_offsets()) for c in ax.collections if not isinstance(c, Quiver)
                      and hasattr(c, "get_offsets") and c.get_array() is not None)
        assert markers == finite
    # Case 2's 1.5 m point is clipped at the scale's limit and labelled with its length.
    texts = [t.get_text() for t in maps[1].texts]
    assert any(t == f"{100 * np.hypot(1.2, 0.9):.0f} cm" for t in texts), texts
    assert any(t.startswith("dZ +40") for t in texts)  # beyond the colour scale: its value written
    sc = vector_scale(panels, 400.0)
    assert sc.limit_m < 1.5 and sc.reference_m <= sc.limit_m
    bar = [ax for ax in fig.axes if hasattr(ax, "_colorbar")][0]._colorbar
    assert bar.norm.vmin == -bar.norm.vmax and "[cm]" in bar.ax.get_xlabel()  # below the maps
    assert min(_font_sizes(fig)) >= 8
    import matplotlib.pyplot as plt

    plt.close(fig)
    assert plot_point_vectors(panels, layout.crs_name, tmp_path / "v.png", context=layout).stat().st_size > 10_000


def test_residual_histograms(tmp_path):
    rng = np.random.default_rng(6)
    r = _residuals(7)
    h = ResidualHistogram("case 1", np.abs(rng.normal(0, 0.4, 500)), np.r_[np.abs(rng.normal(0, 0.8, 400)), 9.0],
                          r.error_m[~r.is_control], inlier_limit_px=6.0)
    fig = draw_residual_histograms(h, max_px=3.0)
    a, b = fig.axes
    labels = [t.get_text() for t in a.get_legend().get_texts()]
    assert any("1 beyond 3 px" in t for t in labels) and any(t.startswith("photos: 500") for t in labels)
    assert "check points" in b.get_legend().get_title().get_text() and "cm" in b.get_xlabel()
    assert min(_font_sizes(fig)) >= 8
    import matplotlib.pyplot as plt

    plt.close(fig)
    no_ties = ResidualHistogram("case 3", None, None, r.error_m)
    assert plot_residual_histograms(no_ties, tmp_path / "h.png").is_file()


# ---------------------------------------------------------------------------- report
def _metrics() -> BlockDemoMetrics:
    st = PointStats(12, np.array([0.03, 0.02, 0.13]), 0.33)
    case = BlockCase(st, st, TieReprojection(0.4, 0.6), 14, 28, 6000, PhotoLidargramMatches(28, 40.0), {},
                     Precision(), None)
    cloud = CloudErrorSummary(1000, 0.37, 0.12, 0.32, (0.2, 0.2, 0.2), (0.07, 0.07, 0.07), 1.5, 0.5)
    return BlockDemoMetrics("block", 3, (), "sift", {1: case, 3: BlockCase(None, st, *[getattr(case, f) for f in (
        "tie_reprojection", "photos", "lidargrams", "tracks", "photo_lidargram_matches", "timings_s", "precision",
        "photo_block_precision")])}, {1: cloud}, {"total": 1.0})


def test_report_has_the_layout_the_maps_and_the_tables_worst_first(tmp_path):
    r = _residuals(8)
    (tmp_path / "case1").mkdir()
    r.write(tmp_path / "case1" / "point_residuals.csv")
    _write_report(BlockDemoResult(tmp_path, tmp_path / "report.html", _metrics()))
    page = (tmp_path / "report.html").read_text()
    assert page.index("Block layout") < page.index("Tables 1-6") < page.index("Point by point")
    assert page.count("<details") == 1 and "<details open>" in page  # case 1; case 3 wrote no file
    assert "case1/point_residuals.csv" in page and "no point_residuals.csv" in page
    chk = r.subset(~r.is_control)
    rows = point_table_rows(chk)
    assert rows[0][0] == "P01" and rows[-1][0] == "P02" and rows[-1][1] == "–"
    assert "worst P01, 155.2 cm 3-D" in page  # |(1.2, -0.9, 0.4)| m
    assert page.index(">P01<") < page.index(">P04<")


def test_the_block_verdict_flags_each_figure_the_paper_beats():
    from georefine.demo.block import graz_verdict
    from georefine.evaluation.coadjust import PAPER_004_GRAZ
    from georefine.lidargrammetry.bundle import PointStats

    paper = PAPER_004_GRAZ[2]["check_points"]  # 0.012 / 0.028 / 0.111 m, 0.335 px
    case2 = PointStats(12, np.array([0.015, 0.030, 0.206]), 0.31)  # the example: Z twice the paper's
    assert graz_verdict(case2, paper) == "✗ Z 0.206 > 0.111"
    within = PointStats(12, np.array([0.016, 0.032, 0.115]), 0.38)  # within 5 mm and 0.05 px: rounding
    assert graz_verdict(within, paper) == "✓"
    worse = PointStats(12, np.array([0.020, 0.030, 0.100]), 0.50)
    assert graz_verdict(worse, paper) == "✗ X 0.020 > 0.012, RE 0.500 > 0.335"
    assert graz_verdict(case2, None) == "–"
