"""One packet, walked again with a recorder: which BVH nodes it visited and how many of its
rays were alive at each (``packetrt show``). And, for the ray-space hierarchy, the cone-sphere
node of one packet's screen tile with the triangles that survive down to it.

Speed does not matter here (one packet), faithfulness does. The walk is Python, but every
decision is taken by the very numba functions the packet kernels inline -- ``load_packet``,
``slab_mask4``, ``first_hit``, ``last_hit``, ``part_rays``, ``leaf_triangles``,
``intersect_lanes``, ``frustum_misses_box`` -- called through the small wrappers below, on the
kernels' own packet-local state (rf, ri), in the kernels' order (near child first from the
packet's direction signs). So the recorded hits are the traversal's hits bit for bit, which
the tests check against the real plugins.

Per traversal:

- ``partition``: a node is visited when popped; the frustum may reject it (``culled``); else
  the SIMD rays listed for it are partitioned, and ``alive`` is the lanes of those that hit
  its box.
- ``masked``: the whole packet enters while one SIMD ray hits; ``alive`` counts every live
  lane that hits the box (the kernel stops at the first, the count is for the picture).
- ``ranged``: rays from the entry's ``ia`` on; ``alive`` counts the lanes of SIMD rays
  ia .. end that hit the box.
- ``simd``: each SIMD ray walks alone; a node's ``alive`` sums the lanes of every SIMD ray
  that entered it.
- ``single`` (and ``embree``, whose own BVH is not ours to show): each ray walks alone as
  ``single`` does; ``alive`` is the number of rays that reached the node.

``alive`` is measured against each lane's segment at that moment: a closest-hit search
shortens a lane's segment as it finds hits, an occlusion query kills the lane.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from engine.rayspace.cone_sphere import absolute_slack, build_hierarchy, cone_sphere_overlap
from engine.packet.frustum_cull import frustum_misses_box, load_frustum
from engine.core.triangle import F32_INF, closer, intersect_triangle, ray_shear, slab_test
from engine.packet.kernels import (BEST_PRIM, BEST_T, BEST_U, BEST_V, child_order_keys, first_hit,
                             intersect_lanes, leaf_triangles, live_mask4, load_packet, node_box,
                             packet_scratch, slab_mask4)
from engine.rayspace.triangle_spheres import triangle_spheres
from engine.core.types import MAX_BVH_DEPTH

# The two traversal-specific steps, from the plugins themselves (importing them registers
# nothing new: the registry loads the same modules).
from traversals.partition import part_rays  # noqa: E402
from traversals.ranged import last_hit  # noqa: E402

#: Traversals walked packet-wise, and the ones walked ray by ray as ``single`` does.
PACKET_WALKS = ("partition", "masked", "ranged", "simd")
RAY_WALKS = ("single", "embree")

CULLED, MISSED, ENTERED = "culled", "missed", "entered"


# -- thin wrappers: the kernels' own inline functions, callable from Python --------------------

@njit(cache=True)
def _load(org, inv, dirs, tmin, tmax, start, n):
    rf, ri, near, fr, _ = packet_scratch(n, 1)
    live = load_packet(org, inv, dirs, tmin, tmax, start, n, rf, ri, near)
    return rf, ri, near, live


@njit(cache=True)
def _load_frustum(planes, valid, k):
    fr = np.zeros(16, np.float32)
    cull = load_frustum(planes, valid, k, fr)
    return fr, cull


@njit(cache=True)
def _frustum_misses(fr, bmin, bmax, node):
    return frustum_misses_box(fr, node_box(bmin, bmax, node))


@njit(cache=True)
def _masks(rf, lo, hi, bmin, bmax, node):
    """i32[hi-lo]: slab_mask4 of SIMD rays lo .. hi-1 against the node's box."""
    box = node_box(bmin, bmax, node)
    out = np.zeros(max(hi - lo, 0), np.int32)
    for i in range(lo, hi):
        out[i - lo] = slab_mask4(rf, 4 * i, box)
    return out


@njit(cache=True)
def _live_masks(rf, n_simd):
    out = np.zeros(n_simd, np.int32)
    for i in range(n_simd):
        out[i] = live_mask4(rf, 4 * i)
    return out


@njit(cache=True)
def _first_hit(rf, lo, hi, bmin, bmax, node, fr, cull):
    return first_hit(rf, lo, hi, node_box(bmin, bmax, node), fr, cull)


@njit(cache=True)
def _part_rays(rf, ids, masks, m, bmin, bmax, node):
    return part_rays(rf, ids, masks, m, node_box(bmin, bmax, node))


@njit(cache=True)
def _last_hit(rf, ia, hi, bmin, bmax, node):
    return last_hit(rf, ia, hi, node_box(bmin, bmax, node))


