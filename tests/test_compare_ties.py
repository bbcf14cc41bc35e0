"""The tie rules only forgive answers that are both real: a hit must lie on its own triangle and
inside its segment, and a miss where the other side crossed an interior edge is a crack, not a
graze. Hand-made rays over a unit quad (two triangles sharing the diagonal (0,0)-(1,1)), a closed
tetrahedron, and an audit of a real render whose reflection rays answer wrongly."""
import numpy as np
import pytest

from engine.core.scene import make_triangles
from engine.core.types import Hits, RayBatch
from engine.render.config import Config, with_overrides
from engine.render.tracer import Tracer
from scenes.catalog import scene_from_config
from validation.audit import audit
from validation.compare import compare_hits, compare_occlusion

QUAD = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
FAR = np.array([[10, 10, -5], [11, 10, -5], [10, 11, -5]], np.float32)   # a triangle off every ray
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]], np.int32)
quad = make_triangles(np.vstack([QUAD, FAR]), QUAD_FACES, 0)


def batch(org, d, tmin=0.0, tmax=np.inf):
    org = np.array(org, np.float32).reshape(-1, 3)
    d = np.array(d, np.float32).reshape(-1, 3)
    n = len(org)
    with np.errstate(divide="ignore"):
        inv = (1 / d).astype(np.float32)
    return RayBatch(org, d, inv, np.full(n, tmin, np.float32), np.full(n, tmax, np.float32),
                    np.arange(n, dtype=np.int32), np.ones((n, 3), np.float32), "reflection")


def hits(t, prim, rays=None, tris=None):
    """Hits at t on triangles prim; with rays and tris, the barycentrics of each ray's point at t
    in its triangle's plane (what a real kernel returns), else zeros."""
    n = len(t)
    t, prim = np.array(t, np.float32), np.array(prim, np.int32)
    u, v = np.zeros(n, np.float32), np.zeros(n, np.float32)
    if rays is not None:
        for i in np.flatnonzero(prim >= 0):
            point = rays.org[i].astype(np.float64) + float(t[i]) * rays.dir[i]
            edges = np.stack([tris.e1[prim[i]], tris.e2[prim[i]]], axis=1).astype(np.float64)
            u[i], v[i] = np.linalg.lstsq(edges, point - tris.v0[prim[i]], rcond=None)[0]
    return Hits(t, prim, u, v)


MISS = ([np.inf], [-1])
DOWN = [0, 0, -1.0]


def verdict(rays, ours, oracle, tris=quad):
    c = compare_hits(rays, hits(*ours, rays, tris), hits(*oracle, rays, tris), tris)
    return "agree" if c.agree[0] else "tie" if c.tie[0] else "mismatch"


def test_a_hit_at_tmin_on_a_triangle_the_origin_is_not_on_is_a_mismatch():
    # The oracle hits triangle 1 at t = 1; ours claims triangle 0 at the segment's start.
    assert verdict(batch([0.25, 0.75, 1.0], DOWN), ([0.0], [0]), ([1.0], [1])) == "mismatch"
    # The oracle misses; ours claims a hit at tmin far from any triangle.
    assert verdict(batch([5.0, 5.0, 1.0], DOWN), ([0.0], [0]), MISS) == "mismatch"


def test_a_hit_on_a_triangle_the_ray_never_meets_is_a_mismatch():
    ray = batch([0.5, 0.5, 1.0], DOWN)
    assert verdict(ray, ([6.0], [2]), ([1.0], [0])) == "mismatch"
    assert verdict(ray, ([1e6], [2]), ([1.0], [0])) == "mismatch"
    # At tmax of a short segment, through nothing.
    assert verdict(batch([5.0, 5.0, 1.0], DOWN, tmax=1.0), ([1.0], [0]), MISS) == "mismatch"


def test_a_miss_through_an_interior_edge_is_a_crack():
    ray = batch([0.5, 0.5, 1.0], DOWN)   # straight through the shared diagonal
    assert verdict(ray, MISS, ([1.0], [0])) == "mismatch"
    # Slipping through the diagonal to a surface behind is the same crack.
    behind = make_triangles(np.vstack([QUAD, QUAD - [0, 0, 1]]), np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]]), 0)
    assert verdict(ray, ([2.0], [2]), ([1.0], [0]), behind) == "mismatch"
    occluded = compare_occlusion(ray, np.array([False]), np.array([True]), quad, hits(*MISS), hits([1.0], [0]))
    assert occluded.mismatch[0]


