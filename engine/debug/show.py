"""``packetrt show``: a debugging picture of one packet, rendered offscreen to PNG with Open3D.

    packetrt show [CONFIG] [selectors] [--kind K] [--packet-index I] [--picture WxH] [-o OUT.png]

Renders the configured image once, keeps the ray batch of the chosen kind (its first batch:
depth 1 for reflections and refractions, the first light for shadows) and picks one packet:
``--packet-index``, or by default the packet whose rays' pixels lie nearest the image centre.
That packet's walk is recorded by the traversal kernel itself (``engine.debug.packet_trace``),
and the picture shows

- the scene as a light-grey wireframe (a sample of it for big meshes), the triangles of the
  leaves the packet entered darker, and the triangles its rays hit in orange;
- the packet's rays, from their start to their hit (dark blue) or to where they leave the
  scene or end (light blue);
- its frustum (the four side planes, cut where the rays start and end) in magenta;
- every BVH node it visited as a box coloured by the number of its rays alive there
  (viridis, legend at the left), boxes that no live ray hit in grey, boxes the frustum
  rejected in red.

For the ``auto`` traversal the frustum is drawn in the colour of the strategy ``auto`` chose for
the packet (Masked, Ranged or Partition; ``engine.packet.choose``), and a map in the legend
shows every packet of the batch at its screen tile in the colour of its strategy,
the drawn packet outlined.

For the ``rayspace`` traversal there is no BVH: the picture shows the cone-sphere node over the
packet's screen tile (sphere in green, cone in magenta, cut at the node's reach) and the
triangles that survive the cone-sphere tests down to it, in orange.

Open3D renders on the CPU (Filament on Mesa's lavapipe Vulkan driver, or EGL): no GPU and no
display needed. ``OPEN3D_CPU_RENDERING=true`` is set before Open3D is imported.
"""
from __future__ import annotations

import math
import os
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from engine.core.atomic import replacing
from engine.core.errors import ConfigError, PacketrtError
from engine.core.types import RAY_KINDS, Hits, RayBatch, copied_batch

#: Most scene triangles drawn as wireframe; a bigger scene shows a fixed random sample.
MAX_WIREFRAME_TRIANGLES = 12000
PICTURE_SIZE = (800, 600)
FOV = 40.0
#: The framed region's radius is at least this fraction of the scene's.
MIN_FOCUS = 0.2

GREY = (0.80, 0.80, 0.80)
LEAF_GREY = (0.45, 0.45, 0.45)
HIT_TRIANGLE = (1.0, 0.55, 0.0)
RAY_HIT = (0.05, 0.25, 0.85)
RAY_MISS = (0.55, 0.75, 1.0)
FRUSTUM = (0.85, 0.0, 0.75)
NODE_MISSED = (0.6, 0.62, 0.7)
NODE_CULLED = (0.9, 0.15, 0.15)
SPHERE = (0.0, 0.6, 0.2)
COLORMAP = "viridis"
#: ``auto``'s strategies, in the frustum and the packet map.
STRATEGY_COLOURS = {"masked": (0.55, 0.35, 0.15), "ranged": (0.15, 0.65, 0.2), "partition": (0.0, 0.5, 0.6)}
NO_PACKET = (0.93, 0.93, 0.93)
#: Largest side of the packet map, pixels.
MAP_SIDE = 96


@dataclass
class Picture:
    """Everything drawn: Open3D-free geometry, so it can be tested without rendering.

    lines: list of (name, points f64[P,3], segments i32[L,2], colours f64[L,3], width px).
    focus: f64[2,3] the box the camera frames; view_dir: unit vector from the focus to the eye.
    legend: lines of text; scale: (label, maximum) of the node colour bar, or None.
    keys: [(colour, label)] for the legend swatches.
    tiles: f64[TY,TX,3] a screen map of the batch's packets coloured by ``auto``'s choice, or
        None; tile: (tx, ty) of the drawn packet in it.
    """

    lines: list = field(default_factory=list)
    focus: np.ndarray = None
    view_dir: np.ndarray = None
    up: np.ndarray = None
    legend: list = field(default_factory=list)
    scale: tuple = None
    keys: list = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    tiles: np.ndarray = None
    tile: tuple = None


# -- choosing the packet ---------------------------------------------------------------------

class CapturedBatch(NamedTuple):
    """The first batch of one ray kind a render cast: its rays and packets, its query
    ("intersect" or "occluded") and answer (Hits or bool[R]), how many batches of that kind the
    render cast, and whether the render walked it from the rays' far ends (a shadow batch walked
    from the light, ``[render] shadow_order``)."""

    rays: RayBatch
    packets: object
    query: str
    answer: object
    n_batches: int
    from_end: bool


