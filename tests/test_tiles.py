"""Time tiles and the task runner: streamed per-point work gives what the whole strip gives.

A synthetic strip is swept along x over a ground plane with roofs (identity trajectory, so
scanner and mapping frames coincide): its time index, record ranges, tile plan, planar
features per tile and georeferenced output are checked against the whole strip, on the
``sync`` scheduler and on a two-process ``dask.distributed.LocalCluster``.
"""

from __future__ import annotations

import math
import os
import pickle
import signal
import subprocess
import sys
import time

import laspy
import numpy as np
import pytest

from georefine.config import PlaneExtractionConfig, ScaleConfig
from georefine.errors import InputError
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.las import PointCloud, read_las, read_las_range, time_index
from georefine.io.las_writer import LasWriter
from georefine.lidar.georeference import PoseInterpolator
from georefine.lidar.planes import extract_features
from georefine.lidar.tiles import (
    georeference_strip,
    georeference_strips,
    plan_strip,
    tile_features,
    tile_points,
)
from georefine.tasks import TaskRunner, check_scheduler
from georefine.trajectory.sampled import Trajectory
from georefine.workflows.strips import sort_features

T0 = 1.4e9  # GPS seconds of the epoch
RATE = 40_000  # points per second
SPEED = 40.0  # m/s along x
DURATION = 12.0


def _scene(rng, n):
    """Times, points and channels of a sweep over ground (z=0) and three tilted roofs."""
    t = np.sort(rng.uniform(0.0, DURATION, n))
    x = SPEED * t + rng.normal(0.0, 0.3, n)
    y = rng.uniform(-30.0, 30.0, n)
    z = np.zeros(n)
    for cx in (80.0, 230.0, 390.0):  # 12 m x 16 m roofs, 30 % slope, 6 m above the ground
        m = (np.abs(x - cx) < 6.0) & (np.abs(y) < 8.0)
        z[m] = 6.0 + 0.3 * (x[m] - cx)
    z += rng.normal(0.0, 0.003, n)
    ch = (np.floor(t * 120.0).astype(int) % 3).astype(np.uint8)
    return t, np.column_stack([x, y, z]), ch


@pytest.fixture(scope="module")
def strip(tmp_path_factory):
    rng = np.random.default_rng(3)
    t, xyz, ch = _scene(rng, int(RATE * DURATION))
    path = tmp_path_factory.mktemp("tiles") / "strip_5.laz"
    n = t.size
    ones = np.ones(n, np.uint8)
    with LasWriter(path, scale=1e-4) as w:
        for a in range(0, n, 100_000):
            s = slice(a, a + 100_000)
            w.write(PointCloud(t[s] + T0, xyz[s], np.full(xyz[s].shape[0], 100), ch[s],
                               np.full(xyz[s].shape[0], 5), ones[s], ones[s]))
    return path


@pytest.fixture(scope="module")
def poses():
    time = np.arange(-1.0, DURATION + 1.0, 0.01)
    R = np.broadcast_to(np.eye(3), (time.size, 3, 3)).copy()
    return PoseInterpolator(Trajectory(time, np.zeros((time.size, 3)), R, T0))


@pytest.fixture(scope="module")
def cluster():
    with TaskRunner("processes", workers=2) as runner:
        yield runner


def test_time_index_samples_every_step_and_checks_the_order(strip, tmp_path):
    full = read_las(strip)
    ti = time_index(strip, step=1000)
    assert ti.point_count == len(full) and ti.ordered and ti.first_unordered == -1
    assert ti.index[0] == 0 and ti.index[-1] == len(full) - 1 and np.all(np.diff(ti.index[:-1]) == 1000)
    assert np.array_equal(ti.time_gps, full.time_gps[ti.index])
    assert sum(ti.channel_counts) == len(full) and ti.channel_counts[3] == 0
    # A record out of time order is found, wherever it is (not only at the samples).
    t = full.time_gps.copy()
    t[12_345], t[12_346] = t[12_346], t[12_345] - 1e-3
    bad = tmp_path / "unordered.laz"
    with LasWriter(bad, scale=1e-4) as w:
        w.write(PointCloud(t, full.xyz, full.intensity, full.scanner_channel, full.point_source_id,
                           full.return_number, full.number_of_returns))
    tb = time_index(bad, step=1000)
    assert not tb.ordered and tb.first_unordered == 12_346
    # Such a strip is one tile (it cannot be cut by time), with a warning.
    plan = plan_strip(bad, 5, T0, 50_000, 0.5, index=tb)
    assert not plan.ordered and len(plan.tiles) == 1 and plan.tiles[0].own_t0 == -math.inf


