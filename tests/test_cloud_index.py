"""The cloud read block by block for lidargrammetry gives what the cloud read whole gives."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from georefine.errors import InputError
from georefine.geometry.camera import Camera, R_w_c_from_opk
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.las import PointCloud, read_las
from georefine.io.las_writer import write_las
from georefine.lidargrammetry.reintersect import Reintersector, reintersect
from georefine.lidargrammetry.render import NEAR_M, max_normalised_radius2, render_lidargram
from georefine.tasks import TaskRunner
from georefine.workflows.cloud_index import BLOCK_POINTS, index_cloud
from georefine.workflows.photo_block import render_in_cloud, write_cloud

CRS = OutputCRS(25832)
FRAME = LocalFrame.from_degrees(49.6, 9.0, 200.0)
CAMERA = Camera(400, 300, 500.0, 500.0, 200.0, 150.0, k1=-0.02, k2=0.004)


def _strip(rng, n: int, y0: float, source: int) -> tuple[np.ndarray, PointCloud]:
    """A strip scanned along x (points in time order) over a wavy terrain with houses."""
    x = np.sort(rng.uniform(-300.0, 300.0, n))
    y = y0 + rng.uniform(-60.0, 60.0, n)
    z = 3.0 * np.sin(x / 40.0) + np.where((np.abs(x % 50 - 25) < 8) & (np.abs(y % 40 - 20) < 6), 8.0, 0.0)
    xyz_w = np.column_stack([x, y, z + rng.normal(0, 0.02, n)])
    cloud = PointCloud(1.4e9 + np.arange(n) * 1e-5, CRS.from_w(FRAME, xyz_w), rng.integers(0, 4000, n),
                       np.zeros(n, np.uint8), np.full(n, source), np.ones(n), np.ones(n))
    return xyz_w, cloud


@pytest.fixture(scope="module")
def strips(tmp_path_factory) -> tuple[list[Path], np.ndarray]:
    """Two overlapping LAZ strips of 7.3 and 4.1 blocks; the whole cloud in ``w`` as read back."""
    rng = np.random.default_rng(8)
    folder = tmp_path_factory.mktemp("cloud")
    files = []
    for k, (n, y0) in enumerate([(int(7.3 * BLOCK_POINTS), -20.0), (int(4.1 * BLOCK_POINTS), 30.0)]):
        _, cloud = _strip(rng, n, y0, k + 1)
        files.append(write_las(folder / f"strip_{k + 1}.laz", cloud, scale=0.001, crs=CRS.crs))
    whole = np.concatenate([CRS.to_w(FRAME, read_las(f, extra_dims=()).xyz) for f in files])
    return files, whole


def _poses():
    """Nadir, oblique, rotated and half-off-the-strip stations 250-400 m above the terrain."""
    return [(R_w_c_from_opk(0.0, 0.0, 0.0), np.array([0.0, 0.0, 300.0])),
            (R_w_c_from_opk(np.radians(20.0), np.radians(-10.0), np.radians(35.0)), np.array([-120.0, 40.0, 250.0])),
            (R_w_c_from_opk(0.0, 0.0, np.radians(90.0)), np.array([250.0, -10.0, 400.0])),
            (R_w_c_from_opk(np.radians(-5.0), 0.0, 0.0), np.array([-330.0, 0.0, 300.0]))]


def test_index_bounds_and_identifiers(strips):
    files, whole = strips
    idx = index_cloud(files, FRAME, CRS)
    assert idx.n_points == len(whole) and idx.file_start[1] == int(7.3 * BLOCK_POINTS)
    assert len(idx.block_start) == 8 + 5 and np.all(idx.block_stop - idx.block_start <= BLOCK_POINTS)
    for b in range(len(idx.block_start)):
        pts = whole[idx.block_start[b]:idx.block_stop[b]]
        np.testing.assert_array_equal(idx.lo[b], pts.min(axis=0))
        np.testing.assert_array_equal(idx.hi[b], pts.max(axis=0))
    np.testing.assert_array_equal(idx.strip_of(np.array([0, idx.file_start[1] - 1, idx.file_start[1]])), [0, 0, 1])
    rng = np.random.default_rng(3)
    ids = np.unique(rng.integers(0, len(whole), 5000))
    np.testing.assert_array_equal(idx.gather(ids, max_points=2 * BLOCK_POINTS), whole[ids])
    with TaskRunner("threads", workers=2) as runner:  # indexing as tasks: the same index
        par = index_cloud(files, FRAME, CRS, runner=runner)
    np.testing.assert_array_equal(par.lo, idx.lo)
    np.testing.assert_array_equal(par.hi, idx.hi)


def test_blocks_in_view_hold_every_point_the_renderer_sees(strips):
    files, whole = strips
    idx = index_cloud(files, FRAME, CRS)
    block_of = np.searchsorted(idx.block_start, np.arange(len(whole)), side="right") - 1
    for R, p in _poses():
        rn2 = max_normalised_radius2(CAMERA, 7.0)
        sel = idx.blocks_in_view(CAMERA, R, p, rn2, NEAR_M)
        x_c = (whole - p) @ R
        seen = (x_c[:, 2] > NEAR_M) & ((x_c[:, 0] ** 2 + x_c[:, 1] ** 2) / x_c[:, 2] ** 2 <= rn2)
        assert np.isin(block_of[seen], sel).all()
        assert len(sel) < len(idx.block_start)  # the view test prunes
    up = R_w_c_from_opk(np.pi, 0.0, 0.0)  # looking at the sky: nothing in view
    assert idx.blocks_in_view(CAMERA, up, np.array([0.0, 0.0, 300.0]), rn2, NEAR_M).size == 0


def test_lidargrams_from_blocks_are_those_of_the_whole_cloud(strips):
    """Per strip and of all strips: the same image, depth, ULPI and points as rendering the cloud read whole."""
    files, whole = strips
    idx = index_cloud(files, FRAME, CRS)
    inten = np.concatenate([read_las(f, extra_dims=()).intensity for f in files])
    strip = idx.strip_of(np.arange(len(whole)))
    for R, p in _poses():
        for s in (-1, 0, 1):
            sel = np.arange(len(whole)) if s < 0 else np.flatnonzero(strip == s)
            ref = render_lidargram(whole[sel], inten[sel], CAMERA, R, p, point_spacing_m=0.5, fill_holes=True)
            lg = render_in_cloud(idx, s, CAMERA, R, p, 0.5, 1.0, True, 0.0)
            if not ref.point_index.size:
                assert lg is None
                continue
            np.testing.assert_array_equal(lg.image, ref.image)
            np.testing.assert_array_equal(lg.depth, ref.depth)
            np.testing.assert_array_equal(lg.ulpi, np.where(ref.ulpi >= 0, sel[np.maximum(ref.ulpi, 0)], -1))
            np.testing.assert_array_equal(lg.point_index, sel[ref.point_index])
            np.testing.assert_array_equal(lg.point_uv, ref.point_uv)


@pytest.mark.parametrize("scheduler", ["sync", "processes"])
def test_refined_cloud_streamed_is_the_cloud_refined_whole(strips, tmp_path, scheduler):
    """Re-intersection range by range, as tasks, writes the points the in-memory re-intersection gives."""
    files, whole = strips
    idx = index_cloud(files, FRAME, CRS)
    rng = np.random.default_rng(5)
    strip = idx.strip_of(np.arange(len(whole)))
    poses = _poses()[:3]
    shown = [np.unique(rng.choice(np.flatnonzero(strip == 0), 40_000, replace=False)) for _ in poses]
    shown[2] = np.unique(rng.choice(len(whole), 30_000, replace=False))  # both strips
    R0 = np.stack([R for R, _ in poses])
    p0 = np.stack([p for _, p in poses])
    dR = Rotation.from_rotvec([1e-4, -2e-4, 3e-4]).as_matrix()
    R1, p1 = dR @ R0, p0 + [0.1, -0.05, 0.03]
    ref = reintersect(whole, strip, shown, R0, p0, R1, p1, k=6, max_distance_m=3.0)
    u = np.unique(np.concatenate(shown))
    refine = Reintersector(u, idx.gather(u), idx.strip_of(u), shown, R0, p0, R1, p1, k=6, max_distance_m=3.0)
    with pytest.raises(ValueError, match="lidargram 1 shows points that index does not hold"):
        Reintersector(u[1:], idx.gather(u[1:]), idx.strip_of(u[1:]), [shown[0][1:], shown[2]], R0, p0, R1, p1)
    with TaskRunner(scheduler, workers=2) as runner:
        counts = write_cloud(idx, refine, tmp_path / "points", runner=runner)
    assert counts == ref.summary()
    assert 0 < counts["interpolated"] and 0 < counts["unchanged"] and 0 < counts["multi_ray"]
    done = 0
    for f in files:
        out, inp = laspy.read(tmp_path / "points" / f.name), laspy.read(f)
        n = len(inp.points)
        np.testing.assert_array_equal(out.gps_time, inp.gps_time)  # same points, same order
        np.testing.assert_array_equal(out.intensity, inp.intensity)
        xyz = np.column_stack([out.x, out.y, out.z])
        expected = CRS.from_w(FRAME, ref.xyz_w[done:done + n])
        assert np.abs(xyz - expected).max() <= 0.0005 + 1e-9  # the 1 mm quantisation
        np.testing.assert_array_equal(np.asarray(out.lidargrams), ref.n_lidargrams[done:done + n])
        done += n


def test_write_cloud_files_do_not_depend_on_the_scheduler(strips, tmp_path):
    files, _ = strips
    idx = index_cloud(files, FRAME, CRS)
    u = np.arange(0, idx.n_points, 97)
    R, p = _poses()[0]
    refine = Reintersector(u, idx.gather(u), idx.strip_of(u), [u], R[None], p[None], R[None], (p + 0.2)[None])
    write_cloud(idx, refine, tmp_path / "a")
    with TaskRunner("threads", workers=2) as runner:
        write_cloud(idx, refine, tmp_path / "b", runner=runner)
    for f in files:
        assert (tmp_path / "a" / f.name).read_bytes() == (tmp_path / "b" / f.name).read_bytes()


def test_bad_clouds_are_refused_with_the_file(strips, tmp_path):
    files, _ = strips
    cut = tmp_path / "cut.laz"
    cut.write_bytes(files[1].read_bytes()[: files[1].stat().st_size // 2])
    with pytest.raises(InputError) as err:
        index_cloud([files[0], cut], FRAME, CRS)
    assert err.value.path == cut
    empty = write_las(tmp_path / "empty.laz", PointCloud.empty(), scale=0.001, crs=CRS.crs)
    with pytest.raises(InputError, match="no points"):
        index_cloud([empty], FRAME, CRS)
