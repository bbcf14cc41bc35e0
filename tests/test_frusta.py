"""Frustum builders (pinhole, pointlight, general): conservative on random packets, invalid where
no frustum can be built.

Conservative means: no ray of the packet hits (by the engine's own slab test and watertight
triangle test) a box or a triangle that the frustum culls. The random geometry is scattered
around points on the rays at the scale of the packet's spread, so a good share of it lies just
outside the frustum, where a wrong plane would show; tiny triangles pierced by the corner rays
probe the margin the builders leave for rounding.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from engine.packet.frustum_build import EMPTY_EXTENT, dominant_axis, grow_extent
from engine.packet.frustum_cull import frustum_misses_box, frustum_misses_triangle, load_frustum
from engine.core.triangle import F32_INF, intersect_triangle, ray_shear, safe_inverse, slab_test
from engine.packet.kernels import node_box
from engine.render.plugins import make_frustum
from engine.core.types import Packets, RayBatch

BUILDERS = ["pinhole", "pointlight", "general"]
RAYS = 64
GEOMETRY = 300


def one_packet(org, direction, tmin, tmax) -> tuple:
    """(RayBatch, Packets) of a single packet over the given rays (f[M,3], f[M,3], f[M], f[M])."""
    org = np.ascontiguousarray(org, np.float32)
    direction = np.ascontiguousarray(direction, np.float32)
    m = len(org)
    rays = RayBatch(org, direction, safe_inverse(direction), np.asarray(tmin, np.float32),
                    np.asarray(tmax, np.float32), np.arange(m, dtype=np.int32), np.ones((m, 3), np.float32),
                    "primary")
    return rays, Packets(np.array([0, m], np.int32), 8, m, 1)


def random_packet(kind: str, rng: np.random.Generator):
    """Rays of one packet as the builder ``kind`` expects them, with a dead lane at the end.

    Returns (rays, packets, spread): spread is the directions' angular spread.
    """
    centre = rng.normal(size=3)
    centre /= np.linalg.norm(centre)
    e1 = np.cross(centre, rng.normal(size=3))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(centre, e1)
    spread = 10.0 ** rng.uniform(-4, -0.5)
    a, b = rng.uniform(-1, 1, (2, RAYS, 1))
    d = centre + spread * (a * e1 + b * e2)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tmin = np.zeros(RAYS)
    tmax = np.full(RAYS, np.inf)
    if kind == "pinhole":
        org = np.tile(rng.uniform(-10, 10, 3), (RAYS, 1))
    elif kind == "pointlight":
        light = rng.uniform(-10, 10, 3).astype(np.float32)
        org = (light + d * rng.uniform(0.5, 20, (RAYS, 1))).astype(np.float32)  # surface points
        to_light = light - org
        tmax = np.linalg.norm(to_light, axis=1) * (1 - 1e-4)
        d = to_light / np.linalg.norm(to_light, axis=1, keepdims=True)
    else:
        org = rng.uniform(-10, 10, 3) + rng.uniform(-1, 1, (RAYS, 3)) * 10.0 ** rng.uniform(-3, 0.5)
    tmin[-1], tmax[-1] = 1.0, 0.0  # a dead lane: ignored by the builders
    rays, packets = one_packet(org, d, tmin, tmax)
    return rays, packets, spread


def extremal_rays(rays, planes):
    """Index of the live ray nearest to each plane (f32[4,4]) at t = 1: the packet's corner rays."""
    live = np.flatnonzero(rays.tmin <= rays.tmax)
    reach = np.minimum(rays.tmax[live], 1.0)[:, None]
    points = (rays.org[live] + reach * rays.dir[live]).astype(np.float64)
    distance = points @ planes[:, :3].T.astype(np.float64) + planes[:, 3]
    return live[np.argmin(distance, axis=0)]


