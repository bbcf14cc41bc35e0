"""One packet's walk through the BVH as recorded by the traversal kernel itself: which nodes it
visited and how many of its rays were alive at each (``packetrt show``). And, for the ray-space
hierarchy, the cone-sphere node of one packet's screen tile with the triangles that survive
down to it.

The packet traversals (``PACKET_WALKS``, the strategies of ``engine.packet.strategies``) are
not walked again here: the packet is cut out of its batch and traced by the renderer's
``Tracer`` (``record_walk``: the tracer builds its frustum and calls the plugin, whose one packet
walk, ``engine.packet.walk``, fills a record, ``engine.packet.record``), so the nodes, their
order and the answers are the kernel's. Per traversal, a visit's ``alive`` counts the live lanes whose segment meets the
node's box among

- ``partition``: the SIMD rays listed for the node (those that hit its parent);
- ``masked``: every SIMD ray of the packet (the kernel stops at the first that hits; the
  record tests the rest, for the picture);
- ``ranged``: the SIMD rays from the entry's ``ia`` on (likewise);
- ``simd``: the one SIMD ray walking; a node's ``alive`` sums the lanes of every SIMD ray
  that entered it.
- ``auto``: as the strategy it chose for the packet (``engine.packet.choose``).

``single`` (and ``embree``, whose own BVH is not ours to show): each ray walks alone as
``single`` does; ``alive`` is the number of rays that reached the node. ``single``'s kernel
keeps no record, so this module runs its per-ray walk (``traversals.single.walk_ray``) with a node list.

``alive`` is measured against each lane's segment at that moment: a closest-hit search
shortens a lane's segment as it finds hits, an occlusion query kills the lane.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from engine.core.types import MAX_BVH_DEPTH, Frusta, Packets, RayBatch, empty_hits
from engine.packet.frustum_cull import load_frustum
from engine.packet.kernels import leaf_triangles
from engine.packet.record import DEPTH, LANES, NODE, OUTCOME, kept_visits, new_record
from engine.packet import strategies
from traversals.single import walk_ray
from engine.rayspace.cone_sphere import absolute_slack, build_hierarchy, cone_sphere_overlap
from engine.rayspace.triangle_spheres import triangle_spheres

#: Traversals walked packet-wise, and the ones walked ray by ray as ``single`` does.
PACKET_WALKS = tuple(strategies.STRATEGIES)
RAY_WALKS = ("single", "embree")

CULLED, MISSED, ENTERED = "culled", "missed", "entered"
OUTCOME_NAMES = {strategies.CULLED: CULLED, strategies.MISSED: MISSED, strategies.ENTERED: ENTERED}

#: Visits a first record has room for; a walk that makes more is recorded again with room for all.
RECORD_CAPACITY = 4096


@njit(cache=True)
def _tested_triangles(first, count, prim, node, v0, v1, v2, planes, valid, k):
    """i32[M]: the triangles of leaf ``node`` that packet k's frustum does not cull, as the
    kernel's leaf step lists them."""
    fr = np.zeros(16, np.float32)
    cull = load_frustum(planes, valid, k, fr)
    out = np.empty(max(count[node], 1), np.int32)
    n = leaf_triangles(first, count, prim, node, v0, v1, v2, fr, cull, out)
    return out[:n].copy()


@njit(cache=True)
def _single_walk(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax, r,
                 any_hit, nodes):
    """``single``'s own walk of ray r (``traversals.single.walk_ray``), recording each popped
    node in nodes (i32[N]); returns (visited, t, prim, u, v)."""
    stack = np.empty(2 * MAX_BVH_DEPTH + 2, np.int32)
    stack_depth = np.empty(2 * MAX_BVH_DEPTH + 2, np.int32)
    t, hit, u, v, visited = walk_ray(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax,
                                     r, any_hit, stack, stack_depth, None, 0, nodes)
    return visited, t, hit, u, v


# -- the record ---------------------------------------------------------------------------------

@dataclass
class PacketTrace:
    """What one packet did in the BVH.

    walk: the traversal walked ("partition", ...; "single" for embree).
    start, n: the packet's rays are start .. start+n of the batch; live: lanes alive at the start.
    nodes i32[V], depth i32[V], alive i32[V], outcome list[V] (ENTERED, MISSED or CULLED):
        every node visited, in first-visit order (ray-wise walks: each node once, alive summed).
    leaves: {leaf node: triangles tested there (after frustum culling)} for entered leaves.
    pops i64[MAX_BVH_DEPTH]: stack pops per BVH depth, as the kernels count them (their
        ``nodes`` counter): every visit of every SIMD ray or ray, repeats included.
    t f32[n], prim i32[n], u, v f32[n]: the packet's answers (closest hit, or for an occlusion
        query the first hit found: prim >= 0 means occluded).
    """

    walk: str
    start: int
    n: int
    live: int
    nodes: np.ndarray
    depth: np.ndarray
    alive: np.ndarray
    outcome: list
    leaves: dict
    pops: np.ndarray
    t: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    notes: list = field(default_factory=list)


