"""The cone-sphere ray-space hierarchy of Roger, Assarsson and Holzschuch (2007) and its test.

A node bounds a set of ray segments by

- a sphere (``centre``, ``radius``) holding every ray's origin,
- a cone of directions (unit ``axis``, half-angle ``alpha`` in [0, pi], kept with its
  ``cos_a`` and ``sin_a``) holding every ray's direction; the spread may exceed 90 degrees,
- a reach ``far``: every point of every segment lies within ``far`` of the centre
  (inf for unbounded rays).

Every segment point therefore lies in the cone with apex ``centre`` grown by ``radius``
(Minkowski sum) and inside the ball of radius ``far``. A node with no rays has radius -1.

Layout (mip-map over the screen grid of ancestral pixels, W x H = packets.width x height):

- level 0: one slot per live ray (several rays may share a pixel), grouped by 2x2 pixel block;
  ``slot_ray`` maps a slot to its ray, ``block_start`` gives each block's slots.
- level k >= 1: a dense row-major grid of ceil(W / 2^k) x ceil(H / 2^k) nodes; node (x, y) of
  level k covers pixels [x 2^k, (x+1) 2^k) x [y 2^k, (y+1) 2^k). Its children at level k-1 >= 1
  are (2x+i, 2y+j), i, j in {0, 1}, where inside the grid (implicit, like a mip-map); at
  level 1 its children are the slots of block y * ceil(W/2) + x (see ``children``).
- the root is the single node of level ``levels``.

All node arrays cover every level, level 0 first; level k's nodes are
``level_offset[k] : level_offset[k+1]``. The build computes in float64 and stores float32
with radii, reaches and angles rounded outwards, so a parent holds its children exactly.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

# Outward rounding of float64 lengths before they are stored as float32 (>> one float32 ulp).
GROWTH = 1.0 + 2.0 ** -20
# Angle added to a merged cone so its float32-rounded axis and angle still hold the children
# (radians): storage costs ~1e-7 each; the float64 merge itself is exact to ~1e-14.
ANGLE_SLACK = 2.0 ** -20
# Relative slack of the float32 test: covers its own rounding and the watertight test's
# acceptance of hits a few ulps outside a triangle or past tmax (both ~1e-7 relative).
TEST_SLACK = np.float32(2.0 ** -16)
EMPTY = np.float32(-1.0)


class RayHierarchy(NamedTuple):
    """Cone-sphere hierarchy over one ray batch (M nodes over all levels, S live-ray slots).

    centre: f32[M,3]; radius: f32[M] (-1 = empty); axis: f32[M,3] unit; alpha, cos_a, sin_a:
    f32[M]; far: f32[M].
    level_offset: i64[levels+2]  level k nodes are level_offset[k] : level_offset[k+1].
    level_width, level_height: i64[levels+1]  grid size of level k >= 1 (level 0: S x 1).
    block_start: i64[n1+1]  slots of level-1 block b are block_start[b] : block_start[b+1].
    slot_ray: i32[S]  ray index of each slot.
    levels: int  the root's level (>= 1).
    max_block_rays: int  most slots under one level-1 node.
    """

    centre: np.ndarray
    radius: np.ndarray
    axis: np.ndarray
    alpha: np.ndarray
    cos_a: np.ndarray
    sin_a: np.ndarray
    far: np.ndarray
    level_offset: np.ndarray
    level_width: np.ndarray
    level_height: np.ndarray
    block_start: np.ndarray
    slot_ray: np.ndarray
    levels: int
    max_block_rays: int


# ---------------------------------------------------------------------------------------
# The test
# ---------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def cone_sphere_overlap(h, node, sx, sy, sz, rho, abs_tol):
    """May a segment of node ``node`` (global index) touch the sphere (s, rho)?

    Growing the sphere by the node radius reduces the node to a cone with a point apex; in
    the plane of the cone axis and the sphere centre the cone is a 2D wedge and the test is
    the distance from the centre to the wedge. Conservative: never False when a segment of
    the node meets the sphere. abs_tol: absolute slack for the coordinates' magnitude.
    """
    return node_overlap(h.centre, h.radius, h.axis, h.cos_a, h.sin_a, h.far, node, sx, sy, sz, rho, abs_tol)


@njit(cache=True, inline="always")
def node_overlap(centre, radius, axis, cos_a, sin_a, far, node, sx, sy, sz, rho, abs_tol):
    """``cone_sphere_overlap`` on the node arrays themselves (f32[M,3] / f32[M]), so the CPU
    build and the device (``engine.gpu.rayspace``, through a twin) run the same test."""
    r = radius[node]
    vx = sx - centre[node, 0]
    vy = sy - centre[node, 1]
    vz = sz - centre[node, 2]
    dist = np.sqrt(vx * vx + vy * vy + vz * vz)
    grown = rho + r
    tol = TEST_SLACK * (dist + grown) + abs_tol
    dx, dy, dz = axis[node, 0], axis[node, 1], axis[node, 2]
    a = vx * dx + vy * dy + vz * dz  # along the axis
    # The off-axis part from |v x d|, not sqrt(dist^2 - a^2): no cancellation near the axis.
    cx = vy * dz - vz * dy
    cy = vz * dx - vx * dz
    cz = vx * dy - vy * dx
    b = np.sqrt(cx * cx + cy * cy + cz * cz)
    ca, sa = cos_a[node], sin_a[node]
    # Every clause is evaluated and combined with & and | rather than branched on: the
    # outcome is unpredictable, and a mispredicted branch costs more than the arithmetic.
    reach = dist - rho <= far[node] + tol   # not past the end of every segment
    apex = dist <= grown + tol                # the apex is inside the grown sphere
    # Signed distance to the wedge's edge line, negative inside the cone; it is the distance
    # to the wedge where the nearest wedge point is not the apex (a ca + b sa >= 0), which
    # covers the cone's inside up to 90 degrees from its edge.
    edge = (a * ca + b * sa >= 0) & (b * ca - a * sa <= grown + tol)
    # Deeper inside a spread beyond 90 degrees. No slack here: the clause only decides far
    # from the edge, and a length slack on a cosine would widen a narrow cone by
    # sqrt(2 tol / dist) radians.
    inside = a >= dist * ca
    return (r >= 0) & reach & (apex | edge | inside)


@njit(cache=True, inline="always")
def children(h, level, node):
    """Children of node ``node`` (index within ``level`` >= 1), as indices within level - 1:
    first + jy * stride + jx for jy < ny, jx < nx (empty ones included).

    Level 1: the block's slots (one row). Coarser: the 2x2 nodes below, clipped at the
    grid's edge. One integer division per node, none per child.
    """
    return child_grid(h.block_start, h.level_width, h.level_height, level, node)


@njit(cache=True, inline="always")
def child_grid(block_start, level_width, level_height, level, node):
    """``children`` on the layout arrays themselves (shared with the device build)."""
    if level == 1:
        first = block_start[node]
        return first, block_start[node + 1] - first, 1, 0
    width = level_width[level]
    y = node // width
    x0 = 2 * (node - y * width)
    y0 = 2 * y
    below = level_width[level - 1]
    return y0 * below + x0, min(2, below - x0), min(2, level_height[level - 1] - y0), below


# ---------------------------------------------------------------------------------------
# The build
# ---------------------------------------------------------------------------------------

def level_grid(width: int, height: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(grid widths i64[L+1], grid heights i64[L+1], L) of the mip-map over W x H pixels."""
    widths, heights = [0], [0]
    w, h = width, height
    while True:
        w, h = -(-w // 2), -(-h // 2)
        widths.append(w)
        heights.append(h)
        if w == 1 and h == 1:
            break
    return np.array(widths, np.int64), np.array(heights, np.int64), len(widths) - 1


@njit(cache=True)
def _sort_slots(pixel, tmin, tmax, width, block_width, n_blocks):
    """Counting sort of the live rays by 2x2 pixel block (stable: rays keep batch order).

    Returns (block_start i64[n_blocks+1], slot_ray i32[S]).
    """
    counts = np.zeros(n_blocks + 1, np.int64)
    n_live = 0
    for r in range(pixel.shape[0]):
        if pixel[r] >= 0 and tmin[r] <= tmax[r]:
            b = (pixel[r] // width // 2) * block_width + (pixel[r] % width) // 2
            counts[b + 1] += 1
            n_live += 1
    for b in range(n_blocks):
        counts[b + 1] += counts[b]
    block_start = counts.copy()
    slot_ray = np.empty(n_live, np.int32)
    for r in range(pixel.shape[0]):
        if pixel[r] >= 0 and tmin[r] <= tmax[r]:
            b = (pixel[r] // width // 2) * block_width + (pixel[r] % width) // 2
            slot_ray[counts[b]] = r
            counts[b] += 1
    return block_start, slot_ray


@njit(cache=True)
def store_length(x):
    """float64 length >= 0 -> float32 no smaller (inf stays inf)."""
    return np.float32(x * GROWTH)


@njit(cache=True)
def reversed_segment(org, dirs, tmin, tmax, r, ax, ay, az):
    """Ray r (o + t d, t in [tmin, tmax]) seen from the point a, in float64: (gap, reach).

    The segment is P - s d for s in [tP - tmax, tP - tmin], where P = o + tP d is the point
    of the ray's line nearest a, or the segment's end if that lies further on. gap = |P - a|
    (rounding-small when the ray aims at a); reach bounds |x - a| over the segment. The
    direction must not be zero.
    """
    ox, oy, oz = np.float64(org[r, 0]), np.float64(org[r, 1]), np.float64(org[r, 2])
    dx, dy, dz = np.float64(dirs[r, 0]), np.float64(dirs[r, 1]), np.float64(dirs[r, 2])
    length2 = dx * dx + dy * dy + dz * dz
    tp = max(((ax - ox) * dx + (ay - oy) * dy + (az - oz) * dz) / length2, np.float64(tmax[r]))
    gx, gy, gz = ox + tp * dx - ax, oy + tp * dy - ay, oz + tp * dz - az
    gap = np.sqrt(gx * gx + gy * gy + gz * gz)
    return gap, gap + (tp - np.float64(tmin[r])) * np.sqrt(length2)


@njit(cache=True)
def _leaf_node(h, s, org, dirs, tmin, tmax, reverse, ax, ay, az):
    """Level-0 node of slot ``s``: its exact ray (radius 0, spread 0), or the ray reversed
    to leave the point a.

    Forward: apex at the origin; a negative tmin puts the part behind the origin in the
    sphere. Reversed: apex at a, direction -dir, radius and reach from ``reversed_segment``.
    """
    leaf_node(h.centre, h.radius, h.axis, h.alpha, h.cos_a, h.sin_a, h.far, h.slot_ray, s, org, dirs, tmin, tmax,
              reverse, ax, ay, az)


@njit(cache=True, inline="always")
def leaf_node(centre, radius, axis, alpha, cos_a, sin_a, far, slot_ray, s, org, dirs, tmin, tmax, reverse,
              ax, ay, az):
    """``_leaf_node`` on the node arrays themselves (shared with the device build)."""
    r = slot_ray[s]
    dx, dy, dz = np.float64(dirs[r, 0]), np.float64(dirs[r, 1]), np.float64(dirs[r, 2])
    length = np.sqrt(dx * dx + dy * dy + dz * dz)
    lo, hi = np.float64(tmin[r]), np.float64(tmax[r])
    sign = 1.0
    if reverse and length > 0:
        gap, reach = reversed_segment(org, dirs, tmin, tmax, r, ax, ay, az)
        centre[s, 0] = ax
        centre[s, 1] = ay
        centre[s, 2] = az
        radius[s] = store_length(gap)
        far[s] = store_length(reach)
        sign = -1.0
    else:
        centre[s, 0] = org[r, 0]
        centre[s, 1] = org[r, 1]
        centre[s, 2] = org[r, 2]
        behind = max(0.0, -lo) * length
        radius[s] = store_length(behind)
        # A zero direction reaches nowhere (and 0 * inf would be NaN).
        far[s] = store_length(max(behind, hi * length)) if length > 0 else radius[s]
    if length > 0:
        axis[s, 0] = np.float32(sign * dx / length)
        axis[s, 1] = np.float32(sign * dy / length)
        axis[s, 2] = np.float32(sign * dz / length)
        alpha[s] = 0.0
        cos_a[s] = 1.0
        sin_a[s] = 0.0
    else:  # a zero direction has no cone: allow every direction
        axis[s, 0] = 0.0
        axis[s, 1] = 0.0
        axis[s, 2] = 1.0
        alpha[s] = np.pi
        cos_a[s] = -1.0
        sin_a[s] = 0.0


@njit(cache=True, parallel=True)
def _leaf_nodes(h, org, dirs, tmin, tmax, reverse, ax, ay, az):
    """Every level-0 node (see ``_leaf_node``), parallel over slots.

    The body is a separate function: numba's parfor loses some writes made through a
    named-tuple attribute directly inside a prange body.
    """
    for s in prange(h.slot_ray.shape[0]):
        _leaf_node(h, s, org, dirs, tmin, tmax, reverse, ax, ay, az)


@njit(cache=True)
def grow_sphere(cx, cy, cz, r, ox, oy, oz, orad):
    """Smallest sphere holding the spheres (c, r) and (o, orad), float64."""
    dx, dy, dz = ox - cx, oy - cy, oz - cz
    dist = np.sqrt(dx * dx + dy * dy + dz * dz)
    if dist + orad <= r:
        return cx, cy, cz, r
    if dist + r <= orad:
        return ox, oy, oz, orad
    grown = 0.5 * (dist + r + orad)
    shift = (grown - r) / dist
    return cx + dx * shift, cy + dy * shift, cz + dz * shift, grown


@njit(cache=True)
def grow_cone(ax, ay, az, a, bx, by, bz, b):
    """Smallest cone (about a great-circle blend of the axes) holding cones (A, a) and (B, b)."""
    # Exactly unit axes first: float32-stored ones are off by ~1e-7, and for near-opposite
    # axes the blend below divides by sin(theta), which would magnify that into the angle.
    norm_a = np.sqrt(ax * ax + ay * ay + az * az)
    norm_b = np.sqrt(bx * bx + by * by + bz * bz)
    ax, ay, az = ax / norm_a, ay / norm_a, az / norm_a
    bx, by, bz = bx / norm_b, by / norm_b, bz / norm_b
    crx = ay * bz - az * by
    cry = az * bx - ax * bz
    crz = ax * by - ay * bx
    sin_t = np.sqrt(crx * crx + cry * cry + crz * crz)
    cos_t = ax * bx + ay * by + az * bz
    theta = np.arctan2(sin_t, cos_t)  # accurate for tiny and near-pi angles alike
    if theta + b <= a:
        return ax, ay, az, a
    if theta + a <= b:
        return bx, by, bz, b
    grown = 0.5 * (a + b + theta)
    if grown >= np.pi:
        return ax, ay, az, np.pi
    if sin_t < 1e-12:
        if cos_t > 0:  # axes parallel up to rounding: widening A by theta is enough
            return ax, ay, az, max(a, b) + theta
        return ax, ay, az, np.pi  # opposite axes: no meaningful blend
    phi = grown - a  # rotate A towards B by phi
    wa = np.sin(theta - phi) / sin_t
    wb = np.sin(phi) / sin_t
    nx, ny, nz = wa * ax + wb * bx, wa * ay + wb * by, wa * az + wb * bz
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    return nx / norm, ny / norm, nz / norm, grown


@njit(cache=True)
def _merge_children(h, parent, level, local):
    """Parent node ``parent`` (global) from the children of node ``local`` at ``level`` >= 1."""
    merge_node(h.centre, h.radius, h.axis, h.alpha, h.cos_a, h.sin_a, h.far, h.level_offset, h.block_start,
               h.level_width, h.level_height, parent, level, local)


@njit(cache=True, inline="always")
def merge_node(centre, radius, axis, alpha, cos_a, sin_a, far, level_offset, block_start, level_width,
               level_height, parent, level, local):
    """``_merge_children`` on the node and layout arrays themselves (shared with the device build)."""
    base = level_offset[level - 1]
    first, nx, ny, stride = child_grid(block_start, level_width, level_height, level, local)
    # Pass 1: merged sphere and cone, children taken one by one.
    found = False
    cx = cy = cz = rad = 0.0
    ax = ay = az = 0.0
    spread = 0.0
    for j in range(nx * ny):
        n = base + first + (j // nx) * stride + j % nx
        if radius[n] < 0:
            continue
        ocx, ocy, ocz = np.float64(centre[n, 0]), np.float64(centre[n, 1]), np.float64(centre[n, 2])
        oax, oay, oaz = np.float64(axis[n, 0]), np.float64(axis[n, 1]), np.float64(axis[n, 2])
        if not found:
            cx, cy, cz, rad = ocx, ocy, ocz, np.float64(radius[n])
            ax, ay, az, spread = oax, oay, oaz, np.float64(alpha[n])
            found = True
        else:
            cx, cy, cz, rad = grow_sphere(cx, cy, cz, rad, ocx, ocy, ocz, np.float64(radius[n]))
            ax, ay, az, spread = grow_cone(ax, ay, az, spread, oax, oay, oaz, np.float64(alpha[n]))
    if not found:
        radius[parent] = EMPTY
        far[parent] = EMPTY
        centre[parent, 0] = centre[parent, 1] = centre[parent, 2] = 0.0
        axis[parent, 0] = axis[parent, 1] = 0.0
        axis[parent, 2] = 1.0
        alpha[parent], cos_a[parent], sin_a[parent] = 0.0, 1.0, 0.0
        return
    centre[parent, 0], centre[parent, 1], centre[parent, 2] = cx, cy, cz
    # Pass 2: radius and reach measured from the stored (rounded) centre.
    qx, qy, qz = np.float64(centre[parent, 0]), np.float64(centre[parent, 1]), np.float64(centre[parent, 2])
    rad = 0.0
    reach = 0.0
    for j in range(nx * ny):
        n = base + first + (j // nx) * stride + j % nx
        if radius[n] < 0:
            continue
        gx = np.float64(centre[n, 0]) - qx
        gy = np.float64(centre[n, 1]) - qy
        gz = np.float64(centre[n, 2]) - qz
        gap = np.sqrt(gx * gx + gy * gy + gz * gz)
        rad = max(rad, gap + np.float64(radius[n]))
        reach = max(reach, gap + np.float64(far[n]))
    radius[parent] = store_length(rad)
    far[parent] = store_length(reach)
    axis[parent, 0], axis[parent, 1], axis[parent, 2] = ax, ay, az
    if spread > 0:
        spread = spread + ANGLE_SLACK
    spread = min(spread, np.pi)
    alpha[parent] = spread
    cos_a[parent] = np.cos(spread)
    sin_a[parent] = np.sin(spread)


@njit(cache=True, parallel=True)
def _inner_level(h, level):
    """Every node of ``level`` >= 1 from its children (parallel over the level's nodes)."""
    start = h.level_offset[level]
    for local in prange(h.level_offset[level + 1] - start):
        _merge_children(h, start + local, level, local)


def build_hierarchy(org, dirs, tmin, tmax, pixel, width: int, height: int, apex=None) -> RayHierarchy:
    """Cone-sphere hierarchy over a ray batch.

    org, dirs: f32[R,3]; tmin, tmax: f32[R]; pixel: i32[R] ancestral pixel y * width + x
    (-1 = padding); a lane with tmax < tmin is dead and gets no slot. apex: None, or a point
    f64[3] that every ray aims at (a point light): the rays are then indexed reversed, as
    segments leaving the apex, which gives the hierarchy zero spatial extent.
    """
    pixel = np.ascontiguousarray(pixel, np.int32)
    live = (pixel >= 0) & (tmin <= tmax)
    if np.any(pixel[live] >= width * height):
        bad = int(pixel[live].max())
        raise ValueError(f"ray pixel {bad} is outside the {width}x{height} screen grid")
    widths, heights, levels = level_grid(width, height)
    block_start, slot_ray = _sort_slots(pixel, tmin, tmax, width, int(widths[1]), int(widths[1] * heights[1]))
    n_slots = slot_ray.shape[0]
    sizes = np.r_[n_slots, widths[1:] * heights[1:]]
    level_offset = np.zeros(levels + 2, np.int64)
    np.cumsum(sizes, out=level_offset[1:])
    widths[0], heights[0] = n_slots, 1
    m = int(level_offset[-1])
    h = RayHierarchy(np.empty((m, 3), np.float32), np.empty(m, np.float32), np.empty((m, 3), np.float32),
                     np.empty(m, np.float32), np.empty(m, np.float32), np.empty(m, np.float32),
                     np.empty(m, np.float32), level_offset, widths, heights, block_start, slot_ray,
                     int(levels), int(np.diff(block_start).max(initial=0)))
    if apex is None:
        _leaf_nodes(h, org, dirs, tmin, tmax, False, 0.0, 0.0, 0.0)
    else:
        a = np.asarray(apex, np.float32).astype(np.float64)  # the stored centre is float32
        _leaf_nodes(h, org, dirs, tmin, tmax, True, a[0], a[1], a[2])
    for level in range(1, levels + 1):
        _inner_level(h, level)
    return h


def absolute_slack(h: RayHierarchy, sphere_c: np.ndarray, sphere_r: np.ndarray) -> float:
    """The test's absolute slack for these rays and spheres (f32[T,3], f32[T]): rounding of
    float32 coordinates grows with their magnitude, not with the distances involved."""
    scale = float(np.abs(h.centre[h.radius >= 0]).max(initial=0.0))
    if sphere_r.shape[0]:
        scale = max(scale, float(np.abs(sphere_c).max() + sphere_r.max()))
    return float(TEST_SLACK) * scale