@njit(cache=True)
def _leaf_triangles(first, count, prim, node, v0, v1, v2, fr, cull):
    out = np.empty(max(count[node], 1), np.int32)
    n = leaf_triangles(first, count, prim, node, v0, v1, v2, fr, cull, out)
    return out[:n].copy()


@njit(cache=True)
def _intersect(rf, ri, simd, mask, tris, v0, v1, v2, any_hit):
    return intersect_lanes(rf, ri, 4 * simd, mask, tris, tris.shape[0], v0, v1, v2, any_hit)


@njit(cache=True)
def _single_walk(bmin, bmax, first, count, prim, v0, v1, v2, org, inv, dirs, tmin, tmax, r,
                 any_hit, nodes):
    """``single``'s walk of ray r (see traversals/single.py), recording each popped node in
    nodes (i32[N]); returns (visited, t, prim, u, v, leaves holding the best hit)."""
    best_t = F32_INF
    best_prim = -1
    best_u = np.float32(0.0)
    best_v = np.float32(0.0)
    best_leaf = -1
    t_lo = tmin[r]
    t_hi = tmax[r]
    if not t_lo <= t_hi:
        return 0, best_t, best_prim, best_u, best_v, best_leaf
    ox, oy, oz = org[r, 0], org[r, 1], org[r, 2]
    ix, iy, iz = inv[r, 0], inv[r, 1], inv[r, 2]
    kx, ky, kz, sx, sy, sz = ray_shear(dirs[r, 0], dirs[r, 1], dirs[r, 2])
    okx, oky, okz = org[r, kx], org[r, ky], org[r, kz]
    stack = np.empty(2 * MAX_BVH_DEPTH + 2, np.int32)
    top = 0
    if slab_test(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, 0) < F32_INF:
        stack[0] = 0
        top = 1
    visited = 0
    done = False
    while top > 0 and not done:
        top -= 1
        node = stack[top]
        nodes[visited] = node
        visited += 1
        if count[node] > 0:
            for i in range(first[node], first[node] + count[node]):
                tri = prim[i]
                t, u, v = intersect_triangle(okx, oky, okz, kx, ky, kz, sx, sy, sz, t_lo, t_hi, v0, v1, v2, tri)
                if t < F32_INF and closer(t, tri, best_t, best_prim):
                    best_t, best_prim, best_u, best_v, best_leaf = t, tri, u, v, node
                    if any_hit:
                        done = True
                        break
                    t_hi = t
            continue
        left = first[node]
        t_left = slab_test(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, left)
        t_right = slab_test(ox, oy, oz, ix, iy, iz, t_lo, t_hi, bmin, bmax, left + 1)
        near, far = left, left + 1
        t_near, t_far = t_left, t_right
        if t_right < t_left:
            near, far = left + 1, left
            t_near, t_far = t_right, t_left
        if t_far < F32_INF:
            stack[top] = far
            top += 1
        if t_near < F32_INF:
            stack[top] = near
            top += 1
    return visited, best_t, best_prim, best_u, best_v, best_leaf


def _popcount(masks) -> int:
    return int(sum(bin(int(m)).count("1") for m in masks))


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
    hit_leaf i32[n]: the leaf in which each lane found its final hit (-1 = none).
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
    hit_leaf: np.ndarray
    t: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    notes: list = field(default_factory=list)


class _Recorder:
    def __init__(self):
        self.index = {}
        self.nodes, self.depth, self.alive, self.outcome = [], [], [], []
        self.leaves = {}
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