def capture_batch(renderer, kind: str):
    """Render once; the CapturedBatch of the first batch of ``kind``, or None when the render
    cast no ray of that kind."""
    seen = []

    def observer(k, query, rays, packets, answer, from_end=False):
        if k == kind:
            if not seen:
                # The renderer reuses its per-lane arrays for later batches: keep copies of the first.
                rays, packets = copied_batch(rays, packets)
                answer = Hits(*(np.array(a) for a in answer)) if query == "intersect" else np.array(answer)
            seen.append((rays, packets, query, answer, bool(from_end)))

    observer.wants_walk_order = True
    previous = renderer.observer
    renderer.observer = observer
    try:
        renderer.render()
    finally:
        renderer.observer = previous
    if not seen:
        return None
    rays, packets, query, answer, from_end = seen[0]
    return CapturedBatch(rays, packets, query, answer, len(seen), from_end)


def centre_packet(rays, packets) -> int:
    """The packet whose live rays' mean pixel lies nearest the image centre."""
    offsets = np.asarray(packets.offsets, np.int64)
    owner = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    live = (rays.pixel >= 0) & (rays.tmin <= rays.tmax)
    x = (rays.pixel % packets.width).astype(np.float64)
    y = (rays.pixel // packets.width).astype(np.float64)
    counts = np.bincount(owner[live], minlength=len(offsets) - 1)
    mx = np.bincount(owner[live], x[live], minlength=len(offsets) - 1) / np.maximum(counts, 1)
    my = np.bincount(owner[live], y[live], minlength=len(offsets) - 1) / np.maximum(counts, 1)
    dist = (mx - packets.width / 2) ** 2 + (my - packets.height / 2) ** 2
    dist[counts == 0] = np.inf
    return int(np.argmin(dist))


def packet_tiles(rays, packets) -> np.ndarray:
    """i64[K,2]: each packet's screen tile (tx, ty) from its first live ray's pixel, (-1, -1)
    for a packet without one."""
    offsets = np.asarray(packets.offsets, np.int64)
    out = np.full((len(offsets) - 1, 2), -1, np.int64)
    live = (rays.pixel >= 0) & (rays.tmin <= rays.tmax)
    for k in range(len(offsets) - 1):
        pixels = rays.pixel[offsets[k]:offsets[k + 1]][live[offsets[k]:offsets[k + 1]]]
        if pixels.size:
            p = int(pixels.min())
            out[k] = (p % packets.width) // packets.size, (p // packets.width) // packets.size
    return out


def choice_map(rays, packets, choices) -> np.ndarray:
    """f64[TY,TX,3]: the screen's packet tiles coloured by the strategy each packet was given
    (choices i8[K], ``engine.packet.strategies`` numbers); tiles without a packet in NO_PACKET."""
    from engine.packet.strategies import CHOSEN_NAMES

    tiles = packet_tiles(rays, packets)
    ty = -(-packets.height // packets.size)
    tx = -(-packets.width // packets.size)
    out = np.tile(np.asarray(NO_PACKET, np.float64), (ty, tx, 1))
    for (x, y), choice in zip(tiles.tolist(), choices.tolist()):
        if x >= 0:
            out[y, x] = STRATEGY_COLOURS[CHOSEN_NAMES[choice]]
    return out


# -- geometry -------------------------------------------------------------------------------

def box_lines(bmin, bmax):
    """(points f64[8B,3], segments i32[12B,2]) of B boxes."""
    bmin, bmax = np.asarray(bmin, np.float64).reshape(-1, 3), np.asarray(bmax, np.float64).reshape(-1, 3)
    corner = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64)
    points = bmin[:, None, :] + corner[None] * (bmax - bmin)[:, None, :]
    edges = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7],
                      [0, 4], [1, 5], [2, 6], [3, 7]], np.int32)
    segments = (edges[None] + 8 * np.arange(len(bmin))[:, None, None]).reshape(-1, 2)
    return points.reshape(-1, 3), segments.astype(np.int32)


def triangle_lines(tris, which):
    """(points, segments) of the edges of triangles ``which``."""
    which = np.asarray(which, np.int64)
    points = np.stack([tris.v0[which], tris.v1[which], tris.v2[which]], axis=1).reshape(-1, 3).astype(np.float64)
    base = 3 * np.arange(len(which))[:, None, None]
    segments = (np.array([[0, 1], [1, 2], [2, 0]])[None] + base).reshape(-1, 2)
    return points, segments.astype(np.int32)


