"""Flight plans: Dubins turns between lines, area blocks with cross lines, bending and parallel corridors, line files."""

import numpy as np
import pytest

from georefine.errors import ConfigError, InputError
from georefine.geometry.frames import LocalFrame
from georefine.sim.flight import FlightConfig, simulate_flight
from georefine.sim.flight_plan import (
    FlightPlanConfig,
    PlannedLine,
    dubins_path,
    follow,
    plan_lines,
    read_line_file,
    swath_width_m,
)
from georefine.sim.scenarios import flight_passes, resolve_scenario

FRAME = LocalFrame.from_degrees(46.7, 11.65, 600.0)


def terrain(x, y):
    return 500.0 + 0.01 * np.asarray(y) + 0.002 * np.asarray(x)


def test_dubins_paths_reach_the_goal_pose_and_are_no_longer_than_alternatives():
    rng = np.random.default_rng(3)
    R = 200.0
    for _ in range(500):
        p0, p1 = rng.uniform(-1500, 1500, (2, 2))
        a0, a1 = rng.uniform(0, 2 * np.pi, 2)
        path = dubins_path(p0, a0, p1, a1, R)
        end, az = follow(path, p0, a0)
        np.testing.assert_allclose(end, p1, atol=1e-6)
        assert abs(np.angle(np.exp(1j * (az - a1)))) < 1e-9
        length = sum(q.path_length_m for q in path)
        # Never shorter than the straight distance, and no turn tighter than R.
        assert length >= np.linalg.norm(p1 - p0) - 1e-6
        assert all(q.radius_m == R for q in path if q.turn_rad)


def test_dubins_between_parallel_lines_is_a_u_turn():
    # Lines 600 m apart, opposite headings: half circle, straight across, half circle (RSR).
    path = dubins_path((0.0, 1000.0), 0.0, (600.0, 1000.0), np.pi, 200.0)
    assert [round(np.degrees(q.turn_rad)) for q in path] == [90, 0, 90]
    assert path[1].length_m == pytest.approx(200.0)


def test_area_block_lines_spacing_order_and_cross_lines():
    swath = swath_width_m(160.0, 100.0)
    assert swath == pytest.approx(381.4, abs=0.1)
    plan = FlightPlanConfig(kind="area", lines=8, sidelap=0.3, cross_lines=2)
    lines = plan_lines(plan, length_m=2000.0, width_m=2300.0, swath_m=swath)
    assert [ln.line_id for ln in lines] == [1, 5, 2, 6, 3, 7, 4, 8, 9, 10]
    x = {ln.line_id: ln.vertices[0, 0] for ln in lines[:8]}
    np.testing.assert_allclose(np.diff([x[i] for i in range(1, 9)]), 0.7 * swath)
    # Racetrack: consecutive parallel lines at least two turn radii apart, flown back and forth.
    gaps = np.abs(np.diff([ln.vertices[0, 0] for ln in lines[:8]]))
    assert gaps.min() >= 400.0
    headings = np.degrees([ln.start_heading for ln in lines[:8]]) % 360
    np.testing.assert_allclose(headings, [0, 180] * 4, atol=1e-9)
    # Cross lines span the whole block, across it.
    for ln in lines[8:]:
        assert ln.vertices[0, 1] == pytest.approx(ln.vertices[1, 1])
        assert abs(ln.vertices[0, 0] - ln.vertices[1, 0]) == pytest.approx(7 * 0.7 * swath + swath)
    with pytest.raises(ConfigError, match="misses the scene"):
        plan_lines(plan, length_m=2000.0, width_m=1500.0, swath_m=swath)


