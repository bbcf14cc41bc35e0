"""The packet traversals (simd, masked, ranged, partition, auto) and the 8-wide single-ray walk
(wide) against the reference ``single``.

Every traversal, with and without the frustum for its ray kind, at every packet size, must
return exactly the reference's prim, t, u, v (closest hit) and occlusion answers on primary,
shadow, reflection and refraction rays: they share the one triangle test and tie rule, so any
difference is a traversal or culling bug. Also: the counters are filled, frustum culling only
ever removes work, and the paper's Figure 6 finding on ray-box / ray-triangle test counts.
"""
from __future__ import annotations

import numba
import numpy as np
import pytest

from engine.packet.layout import PACKET_SIZES, make_batch
from engine.render.plugins import make_frustum, make_traversal
from engine.core.types import COUNTER_NODES, RAY_KINDS, Frusta, empty_hits, new_stats, stats_totals
from conftest import needs_shared_scenes
from packet_raysets import scene_rays
from scenes.catalog import load_named

PACKET_TRAVERSALS = ["simd", "masked", "ranged", "partition", "auto"]
#: ``auto`` with every batch whose sample is split chosen packet by packet: the test batches are
#: smaller than its default ``split_min_packets`` and would otherwise all be walked whole.
OPTIONS = {"auto-split": ("auto", {"split_min_packets": 0})}
#: Single-ray walks held to the same answers: ``wide`` (the 8-wide tree of the mesh queries).
SINGLE_RAY_PEERS = ["wide"]
FRUSTUM_FOR = {"primary": "pinhole", "shadow": "pointlight", "reflection": "general", "refraction": "general"}
SCENES = {"bunny": {"lod": 3}, "cornell-box": {}, "whitted": {}}
SIZE = 64


def load_scene(name, params):
    if name != "whitted":  # the bunny and the Cornell box need the shared scene folder
        needs_shared_scenes()
    return load_named(name, params)


@pytest.fixture(scope="module", params=sorted(SCENES))
def rayset(request):
    rs = scene_rays(load_scene(request.param, SCENES[request.param]), SIZE, SIZE)
    rs.reference = {}
    return rs


def answers(name, rs, rays, packets, frusta, stats=None):
    """(Hits, occluded bool[R]) of traversal ``name`` (or of a variant in ``OPTIONS``)."""
    traversal = make_traversal(*OPTIONS.get(name, (name,)))
    hits = empty_hits(rays.org.shape[0])
    traversal.intersect(rs.bvh, rs.tris, rays, packets, frusta, hits, stats)
    occluded = np.zeros(rays.org.shape[0], np.bool_)
    traversal.occluded(rs.bvh, rs.tris, rays, packets, frusta, occluded, stats)
    return hits, occluded


def batch_and_reference(rs, kind, n):
    key = (kind, n)
    if key not in rs.reference:
        rays, packets = rs.rays[kind].batch(rs.width, rs.height, n)
        rs.reference[key] = (rays, packets, *answers("single", rs, rays, packets, None))
    return rs.reference[key]


@pytest.mark.parametrize("frustum", [False, True], ids=["no-frustum", "frustum"])
@pytest.mark.parametrize("traversal", PACKET_TRAVERSALS + list(OPTIONS) + SINGLE_RAY_PEERS)
@pytest.mark.parametrize("kind", RAY_KINDS)
def test_same_hits_as_single(rayset, kind, traversal, frustum):
    for n in PACKET_SIZES:
        rays, packets, ref_hits, ref_occluded = batch_and_reference(rayset, kind, n)
        assert (ref_hits.prim >= 0).any(), "a ray set without hits tests nothing"
        frusta = make_frustum(FRUSTUM_FOR[kind]).build(rays, packets, rayset.bounds) if frustum else None
        hits, occluded = answers(traversal, rayset, rays, packets, frusta)
        for field in ("prim", "t", "u", "v"):
            np.testing.assert_array_equal(getattr(hits, field), getattr(ref_hits, field),
                                          err_msg=f"{field} differs for {n}x{n} packets")
        np.testing.assert_array_equal(occluded, ref_occluded, err_msg=f"occlusion differs for {n}x{n} packets")


def counted(name, rs, rays, packets, frusta):
    stats = new_stats(numba.get_num_threads())
    hits, occluded = answers(name, rs, rays, packets, frusta, stats)
    return hits, occluded, stats