class _Recorder:
    """Visits merged per node, in first-visit order."""

    def __init__(self):
        self.index = {}
        self.nodes, self.depth, self.alive, self.outcome = [], [], [], []
        self.pops = np.zeros(MAX_BVH_DEPTH, np.int64)

    def visit(self, node, depth, outcome, alive):
        self.pops[depth] += 1
        if node in self.index:  # ray-wise walks meet a node many times
            i = self.index[node]
            self.alive[i] += alive
            if outcome == ENTERED or (outcome == MISSED and self.outcome[i] == CULLED):
                self.outcome[i] = outcome
            return
        self.index[node] = len(self.nodes)
        self.nodes.append(node)
        self.depth.append(depth)
        self.alive.append(alive)
        self.outcome.append(outcome)

    def trace(self, walk, start, n, live, leaves, answers, notes=()) -> PacketTrace:
        return PacketTrace(walk, start, n, live, np.array(self.nodes, np.int32), np.array(self.depth, np.int32),
                           np.array(self.alive, np.int32), self.outcome, leaves, self.pops,
                           answers.t, answers.prim, answers.u, answers.v, list(notes))


def trace_packet(tracer, kind: str, rays, packets, k: int, any_hit: bool, from_end: bool = False) -> PacketTrace:
    """Packet ``k`` of ``rays`` (in ``packets``, of ray kind ``kind``) as the tracer's traversal
    for that kind takes it (one of PACKET_WALKS or RAY_WALKS) through the tracer's BVH, with the
    frustum the tracer builds for it. Packet traversals record through ``Tracer.record_walk``;
    ``from_end``: the far child first, as the render walks shadow rays from the light."""
    walk = getattr(tracer.traversal[kind], "name", None)
    if walk not in PACKET_WALKS + RAY_WALKS:
        raise ValueError(f"no packet walk for traversal {walk!r}; known: {', '.join(PACKET_WALKS + RAY_WALKS)}")
    offsets = np.asarray(packets.offsets)
    if not 0 <= k < len(offsets) - 1:
        raise ValueError(f"packet {k} out of range 0..{len(offsets) - 2}")
    start, n = int(offsets[k]), int(offsets[k + 1] - offsets[k])
    bvh, tris = tracer.bvh, tracer.tris
    rec = _Recorder()
    if walk in RAY_WALKS:
        return _ray_walk(bvh, tris, rays, start, n, any_hit, rec, walk)
    alone, alone_packets = packet_alone(rays, packets, k)
    capacity = RECORD_CAPACITY
    while True:
        record = new_record(capacity)
        answers, alone_frusta = tracer.record_walk(kind, alone, alone_packets, any_hit, record, from_end)
        if record.count[0] <= capacity:
            break
        capacity = int(record.count[0])
    if alone_frusta is None:                     # no culling: an all-invalid frustum lists every triangle
        alone_frusta = Frusta(np.zeros((1, 4, 4), np.float32), np.zeros(1, np.bool_))
    for node, depth, outcome, lanes in kept_visits(record)[:, [NODE, DEPTH, OUTCOME, LANES]].tolist():
        rec.visit(node, depth, OUTCOME_NAMES[outcome], lanes)
    leaves = {node: _tested_triangles(bvh.first, bvh.count, bvh.prim, node, tris.v0, tris.v1, tris.v2,
                                      alone_frusta.planes, alone_frusta.valid, 0)
              for node, outcome in zip(rec.nodes, rec.outcome) if outcome == ENTERED and bvh.count[node] > 0}
    live = int(np.count_nonzero(alone.tmin <= alone.tmax))
    return rec.trace(walk, start, n, live, leaves, answers)


def packet_alone(rays, packets, k: int):
    """Packet k as a batch of its own: (RayBatch, Packets). Frusta are built per packet from
    its own rays, so the tracer builds this packet the frustum it had in its batch."""
    start, stop = int(packets.offsets[k]), int(packets.offsets[k + 1])
    alone = RayBatch(*(np.ascontiguousarray(getattr(rays, f)[start:stop]) for f in RayBatch._fields[:-1]),
                     rays.kind)
    return alone, Packets(np.array([0, stop - start], np.int32), packets.size, packets.width, packets.height)