def random_geometry(rays, spread, corner_rays, rng):
    """Boxes (bmin, bmax f32[G,3]) and triangles (v0, v1, v2 f32[G,3]) near points on the rays.

    Boxes and odd triangles are scattered around points on random rays at the packet's scale;
    even triangles are pierced by a corner ray and range from that scale down to 1e-7 of their
    distance, so only the margin the builders leave for rounding keeps them from being culled.
    """
    live = np.flatnonzero(rays.tmin <= rays.tmax)
    pick = rng.choice(live, GEOMETRY)
    pierced = np.arange(GEOMETRY) % 2 == 0
    pick[pierced] = rng.choice(corner_rays, int(pierced.sum()))
    reach = np.minimum(rays.tmax[pick], 30.0)
    t = rng.uniform(0.02, 1.0, GEOMETRY) * reach
    size = (spread * t)[:, None]
    on_ray = rays.org[pick] + t[:, None] * rays.dir[pick]
    centre = on_ray + rng.normal(size=(GEOMETRY, 3)) * size * 1.5
    half = np.abs(rng.normal(size=(GEOMETRY, 3))) * size * 0.3
    hub = np.where(pierced[:, None], on_ray, centre)
    scale = np.where(pierced, 10.0 ** rng.uniform(-7, -2, GEOMETRY) * t, size[:, 0] * 0.3)[:, None]
    corners = [hub + rng.normal(size=(GEOMETRY, 3)) * scale for _ in range(3)]
    as32 = lambda x: np.ascontiguousarray(x, np.float32)
    return as32(centre - half), as32(centre + half), *(as32(c) for c in corners)


@njit(cache=True)
def culled_yet_hit(planes, valid, org, dirs, inv, tmin, tmax, bmin, bmax, v0, v1, v2):
    """(boxes culled, culled boxes some ray hits, triangles culled, culled triangles some ray hits)
    for the single packet's frustum."""
    fr = np.zeros(16, np.float32)
    load_frustum(planes, valid, 0, fr)
    n_rays = org.shape[0]
    boxes = box_errors = tris = tri_errors = 0
    for g in range(bmin.shape[0]):
        if frustum_misses_box(fr, node_box(bmin, bmax, g)):
            boxes += 1
            for r in range(n_rays):
                if slab_test(org[r, 0], org[r, 1], org[r, 2], inv[r, 0], inv[r, 1], inv[r, 2],
                             tmin[r], tmax[r], bmin, bmax, g) < F32_INF:
                    box_errors += 1
                    break
        if frustum_misses_triangle(fr, v0, v1, v2, g):
            tris += 1
            for r in range(n_rays):
                if not tmin[r] <= tmax[r]:
                    continue
                kx, ky, kz, sx, sy, sz = ray_shear(dirs[r, 0], dirs[r, 1], dirs[r, 2])
                t, u, v = intersect_triangle(org[r, kx], org[r, ky], org[r, kz], kx, ky, kz, sx, sy, sz,
                                             tmin[r], tmax[r], v0, v1, v2, g)
                if t < F32_INF:
                    tri_errors += 1
                    break
    return boxes, box_errors, tris, tri_errors


def cull_check(kind, seed):
    rng = np.random.default_rng(seed)
    rays, packets, spread = random_packet(kind, rng)
    # A scene box around everything the geometry below can reach.
    live = rays.tmin <= rays.tmax
    bounds = np.stack([rays.org[live].min(0) - 40, rays.org[live].max(0) + 40]).astype(np.float32)
    frusta = make_frustum(kind).build(rays, packets, bounds)
    assert frusta.valid.tolist() == [True]
    bmin, bmax, v0, v1, v2 = random_geometry(rays, spread, extremal_rays(rays, frusta.planes[0]), rng)
    return culled_yet_hit(frusta.planes, frusta.valid, rays.org, rays.dir, rays.inv_dir, rays.tmin, rays.tmax,
                          bmin, bmax, v0, v1, v2)


@settings(max_examples=60, deadline=None)
@given(kind=st.sampled_from(BUILDERS), seed=st.integers(0, 2 ** 32 - 1))
def test_frustum_is_conservative(kind, seed):
    boxes, box_errors, tris, tri_errors = cull_check(kind, seed)
    assert box_errors == 0, f"{box_errors} of {boxes} culled boxes are hit"
    assert tri_errors == 0, f"{tri_errors} of {tris} culled triangles are hit"