def test_read_range_is_the_slice_of_the_whole_file(strip):
    full = read_las(strip)
    for a, b in ((0, 1), (49_999, 50_001), (123_457, 300_000), (len(full) - 7, len(full))):
        r = read_las_range(strip, a, b)
        assert np.array_equal(r.time_gps, full.time_gps[a:b]) and np.array_equal(r.xyz, full.xyz[a:b])
    with pytest.raises(ValueError):
        read_las_range(strip, 10, len(full) + 1)


def test_plan_owns_every_record_once_and_reads_the_margins(strip):
    full = read_las(strip)
    t = full.time_gps - T0
    plan = plan_strip(strip, 5, T0, 60_000, 1.0, index=time_index(strip, step=4096))
    assert len(plan.tiles) > 4 and plan.ordered
    assert plan.tiles[0].start == 0 and plan.tiles[-1].stop == len(full)
    for a, b in zip(plan.tiles[:-1], plan.tiles[1:]):
        assert a.stop == b.start and a.own_t1 == b.own_t0
    for tile in plan.tiles:
        own = np.flatnonzero((t >= tile.own_t0) & (t < tile.own_t1))  # times strictly increase here
        assert own[0] == tile.start and own[-1] == tile.stop - 1 and own.size == tile.points
        # the records a feature task reads hold every point within the margin of its own times
        need = np.flatnonzero((t >= tile.own_t0 - 1.0) & (t < tile.own_t1 + 1.0))
        assert tile.read_start <= need.min() and need.max() < tile.read_stop


def test_tile_size_follows_the_memory_budget():
    small, large = ScaleConfig(memory_budget_gb=0.5), ScaleConfig(memory_budget_gb=4.0)
    assert tile_points(large, 2) == pytest.approx(8 * tile_points(small, 2), rel=0.01)
    assert tile_points(large, 4) < tile_points(large, 1)
    assert tile_points(ScaleConfig(memory_budget_gb=0.01), 8, margin_points=10**6) == ScaleConfig().min_tile_points


@pytest.mark.parametrize("tile_size", [30_000, 100_000])
def test_tile_features_are_those_of_the_whole_view(strip, poses, tile_size):
    cfg = PlaneExtractionConfig()
    full = read_las(strip)
    t = full.time_gps - T0
    whole = []
    for c in (0, 1, 2):
        m = full.scanner_channel == c
        whole.append(extract_features(full.xyz[m], t[m], 5, c, poses, np.zeros(3), np.eye(3), cfg))
    from georefine.lidar.planes import PlanarFeatures

    whole = sort_features(PlanarFeatures.concatenate(whole))
    plan = plan_strip(strip, 5, T0, tile_size, 2 * cfg.max_time_span_s, index=time_index(strip))
    assert len(plan.tiles) >= 4
    parts = [tile_features(tile, poses, T0, np.zeros(3), np.eye(3), (0, 1, 2), cfg) for tile in plan.tiles]
    tiled = sort_features(PlanarFeatures.concatenate([p.features for p in parts]))
    assert len(whole) > 300 and len(tiled) == len(whole)
    np.testing.assert_array_equal(tiled.n_points, whole.n_points)
    np.testing.assert_array_equal(tiled.channel, whole.channel)
    for name in ("time", "centre_w", "normal_w", "sigma_d_m"):  # the same sums in another order: 1e-15
        np.testing.assert_allclose(getattr(tiled, name), getattr(whole, name), rtol=1e-12, atol=1e-12, err_msg=name)
    assert sum(p.points_outside for p in parts) == 0


