"""Tests of the simulated scene (georefine.sim.scene)."""

import pickle

import numpy as np
import pydantic
import pytest

from georefine.sim.scene import Material, Scene, SceneConfig, build_scene

TINY = SceneConfig(length_m=600.0, width_m=500.0, end_margin_m=100.0, settlement_count=2,
                   buildings_per_settlement=8, scattered_building_count=2)


def down_rays(rng, n, half_x, y_lo, y_hi):
    """Ray origins 250 m up over a box."""
    return np.column_stack([rng.uniform(-half_x, half_x, n), rng.uniform(y_lo, y_hi, n),
                            np.full(n, 250.0)])


@pytest.fixture(scope="module")
def scene() -> Scene:
    return build_scene(TINY, np.random.default_rng(42))


def test_deterministic_for_seed(scene):
    again = build_scene(TINY, np.random.default_rng(42))
    np.testing.assert_array_equal(again.mesh.vertices, scene.mesh.vertices)
    np.testing.assert_array_equal(again.mesh.faces, scene.mesh.faces)
    np.testing.assert_array_equal(again.face_material, scene.face_material)
    assert again.texture_seed == scene.texture_seed
    for a, b in zip(again.reference_surfaces, scene.reference_surfaces):
        np.testing.assert_array_equal(a.corners_w, b.corners_w)
    other = build_scene(TINY, np.random.default_rng(43))
    assert not np.array_equal(other.mesh.vertices[-100:], scene.mesh.vertices[-100:])


def test_content(scene):
    counts = np.bincount(scene.face_material, minlength=len(Material))
    assert np.all(counts > 0), dict(zip(Material, counts))  # every material present
    assert len(scene.mesh.faces) == len(scene.face_material)
    assert len(scene.pylon_bases_w) == 3  # every 300 m on 600 m
    lo, hi = scene.mesh.bounds
    assert lo[0] <= -250 + 1e-9 and hi[0] >= 250 - 1e-9 and lo[1] <= -100 and hi[1] >= 700
    np.testing.assert_allclose(scene.axis_w[:, 0], 0.0)
    assert scene.axis_w[0, 1] == 0.0 and scene.axis_w[-1, 1] == 600.0
    # outward normals: ground and roofs up, facades horizontal
    n = scene.surface_normal(np.arange(len(scene.face_material)))
    m = scene.face_material
    assert np.all(n[m <= Material.ROAD, 2] > 0.3)
    assert np.all(n[(m == Material.ROOF_TILE) | (m == Material.ROOF_FLAT), 2] > 0.5)
    assert np.all(np.abs(n[m == Material.FACADE, 2]) < 1e-9)


def test_config_forbids_unknown_keys():
    with pytest.raises(pydantic.ValidationError):
        SceneConfig(lenght_m=100.0)


def test_reference_surfaces_planar_and_in_mesh(scene):
    refs = scene.reference_surfaces
    assert len(refs) == 6 and len({r.site_id for r in refs}) == 4
    assert len({r.surface_id for r in refs}) == 6
    V, F = np.asarray(scene.mesh.vertices), np.asarray(scene.mesh.faces)
    for r in refs:
        c = r.corners_w
        assert c.shape == (4, 3)
        np.testing.assert_allclose(np.linalg.norm(r.normal_w), 1.0)
        dist = (c - c.mean(axis=0)) @ r.normal_w
        assert np.max(np.abs(dist)) < 1e-9
        side = np.linalg.norm(np.diff(np.vstack([c, c[:1]]), axis=0), axis=1)
        np.testing.assert_allclose(side, TINY.reference_size_m, atol=1e-9)
        # the two top faces are spanned by exactly the surveyed corners
        tri = V[F[r.face_ids]]
        assert {tuple(p) for p in tri.reshape(-1, 3)} == {tuple(p) for p in c}
        assert np.all(scene.face_material[r.face_ids] == Material.REFERENCE)
        # raised above the terrain under the slab
        ground = scene.terrain_height(c[:, 0], c[:, 1])
        assert np.all(c[:, 2] - ground >= TINY.reference_raise_m - 1e-3)
        assert np.all(c[:, 2] - ground < TINY.reference_raise_m + 1.0)


def test_vertical_rays_hit_reference_surfaces_exactly(scene):
    rng = np.random.default_rng(0)
    for r in scene.reference_surfaces:
        c = r.corners_w
        u, v = rng.uniform(0.05, 0.95, (2, 200))
        p = c[0] + u[:, None] * (c[1] - c[0]) + v[:, None] * (c[3] - c[0])
        origins = p + [0.0, 0.0, 150.0]
        rng_m, face = scene.intersect(origins, np.tile([0.0, 0.0, -1.0], (200, 1)))
        assert np.all(np.isin(face, r.face_ids))
        hit = origins + rng_m[:, None] * [0.0, 0.0, -1.0]
        assert np.max(np.abs(hit[:, 2] - c[0, 2])) < 1e-6
        # oblique rays too: the hit point lies on the plane
        d = np.column_stack([rng.normal(0, 0.3, 200), rng.normal(0, 0.3, 200), -np.ones(200)])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        origins = p - 150.0 * d
        rng_m, face = scene.intersect(origins, d)
        on = np.isin(face, r.face_ids)
        assert on.mean() > 0.9  # a few may be blocked by vegetation
        hit = origins[on] + rng_m[on, None] * d[on]
        assert np.max(np.abs((hit - c[0]) @ r.normal_w)) < 1e-6


