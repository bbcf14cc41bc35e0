"""``wide``: one ray at a time over an 8-wide tree, the mesh queries' walk, as a render traversal.

The strong single-ray peer of the packet traversals inside the engine: the walk that
``engine.RayMeshIntersector`` uses (``engine.query.walk``: an 8-wide node as one <8 x float>
box test, leaves as blocks of four triangles in one <4 x float> watertight test, pushed children
prefetched), over the 8-wide tree collapsed from the render's own binary BVH
(``engine.query.wide``) with the leaves' triangles copied into blocks (``engine.query.leaf_blocks``).
It answers with the render's triangle indices and, sharing the triangle test and the tie rule,
returns exactly the hits of ``single`` and of every packet traversal
(``tests/test_packet_traversals.py``). Parallel over chunks of rays; ignores packets and frusta.

The 8-wide structure is built from the BVH at the first batch traced over it and kept while the
same BVH and triangles are traced (a refitted or rebuilt tree is a new one): the renderer's
warm-up frame builds it, outside any timed frame. ``stats.extra["wide"]`` records its size and
build time. Counters are not kept (the walk is the queries' hot loop, uninstrumented).
"""
from __future__ import annotations

import time

import numpy as np
from numba import njit, prange

from engine.core.registry import register_traversal
from engine.core.types import check_answer_arrays
from engine.query.walk import ANY, CLOSEST, new_stack, walk
from engine.query.wide import packed_tree

CHUNK = 256  # rays per prange task: one stack allocation per chunk
F32_INF = np.float32(np.inf)


@njit(cache=True, parallel=True)
def closest_hits(nodes, node_bits, block_tri, blocks, org, dirs, tmin, tmax, out_t, out_prim, out_u, out_v):
    """Closest hit of every ray (org, dirs f32[R,3], segment tmin..tmax f32[R]; a ray with
    tmin > tmax is dead and misses) over the packed 8-wide tree: out_t, out_u, out_v f32[R],
    out_prim i32[R] (-1 and t = inf: a miss)."""
    n = org.shape[0]
    no_t, no_i = np.empty(0, np.float32), np.empty(0, np.int32)
    for c in prange((n + CHUNK - 1) // CHUNK):
        stack, stack_t, entries, answers = new_stack()
        for r in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            out_t[r], out_prim[r], out_u[r], out_v[r] = F32_INF, -1, 0, 0
            if not tmin[r] <= tmax[r]:
                continue
            hit, t, tri, u, v = walk(nodes, node_bits, block_tri, blocks, org[r, 0], org[r, 1], org[r, 2],
                                     dirs[r, 0], dirs[r, 1], dirs[r, 2], tmin[r], tmax[r], CLOSEST, stack, stack_t,
                                     entries, answers, no_t, no_i, no_t, no_t, 0)
            if hit:
                out_t[r], out_prim[r], out_u[r], out_v[r] = t, tri, u, v


@njit(cache=True, parallel=True)
def any_hits(nodes, node_bits, block_tri, blocks, org, dirs, tmin, tmax, occluded):
    """occluded bool[R]: whether each ray (as in ``closest_hits``) hits anything on its segment."""
    n = org.shape[0]
    no_t, no_i = np.empty(0, np.float32), np.empty(0, np.int32)
    for c in prange((n + CHUNK - 1) // CHUNK):
        stack, stack_t, entries, answers = new_stack()
        for r in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            occluded[r] = False
            if not tmin[r] <= tmax[r]:
                continue
            hit, _, _, _, _ = walk(nodes, node_bits, block_tri, blocks, org[r, 0], org[r, 1], org[r, 2],
                                   dirs[r, 0], dirs[r, 1], dirs[r, 2], tmin[r], tmax[r], ANY, stack, stack_t,
                                   entries, answers, no_t, no_i, no_t, no_t, 0)
            occluded[r] = hit > 0


@register_traversal("wide")
class WideTraversal:
    """One ray at a time over an 8-wide tree of the render's BVH (the mesh queries' walk)."""

    #: Frusta are not read: the tracer builds none for this traversal.
    uses_frusta = False

    #: Every ray's answer is written (dead rays as misses): the tracer need not reset them.
    writes_every_answer = True

    def __init__(self):
        self._built = None  # (bmin, v0, structure, stats): this instance's tree, for one BVH at a time

    def structure(self, bvh, tris):
        """(nodes, node_bits, block_tri, blocks) of the 8-wide tree over ``bvh`` and ``tris``,
        built at the first call for this BVH and triangle set."""
        built = self._built
        if built is None or built[0] is not bvh.bmin or built[1] is not tris.v0:
            start = time.perf_counter()
            nodes, block_tri, blocks = packed_tree(bvh, tris.v0, tris.v1, tris.v2)
            info = {"nodes": int(nodes.shape[0]), "blocks": int(blocks.shape[0]),
                    "build_seconds": time.perf_counter() - start}
            built = self._built = (bvh.bmin, tris.v0, (nodes, nodes.view(np.int32), block_tri, blocks), info)
        return built[2]

    def _record(self, stats):
        if stats is not None:
            stats.extra["wide"] = dict(self._built[3])

    def intersect(self, bvh, tris, rays, packets, frusta, hits, stats):
        check_answer_arrays(rays.org.shape[0], hits.t, hits.prim, hits.u, hits.v)
        closest_hits(*self.structure(bvh, tris), rays.org, rays.dir, rays.tmin, rays.tmax,
                     hits.t, hits.prim, hits.u, hits.v)
        self._record(stats)

    def occluded(self, bvh, tris, rays, packets, frusta, occluded, stats):
        check_answer_arrays(rays.org.shape[0], occluded)
        any_hits(*self.structure(bvh, tris), rays.org, rays.dir, rays.tmin, rays.tmax, occluded)
        self._record(stats)