def trace_packet(bvh, tris, rays, packets, frusta, k: int, walk: str, any_hit: bool) -> PacketTrace:
    """Walk packet ``k`` of ``rays`` (in ``packets``) through ``bvh`` as traversal ``walk`` does
    (one of PACKET_WALKS or RAY_WALKS), with its frustum from ``frusta`` (None = no culling)."""
    if walk not in PACKET_WALKS + RAY_WALKS:
        raise ValueError(f"no packet walk for traversal {walk!r}; known: {', '.join(PACKET_WALKS + RAY_WALKS)}")
    offsets = np.asarray(packets.offsets)
    if not 0 <= k < len(offsets) - 1:
        raise ValueError(f"packet {k} out of range 0..{len(offsets) - 2}")
    start, n = int(offsets[k]), int(offsets[k + 1] - offsets[k])
    if frusta is None:
        planes, valid = np.zeros((k + 1, 4, 4), np.float32), np.zeros(k + 1, np.bool_)
    else:
        planes = np.ascontiguousarray(frusta.planes, np.float32)
        valid = np.ascontiguousarray(frusta.valid, np.bool_)
    rec = _Recorder()
    if walk in RAY_WALKS:
        return _ray_walk(bvh, tris, rays, start, n, any_hit, rec, walk)
    rf, ri, near, live = _load(rays.org, rays.inv_dir, rays.dir, rays.tmin, rays.tmax, start, n)
    fr, cull = _load_frustum(planes, valid, k)
    order = child_order_keys(bvh.bmin, bvh.bmax, bvh.first, bvh.count)
    hit_leaf = np.full(n, -1, np.int32)
    walker = {"partition": _walk_partition, "masked": _walk_masked, "ranged": _walk_ranged,
              "simd": _walk_simd}[walk]
    walker(bvh, tris, rf, ri, near, order, fr, cull, n // 4, int(live), any_hit, rec, hit_leaf)
    return PacketTrace(walk, start, n, int(live), np.array(rec.nodes, np.int32), np.array(rec.depth, np.int32),
                       np.array(rec.alive, np.int32), rec.outcome, rec.leaves, rec.pops, hit_leaf,
                       rf[BEST_T, :n].copy(), ri[BEST_PRIM, :n].copy(), rf[BEST_U, :n].copy(),
                       rf[BEST_V, :n].copy())


def _children(bvh, order, near, node):
    near_child = int(bvh.first[node] + near[order[node]])
    return near_child, 2 * int(bvh.first[node]) + 1 - near_child


def _leaf(bvh, tris, rf, ri, fr, cull, node, simds, masks, any_hit, rec, hit_leaf):
    """Intersect the given SIMD rays' masked lanes with the leaf; returns lanes that died."""
    leaf_tris = _leaf_triangles(bvh.first, bvh.count, bvh.prim, node, tris.v0, tris.v1, tris.v2, fr, cull)
    rec.leaves[node] = leaf_tris
    died = 0
    for i, mask in zip(simds, masks):
        before = ri[BEST_PRIM, 4 * i:4 * i + 4].copy()
        best_t = rf[BEST_T, 4 * i:4 * i + 4].copy()
        _, d = _intersect(rf, ri, int(i), int(mask), leaf_tris, tris.v0, tris.v1, tris.v2, any_hit)
        died += d
        changed = (ri[BEST_PRIM, 4 * i:4 * i + 4] != before) | (rf[BEST_T, 4 * i:4 * i + 4] != best_t)
        hit_leaf[4 * i:4 * i + 4][changed] = node
    return died


def _walk_partition(bvh, tris, rf, ri, near, order, fr, cull, n_simd, live, any_hit, rec, hit_leaf):
    ids = np.flatnonzero(_live_masks(rf, n_simd)).astype(np.int32)
    masks = np.zeros(max(n_simd, 1), np.int32)
    stack = [(0, len(ids), 0)] if len(ids) else []
    while stack and live > 0:
        node, m_in, depth = stack.pop()
        if cull and _frustum_misses(fr, bvh.bmin, bvh.bmax, node):
            rec.visit(node, depth, CULLED, 0)
            continue
        m = _part_rays(rf, ids, masks, m_in, bvh.bmin, bvh.bmax, node)
        rec.visit(node, depth, ENTERED if m else MISSED, _popcount(masks[:m]))
        if m == 0:
            continue
        if bvh.count[node] > 0:
            live -= _leaf(bvh, tris, rf, ri, fr, cull, node, ids[:m].tolist(), masks[:m].tolist(), any_hit,
                          rec, hit_leaf)
            continue
        near_child, far_child = _children(bvh, order, near, node)
        stack.append((far_child, m, depth + 1))
        stack.append((near_child, m, depth + 1))


def _walk_masked(bvh, tris, rf, ri, near, order, fr, cull, n_simd, live, any_hit, rec, hit_leaf):
    stack = [(0, 0)] if live > 0 else []
    while stack and live > 0:
        node, depth = stack.pop()
        masks = _masks(rf, 0, n_simd, bvh.bmin, bvh.bmax, node)
        alive = _popcount(masks)
        if bvh.count[node] > 0:
            if cull and _frustum_misses(fr, bvh.bmin, bvh.bmax, node):
                rec.visit(node, depth, CULLED, 0)
                continue
            hit = [i for i in range(n_simd) if masks[i]]
            rec.visit(node, depth, ENTERED if hit else MISSED, alive)
            live -= _leaf(bvh, tris, rf, ri, fr, cull, node, hit, [masks[i] for i in hit], any_hit, rec, hit_leaf)
            continue
        first, _ = _first_hit(rf, 0, n_simd, bvh.bmin, bvh.bmax, node, fr, cull)
        if first >= n_simd:
            # Rejected by the frustum when SIMD ray 0 missed and a valid frustum misses the box.
            culled = cull and masks[0] == 0 and _frustum_misses(fr, bvh.bmin, bvh.bmax, node)
            rec.visit(node, depth, CULLED if culled else MISSED, 0 if culled else alive)
            continue
        rec.visit(node, depth, ENTERED, alive)
        near_child, far_child = _children(bvh, order, near, node)
        stack.append((far_child, depth + 1))
        stack.append((near_child, depth + 1))


def _walk_ranged(bvh, tris, rf, ri, near, order, fr, cull, n_simd, live, any_hit, rec, hit_leaf):
    stack = [(0, 0, 0)] if live > 0 else []
    while stack and live > 0:
        node, ia_in, depth = stack.pop()
        ia, _ = _first_hit(rf, ia_in, n_simd, bvh.bmin, bvh.bmax, node, fr, cull)
        masks = _masks(rf, ia_in, n_simd, bvh.bmin, bvh.bmax, node)
        alive = _popcount(masks)
        if ia >= n_simd:
            culled = (cull and ia_in < n_simd and masks[0] == 0
                      and _frustum_misses(fr, bvh.bmin, bvh.bmax, node))
            rec.visit(node, depth, CULLED if culled else MISSED, 0 if culled else alive)
            continue
        rec.visit(node, depth, ENTERED, alive)
        if bvh.count[node] > 0:
            ie, _ = _last_hit(rf, ia, n_simd, bvh.bmin, bvh.bmax, node)
            simds = list(range(ia, ie))
            live -= _leaf(bvh, tris, rf, ri, fr, cull, node, simds, [0xF] * len(simds), any_hit, rec, hit_leaf)
            continue
        near_child, far_child = _children(bvh, order, near, node)
        stack.append((far_child, ia, depth + 1))
        stack.append((near_child, ia, depth + 1))


def _walk_simd(bvh, tris, rf, ri, near, order, fr, cull, n_simd, live, any_hit, rec, hit_leaf):
    for i in range(n_simd):
        lanes = int(_live_masks(rf, n_simd)[i])
        stack = [(0, 0)] if lanes else []
        while stack and lanes:
            node, depth = stack.pop()
            if cull and _frustum_misses(fr, bvh.bmin, bvh.bmax, node):
                rec.visit(node, depth, CULLED, 0)
                continue
            mask = int(_masks(rf, i, i + 1, bvh.bmin, bvh.bmax, node)[0])
            rec.visit(node, depth, ENTERED if mask else MISSED, _popcount([mask]))
            if mask == 0:
                continue
            if bvh.count[node] > 0:
                if _leaf(bvh, tris, rf, ri, fr, cull, node, [i], [mask], any_hit, rec, hit_leaf):
                    lanes = int(_live_masks(rf, n_simd)[i])
                continue
            near_child, far_child = _children(bvh, order, near, node)
            stack.append((far_child, depth + 1))
            stack.append((near_child, depth + 1))


def _ray_walk(bvh, tris, rays, start, n, any_hit, rec, walk) -> PacketTrace:
    depth_of = _node_depths(bvh)
    buffer = np.empty(bvh.first.shape[0], np.int32)
    t = np.full(n, np.inf, np.float32)
    prim = np.full(n, -1, np.int32)
    u = np.zeros(n, np.float32)
    v = np.zeros(n, np.float32)
    hit_leaf = np.full(n, -1, np.int32)
    live = 0
    for lane in range(n):
        r = start + lane
        live += bool(rays.tmin[r] <= rays.tmax[r])
        count, t[lane], prim[lane], u[lane], v[lane], hit_leaf[lane] = _single_walk(
            bvh.bmin, bvh.bmax, bvh.first, bvh.count, bvh.prim, tris.v0, tris.v1, tris.v2,
            rays.org, rays.inv_dir, rays.dir, rays.tmin, rays.tmax, r, any_hit, buffer)
        for node in buffer[:count]:
            node = int(node)
            rec.visit(node, int(depth_of[node]), ENTERED, 1)
            if bvh.count[node] > 0 and node not in rec.leaves:
                f, c = int(bvh.first[node]), int(bvh.count[node])
                rec.leaves[node] = bvh.prim[f:f + c].copy()
    notes = ["embree uses its own BVH: shown is packetrt's BVH walked ray by ray as `single` does"] \
        if walk == "embree" else []
    return PacketTrace("single", start, n, live, np.array(rec.nodes, np.int32), np.array(rec.depth, np.int32),
                       np.array(rec.alive, np.int32), rec.outcome, rec.leaves, rec.pops, hit_leaf, t, prim, u, v, notes)


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
    """The hierarchy ``rayspace`` builds for this batch, and its node over packet k's tile."""
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
