"""The intersection kernels every CPU traversal shares.

- ``ray_shear``: per-ray set-up of the watertight test (axis permutation and shear).
- ``intersect_triangle``: the watertight ray-triangle test of Woop, Benthin and Wald,
  "Watertight Ray/Triangle Intersection" (JCGT 2013). Because every traversal calls
  this one function with the same per-ray inputs, they all compute bit-identical
  (t, u, v) for a (ray, triangle) pair.
- ``closer``: the one tie-breaking rule (smaller t, then smaller triangle index), so the
  closest hit does not depend on the order a traversal visits triangles in.
- ``slab_test``: the conservative ray-AABB test of one ray (the packet kernels' 4-lane
  version is ``engine.packet.simd4.slab4``).

All arithmetic is float32; constants are float32 globals so numba does not promote.
"""
import numpy as np
from numba import njit

F32_INF = np.float32(np.inf)
F32_ZERO = np.float32(0.0)
F32_ONE = np.float32(1.0)
# Slack for the slab test's rounding, 2*gamma(3) of Ize (2013), so a box never loses a
# ray that the watertight triangle test would accept on its boundary.
SLAB_SLACK = np.float32(2.0 * 3.0 * 2.0 ** -24 / (1.0 - 3.0 * 2.0 ** -24))
# 1/0 replacement in inv_dir: large but finite, so (b - o) * inv never makes NaN.
HUGE_INV = np.float32(1e30)


@njit(cache=True)
def ray_shear(dx, dy, dz):
    """Axis permutation and shear for one ray direction.

    Returns (kx, ky, kz, sx, sy, sz): kz is the dominant axis, kx/ky the others (swapped
    when d[kz] < 0 to keep the winding), and sx = d[kx]/d[kz], sy = d[ky]/d[kz],
    sz = 1/d[kz]. The direction must not be zero.
    """
    ax, ay, az = abs(dx), abs(dy), abs(dz)
    if ax >= ay and ax >= az:
        kz = 0
        dkz = dx
    elif ay >= az:
        kz = 1
        dkz = dy
    else:
        kz = 2
        dkz = dz
    kx = kz + 1
    if kx == 3:
        kx = 0
    ky = kx + 1
    if ky == 3:
        ky = 0
    if dkz < F32_ZERO:
        kx, ky = ky, kx
    dkx = dx if kx == 0 else (dy if kx == 1 else dz)
    dky = dx if ky == 0 else (dy if ky == 1 else dz)
    return kx, ky, kz, dkx / dkz, dky / dkz, F32_ONE / dkz


@njit(cache=True)
def intersect_triangle(okx, oky, okz, kx, ky, kz, sx, sy, sz, tmin, tmax, v0, v1, v2, tri):
    """Watertight ray-triangle test.

    okx, oky, okz: the ray origin's components along kx, ky, kz (from ``ray_shear``).
    v0, v1, v2: f32[T,3] triangle corners; tri: the triangle index.
    Returns (t, u, v) with t in [tmin, tmax], or (inf, 0, 0) on a miss. u, v are the
    barycentrics of v1 and v2. Shared edges and vertices are never missed: the edge
    functions of two triangles sharing an edge see the same transformed vertices.
    """
    ax_ = v0[tri, kx] - okx
    ay_ = v0[tri, ky] - oky
    az_ = v0[tri, kz] - okz
    bx_ = v1[tri, kx] - okx
    by_ = v1[tri, ky] - oky
    bz_ = v1[tri, kz] - okz
    cx_ = v2[tri, kx] - okx
    cy_ = v2[tri, ky] - oky
    cz_ = v2[tri, kz] - okz
    ax = ax_ - sx * az_
    ay = ay_ - sy * az_
    bx = bx_ - sx * bz_
    by = by_ - sy * bz_
    cx = cx_ - sx * cz_
    cy = cy_ - sy * cz_
    # Edge functions from exact float32 products in double: the sign is then exact, so two
    # triangles sharing an edge always agree on which side the ray passes. (Rounding them in
    # float32, with a double fallback only on an exact zero, lets neighbours disagree and
    # rays aimed at shared vertices slip through.)
    eu = np.float32(np.float64(cx) * np.float64(by) - np.float64(cy) * np.float64(bx))
    ev = np.float32(np.float64(ax) * np.float64(cy) - np.float64(ay) * np.float64(cx))
    ew = np.float32(np.float64(bx) * np.float64(ay) - np.float64(by) * np.float64(ax))
    if (eu < F32_ZERO or ev < F32_ZERO or ew < F32_ZERO) and \
            (eu > F32_ZERO or ev > F32_ZERO or ew > F32_ZERO):
        return F32_INF, F32_ZERO, F32_ZERO
    det = eu + ev + ew
    if det == F32_ZERO:
        return F32_INF, F32_ZERO, F32_ZERO
    scaled_t = eu * (sz * az_) + ev * (sz * bz_) + ew * (sz * cz_)
    rcp = F32_ONE / det
    t = scaled_t * rcp
    if not (t >= tmin and t <= tmax):
        return F32_INF, F32_ZERO, F32_ZERO
    return t, ev * rcp, ew * rcp


@njit(cache=True)
def closer(t, tri, best_t, best_tri):
    """True when a hit (t, tri) beats the current best: smaller t, ties to the smaller index."""
    return t < best_t or (t == best_t and tri < best_tri)


@njit(cache=True)
def slab_interval(ox, oy, oz, ix, iy, iz, tmin, tmax, x0, y0, z0, x1, y1, z1):
    """Conservative ray-box test of one ray against the box (x0, y0, z0)-(x1, y1, z1): the
    entry distance (>= tmin) when the ray's [tmin, tmax] overlaps the box, else inf. The one
    box test of the CPU walks and, as a device twin, of the GPU's (``engine.gpu.bvh_trace``)."""
    t0 = (x0 - ox) * ix
    t1 = (x1 - ox) * ix
    tn = min(t0, t1)
    tf = max(t0, t1)
    t0 = (y0 - oy) * iy
    t1 = (y1 - oy) * iy
    tn = max(tn, min(t0, t1))
    tf = min(tf, max(t0, t1))
    t0 = (z0 - oz) * iz
    t1 = (z1 - oz) * iz
    tn = max(tn, min(t0, t1))
    tf = min(tf, max(t0, t1))
    tn = max(tn - abs(tn) * SLAB_SLACK, tmin)
    tf = min(tf + abs(tf) * SLAB_SLACK, tmax)
    if tn <= tf:
        return tn
    return F32_INF


@njit(cache=True)
def slab_test(ox, oy, oz, ix, iy, iz, tmin, tmax, bmin, bmax, node):
    """Conservative ray-box test for one ray against node ``node`` of bmin, bmax (f32[N,3]);
    ix, iy, iz: the ray's inv_dir (finite). See ``slab_interval``."""
    return slab_interval(ox, oy, oz, ix, iy, iz, tmin, tmax, bmin[node, 0], bmin[node, 1], bmin[node, 2],
                         bmax[node, 0], bmax[node, 1], bmax[node, 2])


def safe_inverse(directions: np.ndarray) -> np.ndarray:
    """1/d for f32[R,3] directions, zero components mapped to +-HUGE_INV (never inf or NaN)."""
    d = np.asarray(directions, np.float32)
    safe = np.where(d == 0, np.copysign(np.float32(1.0) / HUGE_INV, d), d)
    with np.errstate(divide="ignore", over="ignore"):
        inv = (np.float32(1.0) / safe).astype(np.float32)
    return np.ascontiguousarray(inv)
