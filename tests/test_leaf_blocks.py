"""The mesh queries' leaf blocks (``engine.query.leaf_blocks``) hold every leaf's triangles in the
BVH's prim order, and queries through them answer as the shared triangle kernel does, for leaves
of one block and of several."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from numba import njit

from brute_force import brute_force
from engine.core.bvh import build_bvh
from engine.query.frame import local_ray
from engine.query.intersector import RayMeshIntersector
from engine.query.leaf_blocks import TRI_ROW, leaf_blocks
from engine.query.wide import collapse
from scenes.catalog import load_named


@pytest.mark.parametrize("leaf_size", [1, 3, 4, 6, 11])
def test_every_leaf_slot_points_at_its_triangles_in_prim_order(leaf_size):
    tris = load_named("whitted", {"checks": 4, "subdivisions": 1}).triangles
    bvh = build_bvh(tris, leaf_size=leaf_size)
    box, child, size = collapse(bvh.bmin, bvh.bmax, bvh.first, bvh.count)
    child_blocks, block_tri, blocks = leaf_blocks(bvh.first, bvh.count, bvh.prim, tris.v0, tris.v1, tris.v2,
                                                  child, size)
    assert blocks.shape == block_tri.shape == (len(blocks), 10, 4) and blocks.flags.c_contiguous
    assert np.shares_memory(blocks, block_tri) and block_tri.dtype == np.int32
    lane_tri = block_tri[:, TRI_ROW, :].reshape(-1)   # the triangle in each lane, block by block
    np.testing.assert_array_equal(child_blocks[size <= 0], child[size <= 0])   # inner and empty slots kept
    seen = np.zeros(len(lane_tri), bool)
    for w, s in zip(*np.nonzero(size > 0)):
        n, g = size[w, s], child_blocks[w, s]
        lanes = np.arange(4 * g, 4 * g + 4 * ((n + 3) // 4))
        np.testing.assert_array_equal(lane_tri[lanes[:n]], bvh.prim[child[w, s]:child[w, s] + n])
        assert (lane_tri[lanes[n:]] == -1).all()
        seen[lanes] = True
        for k, tri in enumerate(lane_tri[lanes[:n]]):
            g_k, j = divmod(int(lanes[k]), 4)
            corners = blocks[g_k, :TRI_ROW, j].reshape(3, 3)
            np.testing.assert_array_equal(corners, np.stack([tris.v0[tri], tris.v1[tri], tris.v2[tri]]))
    assert seen.all()   # every block belongs to exactly one leaf slot
    assert sorted(lane_tri[lane_tri >= 0]) == list(range(len(tris.v0)))


@njit(cache=True)
def local_rays(origins, directions, center, scale):
    """(org, dirs f32[n,3]): the rays as the queries walk them (``engine.query.frame.local_ray``)."""
    n = origins.shape[0]
    org, dirs = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    for i in range(n):
        _, org[i, 0], org[i, 1], org[i, 2], dirs[i, 0], dirs[i, 1], dirs[i, 2] = local_ray(origins, directions, i,
                                                                                           center, scale)
    return org, dirs


@pytest.mark.parametrize("leaf_size", [1, 6, 11])
def test_queries_through_multi_block_leaves_answer_as_the_kernel(leaf_size):
    """First hits, any hits and all hits on a sphere with leaves of up to three blocks: the
    closest triangle of the shared kernel over every triangle (brute force, on the rays as the
    queries move them into the mesh's frame), and every hit the default leaves give."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(leaf_size)
    origins = rng.normal(size=(600, 3)) * 3
    directions = rng.normal(size=(600, 3)) * 0.4 - origins
    query = RayMeshIntersector(mesh, leaf_size=leaf_size)
    first = query.intersects_first(origins, directions)

    s = query._structure()
    org, dirs = local_rays(origins, directions, s.frame.center, float(s.frame.scale))
    t = np.empty(len(origins), np.float32)
    prim = np.empty(len(origins), np.int32)
    brute_force(org, dirs, np.zeros(len(origins), np.float32), np.full(len(origins), np.inf, np.float32),
                s.tris.v0, s.tris.v1, s.tris.v2, t, prim)
    assert (prim >= 0).sum() > 300
    np.testing.assert_array_equal(first, prim)
    np.testing.assert_array_equal(query.intersects_any(origins, directions), prim >= 0)
    ours = query.intersects_id(origins, directions)
    default = RayMeshIntersector(mesh).intersects_id(origins, directions)
    for a, b in zip(ours, default):
        np.testing.assert_array_equal(a, b)
