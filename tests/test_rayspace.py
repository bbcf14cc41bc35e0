"""The ray-space hierarchy traversal (Roger et al. 2007): same hits as ``single``, a
conservative cone-sphere test, batching under a pair budget, option checking."""
from __future__ import annotations

import math

import numba
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from engine.core.bvh import build_bvh
from engine.rayspace.cone_sphere import RayHierarchy, absolute_slack, build_hierarchy, cone_sphere_overlap
from engine.core.errors import ConfigError
from engine.core.triangle import F32_INF, intersect_triangle, ray_shear
from engine.core.offset import offset_origin
from engine.packet.layout import make_batch
from engine.render.plugins import make_traversal
from engine.core.scene import make_triangles
from engine.core.threads import numba_threads
from engine.rayspace.triangle_spheres import triangle_spheres
from engine.core.types import COUNTER_RAY_TRI, empty_hits, new_stats
from engine.render.camera import camera_rays

from brute_force import brute_force
from conftest import needs_shared_scenes

SIZE = 64
PACKET = 8


@pytest.fixture
def rayspace():
    """A new rayspace plugin with the default options."""
    return make_traversal("rayspace")


# -- scenes and secondary rays built from single's primary hits -------------------------

class Setup:
    """A scene, its BVH (``bvh``: one already built over its triangles) and single's primary
    hits on a SIZE x SIZE image."""

    def __init__(self, scene, width=SIZE, height=SIZE, bvh=None):
        self.scene = scene
        self.tris = scene.triangles
        self.bvh = build_bvh(self.tris) if bvh is None else bvh
        self.width, self.height = width, height
        org, d = camera_rays(scene, width, height)
        count = width * height
        rays, packets = make_batch("primary", org, d, np.zeros(count), np.full(count, np.inf),
                                   np.arange(count, dtype=np.int32), np.ones((count, 3)), width, height, PACKET)
        self.primary, self.primary_packets = rays, packets
        hits = empty_hits(len(rays.org))
        make_traversal("single").intersect(self.bvh, self.tris, rays, packets, None, hits, None)
        idx = np.flatnonzero(hits.prim >= 0)
        self.pixel = rays.pixel[idx]
        self.d = rays.dir[idx]
        self.point = (rays.org[idx] + hits.t[idx, None] * rays.dir[idx]).astype(np.float32)
        ng = self.tris.ng[hits.prim[idx]]
        self.ng = np.where((np.einsum("ij,ij->i", ng, self.d) < 0)[:, None], ng, -ng).astype(np.float32)

    def batch(self, kind, org, direction, tmax, pixel=None, tmin=None):
        pixel = self.pixel if pixel is None else pixel
        tmin = np.zeros(len(org)) if tmin is None else tmin
        return make_batch(kind, org, direction, tmin, tmax, pixel, np.ones((len(org), 3)),
                          self.width, self.height, PACKET)

    def reflection(self):
        """Mirror reflection about the geometric normal, leaving on the incoming side."""
        refl = self.d - 2 * np.einsum("ij,ij->i", self.d, self.ng)[:, None] * self.ng
        return self.batch("reflection", offset_origin(self.point, self.ng), refl.astype(np.float32),
                          np.full(len(refl), np.inf))

    def refraction(self, eta=1 / 1.5):
        """Snell refraction through the geometric normal (reflection on total internal reflection)."""
        d = self.d / np.linalg.norm(self.d, axis=1, keepdims=True)
        cos_i = -np.einsum("ij,ij->i", d, self.ng)
        k = 1 - eta * eta * (1 - cos_i * cos_i)
        refr = eta * d + (eta * cos_i - np.sqrt(np.maximum(k, 0)))[:, None] * self.ng
        tir = k < 0
        refr[tir] = (d + 2 * cos_i[:, None] * self.ng)[tir]
        side = np.where(tir[:, None], self.ng, -self.ng)
        return self.batch("refraction", offset_origin(self.point, side), refr.astype(np.float32),
                          np.full(len(refr), np.inf))

    def shadow(self, light=None):
        """Rays from the offset surface point to a point light, stopping just short of it (as
        the Whitted loop casts them)."""
        light = np.asarray(self.scene.lights[0].position if light is None else light, np.float32)
        org = offset_origin(self.point, self.ng)
        to = light - org
        dist = np.linalg.norm(to, axis=1)
        return self.batch("shadow", org, (to / dist[:, None]).astype(np.float32),
                          (dist * np.float32(1 - 1e-4)).astype(np.float32))


_SETUPS: dict = {}