def test_real_ties_stay_ties():
    # An outer edge of the quad: either side may miss.
    outer = batch([0.5, 0.0, 1.0], DOWN)
    assert verdict(outer, MISS, ([1.0], [0])) == "tie"
    assert verdict(outer, ([1.0], [0]), MISS) == "tie"
    # The oracle cracks (misses at the diagonal) where we hit: ours is a real hit on the edge.
    assert verdict(batch([0.5, 0.5, 1.0], DOWN), ([1.0], [0]), MISS) == "tie"
    # Either triangle at the diagonal.
    assert verdict(batch([0.5, 0.5, 1.0], DOWN), ([1.0], [1]), ([1.0], [0])) == "tie"
    # A vertex shared by both triangles.
    assert verdict(batch([0.0, 0.0, 1.0], DOWN), MISS, ([1.0], [1])) == "tie"
    # A secondary ray leaving the quad's surface may report it at tmin, when it really starts on it.
    assert verdict(batch([0.25, 0.75, 0.0], [0, 0, 1.0]), ([0.0], [1]), MISS) == "tie"


def test_a_silhouette_edge_of_a_closed_mesh_is_a_tie():
    # Tetrahedron; the ray runs along the plane through edge (0,1) and touches it from outside:
    # both faces at that edge lie below the ray, so missing it is a graze, not a crack.
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, 0.3, 1]], np.float32)
    f = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]], np.int32)
    tet = make_triangles(v, f, 0)
    ray = batch([0.5, -1.0, 0.0], [0, 1.0, 0])   # in the base plane, meeting edge (0,1) at (0.5, 0, 0)
    ours = verdict(ray, MISS, ([1.0], [1]), tet)
    assert ours == "tie"


def test_the_audit_catches_reflection_rays_that_hit_the_wrong_triangle_at_tmin(monkeypatch, shared_scenes):
    real_trace = Tracer.trace

    def self_hit(self, kind, query, rays, packets, *args, **kwargs):
        out = real_trace(self, kind, query, rays, packets, *args, **kwargs)
        if kind == "reflection" and query == "intersect":
            hit = np.flatnonzero((rays.tmin <= rays.tmax) & (out.prim >= 0))
            out.t[hit] = rays.tmin[hit]
            out.prim[hit] = (out.prim[hit] + 7) % self.tris.v0.shape[0]
        return out

    monkeypatch.setattr(Tracer, "trace", self_hit)
    config = with_overrides(Config(), scene="cornell-box", size=(48, 48), depth=2)
    report, _, _ = audit(scene_from_config(config.scene, "reflective"), config)
    wrong = report["by_kind"]["reflection"]
    assert wrong["checked"] > 100
    # Some rays start within the tolerance of the claimed triangle (a coplanar neighbour of the
    # surface they leave): a hit there at tmin is a valid start-on-surface answer. The rest are
    # wrong (the comparison used to call all of them ties).
    assert report["mismatch_count"] >= 0.7 * wrong["checked"], wrong


def test_the_same_triangle_at_other_barycentrics_is_a_mismatch():
    """Shading interpolates normals and uvs with (u, v): a hit on the right triangle at the right
    t but with wrong barycentrics (here swapped) is wrong."""
    rays = batch([0.7, 0.2, 1.0], DOWN)   # inside triangle 0 (corners (0,0), (1,0), (1,1))
    point = np.array([0.7, 0.2])
    # Triangle 0: v0 = (0,0), e1 = (1,0), e2 = (1,1): point = u e1 + v e2 -> v = 0.2, u = 0.5.
    u, v = 0.5, 0.2
    assert np.allclose(u * np.array([1, 0]) + v * np.array([1, 1]), point)
    right = Hits(np.array([1.0], np.float32), np.array([0], np.int32), np.array([u], np.float32), np.array([v], np.float32))
    swapped = right._replace(u=right.v.copy(), v=right.u.copy())
    assert compare_hits(rays, right, right, quad).agree[0]
    assert compare_hits(rays, swapped, right, quad).mismatch[0]
    nudged = right._replace(u=right.u + np.float32(1e-6))   # float32 noise in u stays agreement
    assert compare_hits(rays, nudged, right, quad).agree[0]


TET_V = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, 0.3, 1]], np.float32)
TET_F = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]], np.int32)


def test_a_miss_through_a_vertex_the_surface_closes_around_is_a_crack():
    tet = make_triangles(TET_V, TET_F, 0)
    down = batch([0.5, 0.3, 2.0], DOWN)   # straight down through the apex, into the solid
    assert verdict(down, MISS, ([1.0], [1]), tet) == "mismatch"
    # The apex hit itself is a tie whichever of its three triangles names it.
    assert verdict(down, ([1.0], [2]), ([1.0], [1]), tet) == "tie"
    # Past the apex to the base behind it is the same crack as a miss.
    assert verdict(down, ([2.0], [0]), ([1.0], [1]), tet) == "mismatch"


