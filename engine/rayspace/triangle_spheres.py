"""Bounding spheres of triangles: the only view of the scene the ray-space hierarchy needs.

The smallest enclosing sphere of a triangle is centred at the midpoint of its longest edge
when the triangle is right or obtuse (that sphere already holds the third corner), else at
its circumcentre. Computed in float64, stored as float32 with the radius rounded up (subnormal radii included) and
measured from the stored (rounded) centre, so every corner is inside the stored sphere.
Recomputed from the vertices on every call: nothing to refit for dynamic scenes.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

# Relative growth of a float64 radius before it is rounded to float32 (2^-20 >> one float32 ulp).
RADIUS_GROWTH = 1.0 + 2.0 ** -20
# And an absolute one: the float32 subnormals' ulp, 2^-149. Below 2^-126 an ulp is no longer
# relative, and a radius of 1.98e-45 rounded to nearest gave 1.4e-45: a triangle of corners
# (0,0,0), (0,0,0), (0,1.4e-45,1.4e-45) left a corner outside its sphere (hypothesis found it).
# Adding one subnormal ulp before rounding to nearest never rounds below the float64 radius.
RADIUS_FLOOR = 2.0 ** -149


@njit(cache=True)
def smallest_sphere(ax, ay, az, bx, by, bz, cx, cy, cz):
    """Centre (float64 x, y, z) of the smallest sphere holding the points a, b, c."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    bcx, bcy, bcz = cx - bx, cy - by, cz - bz
    ab2 = abx * abx + aby * aby + abz * abz
    ac2 = acx * acx + acy * acy + acz * acz
    bc2 = bcx * bcx + bcy * bcy + bcz * bcz
    # A corner with a non-acute angle sits inside the sphere over the opposite (longest) edge.
    if ab2 + ac2 <= bc2:
        return 0.5 * (bx + cx), 0.5 * (by + cy), 0.5 * (bz + cz)
    if ab2 + bc2 <= ac2:
        return 0.5 * (ax + cx), 0.5 * (ay + cy), 0.5 * (az + cz)
    if ac2 + bc2 <= ab2:
        return 0.5 * (ax + bx), 0.5 * (ay + by), 0.5 * (az + bz)
    # Acute: circumcentre a + (|ac|^2 (n x ab) + |ab|^2 (ac x n)) / (2 |n|^2), n = ab x ac.
    nx = aby * acz - abz * acy
    ny = abz * acx - abx * acz
    nz = abx * acy - aby * acx
    n2 = nx * nx + ny * ny + nz * nz
    if n2 == 0.0:  # unreachable for an acute triangle, kept so rounding can never divide by 0
        return (ax + bx + cx) / 3.0, (ay + by + cy) / 3.0, (az + bz + cz) / 3.0
    px = ac2 * (ny * abz - nz * aby) + ab2 * (acy * nz - acz * ny)
    py = ac2 * (nz * abx - nx * abz) + ab2 * (acz * nx - acx * nz)
    pz = ac2 * (nx * aby - ny * abx) + ab2 * (acx * ny - acy * nx)
    scale = 0.5 / n2
    return ax + px * scale, ay + py * scale, az + pz * scale


@njit(cache=True, inline="always")
def store_sphere(v0, v1, v2, i, centre, radius):
    """Writes triangle i's sphere into centre f32[T,3], radius f32[T] (the body of
    ``triangle_spheres``, shared with the device)."""
    ax, ay, az = np.float64(v0[i, 0]), np.float64(v0[i, 1]), np.float64(v0[i, 2])
    bx, by, bz = np.float64(v1[i, 0]), np.float64(v1[i, 1]), np.float64(v1[i, 2])
    cx, cy, cz = np.float64(v2[i, 0]), np.float64(v2[i, 1]), np.float64(v2[i, 2])
    sx, sy, sz = smallest_sphere(ax, ay, az, bx, by, bz, cx, cy, cz)
    centre[i, 0] = np.float32(sx)
    centre[i, 1] = np.float32(sy)
    centre[i, 2] = np.float32(sz)
    # Measure from the rounded centre so the stored sphere really holds the corners.
    qx, qy, qz = np.float64(centre[i, 0]), np.float64(centre[i, 1]), np.float64(centre[i, 2])
    r2 = max((ax - qx) ** 2 + (ay - qy) ** 2 + (az - qz) ** 2,
             (bx - qx) ** 2 + (by - qy) ** 2 + (bz - qz) ** 2,
             (cx - qx) ** 2 + (cy - qy) ** 2 + (cz - qz) ** 2)
    radius[i] = np.float32(np.sqrt(r2) * RADIUS_GROWTH + RADIUS_FLOOR)


@njit(cache=True, parallel=True)
def triangle_spheres(v0, v1, v2):
    """Bounding spheres of T triangles.

    v0, v1, v2: f32[T,3] corners. Returns (centre f32[T,3], radius f32[T]); every corner lies
    within radius of centre in exact arithmetic on the stored float32 values.
    """
    n = v0.shape[0]
    centre = np.empty((n, 3), np.float32)
    radius = np.empty(n, np.float32)
    for i in prange(n):
        store_sphere(v0, v1, v2, i, centre, radius)
    return centre, radius