def setup_for(name):
    needs_shared_scenes()
    if name not in _SETUPS:
        from scenes.catalog import load_named

        _SETUPS[name] = Setup(load_named(name, {"lod": 3} if name == "bunny" else {}))
    return _SETUPS[name]


SCENES = ["bunny", "cornell-box", "whitted"]


def intersect_both(plugin, setup, rays, packets, stats=None):
    ref = empty_hits(len(rays.org))
    make_traversal("single").intersect(setup.bvh, setup.tris, rays, packets, None, ref, None)
    got = empty_hits(len(rays.org))
    plugin.intersect(setup.bvh, setup.tris, rays, packets, None, got, stats)
    return ref, got


def occluded_both(plugin, setup, rays, packets, stats=None):
    ref = np.zeros(len(rays.org), np.bool_)
    make_traversal("single").occluded(setup.bvh, setup.tris, rays, packets, None, ref, None)
    got = np.zeros(len(rays.org), np.bool_)
    plugin.occluded(setup.bvh, setup.tris, rays, packets, None, got, stats)
    return ref, got


def assert_same_hits(ref, got):
    """Bit-identical: same kernel, same tie rule."""
    np.testing.assert_array_equal(got.prim, ref.prim)
    np.testing.assert_array_equal(got.t, ref.t)
    np.testing.assert_array_equal(got.u, ref.u)
    np.testing.assert_array_equal(got.v, ref.v)


# -- same hits as single ------------------------------------------------------------------

@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("kind", ["reflection", "refraction", "shadow"])
def test_closest_hits_match_single(rayspace, scene, kind):
    setup = setup_for(scene)
    rays, packets = getattr(setup, kind)()
    stats = new_stats(numba.get_num_threads())
    ref, got = intersect_both(rayspace, setup, rays, packets, stats)
    assert_same_hits(ref, got)
    extra = stats.extra["rayspace"]
    assert extra["rays"] == int(np.count_nonzero(rays.pixel >= 0))
    # Every final candidate got exactly one triangle test.
    assert stats.counters[:, COUNTER_RAY_TRI, 0].sum() == extra["candidates"]


def test_a_whitted_frame_by_rayspace_audits_clean_against_embree(tmp_path):
    """Every ray of a frame, rayspace for every kind with its default grids (each light's shadow
    rays by direction from it, secondary rays by tile and direction), checked against Embree."""
    import json

    from engine.cli import main

    report = tmp_path / "audit.json"
    assert main(["audit", "--size", "48x48", "--traversal", "rayspace", "--json", str(report)]) == 0
    data = json.loads(report.read_text())
    assert data["mismatches"] == [] and data["agreement"] == 1.0
    assert all(data["by_kind"][kind]["checked"] > 0 for kind in ("primary", "shadow", "reflection", "refraction"))


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("kind", ["reflection", "refraction", "shadow"])
def test_the_papers_pixel_layout_gives_the_same_hits(scene, kind):
    """``shadow_grid`` and ``secondary_grid`` "pixel" (the paper's layout; the defaults group
    by direction): the same hits as single, and other (node, triangle) pairs tested."""
    setup = setup_for(scene)
    rays, packets = getattr(setup, kind)()
    paper = make_traversal("rayspace", {"shadow_grid": "pixel", "secondary_grid": "pixel"})
    by_pixel, by_grid = new_stats(numba.get_num_threads()), new_stats(numba.get_num_threads())
    ref, got = intersect_both(paper, setup, rays, packets, by_pixel)
    assert_same_hits(ref, got)
    intersect_both(make_traversal("rayspace"), setup, rays, packets, by_grid)
    assert by_pixel.extra["rayspace"]["cone_sphere_tests"] != by_grid.extra["rayspace"]["cone_sphere_tests"]


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("kind", ["reflection", "shadow"])
def test_occlusion_matches_single(rayspace, scene, kind):
    setup = setup_for(scene)
    rays, packets = getattr(setup, kind)()
    ref, got = occluded_both(rayspace, setup, rays, packets)
    np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("scene", ["cornell-box", "bunny"])