def ray_segments(rays, start, stop, t_end, bounds):
    """(p0 f64[M,3], p1 f64[M,3], lanes i64[M]) of the packet's live rays: from org + tmin dir to
    org + t_end dir, where an infinite t_end is cut where the ray leaves the scene box."""
    lanes = np.flatnonzero((rays.tmin[start:stop] <= rays.tmax[start:stop]) & (rays.pixel[start:stop] >= 0))
    r = start + lanes
    org = rays.org[r].astype(np.float64)
    d = rays.dir[r].astype(np.float64)
    t0 = np.maximum(rays.tmin[r].astype(np.float64), 0.0)
    t1 = np.asarray(t_end, np.float64)[lanes]
    t1 = np.minimum(t1, rays.tmax[r].astype(np.float64))
    lo, hi = np.asarray(bounds, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (lo - org) / d
        b = (hi - org) / d
    exit_t = np.nanmin(np.where(np.isnan(np.maximum(a, b)), np.inf, np.maximum(a, b)), axis=1)
    diag = float(np.linalg.norm(hi - lo))
    fallback = np.where(np.isfinite(exit_t) & (exit_t > t0), exit_t, t0 + 0.3 * diag / np.linalg.norm(d, axis=1))
    t1 = np.where(np.isfinite(t1), t1, fallback)
    return org + t0[:, None] * d, org + t1[:, None] * d, lanes


def dominant_axis(d):
    """(axis, sign) along which every direction in d (f[M,3]) has one strict sign, the longest
    summed one; (-1, 0) when none."""
    best, sign, size = -1, 0.0, 0.0
    for a in range(3):
        col = d[:, a]
        if (np.all(col > 0) or np.all(col < 0)) and abs(col.sum()) > size:
            best, sign, size = a, float(np.sign(col[0])), abs(col.sum())
    return best, sign


def frustum_corners(planes, p0, p1, d):
    """The frustum (4 side planes f32[4,4], rows u-low, u-high, v-low, v-high) cut by the two
    planes across the rays' dominant axis through their nearest start and farthest end.
    Returns f64[8,3] (near quad, far quad) or None when the rays have no dominant axis."""
    axis, sign = dominant_axis(d)
    if axis < 0:
        return None
    w_near = float((sign * p0[:, axis]).min())
    w_far = float((sign * p1[:, axis]).max())
    corners = []
    for w in (w_near, w_far):
        for p, q in ((0, 2), (1, 2), (1, 3), (0, 3)):
            m = np.array([planes[p, :3], planes[q, :3], np.eye(3)[axis] * sign], np.float64)
            rhs = np.array([-planes[p, 3], -planes[q, 3], w], np.float64)
            try:
                corners.append(np.linalg.solve(m, rhs))
            except np.linalg.LinAlgError:
                return None
    return np.array(corners)


def frustum_segments():
    return np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                     [0, 4], [1, 5], [2, 6], [3, 7]], np.int32)