@pytest.mark.parametrize("traversal", PACKET_TRAVERSALS)
def test_counters_filled_without_changing_hits(rayset, traversal):
    rays, packets, ref_hits, ref_occluded = batch_and_reference(rayset, "primary", 8)
    frusta = make_frustum("pinhole").build(rays, packets, rayset.bounds)
    hits, occluded, stats = counted(traversal, rayset, rays, packets, frusta)
    np.testing.assert_array_equal(hits.prim, ref_hits.prim)
    np.testing.assert_array_equal(hits.t, ref_hits.t)
    np.testing.assert_array_equal(occluded, ref_occluded)
    totals = stats_totals(stats)
    assert totals["ray_aabb"] > 0 and totals["ray_tri"] > 0 and totals["nodes"] > 0
    # The root is visited once per query by each packet (each SIMD ray for simd) with a live lane.
    live = (rays.tmin <= rays.tmax).reshape(-1, 4).any(axis=1)
    per_packet = np.add.reduceat(live, packets.offsets[:-1] // 4) > 0
    roots = live.sum() if traversal == "simd" else per_packet.sum()
    assert stats.counters[:, COUNTER_NODES, 0].sum() == 2 * roots


# Not auto: a packet without a frustum is walked by another strategy than with one, so its
# work with and without frusta is not the same walk culled or not.
@pytest.mark.parametrize("traversal", [t for t in PACKET_TRAVERSALS if t != "auto"])
@pytest.mark.parametrize("kind", RAY_KINDS)
def test_frustum_culling_only_removes_work(rayset, kind, traversal):
    rays, packets, _, _ = batch_and_reference(rayset, kind, 8)
    frusta = make_frustum(FRUSTUM_FOR[kind]).build(rays, packets, rayset.bounds)
    _, _, plain = counted(traversal, rayset, rays, packets, None)
    _, _, culled = counted(traversal, rayset, rays, packets, frusta)
    assert (culled.counters.sum(axis=0) <= plain.counters.sum(axis=0)).all()
    if kind in ("primary", "shadow"):
        assert frusta.valid.all()
        assert stats_totals(culled)["ray_aabb"] < stats_totals(plain)["ray_aabb"]


def test_figure6_partition_fewer_triangle_tests_ranged_fewer_box_tests():
    """Overbeck et al.'s Figure 6: on coherent primary rays Ranged does fewer ray-box tests than
    Partition; on reflection rays Partition does fewer ray-triangle tests. Bunny LOD 3 at
    256x256 with 16x16 packets (at 64x64 the bunny's triangles are smaller than the pixels and
    primary rays are too incoherent for Ranged to win)."""
    rs = scene_rays(load_scene("bunny", {"lod": 3}), 256, 256)
    for kind, row in (("primary", "ray_aabb"), ("reflection", "ray_tri")):
        rays, packets = rs.rays[kind].batch(rs.width, rs.height, 16)
        for frusta in (None, make_frustum(FRUSTUM_FOR[kind]).build(rays, packets, rs.bounds)):
            ranged = stats_totals(counted("ranged", rs, rays, packets, frusta)[2])[row]
            partition = stats_totals(counted("partition", rs, rays, packets, frusta)[2])[row]
            if kind == "primary":
                assert ranged < partition
            else:
                assert partition < ranged


@pytest.mark.parametrize("traversal", PACKET_TRAVERSALS)
def test_empty_batch_and_mismatched_frusta(traversal):
    from scenes.whitted import whitted_scene

    rs = scene_rays(whitted_scene([], {"subdivisions": 1}, 0.0), 8, 8)
    rays, packets = make_batch("primary", np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0),
                               np.zeros(0, np.int32), np.zeros((0, 3)), 8, 8, 4)
    hits, occluded = answers(traversal, rs, rays, packets, make_frustum("pinhole").build(rays, packets, rs.bounds))
    assert hits.t.shape == (0,) and occluded.shape == (0,)
    rays, packets = rs.rays["primary"].batch(8, 8, 4)
    wrong = Frusta(np.zeros((1, 4, 4), np.float32), np.zeros(1, np.bool_))
    with pytest.raises(ValueError, match="frusta"):
        answers(traversal, rs, rays, packets, wrong)