def test_hits_are_the_kernels_own_answer(rayspace, scene):
    """The conservative hierarchy gives exactly the shared kernel's answer over all triangles.

    These rays leave from org + t dir with an offset relative to the point only, so some start
    on the surface they leave (Cornell floor: x, z in the hundreds, y near 0) and the kernel
    accepts that surface at t = -0.0: a hard case the hierarchy must still answer exactly."""
    shared = setup_for(scene)  # the same scene and BVH, at a finer image
    setup = Setup(shared.scene, width=256, height=256, bvh=shared.bvh)
    for kind in ("shadow", "reflection"):
        rays, packets = getattr(setup, kind)()
        t = np.empty(len(rays.org), np.float32)
        prim = np.empty(len(rays.org), np.int32)
        brute_force(rays.org, rays.dir, rays.tmin, rays.tmax, setup.tris.v0, setup.tris.v1, setup.tris.v2, t, prim)
        got = empty_hits(len(rays.org))
        rayspace.intersect(setup.bvh, setup.tris, rays, packets, None, got, None)
        np.testing.assert_array_equal(got.prim, prim)
        np.testing.assert_array_equal(got.t, t)
        occ = np.zeros(len(rays.org), np.bool_)
        rayspace.occluded(setup.bvh, setup.tris, rays, packets, None, occ, None)
        np.testing.assert_array_equal(occ, prim >= 0)


def test_primary_rays_match_single(rayspace):
    setup = setup_for("bunny")
    ref, got = intersect_both(rayspace, setup, setup.primary, setup.primary_packets)
    assert_same_hits(ref, got)


def test_odd_screen_size_matches_single(rayspace):
    """A grid that is not a power of two: partial 2x2 blocks and mip-map nodes at the edges."""
    shared = setup_for("whitted")  # the same scene and BVH, at another image size
    setup = Setup(shared.scene, width=37, height=23, bvh=shared.bvh)
    for kind in ("reflection", "refraction", "shadow"):
        rays, packets = getattr(setup, kind)()
        ref, got = intersect_both(rayspace, setup, rays, packets)
        assert_same_hits(ref, got)


def test_several_rays_per_pixel(rayspace):
    """Reflection and refraction of the same pixels in one batch: a 2x2 block holds them all."""
    setup = setup_for("whitted")
    parts = [setup.reflection()[0], setup.refraction()[0]]
    live = [p.pixel >= 0 for p in parts]
    cat = lambda field: np.concatenate([getattr(p, field)[m] for p, m in zip(parts, live)])
    rays, packets = make_batch("reflection", cat("org"), cat("dir"), cat("tmin"), cat("tmax"), cat("pixel"),
                               cat("weight"), setup.width, setup.height, PACKET)
    assert np.bincount(rays.pixel[rays.pixel >= 0]).max() >= 2
    ref, got = intersect_both(rayspace, setup, rays, packets)
    assert_same_hits(ref, got)
    ref_o, got_o = occluded_both(rayspace, setup, rays, packets)
    np.testing.assert_array_equal(got_o, ref_o)


def test_crowded_pixels_without_child_masks(rayspace):
    """More rays under one 2x2 block than a child bit mask holds: the scatter re-tests."""
    from engine.rayspace.pair_stream import MASK_BITS

    rng = np.random.default_rng(7)
    verts = (rng.uniform(-3, 3, (40, 1, 3)) + rng.normal(0, 0.8, (40, 3, 3))).reshape(-1, 3)
    tris = make_triangles(verts, np.arange(120).reshape(-1, 3), 0)
    pixel = np.repeat(np.arange(9, dtype=np.int32), 30)  # 3x3 screen: 120 rays in block 0
    n = len(pixel)
    org = rng.uniform(-5, 5, (n, 3)).astype(np.float32)
    aim = verts[rng.integers(0, len(verts), n)] + rng.normal(0, 0.3, (n, 3))  # mostly at triangles
    d = (aim - org).astype(np.float32)
    rays, packets = make_batch("reflection", org, d, np.zeros(n), np.full(n, np.inf), pixel, np.ones((n, 3)), 3, 3, 2)
    h = build_hierarchy(rays.org, rays.dir, rays.tmin, rays.tmax, rays.pixel, 3, 3)
    assert h.max_block_rays > MASK_BITS
    bvh = build_bvh(tris)
    ref = empty_hits(len(rays.org))
    make_traversal("single").intersect(bvh, tris, rays, packets, None, ref, None)
    got = empty_hits(len(rays.org))
    rayspace.intersect(bvh, tris, rays, packets, None, got, None)
    assert_same_hits(ref, got)
    assert (ref.prim >= 0).sum() > n // 4


def test_answer_arrays_must_match_the_batch(rayspace):
    setup = setup_for("cornell-box")
    rays, packets = setup.reflection()
    with pytest.raises(ValueError, match="one entry per ray"):
        rayspace.intersect(setup.bvh, setup.tris, rays, packets, None, empty_hits(len(rays.org) - 2), None)