def test_corridor_plan_with_bends_and_parallel_lines():
    plan = FlightPlanConfig(kind="corridor", polyline_m=((0, 0), (0, 800), (300, 1600)), parallel_lines=2,
                            line_spacing_m=200.0, bend_radius_m=500.0)
    lines = plan_lines(plan, length_m=1700.0, width_m=1200.0, swath_m=380.0)
    assert len(lines) == 2
    a, b = lines[0].vertices, lines[1].vertices[::-1]
    # The two lines are parallel offsets 200 m apart on every segment, the second flown backwards.
    for k in range(2):
        d = (a[k + 1] - a[k]) / np.linalg.norm(a[k + 1] - a[k])
        normal = np.array([d[1], -d[0]])
        assert (b[k] - a[k]) @ normal == pytest.approx(200.0)
    traj = simulate_flight(FlightConfig(static_duration_s=5.0, manoeuvre="none"), FRAME, 1700.0, terrain,
                           lines, bend_radius_m=500.0)
    assert [p[0] for p in traj.passes] == [1, 2]
    # The bend is flown inside the strip: the heading changes by the polyline's angle, at the bend radius.
    sid, t0, t1 = traj.passes[0]
    t = np.linspace(t0, t1, 4000)
    rph = traj.rph(t)
    p, _ = traj.pose(t)
    assert np.degrees(np.abs(rph[:, 0])).max() > 1.5  # banked in the bend
    bend = np.degrees(np.arctan2(300, 800))
    track = np.degrees(np.arctan2(np.diff(p[:, 0]), np.diff(p[:, 1])))
    assert track[10] == pytest.approx(0.0, abs=0.05)
    assert track[-10] == pytest.approx(bend, abs=0.05)


def test_line_file_in_the_output_crs(tmp_path):
    f = tmp_path / "lines.csv"
    f.write_text("# two lines\nline,x0,y0,x1,y1\n7,100,0,100,900\n3,400,900,400,0\n")
    lines = read_line_file(f, lambda en: np.column_stack([en[:, 0] - 50.0, en[:, 1], np.zeros(len(en))]))
    assert [ln.line_id for ln in lines] == [7, 3]
    np.testing.assert_allclose(lines[1].vertices, [[350, 900], [350, 0]])
    f.write_text("line,x0,y0,x1,y1\n1,0,0,0,abc\n")
    with pytest.raises(InputError, match="line 2"):
        read_line_file(f, lambda en: en)
    f.write_text("line,x0,y0,x1,y1\n1,0,0,0,500\n1,10,0,10,500\n")
    with pytest.raises(InputError, match="listed twice"):
        read_line_file(f, lambda en: en)
    with pytest.raises(ValueError, match="closer than 1 m"):
        PlannedLine(1, np.array([[0.0, 0.0], [0.0, 0.5]]))


@pytest.fixture(scope="module")
def block_flight():
    plan = FlightPlanConfig(kind="area", lines=4, sidelap=0.3, cross_lines=1)
    swath = swath_width_m(160.0, 100.0)
    lines = plan_lines(plan, length_m=600.0, width_m=1400.0, swath_m=swath)
    cfg = FlightConfig(static_duration_s=5.0, manoeuvre="s_turns")
    return simulate_flight(cfg, FRAME, 600.0, terrain, lines), lines


def test_block_flight_flies_every_line_straight_and_level_with_the_turns_outside_the_strips(block_flight):
    traj, lines = block_flight
    assert [p[0] for p in traj.passes] == [ln.line_id for ln in lines]
    cfg = traj.config
    spans = np.array([(a, b) for _, a, b in traj.passes])
    assert np.all(spans[1:, 0] > spans[:-1, 1])  # in time order, turns between
    for (_, t0, t1), line in zip(traj.passes, lines):
        t = np.linspace(t0, t1, 500)
        p, _ = traj.pose(t)
        rph = traj.rph(t)
        assert np.degrees(np.abs(rph[:, 0])).max() < 0.01  # wings level: no turn inside a strip
        d = line.vertices[1] - line.vertices[0]
        u = d / np.linalg.norm(d)
        normal = np.array([u[1], -u[0]])
        offset = (p[:, :2] - line.vertices[0]) @ normal
        assert np.abs(offset).max() < 0.5  # on the planned line
        along = (p[:, :2] - line.vertices[0]) @ u
        assert along[0] < -cfg.lead_in_m + 50 and along[-1] > np.linalg.norm(d) + cfg.lead_out_m - 50
        s = traj.state(t)
        np.testing.assert_allclose(np.linalg.norm(s.v_w_b[:, :2], axis=1), cfg.speed_mps, rtol=1e-3)
    # Turns stay within the bank a 200 m radius at 18 m/s needs (9.4 deg) plus the roll-in's smoothing.
    turns = [(a, b) for n, a, b in traj.phases if n == "turn"]
    assert len(turns) == len(lines)
    t = np.concatenate([np.linspace(a, b, 300) for a, b in turns[1:]])
    bank = np.degrees(np.abs(traj.rph(t)[:, 0])).max()
    assert 8.0 < bank < 10.5