@pytest.mark.parametrize("kind", BUILDERS)
def test_frustum_culls_plenty(kind):
    """Not vacuous: a good share of the geometry near the packet is culled."""
    culled = [cull_check(kind, seed) for seed in range(10)]
    assert sum(c[0] for c in culled) > 0.1 * 10 * GEOMETRY
    assert sum(c[2] for c in culled) > 0.1 * 10 * GEOMETRY


BOUNDS = np.array([[-20, -20, -20], [20, 20, 20]], np.float32)


def all_octants():
    """Unit directions into all eight octants: no axis has one sign for them all."""
    d = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("kind", BUILDERS)
def test_mixed_sign_packets_are_invalid(kind):
    d = all_octants()
    if kind == "pointlight":
        light = np.array([1.0, 2.0, 3.0])
        org = light + 5 * d  # surface points on every side of the light
        rays, packets = one_packet(org, -d, np.zeros(8), np.full(8, 5.0))
    else:
        rays, packets = one_packet(np.tile([0.5, 0.5, 0.5], (8, 1)), d, np.zeros(8), np.full(8, np.inf))
    assert make_frustum(kind).build(rays, packets, BOUNDS).valid.tolist() == [False]


@pytest.mark.parametrize("kind", BUILDERS)
def test_dead_packets_are_invalid(kind):
    rays, packets = one_packet(np.zeros((4, 3)), np.tile([0, 0, 1.0], (4, 1)), np.ones(4), np.zeros(4))
    assert make_frustum(kind).build(rays, packets, BOUNDS).valid.tolist() == [False]


def test_pinhole_needs_one_eye():
    d = np.tile([0.0, 0.0, 1.0], (4, 1))
    org = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0.5, 0, 0]], np.float64)
    rays, packets = one_packet(org, d, np.zeros(4), np.full(4, np.inf))
    assert make_frustum("pinhole").build(rays, packets, BOUNDS).valid.tolist() == [False]


def test_pointlight_needs_one_light():
    org = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float64)
    d = np.tile([0.0, 0.0, 1.0], (4, 1))
    # Parallel rays (a directional light) and rays without an end never meet at one point.
    for tmax in (np.full(4, 5.0), np.full(4, np.inf)):
        rays, packets = one_packet(org, d, np.zeros(4), tmax)
        assert make_frustum("pointlight").build(rays, packets, BOUNDS).valid.tolist() == [False]


@pytest.mark.parametrize("kind", ["pinhole", "general"])
def test_pinhole_or_general_is_pinhole_where_the_rays_share_an_eye_and_general_elsewhere(kind):
    """The mesh queries' builder (``PINHOLE_OR_GENERAL``) gives a packet from one eye the
    pinhole frustum and any other packet the general one, plane for plane."""
    from engine.packet.frustum_builders import GENERAL, PINHOLE, PINHOLE_OR_GENERAL, build_frusta

    rng = np.random.default_rng(7)
    packs = [random_packet(k, rng)[0] for k in ("pinhole", "general", "pinhole", "general")]
    org = np.concatenate([p.org for p in packs])
    dirs = np.concatenate([p.dir for p in packs])
    tmin = np.concatenate([p.tmin for p in packs])
    tmax = np.concatenate([p.tmax for p in packs])
    offsets = np.arange(0, RAYS * len(packs) + 1, RAYS, dtype=np.int32)
    bounds = np.stack([org.min(0) - 40, org.max(0) + 40]).astype(np.float32)

    def frusta(builder):
        planes = np.zeros((len(packs), 4, 4), np.float32)
        valid = np.zeros(len(packs), np.bool_)
        build_frusta(builder, org, dirs, tmin, tmax, offsets, bounds, 2, planes, valid)
        return planes, valid

    both, both_valid = frusta(PINHOLE_OR_GENERAL)
    alone, alone_valid = frusta(PINHOLE if kind == "pinhole" else GENERAL)
    mine = [0, 2] if kind == "pinhole" else [1, 3]
    assert both_valid.all() and alone_valid[mine].all()
    assert np.array_equal(both[mine], alone[mine])
    if kind == "pinhole":
        assert not alone_valid[[1, 3]].any()  # the packets the general builder took over