def test_dead_lanes_are_misses(rayspace):
    setup = setup_for("cornell-box")
    rays, packets = setup.reflection()
    tmax = rays.tmax.copy()
    tmax[::3] = -1.0  # tmax < tmin: dead
    rays = rays._replace(tmax=tmax)
    ref, got = intersect_both(rayspace, setup, rays, packets)
    assert_same_hits(ref, got)
    assert (got.prim[::3] == -1).all()


# -- shadow rays reversed at the light ----------------------------------------------------

def test_shadow_batch_to_one_light_is_reversed(rayspace):
    setup = setup_for("whitted")
    rays, packets = setup.shadow()
    stats = new_stats(numba.get_num_threads())
    ref, got = occluded_both(rayspace, setup, rays, packets, stats)
    np.testing.assert_array_equal(got, ref)
    assert ref.any() and not ref.all()
    assert stats.extra["rayspace"]["reversed_batches"] == 1


def test_shadow_rays_ending_exactly_at_the_light(rayspace):
    """tmax = the full distance: the reversed segments start exactly at the apex."""
    setup = setup_for("bunny")
    light = np.asarray(setup.scene.lights[0].position, np.float32)
    org = offset_origin(setup.point, setup.ng)
    to = light - org
    rays, packets = setup.batch("shadow", org, to, np.ones(len(org), np.float32))
    stats = new_stats(numba.get_num_threads())
    ref, got = occluded_both(rayspace, setup, rays, packets, stats)
    np.testing.assert_array_equal(got, ref)
    assert stats.extra["rayspace"]["reversed_batches"] == 1


def test_shadow_batch_to_two_lights_is_not_reversed(rayspace):
    setup = setup_for("whitted")
    a, _ = setup.shadow()
    b, _ = setup.shadow(light=(-4.0, 6.0, 3.0))
    la, lb = a.pixel >= 0, b.pixel >= 0
    cat = lambda field: np.concatenate([getattr(a, field)[la], getattr(b, field)[lb]])
    rays, packets = make_batch("shadow", cat("org"), cat("dir"), cat("tmin"), cat("tmax"), cat("pixel"),
                               cat("weight"), setup.width, setup.height, PACKET)
    stats = new_stats(numba.get_num_threads())
    ref, got = occluded_both(rayspace, setup, rays, packets, stats)
    np.testing.assert_array_equal(got, ref)
    assert stats.extra["rayspace"]["reversed_batches"] == 0


def test_shadow_tmin_offset_is_kept(rayspace):
    """Shadow rays starting on the surface itself with a tmin offset: the answer is the
    original ray's, over [tmin, tmax], reversed or not."""
    setup = setup_for("bunny")
    light = np.asarray(setup.scene.lights[0].position, np.float32)
    to = light - setup.point
    dist = np.linalg.norm(to, axis=1)
    l = (to / dist[:, None]).astype(np.float32)
    for tmin in (0.0, 1e-4, 1e-2):
        rays, packets = setup.batch("shadow", setup.point, l, (dist * np.float32(1 - 1e-4)).astype(np.float32),
                                    tmin=np.full(len(dist), tmin, np.float32))
        stats = new_stats(numba.get_num_threads())
        ref, got = occluded_both(rayspace, setup, rays, packets, stats)
        np.testing.assert_array_equal(got, ref)
        assert stats.extra["rayspace"]["reversed_batches"] == 1


# -- memory budget --------------------------------------------------------------------------