def test_area_scenarios_fly_their_plans():
    cfg = resolve_scenario("area")
    passes = flight_passes(cfg, 42)
    assert [p[0] for p in passes] == [1, 5, 2, 6, 3, 7, 4, 8, 9, 10]
    assert passes[-1][2] > 40 * 60  # over 40 minutes of flight
    tiny = flight_passes(resolve_scenario("area-tiny"), 42)
    assert [p[0] for p in tiny] == [1, 3, 2, 4]


def test_a_bending_corridor_scene_follows_its_axis_and_the_plan_flies_it():
    from georefine.sim.scene import SceneConfig, build_scene
    from georefine.sim.scene_objects import CorridorAxis

    axis = ((0.0, 0.0), (0.0, 500.0), (200.0, 1000.0), (200.0, 1400.0))
    cfg = SceneConfig(length_m=1400.0, width_m=1000.0, axis_m=axis, settlement_count=2, buildings_per_settlement=5,
                      vegetation_per_ha=4.0)
    scene = build_scene(cfg, np.random.default_rng(5))
    line = CorridorAxis(cfg)
    # Pylons stand on the axis, the spacing measured along it; the reference sites lie beside it.
    assert len(scene.pylon_bases_w) == int(line.total // cfg.pylon_spacing_m) + 1
    np.testing.assert_allclose(line.across(scene.pylon_bases_w[:, 0], scene.pylon_bases_w[:, 1]), 0.0, atol=1e-9)
    for r in scene.reference_surfaces:
        c = r.corners_w.mean(axis=0)
        assert 10.0 < abs(float(line.across(c[0], c[1]))) < 110.0
    # The valley floor follows the bend: at y = 1200 it is centred on x = 200, not on x = 0.
    # (floor 150 m either side, then 80 m of rise to the terrain's edge; 3 m of undulation)
    floor, west, east = scene.terrain_height(np.array([200.0, -200.0, 480.0]), np.full(3, 1200.0))
    assert west > floor + 20.0 and east > floor + 20.0
    assert abs(float(scene.terrain_height(np.array([0.0]), np.array([1200.0]))[0]) - floor) < 10.0
    # A corridor plan without its own polyline flies the scene's axis, bends inside the strip.
    plan = FlightPlanConfig(kind="corridor", parallel_lines=1, bend_radius_m=400.0)
    lines = plan_lines(plan, length_m=1400.0, width_m=1000.0, swath_m=380.0, axis_m=axis)
    np.testing.assert_allclose(lines[0].vertices, axis)
    traj = simulate_flight(FlightConfig(static_duration_s=5.0, manoeuvre="none"), FRAME, 1400.0, scene.terrain_height,
                           lines, bend_radius_m=400.0)
    _, t0, t1 = traj.passes[0]
    p, _ = traj.pose(np.linspace(t0, t1, 3000))
    inside = (p[:, 1] > 50) & (p[:, 1] < 1350)
    # Within the arcs' cut of the corners (400 m tan(|bend| / 2): 86 m, 9 m from the vertex) the line is flown.
    assert np.abs(line.across(p[inside, 0], p[inside, 1])).max() < 12.0