@njit(cache=True)
def _axis_of(g):
    """The builders' axis choice for the vectors g (f64[m,3]): their extent grown vector by
    vector, as the builders grow it in their gathering pass, then ``dominant_axis``."""
    e0, e1, e2, e3, e4, e5, e6, e7, e8 = EMPTY_EXTENT
    for i in range(g.shape[0]):
        e0, e1, e2, e3, e4, e5, e6, e7, e8 = grow_extent(e0, e1, e2, e3, e4, e5, e6, e7, e8,
                                                         g[i, 0], g[i, 1], g[i, 2])
    return dominant_axis((e0, e1, e2, e3, e4, e5, e6, e7, e8))


def _axis_rule(g):
    """The rule in plain numpy: among the axes along which every vector has one strict sign, the
    one whose summed component is longest; (-1, 0.0) when there is none or a vector is not finite."""
    if not np.isfinite(g).all():
        return -1, 0.0
    best = (-1, 0.0, 0.0)
    for a in range(3):
        total = abs(g[:, a].sum())
        for sign in (1.0, -1.0):
            if (sign * g[:, a] > 0).all() and total > best[2]:
                best = (a, sign, total)
    return best[0], best[1]


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 40), st.integers(0, 2**31 - 1), st.sampled_from(["cone", "scattered", "nonfinite"]))
def test_the_dominant_axis_is_the_longest_axis_along_which_every_vector_has_one_sign(m, seed, kind):
    rng = np.random.default_rng(seed)
    if kind == "cone":  # rays of one packet: around one direction
        g = rng.normal(size=3) + 0.2 * rng.normal(size=(m, 3))
    else:
        g = rng.normal(size=(m, 3))
    if kind == "nonfinite":
        g[rng.integers(m), rng.integers(3)] = rng.choice([np.inf, -np.inf, np.nan])
    axis, sign = _axis_of(np.ascontiguousarray(g))
    assert (axis, sign) == _axis_rule(g)


def _row_views(rays):
    """The rays with org and dir as views of f32[M,4] blocks: rows that are not 12 contiguous
    bytes, which the builders read one ray at a time."""
    def view(a):
        block = np.zeros((a.shape[0], 4), np.float32)
        block[:, :3] = a
        return block[:, :3]
    return rays._replace(org=view(rays.org), dir=view(rays.dir))


@pytest.mark.parametrize("kind", ["pinhole", "pointlight", "general"])
@pytest.mark.parametrize("seed", range(12))
def test_frusta_eight_rays_at_a_time_are_the_ray_by_ray_frusta(kind, seed):
    """The builders' eight-ray passes (``engine.packet.frustum8``) against the ray-by-ray passes
    on the same packets of 64 rays (packets with a foreign origin, a far end point or a NaN
    segment among them): the same validity and the same planes."""
    rng = np.random.default_rng(seed)
    rays, packets, _ = random_packet(kind, rng)
    if seed % 4 == 1:  # a live ray that leaves elsewhere (pinhole) or ends elsewhere (pointlight)
        org = rays.org.copy()
        org[11, 0] += np.float32(0.5)
        rays = rays._replace(org=org)
    if seed % 4 == 2:  # a NaN segment: a dead ray
        tmin = rays.tmin.copy()
        tmin[5] = np.nan
        rays = rays._replace(tmin=tmin)
    if seed % 4 == 3:  # a packet of 12 rays: one block of eight and four one by one
        packets = Packets(np.array([0, 12], np.int32), 8, 12, 1)
        rays = RayBatch(*(a[:12] for a in rays[:-1]), rays.kind)
    eight = make_frustum(kind).build(rays, packets, BOUNDS)
    one_by_one = make_frustum(kind).build(_row_views(rays), packets, BOUNDS)
    assert eight.valid.tolist() == one_by_one.valid.tolist()
    assert np.array_equal(eight.planes, one_by_one.planes)
    if seed % 4 == 1 and kind != "general":  # a general packet has no common point to miss
        assert eight.valid.tolist() == [False]
    elif seed % 4 in (0, 2):
        assert eight.valid.tolist() == [True]