def test_a_cluster_gives_the_same_features_and_points_as_this_process(strip, poses, cluster, tmp_path):
    cfg = PlaneExtractionConfig()
    plan = plan_strip(strip, 5, T0, 50_000, 2 * cfg.max_time_span_s, index=time_index(strip))
    args = [(tile, poses, T0, np.zeros(3), np.eye(3), (0, 1, 2), cfg) for tile in plan.tiles]
    local = list(TaskRunner("sync").map(tile_features, args))
    shared = cluster.share(poses)
    remote = list(cluster.map(tile_features, [(a[0], shared, *a[2:]) for a in args], window=3))
    assert [len(r.features) for r in remote] == [len(r.features) for r in local]
    for a, b in zip(local, remote):
        np.testing.assert_array_equal(a.features.centre_s, b.features.centre_s)
    # Step 6 on the cluster writes the same LAZ records as in this process, in the input's order.
    frame, crs = LocalFrame(math.radians(48.0), math.radians(11.0), 500.0), OutputCRS(25832)
    a = georeference_strip(plan, tmp_path / "a.laz", poses, T0, np.zeros(3), np.eye(3), frame, crs)
    b = georeference_strip(plan, tmp_path / "b.laz", shared, T0, np.zeros(3), np.eye(3), frame, crs, runner=cluster)
    assert a.points_written == b.points_written == time_index(strip).point_count
    la, lb = laspy.read(a.output), laspy.read(b.output)
    for dim in ("X", "Y", "Z", "gps_time", "scanner_channel"):
        assert np.array_equal(la[dim], lb[dim]), dim
    assert np.all(np.diff(la.gps_time) >= 0)


def test_georeferencing_tasks_compress_on_the_chunk_grid(strip, poses, tmp_path, caplog):
    """Tiles planned in multiples of the LAZ chunk hand their chunks to the file as they are;
    tiles off the grid are compressed again by the writer; both give the same file."""
    import logging

    from georefine.io.las_encode import LAZ_CHUNK_POINTS

    frame, crs = LocalFrame(math.radians(48.0), math.radians(11.0), 500.0), OutputCRS(25832)
    on = plan_strip(strip, 5, T0, 120_000, 0.0, index=time_index(strip))  # sampled every 5000 records
    off = plan_strip(strip, 5, T0, 70_000, 0.0, index=time_index(strip, step=4096))
    assert all(t.start % LAZ_CHUNK_POINTS == 0 for t in on.tiles) and len(on.tiles) >= 3
    assert any(t.start % LAZ_CHUNK_POINTS for t in off.tiles)
    with caplog.at_level(logging.DEBUG, logger="georefine.lidar.tiles"):
        a = georeference_strip(on, tmp_path / "on.laz", poses, T0, np.zeros(3), np.eye(3), frame, crs)
        assert "compressed again" not in caplog.text
        b = georeference_strip(off, tmp_path / "off.laz", poses, T0, np.zeros(3), np.eye(3), frame, crs)
        assert "compressed again" in caplog.text
    assert a.points_written == b.points_written == time_index(strip).point_count
    assert a.output.read_bytes() == b.output.read_bytes()


def test_strips_in_one_stream_give_the_files_of_one_strip_at_a_time(strip, poses, cluster, tmp_path):
    """``georeference_strips`` runs the tiles of all strips as one stream (no worker waits for a
    strip's last tile); the files are those of one strip at a time, and an error leaves none."""
    frame, crs = LocalFrame(math.radians(48.0), math.radians(11.0), 500.0), OutputCRS(25832)
    a = plan_strip(strip, 5, T0, 120_000, 0.0, index=time_index(strip))
    b = plan_strip(strip, 5, T0, 70_000, 0.0, index=time_index(strip, step=4096))
    shared = cluster.share(poses)
    both = georeference_strips([a, b], [tmp_path / "a.laz", tmp_path / "b.laz"], shared, T0, np.zeros(3), np.eye(3),
                               frame, crs, runner=cluster)
    one = georeference_strip(a, tmp_path / "one.laz", poses, T0, np.zeros(3), np.eye(3), frame, crs)
    assert [r.points_written for r in both] == [one.points_written] * 2
    assert both[0].output.read_bytes() == both[1].output.read_bytes() == one.output.read_bytes()
    import json

    from georefine.io.point_manifest import MANIFEST

    listed = {e["file"]: e["points"] for e in json.loads((tmp_path / MANIFEST).read_text())["files"]}
    assert listed["a.laz"] == listed["b.laz"] == one.points_written  # the evaluations read what was written
    # The second strip's file vanished: the first file is complete, the second is not written.
    from dataclasses import replace

    gone = tmp_path / "gone.laz"
    lost = replace(b, path=gone, tiles=tuple(replace(t, path=gone) for t in b.tiles))
    with pytest.raises(InputError, match="gone.laz"):
        georeference_strips([a, lost], [tmp_path / "x.laz", tmp_path / "y.laz"], poses, T0, np.zeros(3), np.eye(3),
                            frame, crs)
    assert (tmp_path / "x.laz").read_bytes() == one.output.read_bytes()
    assert not (tmp_path / "y.laz").exists() and not list(tmp_path.glob(".*.part"))
    assert "y.laz" not in (tmp_path / MANIFEST).read_text()