def test_tiny_budget_splits_into_batches_with_identical_hits(rayspace):
    setup = setup_for("bunny")
    rays, packets = setup.reflection()
    full = new_stats(numba.get_num_threads())
    ref, _ = intersect_both(rayspace, setup, rays, packets, full)
    assert full.extra["rayspace"]["batches"] == 1
    budget = max(full.extra["rayspace"]["peak_pairs"] // 7, 1)
    small = make_traversal("rayspace", {"pair_budget": budget})
    stats = new_stats(numba.get_num_threads())
    got = empty_hits(len(rays.org))
    small.intersect(setup.bvh, setup.tris, rays, packets, None, got, stats)
    assert_same_hits(ref, got)
    extra = stats.extra["rayspace"]
    assert extra["batches"] > 1
    assert extra["peak_pairs"] <= budget
    # Batching must not lose candidates: every surviving pair is still tested.
    assert extra["candidates"] == full.extra["rayspace"]["candidates"]
    occ_ref, occ = occluded_both(small, setup, rays, packets)
    np.testing.assert_array_equal(occ, occ_ref)


def test_budget_too_small_for_one_triangle_names_the_minimum(rayspace):
    setup = setup_for("cornell-box")  # big walls: one triangle meets many rays
    rays, packets = setup.reflection()
    small = make_traversal("rayspace", {"pair_budget": 3})
    with pytest.raises(ConfigError, match=r"pair_budget.*at least \d+"):
        small.intersect(setup.bvh, setup.tris, rays, packets, None, empty_hits(len(rays.org)), None)


@pytest.mark.parametrize("options", [
    {"pair_budget": 0}, {"pair_budget": -5}, {"pair_budget": 2**31}, {"pair_budget": 1.5},
    {"pair_budget": "big"}, {"pair_budget": True}, {"budget": 10}, {"pair_budget": 10, "extra": 1},
    {"shadow_grid": "screen"}, {"shadow_grid": 1}, {"shadow_grid": None}, {"secondary_grid": "light"},
])
def test_bad_options_raise_config_error(options):
    with pytest.raises(ConfigError, match=r"options\.rayspace: .*(pair_budget|allowed|shadow_grid|secondary_grid)"):
        make_traversal("rayspace", options)


def test_options_table_and_instances():
    assert make_traversal("rayspace").OPTIONS == {"pair_budget": 1 << 22, "shadow_grid": "light",
                                                  "secondary_grid": "direction"}
    assert make_traversal("rayspace", {"shadow_grid": "pixel"}).shadow_grid == "pixel"
    assert make_traversal("rayspace", {"secondary_grid": "pixel"}).secondary_grid == "pixel"
    assert make_traversal("rayspace", {"pair_budget": 1000}).pair_budget == 1000
    assert make_traversal("rayspace").pair_budget == 1 << 22


# -- statistics -------------------------------------------------------------------------------

def test_stats_accumulate_across_calls(rayspace):
    setup = setup_for("whitted")
    rays, packets = setup.reflection()
    stats = new_stats(numba.get_num_threads())
    for _ in range(2):
        rayspace.intersect(setup.bvh, setup.tris, rays, packets, None, empty_hits(len(rays.org)), stats)
    extra = stats.extra["rayspace"]
    one = new_stats(numba.get_num_threads())
    rayspace.intersect(setup.bvh, setup.tris, rays, packets, None, empty_hits(len(rays.org)), one)
    single = one.extra["rayspace"]
    assert extra["calls"] == 2 and extra["candidates"] == 2 * single["candidates"]
    assert extra["cone_sphere_tests"] == [2 * n for n in single["cone_sphere_tests"]]
    assert extra["candidates_per_ray"] == pytest.approx(single["candidates_per_ray"])
    levels = single["levels"]
    assert len(single["pairs_after"]) == levels + 1
    assert single["pairs_after"][levels] == setup.tris.v0.shape[0]  # every triangle at the root
    assert all(a <= b for a, b in zip(single["pairs_after"], single["pairs_before"]))
    assert set(single["seconds"]) == {"triangle_spheres", "build", "traversal", "compaction", "sort", "final"}


def test_registered():
    assert "rayspace" in __import__("engine.render.plugins", fromlist=["traversal_names"]).traversal_names()


# -- the cone-sphere test is conservative ---------------------------------------------------

def one_node(centre, radius, axis, alpha, far) -> RayHierarchy:
    a = np.float32(alpha)
    f32 = lambda x: np.array([x], np.float32)
    return RayHierarchy(np.array([centre], np.float32), f32(radius), np.array([axis], np.float32), f32(a),
                        f32(math.cos(a)), f32(math.sin(a)), f32(far), np.array([0, 1, 1], np.int64),
                        np.array([1, 1], np.int64), np.array([1, 1], np.int64), np.array([0, 1], np.int64),
                        np.zeros(1, np.int32), 1, 1)


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def perpendicular(a, w):
    """A unit vector perpendicular to unit a, picked by w."""
    p = np.cross(a, w)
    if np.linalg.norm(p) < 1e-6:
        p = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    return unit(p)


def one_triangle_spheres(tri):
    """``triangle_spheres`` of one triangle, on one numba thread: its parallel loop has one
    iteration, which one thread computes either way, and numba then does not wake its thread
    pool (which spins on after each call) for every example."""
    assert tri.v0.shape[0] == 1
    with numba_threads(1):
        return triangle_spheres(tri.v0, tri.v1, tri.v2)


coord = st.floats(-20, 20, allow_nan=False, width=32)
vec = st.tuples(coord, coord, coord)
direction = vec.filter(lambda v: np.linalg.norm(v) > 1e-2)
# A node and a ray inside it: origin in the sphere, direction in the cone, segment in reach.
# ``outward`` puts the origin off the cone's surface along its outward normal, the worst
# case: every point of the ray is then as far from the cone as the origin is from the centre.
node_and_ray = dict(centre=vec, radius=st.floats(0, 3), axis=direction, alpha=st.floats(0, math.pi),
                    far=st.one_of(st.just(math.inf), st.floats(0.5, 80)), where=st.floats(0, 1),
                    off=direction, turn=st.floats(0, 1), spin=direction, length=st.floats(0, 1),
                    scale=st.floats(0.1, 5), outward=st.booleans())


def ray_in_node(centre, radius, axis, alpha, far, where, off, turn, spin, length, scale, outward):
    """(node, origin f32[3], direction f32[3], tmax f32, point f64[3] on the segment, outward
    unit normal of the cone beside the ray)."""
    c = np.asarray(centre, np.float64)
    a = unit(axis)
    q = perpendicular(a, np.asarray(spin))
    beta = alpha * turn
    d = math.cos(beta) * a + math.sin(beta) * q
    normal = -math.sin(alpha) * a + math.cos(alpha) * q
    origin = c + radius * where * (normal if outward else unit(off))
    d = (d * scale).astype(np.float32)
    o = origin.astype(np.float32)
    reach = far - np.linalg.norm(o.astype(np.float64) - c)
    assume(reach > 1e-3)
    tmax = np.float32(min(reach, 60.0) / np.linalg.norm(d.astype(np.float64)) * (1 - 1e-6))
    p = o.astype(np.float64) + float(tmax) * length * d.astype(np.float64)
    node = one_node(c.astype(np.float32), np.float32(radius * (1 + 1e-6)), a, alpha, far)
    return node, o, d, tmax, p, normal


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(rho=st.floats(0, 2), push=st.one_of(st.none(), direction), **node_and_ray)
def test_cone_sphere_test_keeps_every_sphere_a_ray_touches(rho, push, **ray):
    """The cone-sphere test's contract, sharp: a sphere touching a point of a ray inside the
    node (pushed away from the cone along its outward normal, or any way) is kept."""
    node, o, d, tmax, p, normal = ray_in_node(**ray)
    w = normal if push is None else unit(push)
    s = (p + rho * w).astype(np.float32)
    sr = np.array([rho * (1 + 1e-6) + 4e-7 * np.abs(s).max()], np.float32)  # holds p after rounding s
    abs_tol = np.float32(absolute_slack(node, s[None, :], sr))
    assert cone_sphere_overlap(node, 0, s[0], s[1], s[2], sr[0], abs_tol)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(e1=direction, e2=direction, size=st.floats(1e-3, 0.2),
       bary=st.tuples(st.floats(0.01, 1), st.floats(0.01, 1), st.floats(0.01, 1)), **node_and_ray)
def test_cone_sphere_test_never_culls_a_hit(e1, e2, size, bary, **ray):
    """Any ray inside a node that the watertight test says hits a triangle keeps that
    triangle's pair (the triangle is built around a point of the segment)."""
    node, o, d, tmax, p, _ = ray_in_node(**ray)
    b = np.asarray(bary) / sum(bary)
    e1, e2 = np.asarray(e1) * size, np.asarray(e2) * size  # small triangles make the test sharp
    v0 = p - b[1] * e1 - b[2] * e2
    tri = make_triangles(np.array([v0, v0 + e1, v0 + e2]), [[0, 1, 2]], 0)
    kx, ky, kz, sx, sy, sz = ray_shear(d[0], d[1], d[2])
    t, _, _ = intersect_triangle(o[kx], o[ky], o[kz], kx, ky, kz, sx, sy, sz, np.float32(0), tmax,
                                 tri.v0, tri.v1, tri.v2, 0)
    assume(t < F32_INF)
    sc, sr = one_triangle_spheres(tri)
    abs_tol = np.float32(absolute_slack(node, sc, sr))
    assert cone_sphere_overlap(node, 0, sc[0, 0], sc[0, 1], sc[0, 2], sr[0], abs_tol)


def distance_to_node(node: RayHierarchy, s) -> tuple[float, float]:
    """(distance from s to the cone with apex at the node centre, distance to the centre),
    in float64: the exact quantities the test bounds."""
    v = np.asarray(s, np.float64) - node.centre[0].astype(np.float64)
    axis = node.axis[0].astype(np.float64)
    dist = float(np.linalg.norm(v))
    theta = math.atan2(np.linalg.norm(np.cross(v, axis)), np.dot(v, axis))
    alpha = float(node.alpha[0])
    if theta <= alpha:
        return 0.0, dist
    if theta - alpha >= math.pi / 2:
        return dist, dist
    return dist * math.sin(theta - alpha), dist


@settings(max_examples=400, deadline=None)
@given(centre=vec, radius=st.one_of(st.just(0.0), st.floats(0, 3)), axis=direction,
       alpha=st.one_of(st.just(0.0), st.floats(0, math.pi)), far=st.one_of(st.just(math.inf), st.floats(0.5, 80)),
       spin=direction, log_off=st.floats(-4, 0.15), distance=st.floats(0.01, 60), excess=st.floats(1.5, 20))
def test_cone_sphere_test_is_tight(centre, radius, axis, alpha, far, spin, log_off, distance, excess):
    """The other direction: a sphere just clear of the node (outside the cone by a few times
    0.1 % of its distance, plus 0.01 % of the coordinates' size) is culled, so the slack that
    makes the test conservative stays small. The sphere sits 10^log_off radians outside the
    cone's edge."""
    off = 10.0 ** log_off
    c = np.asarray(centre, np.float64)
    a = unit(axis)
    q = perpendicular(a, np.asarray(spin))
    theta = min(alpha + off, math.pi)
    s = (c + distance * (math.cos(theta) * a + math.sin(theta) * q)).astype(np.float32)
    node = one_node(c.astype(np.float32), radius, a, alpha, far)
    cone, dist = distance_to_node(node, s)
    margin = 1e-3 * dist + 1e-4 * float(np.abs(s).max() + np.abs(node.centre).max())
    rho = cone - float(node.radius[0]) - excess * margin * (1 + float(node.radius[0]))
    assume(rho >= 0)
    abs_tol = np.float32(absolute_slack(node, s[None, :], np.array([rho], np.float32)))
    assert not cone_sphere_overlap(node, 0, s[0], s[1], s[2], np.float32(rho), abs_tol)


def ancestors(h: RayHierarchy, slot: int) -> list:
    """Global node indices of a slot and every node above it, up to the root."""
    block = int(np.searchsorted(h.block_start, slot, side="right") - 1)
    bx, by = block % h.level_width[1], block // h.level_width[1]
    chain = [slot]
    for level in range(1, h.levels + 1):
        x, y = bx >> (level - 1), by >> (level - 1)
        chain.append(int(h.level_offset[level] + y * h.level_width[level] + x))
    return chain


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), width=st.integers(1, 11), height=st.integers(1, 9),
       per_pixel=st.integers(1, 3), aimed=st.booleans())