def circle(centre, normal, radius, steps=48):
    """Points f64[steps,3] on a circle."""
    normal = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    helper = np.array([1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.array([0, 1.0, 0])
    a = np.cross(normal, helper)
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    angle = np.linspace(0, 2 * np.pi, steps, endpoint=False)
    return np.asarray(centre) + radius * (np.cos(angle)[:, None] * a + np.sin(angle)[:, None] * b)


def ring_segments(n, offset=0):
    i = np.arange(n)
    return np.stack([i, (i + 1) % n], axis=1).astype(np.int32) + offset


def cone_sphere_lines(centre, radius, axis, alpha, far):
    """(sphere points, segments), (cone points, segments) of a cone-sphere node."""
    centre = np.asarray(centre, np.float64)
    axis = np.asarray(axis, np.float64) / max(np.linalg.norm(axis), 1e-30)
    sphere_pts, sphere_seg = [], []
    if radius > 0:
        for normal in np.eye(3):
            ring = circle(centre, normal, radius)
            sphere_seg.append(ring_segments(len(ring), sum(len(p) for p in sphere_pts)))
            sphere_pts.append(ring)
    # The cone's rim where it reaches ``far`` (a spread past 90 degrees is drawn at 90).
    shown = min(alpha, math.radians(89.0))
    length = far * math.cos(shown)
    rim = circle(centre + axis * length, axis, max(far * math.sin(shown), 1e-6 * far), 32)
    cone_pts = np.vstack([centre[None], rim])
    spokes = np.array([[0, 1 + 4 * i] for i in range(8)], np.int32)
    cone_seg = np.vstack([spokes, ring_segments(len(rim), 1)])
    if sphere_pts:
        return (np.vstack(sphere_pts), np.vstack(sphere_seg)), (cone_pts, cone_seg)
    return None, (cone_pts, cone_seg)


def node_colours(alive, live):
    """f64[V,3] colours of the viridis map for alive / live."""
    from matplotlib import colormaps

    fraction = np.clip(np.asarray(alive, np.float64) / max(live, 1), 0, 1)
    return colormaps[COLORMAP](0.1 + 0.9 * fraction)[:, :3]


def scene_wireframe(tris, emphasis=(), hits=()):
    """Wireframe line sets: (sampled) scene light grey, ``emphasis`` triangles darker, ``hits``
    orange."""
    n = tris.v0.shape[0]
    which = np.arange(n)
    sampled = n > MAX_WIREFRAME_TRIANGLES
    if sampled:
        which = np.sort(np.random.default_rng(0).choice(n, MAX_WIREFRAME_TRIANGLES, replace=False))
    out = []
    pts, seg = triangle_lines(tris, which)
    out.append(("scene", pts, seg, np.tile(GREY, (len(seg), 1)), 1.0))
    emphasis = np.setdiff1d(np.asarray(emphasis, np.int64), np.asarray(hits, np.int64))
    if emphasis.size:
        pts, seg = triangle_lines(tris, emphasis)
        out.append(("leaf-triangles", pts, seg, np.tile(LEAF_GREY, (len(seg), 1)), 1.5))
    hits = np.unique(np.asarray(hits, np.int64))
    if hits.size:
        pts, seg = triangle_lines(tris, hits)
        out.append(("hit-triangles", pts, seg, np.tile(HIT_TRIANGLE, (len(seg), 1)), 2.5))
    return out, sampled


def _ray_lines(p0, p1, hit):
    pts = np.vstack([p0, p1])
    seg = np.stack([np.arange(len(p0)), len(p0) + np.arange(len(p0))], axis=1).astype(np.int32)
    colours = np.where(np.asarray(hit)[:, None], RAY_HIT, RAY_MISS)
    return ("rays", pts, seg, colours, 1.0)


def _view(p0, p1, up_hint):
    """A three-quarter side view of the packet: from the side of its mean direction, a little
    above and behind its start."""
    d = (p1 - p0).sum(axis=0)
    d = d / max(np.linalg.norm(d), 1e-30)
    up = np.asarray(up_hint, np.float64)
    side = np.cross(d, up)
    if np.linalg.norm(side) < 1e-6:
        side = np.cross(d, [1.0, 0, 0] if abs(d[0]) < 0.9 else [0, 0, 1.0])
    side /= np.linalg.norm(side)
    up = np.cross(side, d)
    view = 0.8 * side + 0.45 * up - 0.4 * d
    return view / np.linalg.norm(view), up


def build_picture(scene, config, kind: str, packet_index=None, renderer=None) -> Picture:
    """Everything ``packetrt show`` draws for one packet (see the module doc)."""
    from engine.debug.packet_trace import PACKET_WALKS, RAY_WALKS, rayspace_node, trace_packet
    from engine.render.plugins import make_traversal
    from engine.render.whitted import WhittedRenderer

    if kind not in RAY_KINDS:
        raise ConfigError(f"--kind must be one of {', '.join(RAY_KINDS)}, got {kind!r}")
    renderer = renderer or WhittedRenderer(scene, config)
    captured = capture_batch(renderer, kind)
    if captured is None:
        secondary = kind in ("reflection", "refraction")
        if secondary and config.render.max_depth == 0:  # no generation after the camera rays
            hint = "max depth 0 casts camera rays only; give --depth 1 or more"
        else:
            hint = {"shadow": "the scene has no lights or nothing is lit",
                    "reflection": "no material reflects; try --override reflective",
                    "refraction": "no material refracts; try --override refractive"}.get(kind, "")
            hint += f", max depth {config.render.max_depth}" if secondary else ""
        raise PacketrtError(f"this render of {scene.name!r} casts no {kind} rays ({hint})")
    rays, packets, query, answer, n_batches, from_end = captured
    n_packets = len(packets.offsets) - 1
    if packet_index is None:
        k = centre_packet(rays, packets)
    elif not 0 <= packet_index < n_packets:
        raise PacketrtError(f"--packet-index {packet_index} is out of range: the first {kind} batch has "
                            f"{n_packets} packets (valid 0..{n_packets - 1})")
    else:
        k = packet_index
    start, stop = int(packets.offsets[k]), int(packets.offsets[k + 1])
    traversal = config.traversal.get(kind)
    frustum_name = config.frustum.get(kind)
    frusta = renderer.tracer.frusta_for(kind, rays, packets)
    any_hit = query == "occluded"
    tris, bvh = renderer.tris, renderer.bvh
    pic = Picture()
    live_pixels = rays.pixel[start:stop][(rays.pixel[start:stop] >= 0) & (rays.tmin[start:stop] <= rays.tmax[start:stop])]
    if live_pixels.size == 0:
        # A shadow batch walked in its parent's lanes keeps the packets of tiles none of whose
        # lanes casts a ray (all of them dead).
        raise PacketrtError(f"{kind} packet {k} of the first {kind} batch has no live ray (no lane of its tile "
                            f"casts one); choose another --packet-index")
    tile = (int(live_pixels.min() % packets.width) // packets.size, int(live_pixels.min() // packets.width) // packets.size)
    pic.legend.append(f"{scene.name} ({scene.n_triangles:,} triangles), {config.render.width}x{config.render.height}")
    pic.legend.append(f"{kind} packet {k} of {n_packets} ({packets.size}x{packets.size} tile {tile[0]},{tile[1]})"
                      + (f", first of {n_batches} {kind} batches" if n_batches > 1 else ""))

    if traversal == "rayspace":
        node = rayspace_node(tris, rays, packets, k)
        if any_hit:
            hit = np.asarray(answer[start:stop])
            t_end = np.where(hit, np.inf, rays.tmax[start:stop])  # occluder unknown: draw the whole segment
            hit_prims = np.zeros(0, np.int64)
        else:
            hit = answer.prim[start:stop] >= 0
            t_end = answer.t[start:stop]
            hit_prims = answer.prim[start:stop][hit]
        p0, p1, lanes = ray_segments(rays, start, stop, t_end, renderer.bounds)
        wire, sampled = scene_wireframe(tris, emphasis=[], hits=hit_prims)
        pic.lines += wire
        pts, seg = triangle_lines(tris, node.survivors)
        pic.lines.append(("survivors", pts, seg, np.tile(HIT_TRIANGLE, (len(seg), 1)), 2.0))
        pic.lines.append(_ray_lines(p0, p1, hit[lanes]))
        # The cone is drawn as far as the packet's rays go (an unbounded ray has an infinite reach).
        reach = float(np.linalg.norm(np.vstack([p0, p1]) - node.centre, axis=1).max()) if len(p0) else 1.0
        sphere, cone = cone_sphere_lines(node.centre, node.radius, node.axis, node.alpha, min(node.far, reach))
        if sphere is not None:
            pic.lines.append(("sphere", sphere[0], sphere[1], np.tile(SPHERE, (len(sphere[1]), 1)), 2.0))
        pic.lines.append(("cone", cone[0], cone[1], np.tile(FRUSTUM, (len(cone[1]), 1)), 2.0))
        pic.legend.append(f"traversal rayspace: cone-sphere node level {node.level} of {node.levels}"
                          + (" (shadow rays reversed from the light)" if node.reversed else ""))
        pic.legend.append(f"{len(lanes)} live rays, {int(hit[lanes].sum())} "
                          f"{'occluded' if any_hit else 'hit'}; {node.survivors.size:,} of {tris.v0.shape[0]:,} "
                          f"triangles survive to the node")
        pic.legend.append("survivors per level, root down: " + ", ".join(f"{c:,}" for c in node.per_level))
        plugin = renderer.tracer.traversal[kind]
        grid = getattr(plugin, "shadow_grid" if kind == "shadow" else "secondary_grid", "pixel")
        if kind != "primary" and grid != "pixel":
            # The render grouped these rays by direction; a node over a screen tile exists only
            # in the paper's pixel layout, which this view builds for the batch.
            option = "shadow_grid" if kind == "shadow" else "secondary_grid"
            pic.legend.append(f"shown in the paper's pixel layout; the render grouped these rays by {option} = "
                              f"{grid!r} (same answers, other nodes)")
        pic.keys = [(RAY_HIT, "ray to its hit" if not any_hit else "occluded ray"),
                    (RAY_MISS, "missing ray" if not any_hit else "unoccluded ray"),
                    (HIT_TRIANGLE, "surviving triangle"), (SPHERE, "node sphere"), (FRUSTUM, "node cone")]
        cone_pts = cone[0]
        focus_pts = [p0, p1, cone_pts[:1]]
        if node.survivors.size and node.survivors.size < 2000:
            focus_pts.append(pts)
        pic.summary = {"packet": k, "packets": n_packets, "traversal": "rayspace", "live": int(len(lanes)),
                       "survivors": int(node.survivors.size), "level": node.level}
    else:
        tracer = renderer.tracer
        if traversal not in PACKET_WALKS + RAY_WALKS:   # a plugin we cannot follow: shown as `single`
            tracer = tracer.with_traversal({**tracer.traversal, kind: make_traversal("single")})
        trace = trace_packet(tracer, kind, rays, packets, k, any_hit, from_end)
        hit = trace.prim >= 0
        t_end = trace.t if not any_hit else np.where(hit, trace.t, rays.tmax[start:stop])
        p0, p1, lanes = ray_segments(rays, start, stop, t_end, renderer.bounds)
        leaves = [int(n) for n, o in zip(trace.nodes, trace.outcome) if o == "entered" and bvh.count[n] > 0]
        leaf_tris = np.unique(np.concatenate([trace.leaves[n] for n in leaves])) if leaves else np.zeros(0, np.int64)
        wire, sampled = scene_wireframe(tris, emphasis=leaf_tris, hits=trace.prim[hit])
        pic.lines += wire
        outcome = np.array(trace.outcome)
        for label, mask, colour, width in (("missed-nodes", outcome == "missed", NODE_MISSED, 1.0),
                                           ("culled-nodes", outcome == "culled", NODE_CULLED, 1.0)):
            if mask.any():
                pts, seg = box_lines(bvh.bmin[trace.nodes[mask]], bvh.bmax[trace.nodes[mask]])
                pic.lines.append((label, pts, seg, np.tile(colour, (len(seg), 1)), width))
        entered = outcome == "entered"
        is_leaf = bvh.count[trace.nodes] > 0
        for label, mask, width in (("nodes", entered & ~is_leaf, 1.5), ("leaf-nodes", entered & is_leaf, 2.5)):
            if mask.any():
                pts, seg = box_lines(bvh.bmin[trace.nodes[mask]], bvh.bmax[trace.nodes[mask]])
                colours = np.repeat(node_colours(trace.alive[mask], trace.live), 12, axis=0)
                pic.lines.append((label, pts, seg, colours, width))
        pic.lines.append(_ray_lines(p0, p1, hit[lanes]))
        # A traversal that takes no frusta (single, wide, embree) was culled by none.
        takes_frusta = getattr(renderer.tracer.traversal[kind], "uses_frusta", True)
        from_light = bool(from_end and renderer.tracer.orders_any_hit(kind))
        fvalid = takes_frusta and frusta is not None and bool(frusta.valid[k])
        chosen = None
        plugin = renderer.tracer.traversal[kind]
        if hasattr(plugin, "choose"):   # auto: which strategy walked each packet of the batch
            from engine.packet.strategies import CHOSEN_NAMES

            choices = plugin.choose(bvh, rays, packets, frusta)
            chosen = CHOSEN_NAMES[int(choices[k])]
            pic.tiles, pic.tile = choice_map(rays, packets, choices), tile
            per = np.bincount(choices, minlength=len(CHOSEN_NAMES))
            pic.legend.append(f"auto walked this packet by {chosen}; the batch's {n_packets} packets: "
                              + ", ".join(f"{int(per[i])} {name}" for i, name in enumerate(CHOSEN_NAMES)))
        frustum_colour = FRUSTUM if chosen is None else STRATEGY_COLOURS[chosen]
        corners = frustum_corners(frusta.planes[k], p0, p1, rays.dir[start + lanes]) if fvalid and len(lanes) else None
        if corners is not None:
            pic.lines.append(("frustum", corners, frustum_segments(), np.tile(frustum_colour, (12, 1)), 1.5))
        counts = {o: int((outcome == o).sum()) for o in ("entered", "missed", "culled")}
        walk_note = "" if trace.walk == traversal else f" (walked as {trace.walk})"
        pic.legend.append(f"traversal {traversal}{walk_note}, "
                          + (f"frustum {frustum_name}" + ("" if fvalid else " (none built for this packet)")
                             if takes_frusta else "no frustum (this traversal culls with none)")
                          + (", walked from the light (shadow_order)" if from_light else ""))
        pic.legend.append(f"{trace.live} live rays, {int(hit.sum())} {'occluded' if any_hit else 'hit'}; "
                          f"{len(trace.nodes)} nodes visited: {counts['entered']} entered, "
                          f"{counts['missed']} missed, {counts['culled']} culled")
        pic.legend += trace.notes
        pic.scale = ("live rays at node" if trace.walk != "single" else "rays through node", trace.live)
        pic.keys = [(RAY_HIT, "ray to its hit" if not any_hit else "occluded ray"),
                    (RAY_MISS, "missing ray" if not any_hit else "unoccluded ray"),
                    (FRUSTUM, "frustum"), (HIT_TRIANGLE, "hit triangle"),
                    (LEAF_GREY, "triangles of entered leaves"), (NODE_MISSED, "node no ray hit"),
                    (NODE_CULLED, "node culled by frustum")]
        if chosen is not None:
            pic.keys[2:3] = [(STRATEGY_COLOURS[name], f"auto: {name} (frustum, map)") for name in STRATEGY_COLOURS]
        elif not takes_frusta:
            pic.keys.remove((FRUSTUM, "frustum"))
        # Framed on where the packet meets geometry: its rays' ends and the leaves it entered
        # (rays from a far-away camera come in from the side of the picture).
        focus_pts = [p1]
        if leaves:
            focus_pts.append(bvh.bmin[leaves])
            focus_pts.append(bvh.bmax[leaves])
        pic.summary = {"packet": k, "packets": n_packets, "traversal": traversal, "walk": trace.walk,
                       "live": trace.live, "visited": len(trace.nodes), **counts,
                       "frustum_valid": fvalid, "hits": int(hit.sum()),
                       "from_light": from_light,
                       **({} if chosen is None else {"auto_choice": chosen})}
    if sampled:
        pic.legend.append(f"scene wireframe: {MAX_WIREFRAME_TRIANGLES:,} sampled triangles")
    allpts = np.vstack([np.asarray(p, np.float64).reshape(-1, 3) for p in focus_pts])
    centre = (allpts.min(axis=0) + allpts.max(axis=0)) / 2
    lo, hi = np.asarray(renderer.bounds, np.float64)
    # At least a little scene around it, for context.
    radius = max(float(np.linalg.norm(allpts.max(axis=0) - allpts.min(axis=0))) / 2 * 1.15,
                 MIN_FOCUS * float(np.linalg.norm(hi - lo)) / 2)
    pic.focus = np.stack([centre - radius / math.sqrt(3), centre + radius / math.sqrt(3)])
    if len(p0):
        pic.view_dir, pic.up = _view(p0, p1, scene.camera.basis()[3])
    else:
        eye, forward, right, up = scene.camera.basis()
        pic.view_dir, pic.up = -forward, up
    return pic


# -- rendering -----------------------------------------------------------------------------

@contextmanager
def _quiet_native_output():
    """Send the native libraries' chatter on stdout (Open3D's and Filament's start-up lines) to
    a file while rendering. Their stderr stays: a fatal native error (an abort in the Vulkan
    set-up, say) still says why."""
    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile(mode="w+b") as sink:
        os.dup2(sink.fileno(), 1)
        try:
            yield
        finally:
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(saved)


def import_open3d():
    """Open3D, set up for CPU rendering (the variable must be set before the import)."""
    os.environ.setdefault("OPEN3D_CPU_RENDERING", "true")
    try:
        import open3d as o3d
    except (ImportError, OSError) as exc:
        raise PacketrtError(f"Open3D is not available ({exc}); `pip install open3d` and, on Debian, "
                            f"`apt-get install libusb-1.0-0`") from None
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def render_lines(lines, focus, view_dir, up, size) -> np.ndarray:
    """Render line sets offscreen: u8[H,W,3] on white, camera framing ``focus`` from
    ``view_dir``."""
    o3d = import_open3d()
    rendering = o3d.visualization.rendering
    width, height = size
    with _quiet_native_output():
        try:
            renderer = rendering.OffscreenRenderer(width, height)
        except RuntimeError as exc:
            renderer = exc
    if isinstance(renderer, RuntimeError):
        detail = str(renderer)
        hint = (" (Open3D renders through Vulkan: on Debian install libvulkan1 and mesa-vulkan-drivers "
                "for CPU rendering)" if "vulkan" in detail.lower() else "")
        raise PacketrtError(f"Open3D could not start its offscreen renderer: {detail}{hint}")
    with _quiet_native_output():
        scene = renderer.scene
        scene.set_background([1.0, 1.0, 1.0, 1.0])
        scene.view.set_post_processing(False)  # exact colours: no tone mapping
        for name, pts, seg, colours, line_width in lines:
            if len(seg) == 0:
                continue
            ls = o3d.geometry.LineSet(o3d.utility.Vector3dVector(np.asarray(pts, np.float64)),
                                      o3d.utility.Vector2iVector(np.asarray(seg, np.int32)))
            ls.colors = o3d.utility.Vector3dVector(np.asarray(colours, np.float64))
            material = rendering.MaterialRecord()
            material.shader = "unlitLine"
            material.line_width = float(line_width)
            scene.add_geometry(name, ls, material)
        centre = focus.mean(axis=0)
        radius = max(float(np.linalg.norm(focus[1] - focus[0])) / 2, 1e-6)
        aspect = width / height
        fit = math.tan(math.radians(FOV) / 2) * min(1.0, aspect)
        eye = centre + view_dir * radius / fit * 1.08
        renderer.setup_camera(FOV, centre, eye, up)
        near, far = max(radius * 1e-3, 1e-4), radius * 100 + float(np.linalg.norm(eye - centre))
        renderer.scene.camera.set_projection(FOV, aspect, near, far, rendering.Camera.FovType.Vertical)
        image = np.asarray(renderer.render_to_image()).copy()
    return image[..., :3]


# -- legend ----------------------------------------------------------------------------------

def _font(size):
    from PIL import ImageFont

    try:
        from matplotlib import font_manager

        return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size)
    except Exception:  # noqa: BLE001 -- any font will do
        return ImageFont.load_default()


def legend_height(pic: Picture) -> int:
    """Pixels of the legend band above the rendering."""
    return (10 + 16 * len(pic.legend) + 14 * ((len(pic.keys) + 2) // 3) + (30 if pic.scale else 0) + 6
            + (_map_cell(pic) * pic.tiles.shape[0] + 8 if pic.tiles is not None else 0))


def _map_cell(pic: Picture) -> int:
    """Pixels per packet tile of the packet map."""
    return max(1, MAP_SIDE // max(pic.tiles.shape[:2]))


def compose(image: np.ndarray, pic: Picture) -> np.ndarray:
    """The legend band (text, colour keys, the node colour bar) above the rendering."""
    from matplotlib import colormaps
    from PIL import Image, ImageDraw

    band = legend_height(pic)
    canvas = Image.new("RGB", (image.shape[1], image.shape[0] + band), (255, 255, 255))
    canvas.paste(Image.fromarray(image), (0, band))
    draw = ImageDraw.Draw(canvas)
    font, small = _font(13), _font(11)
    x, y = 8, 6
    for line in pic.legend:
        draw.text((x, y), line, fill=(0, 0, 0), font=font)
        y += 16
    y += 2
    column = (image.shape[1] - 16) // 3
    for i, (colour, label) in enumerate(pic.keys):
        cx = x + (i % 3) * column
        draw.rectangle([cx, y + 4, cx + 18, y + 8], fill=tuple(int(255 * c) for c in colour))
        draw.text((cx + 24, y - 1), label, fill=(0, 0, 0), font=small)
        if i % 3 == 2 or i == len(pic.keys) - 1:
            y += 14
    if pic.scale:
        label, top = pic.scale
        y += 4
        draw.text((x, y), label, fill=(0, 0, 0), font=small)
        bar_x, bar_w = x + 120, 240
        cmap = colormaps[COLORMAP]
        for i in range(bar_w):
            rgb = tuple(int(255 * c) for c in cmap(0.1 + 0.9 * i / (bar_w - 1))[:3])
            draw.line([bar_x + i, y + 1, bar_x + i, y + 10], fill=rgb)
        for value, at in ((0, 0), (top / 2, 0.5), (top, 1.0)):
            text = f"{value:g}"
            draw.text((bar_x + at * bar_w - draw.textlength(text, font=small) * at, y + 12), text,
                      fill=(0, 0, 0), font=small)
    if pic.tiles is not None:
        _draw_map(canvas, draw, pic, x, y + (30 if pic.scale else 0) + 4)
    draw.line([0, band - 1, image.shape[1], band - 1], fill=(200, 200, 200))
    return np.asarray(canvas)


def _draw_map(canvas, draw, pic: Picture, x0: int, y0: int) -> None:
    """The packet map (``Picture.tiles``) with its top left at (x0, y0), the drawn packet's
    tile outlined in black."""
    from PIL import Image

    ty, tx = pic.tiles.shape[:2]
    cell = _map_cell(pic)
    tiles = Image.fromarray((255 * pic.tiles).astype(np.uint8)).resize((tx * cell, ty * cell), Image.NEAREST)
    canvas.paste(tiles, (x0, y0))
    draw.rectangle([x0 - 1, y0 - 1, x0 + tx * cell, y0 + ty * cell], outline=(160, 160, 160))
    if pic.tile is not None:
        px, py = pic.tile
        draw.rectangle([x0 + px * cell, y0 + py * cell, x0 + (px + 1) * cell - 1, y0 + (py + 1) * cell - 1],
                       outline=(0, 0, 0))


def write_show(scene, config, kind, packet_index, output, size=PICTURE_SIZE) -> dict:
    """Build, render and write the picture; returns the summary."""
    from PIL import Image

    pic = build_picture(scene, config, kind, packet_index)
    band = legend_height(pic)
    if size[1] - band < 64:
        raise ConfigError(f"--picture {size[0]}x{size[1]} leaves no room below the {band}-pixel legend")
    image = compose(render_lines(pic.lines, pic.focus, pic.view_dir, pic.up, (size[0], size[1] - band)), pic)
    try:
        with replacing(output) as tmp:
            Image.fromarray(image).save(tmp, format="PNG", optimize=True)
    except OSError as exc:
        raise PacketrtError(f"cannot write image {output!r}: {exc.strerror or exc}") from None
    return pic.summary