def test_terrain_height_matches_ray_cast(scene):
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-240, 240, 5000), rng.uniform(-90, 690, 5000)
    rng_m, face = scene.intersect(np.column_stack([x, y, np.full_like(x, 1000.0)]),
                                  np.tile([0.0, 0.0, -1.0], (5000, 1)))
    ground = scene.face_material[face] <= Material.ROAD
    assert ground.mean() > 0.7
    np.testing.assert_allclose(1000.0 - rng_m[ground], scene.terrain_height(x, y)[ground],
                               atol=1e-6)
    assert np.all(scene.surface_normal(face[ground])[:, 2] > 0.5)


def test_hits_lie_on_their_triangle(scene):
    rng = np.random.default_rng(2)
    n = 20000
    origins = down_rays(rng, n, 150.0, 100.0, 500.0)
    d = np.column_stack([rng.normal(0, 0.3, n), rng.normal(0, 0.3, n), -np.ones(n)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rng_m, face = scene.intersect(origins, d)
    hit = face >= 0
    assert hit.mean() > 0.99
    p = origins[hit] + rng_m[hit, None] * d[hit]
    tri = np.asarray(scene.mesh.vertices)[np.asarray(scene.mesh.faces)[face[hit]]]
    n_f = scene.surface_normal(face[hit])
    assert np.max(np.abs(np.einsum("ij,ij->i", p - tri[:, 0], n_f))) < 1e-6
    # barycentric coordinates inside the triangle (up to the float32 traversal)
    e1, e2, q = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
    g = np.stack([np.einsum("ij,ij->i", a, b) for a, b in [(e1, e1), (e1, e2), (e2, e2)]])
    r1, r2 = np.einsum("ij,ij->i", q, e1), np.einsum("ij,ij->i", q, e2)
    det = g[0] * g[2] - g[1] ** 2
    ok = det > 1e-12
    s = (g[2] * r1 - g[1] * r2)[ok] / det[ok]
    t = (g[0] * r2 - g[1] * r1)[ok] / det[ok]
    assert np.mean((s > -1e-3) & (t > -1e-3) & (s + t < 1 + 1e-3)) > 0.999


def test_rays_into_the_sky_miss(scene):
    n = 1000
    origins = np.column_stack([np.linspace(-200, 200, n), np.linspace(0, 600, n),
                               np.full(n, 300.0)])
    rng_m, face = scene.intersect(origins, np.tile([0.1, 0.0, 1.0], (n, 1)))
    assert np.all(face == -1) and np.all(np.isinf(rng_m))
    # beyond the maximum range
    rng_m, face = scene.intersect(origins, np.tile([0.0, 0.0, -1.0], (n, 1)), max_range_m=100.0)
    assert np.all(face == -1)


def test_threads_give_same_result(scene):
    rng = np.random.default_rng(3)
    n = 100_000
    origins = down_rays(rng, n, 200.0, 0.0, 600.0)
    d = np.column_stack([rng.normal(0, 0.5, n), rng.normal(0, 0.5, n), -np.ones(n)])
    r1, f1 = scene.intersect(origins, d, n_threads=1)
    r2, f2 = scene.intersect(origins, d, n_threads=3)
    np.testing.assert_array_equal(f1, f2)
    np.testing.assert_array_equal(r1, r2)


def test_albedo(scene):
    rng = np.random.default_rng(4)
    n = 20000
    origins = down_rays(rng, n, 200.0, 0.0, 600.0)
    rng_m, face = scene.intersect(origins, np.tile([0.0, 0.0, -1.0], (n, 1)))
    p = origins + rng_m[:, None] * [0.0, 0.0, -1.0]
    a = scene.albedo(p, face)
    assert a.shape == (n,) and np.all((a >= 0.05) & (a <= 0.9))
    np.testing.assert_array_equal(a, scene.albedo(p, face))  # deterministic
    mat = scene.face_material[face]
    terrain = mat == Material.TERRAIN
    assert 0.02 < np.std(a[terrain]) < 0.2  # textured
    assert np.mean(a[mat == Material.REFERENCE]) > 0.7  # bright paint
    other = build_scene(TINY, np.random.default_rng(42))
    np.testing.assert_array_equal(other.albedo(p, face), a)


def test_pickle_round_trip(scene):
    copy = pickle.loads(pickle.dumps(scene))
    o = np.array([[10.0, 300.0, 500.0]])
    d = np.array([[0.0, 0.0, -1.0]])
    np.testing.assert_array_equal(copy.intersect(o, d)[0], scene.intersect(o, d)[0])