def test_no_hit_is_ever_culled_anywhere_in_the_hierarchy(seed, width, height, per_pixel, aimed):
    """Random triangles and rays (several per pixel, some dead, some aimed at one point and
    indexed reversed): for every (ray, triangle) hit the pair survives at every ancestor,
    and the plugin returns single's hits."""
    rng = np.random.default_rng(seed)
    n_tris = 30
    centres = rng.uniform(-4, 4, (n_tris, 1, 3))
    verts = (centres + rng.normal(0, 1.0, (n_tris, 3, 3))).reshape(-1, 3)
    tris = make_triangles(verts, np.arange(3 * n_tris).reshape(-1, 3), 0)
    pixel = np.repeat(np.arange(width * height, dtype=np.int32), per_pixel)
    n = len(pixel)
    org = rng.uniform(-6, 6, (n, 3)).astype(np.float32)
    tmin = np.where(rng.random(n) < 0.2, rng.uniform(-1, 1, n), 0.0).astype(np.float32)
    if aimed:
        apex = rng.uniform(-6, 6, 3).astype(np.float32)
        to = apex - org
        dist = np.linalg.norm(to, axis=1)
        d = (to / dist[:, None]).astype(np.float32)
        tmax = (dist * rng.uniform(0.999, 1.0, n)).astype(np.float32)
        kind = "shadow"
    else:
        d = rng.normal(size=(n, 3)).astype(np.float32)
        tmax = np.where(rng.random(n) < 0.5, np.inf, rng.uniform(0, 12, n)).astype(np.float32)
        kind = "reflection"
    tmax[rng.random(n) < 0.1] = -2.0  # dead lanes
    rays, packets = make_batch(kind, org, d, tmin, tmax, pixel, np.ones((n, 3)), width, height, 2)
    live = (rays.pixel >= 0) & (rays.tmin <= rays.tmax)

    from traversals.rayspace import shared_apex

    apex = shared_apex(rays, live) if aimed else None
    if aimed and live.sum() >= 3:
        assert apex is not None
    h = build_hierarchy(rays.org, rays.dir, rays.tmin, rays.tmax, rays.pixel, width, height, apex)
    sc, sr = triangle_spheres(tris.v0, tris.v1, tris.v2)
    abs_tol = np.float32(absolute_slack(h, sc, sr))
    assert sorted(h.slot_ray.tolist()) == np.flatnonzero(live).tolist()
    for slot, r in enumerate(h.slot_ray):
        kx, ky, kz, sx, sy, sz = ray_shear(rays.dir[r, 0], rays.dir[r, 1], rays.dir[r, 2])
        o = rays.org[r]
        chain = ancestors(h, slot)
        for tri in range(n_tris):
            t, _, _ = intersect_triangle(o[kx], o[ky], o[kz], kx, ky, kz, sx, sy, sz, rays.tmin[r], rays.tmax[r],
                                         tris.v0, tris.v1, tris.v2, tri)
            if t < F32_INF:
                for node in chain:
                    assert cone_sphere_overlap(h, node, sc[tri, 0], sc[tri, 1], sc[tri, 2], sr[tri], abs_tol), \
                        (slot, tri, node)

    bvh = build_bvh(tris)
    ref = empty_hits(len(rays.org))
    make_traversal("single").intersect(bvh, tris, rays, packets, None, ref, None)
    got = empty_hits(len(rays.org))
    # Batches now and then; never below the live rays, which one triangle may all meet.
    n_live = max(int(live.sum()), 1)
    plugin = make_traversal("rayspace", {"pair_budget": int(rng.integers(n_live, 4 * n_live + 30))})
    plugin.intersect(bvh, tris, rays, packets, None, got, None)
    assert_same_hits(ref, got)