def test_equal_tiles_within_the_budget(strip):
    n = time_index(strip).point_count
    plan = plan_strip(strip, 5, T0, int(0.7 * n), 0.0, index=time_index(strip))
    sizes = [t.points for t in plan.tiles]
    assert len(sizes) == 2 and max(sizes) <= 0.7 * n and min(sizes) >= 0.45 * n


def test_task_errors_reach_the_caller_intact(cluster, tmp_path):
    missing = tmp_path / "nowhere.laz"
    with pytest.raises(InputError) as err:
        list(cluster.map(time_index, [(missing,)]))
    assert err.value.path == missing and "file not found" in str(err.value)
    e = InputError("bad", path="/x", line=4, field="f", expected="1", found="2")
    assert str(pickle.loads(pickle.dumps(e))) == str(e)


def test_scheduler_names_and_addresses():
    assert check_scheduler("threads") == "threads" and check_scheduler("tcp://127.0.0.1:8786").startswith("tcp")
    with pytest.raises(InputError, match="unknown scheduler"):
        check_scheduler("gpu")
    with pytest.raises(InputError, match="cannot reach the Dask scheduler"):
        TaskRunner("tcp://127.0.0.1:9", timeout="1s").start()


def test_a_local_cluster_starts_with_its_first_task_not_on_entering():
    """A run that stops on its inputs starts no cluster; its task slots are known before."""
    for scheduler, workers in (("threads", 3), ("processes", 2)):
        with TaskRunner(scheduler, workers=workers) as runner:
            assert runner.workers == workers and runner._client is None
    with TaskRunner("threads", workers=2) as runner:
        assert list(runner.map(pow, [(3, 2)])) == [9] and runner._client is not None
        assert runner.workers == 2  # now from the running cluster
    assert runner._client is None  # closed on leaving


_STOPPED_CHILD = """
import sys, time
from georefine.tasks import TaskRunner
with TaskRunner("threads", workers=1) as runner:
    assert list(runner.map(pow, [(2, 3)])) == [8]
    print("ready", flush=True)
    sys.stdin.readline()  # the parent stops this process, resumes it, then writes a line
    time.sleep(3.0)  # the scheduler's periodic checks run on the resumed clock
    print(list(runner.map(pow, [(3, 3)])), flush=True)
"""