def test_a_ray_touching_a_vertex_from_outside_is_a_tie():
    tet = make_triangles(TET_V, TET_F, 0)
    # Through corner 0 in a direction the solid lies wholly to one side of: a silhouette vertex.
    touching = batch([-1.0, 1.0, 0.0], [1.0, -1.0, 0.0])
    assert verdict(touching, MISS, ([1.0], [1]), tet) == "tie"


def test_a_crack_at_a_non_manifold_edge_or_a_duplicated_face_is_still_a_crack():
    ray = batch([0.3, 0.3, 2.0], DOWN)   # through the quad's diagonal at (0.3, 0.3)
    fin = np.vstack([QUAD, [[0.2, 0.8, -1.0]]]).astype(np.float32)
    with_fin = make_triangles(fin, np.array([[0, 1, 2], [0, 2, 3], [0, 2, 4]], np.int32), 0)
    doubled = make_triangles(QUAD, np.array([[0, 1, 2], [0, 2, 3], [0, 1, 2]], np.int32), 0)
    for tris in (with_fin, doubled):
        assert verdict(ray, MISS, ([2.0], [0]), tris) == "mismatch"
    # A doubled face in a vertex's fan: the fan still closes around the ray.
    tet = make_triangles(TET_V, np.vstack([TET_F, TET_F[1:2]]), 0)
    assert verdict(batch([0.5, 0.3, 2.0], DOWN), MISS, ([1.0], [1]), tet) == "mismatch"


def test_a_tie_with_barycentrics_naming_another_point_is_a_mismatch():
    ray = batch([0.5, 0.5, 1.0], DOWN)   # on the shared diagonal: either triangle is right
    oracle = hits([1.0], [0], ray, quad)
    right = hits([1.0], [1], ray, quad)
    wrong = right._replace(u=np.array([0.0], np.float32), v=np.array([1.0], np.float32))  # corner (0, 1)
    assert compare_hits(ray, right, oracle, quad).tie[0]
    assert compare_hits(ray, wrong, oracle, quad).mismatch[0]


LAYERS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0],           # A, its outer edge y = 0 at z = 0
                   [-5, -5, -1], [5, -5, -1], [0, 5, -1],      # B, wide, behind it
                   [-5, -5, -2], [5, -5, -2], [0, 5, -2]], np.float32)   # C, behind B
layers = make_triangles(LAYERS, np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]], np.int32), 0)


def test_behind_a_graze_or_a_start_the_oracle_is_asked_what_lies_there():
    from validation.oracle import EmbreeOracle

    oracle = EmbreeOracle(layers)

    def judged(rays, ours, theirs, **kwargs):
        c = compare_hits(rays, hits(*ours, rays, layers), hits(*theirs, rays, layers), layers, **kwargs)
        return "agree" if c.agree[0] else "tie" if c.tie[0] else "mismatch"

    edge = batch([0.5, 0.0, 1.0], DOWN)   # grazes A's outer edge at t = 1; B lies behind at t = 2
    assert judged(edge, MISS, ([1.0], [0])) == "tie"   # without the oracle to ask: the old rule
    assert judged(edge, MISS, ([1.0], [0]), again=oracle.intersect) == "mismatch"
    assert judged(edge, ([3.0], [2]), ([1.0], [0]), again=oracle.intersect) == "mismatch"   # skipped B
    assert judged(edge, ([2.0], [1]), ([1.0], [0]), again=oracle.intersect) == "tie"        # B: right
    blocked = compare_occlusion(edge, np.array([False]), np.array([True]), layers, hits(*MISS),
                                hits([1.0], [0], edge, layers), again=oracle.occluded)
    assert blocked.mismatch[0]
    # A ray starting on A: the oracle reports A at tmin; skipping A is right only onto B.
    start = batch([0.25, 0.25, 0.0], DOWN)
    assert judged(start, ([2.0], [2]), ([0.0], [0]), again=oracle.intersect) == "mismatch"   # C at t = 2
    assert judged(start, ([1.0], [1]), ([0.0], [0]), again=oracle.intersect) == "tie"        # B at t = 1
    # With nothing behind, a miss past an outer edge stays a tie.
    alone = make_triangles(LAYERS[:3], np.array([[0, 1, 2]], np.int32), 0)
    c = compare_hits(edge, hits(*MISS), hits([1.0], [0], edge, alone), alone, again=EmbreeOracle(alone).intersect)
    assert c.tie[0]