def _ray_walk(bvh, tris, rays, start, n, any_hit, rec, walk) -> PacketTrace:
    depth_of = _node_depths(bvh)
    buffer = np.empty(bvh.first.shape[0], np.int32)
    answers = empty_hits(n)
    leaves = {}
    live = 0
    for lane in range(n):
        r = start + lane
        live += bool(rays.tmin[r] <= rays.tmax[r])
        count, answers.t[lane], answers.prim[lane], answers.u[lane], answers.v[lane] = _single_walk(
            bvh.bmin, bvh.bmax, bvh.first, bvh.count, bvh.prim, tris.v0, tris.v1, tris.v2,
            rays.org, rays.inv_dir, rays.dir, rays.tmin, rays.tmax, r, any_hit, buffer)
        for node in buffer[:count].tolist():
            rec.visit(node, int(depth_of[node]), ENTERED, 1)
            if bvh.count[node] > 0 and node not in leaves:
                f, c = int(bvh.first[node]), int(bvh.count[node])
                leaves[node] = bvh.prim[f:f + c].copy()
    notes = ["embree uses its own BVH: shown is packetrt's BVH walked ray by ray as `single` does"] \
        if walk == "embree" else []
    return rec.trace("single", start, n, live, leaves, answers, notes)


def _node_depths(bvh) -> np.ndarray:
    depth = np.zeros(bvh.first.shape[0], np.int32)
    for node in range(bvh.first.shape[0]):  # children always follow their parent
        if bvh.count[node] == 0:
            depth[bvh.first[node]] = depth[bvh.first[node] + 1] = depth[node] + 1
    return depth


# -- the ray-space hierarchy --------------------------------------------------------------------

@dataclass
class RaySpaceNode:
    """The cone-sphere node over one packet's screen tile and the triangles that reach it.

    level, index: the node's level (0 = rays) and index within it; chain: (level, global node)
    from the root's children down to it. centre f32[3], radius, axis f32[3], alpha (radians),
    far: its cone-sphere (``engine.rayspace.cone_sphere``). survivors i32[S]: triangles whose bounding
    sphere passes the cone-sphere test at every node of the chain (every triangle when the node
    is the root). per_level: survivors after each chain node. reversed: shadow rays indexed
    from the light.
    """

    level: int
    index: int
    chain: list
    centre: np.ndarray
    radius: float
    axis: np.ndarray
    alpha: float
    far: float
    survivors: np.ndarray
    per_level: list
    reversed: bool
    levels: int


@njit(cache=True)
def _surviving(h, chain, centre, radius, abs_tol, keep):
    """keep[t] &= the cone-sphere test of triangle t at each global node of chain; returns the
    count after each node."""
    counts = np.zeros(chain.shape[0], np.int64)
    for j in range(chain.shape[0]):
        node = chain[j]
        total = 0
        for t in range(keep.shape[0]):
            if keep[t]:
                keep[t] = cone_sphere_overlap(h, node, centre[t, 0], centre[t, 1], centre[t, 2], radius[t], abs_tol)
                total += keep[t]
        counts[j] = total
    return counts


def rayspace_node(tris, rays, packets, k: int) -> RaySpaceNode:
    """The hierarchy ``rayspace`` builds for this batch in the paper's pixel layout, and its node
    over packet k's tile. (With the default ``shadow_grid`` and ``secondary_grid`` the plugin
    places shadow, reflection and refraction rays by direction instead, where no node covers a
    screen tile; this view keeps the pixels.)"""
    from traversals.rayspace import live_lanes, shared_apex

    offsets = np.asarray(packets.offsets)
    start, stop = int(offsets[k]), int(offsets[k + 1])
    live = live_lanes(rays)
    apex = shared_apex(rays, live) if rays.kind == "shadow" else None
    h = build_hierarchy(rays.org, rays.dir, rays.tmin, rays.tmax, rays.pixel, packets.width, packets.height, apex)
    centre, radius = triangle_spheres(tris.v0, tris.v1, tris.v2)
    abs_tol = absolute_slack(h, centre, radius)
    pixels = rays.pixel[start:stop][live[start:stop]]
    if pixels.size == 0:
        raise ValueError(f"packet {k} has no live ray")
    px, py = int(pixels[0] % packets.width), int(pixels[0] // packets.width)
    level = min(int(np.log2(packets.size)), h.levels)
    chain = []
    for lv in range(h.levels - 1, level - 1, -1):
        local = (py >> lv) * int(h.level_width[lv]) + (px >> lv)
        chain.append((lv, int(h.level_offset[lv]) + local))
    keep = np.ones(tris.v0.shape[0], np.bool_)
    counts = _surviving(h, np.array([g for _, g in chain], np.int64), centre, radius, np.float32(abs_tol), keep)
    node = chain[-1][1] if chain else int(h.level_offset[h.levels])
    return RaySpaceNode(level, node - int(h.level_offset[level]), chain, h.centre[node].copy(), float(h.radius[node]),
                        h.axis[node].copy(), float(h.alpha[node]), float(h.far[node]),
                        np.flatnonzero(keep).astype(np.int32), [int(c) for c in counts], apex is not None,
                        int(h.levels))