@pytest.mark.skipif(not hasattr(signal, "SIGSTOP"), reason="needs POSIX job control")
def test_a_run_whose_process_was_stopped_goes_on_after_it_resumes():
    """A suspended machine or a paused job: the local cluster keeps its worker. With the
    scheduler's time-to-live of workers (here 1 s, at least ten heartbeats: 5 s, instead of 5
    minutes) a process stopped for longer lost its only worker on resuming, and its next task
    waited for ever."""
    env = dict(os.environ, DASK_DISTRIBUTED__SCHEDULER__WORKER_TTL="1s")
    child = subprocess.Popen([sys.executable, "-c", _STOPPED_CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert child.stdout.readline().strip() == "ready", child.stderr.read()
        child.send_signal(signal.SIGSTOP)
        time.sleep(12.0)
        child.send_signal(signal.SIGCONT)
        out, err = child.communicate("go\n", timeout=90)
    finally:
        if child.poll() is None:
            child.kill()
            child.communicate()
    assert child.returncode == 0 and out.strip() == "[27]", err[-3000:]


def test_map_keeps_the_order_and_reports_progress():
    calls = []
    with TaskRunner("threads", workers=2) as runner:
        out = list(runner.map(pow, [(k, 2) for k in range(20)], window=3, label="squares",
                              progress=lambda *a: calls.append(a)))
    assert out == [k * k for k in range(20)]
    assert calls[0] == ("squares", 0, 20.0) and calls[-1] == ("squares", 20, 20.0) and len(calls) == 21


def test_a_range_calibration_moves_every_point_along_its_beam(strip, poses):
    """``ScannerCalibration(range=(r0, k))``: a point read at ``(1 + k) r + r0`` is written at range ``r``, on its
    beam."""
    from georefine.lidar.georeference import ScannerCalibration, calibrated_ranges
    from georefine.lidar.tiles import tile_georeference

    frame, crs = LocalFrame(math.radians(48.0), math.radians(11.0), 500.0), OutputCRS(25832)
    tile = plan_strip(strip, 5, T0, 120_000, 0.0, index=time_index(strip)).tiles[1]
    plain, _ = tile_georeference(tile, poses, T0, np.zeros(3), np.eye(3), frame, crs)
    cal, _ = tile_georeference(tile, poses, T0, np.zeros(3), np.eye(3), frame, crs,
                               calibration=ScannerCalibration(range=(0.03, 1e-4)))
    x_s = read_las_range(tile.path, tile.start, tile.stop, ()).xyz
    expected = crs.from_geodetic(*frame.to_geodetic(calibrated_ranges(x_s, (0.03, 1e-4))))
    np.testing.assert_allclose(cal.xyz, expected, atol=1e-6)
    r = np.linalg.norm(x_s, axis=1)
    moved = np.linalg.norm(cal.xyz - plain.xyz, axis=1)
    # 3 cm + 100 ppm of r, in the projection (its scale within 1e-3 of 1 here)
    np.testing.assert_allclose(moved, r - (r - 0.03) / (1.0 + 1e-4), rtol=1e-3)
    np.testing.assert_array_equal(calibrated_ranges(x_s, None), x_s)


def test_channel_angles_turn_each_point_onto_its_channels_beam(strip, poses):
    """``ScannerCalibration(channel_angles=...)``: each point turned by its channel's tilt and scan-angle error,
    at its range: it moves by the range times the angle (as the sum of both, the scan angle's foreshortened by
    the tilt), the range kept."""
    from georefine.lidar.georeference import ScannerCalibration, beam_angles, calibrated_channels
    from georefine.lidar.tiles import tile_georeference

    frame, crs = LocalFrame(math.radians(48.0), math.radians(11.0), 500.0), OutputCRS(25832)
    tile = plan_strip(strip, 5, T0, 120_000, 0.0, index=time_index(strip)).tiles[1]
    angles = np.radians(np.array([[30.0, -20.0], [-15.0, 10.0], [5.0, 40.0]]) * 1e-3)
    plain, _ = tile_georeference(tile, poses, T0, np.zeros(3), np.eye(3), frame, crs)
    cal, _ = tile_georeference(tile, poses, T0, np.zeros(3), np.eye(3), frame, crs,
                               calibration=ScannerCalibration(channel_angles=angles))
    pc = read_las_range(tile.path, tile.start, tile.stop, ())
    fixed = calibrated_channels(pc.xyz, pc.scanner_channel, angles)
    np.testing.assert_allclose(np.linalg.norm(fixed, axis=1), np.linalg.norm(pc.xyz, axis=1), rtol=1e-12)
    np.testing.assert_allclose(cal.xyz, crs.from_geodetic(*frame.to_geodetic(fixed)), atol=1e-6)
    r, tau, _ = beam_angles(pc.xyz)
    a = angles[pc.scanner_channel]
    moved = np.linalg.norm(cal.xyz - plain.xyz, axis=1)
    np.testing.assert_allclose(moved, r * np.hypot(a[:, 0], np.cos(tau) * a[:, 1]), rtol=2e-3)
    assert len(np.unique(pc.scanner_channel)) > 1
    np.testing.assert_array_equal(calibrated_channels(pc.xyz, pc.scanner_channel, None), pc.xyz)