@settings(max_examples=100, deadline=None)
@given(corners=st.lists(vec, min_size=3, max_size=3))
@example(corners=[(0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 1.4e-45, 1.4e-45)])  # subnormal: rounded down once
def test_triangle_spheres_hold_their_corners(corners):
    v = np.asarray(corners, np.float32)
    tri = make_triangles(v, [[0, 1, 2]], 0)
    c, r = one_triangle_spheres(tri)
    dist = np.linalg.norm(v.astype(np.float64) - c[0].astype(np.float64), axis=1)
    assert (dist <= float(r[0])).all()
    # Smallest enclosing: never larger than the circumscribed sphere of the longest edge's box,
    # up to float32 rounding: relative, and among subnormals a few of their absolute ulps (no
    # float32 lies between 0 and 1.4e-45, so no stored radius can be tighter than that).
    longest = max(np.linalg.norm(v[i].astype(np.float64) - v[j]) for i, j in ((0, 1), (1, 2), (0, 2)))
    assert float(r[0]) <= longest / math.sqrt(3) * (1 + 1e-5) + 4e-7 * float(np.abs(v).max()) + 4 * 2.0 ** -149


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_parents_hold_their_children(seed):
    """Every node's sphere holds its children's spheres, its cone their cones, its reach theirs."""
    rng = np.random.default_rng(seed)
    width, height = 9, 6
    n = width * height
    org = rng.uniform(-5, 5, (n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    tmax = rng.uniform(0.5, 10, n).astype(np.float32)
    h = build_hierarchy(org, d, np.zeros(n, np.float32), tmax, np.arange(n, dtype=np.int32), width, height)
    from engine.rayspace.cone_sphere import children

    pairs = []   # (child, parent): every node below the root, with the node whose children hold it
    for level in range(1, h.levels + 1):
        for local in range(h.level_offset[level + 1] - h.level_offset[level]):
            parent = h.level_offset[level] + local
            first, nx, ny, stride = children(h, level, local)
            pairs += [(h.level_offset[level - 1] + first + jy * stride + jx, parent)
                      for jy in range(ny) for jx in range(nx)]
    child, parent = np.array(pairs).T
    assert len(pairs) == h.level_offset[-2] and len(set(child.tolist())) == len(pairs)  # exactly one parent each
    filled = h.radius[child] >= 0  # empty children hold nothing
    child, parent = child[filled], parent[filled]
    gap = np.linalg.norm(h.centre[child].astype(np.float64) - h.centre[parent], axis=1)
    assert np.all(gap + h.radius[child] <= h.radius[parent])
    assert np.all(gap + h.far[child] <= h.far[parent])
    ac, ap = h.axis[child].astype(np.float64), h.axis[parent].astype(np.float64)
    theta = np.arctan2(np.linalg.norm(np.cross(ac, ap), axis=1), np.sum(ac * ap, axis=1))  # exact near 0 and pi
    full = h.alpha[parent] >= np.float32(math.pi)  # every direction
    assert np.all(full | (theta + h.alpha[child] <= h.alpha[parent] + 1e-6))
