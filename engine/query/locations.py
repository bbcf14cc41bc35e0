"""Hit points in float64, from the mesh's float64 corners rather than the float32 walk.

A hit's point is where the ray meets its triangle's plane, computed in float64 from the world
corners and the ray (so it lies on the ray and on the triangle's plane to float64 rounding,
as trimesh's locations do); when the ray runs (nearly) inside that plane, it is the hit's
barycentric point (1-u-v) c0 + u c1 + v c2 instead.
"""
import numpy as np
from numba import njit, prange


@njit(cache=True, parallel=True)
def locations_kernel(corners, origins, directions, index_ray, index_tri, u, v, out):
    """out (f64[m,3]) for hits (index_ray, index_tri i64[m]; u, v f32[m]) of rays with world
    origins and directions f64[n,3] (any length); corners: f64[T,3,3]."""
    for h in prange(index_ray.shape[0]):
        r = index_ray[h]
        f = index_tri[h]
        dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
        e1x = corners[f, 1, 0] - corners[f, 0, 0]
        e1y = corners[f, 1, 1] - corners[f, 0, 1]
        e1z = corners[f, 1, 2] - corners[f, 0, 2]
        e2x = corners[f, 2, 0] - corners[f, 0, 0]
        e2y = corners[f, 2, 1] - corners[f, 0, 1]
        e2z = corners[f, 2, 2] - corners[f, 0, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        # The normal scaled to a largest component of 1: it grows as the mesh's size squared, and
        # the plane distance below as its cube, which underflowed to t = 0 for a mesh 1e-120 across.
        largest = max(abs(nx), abs(ny), abs(nz))
        if largest > 0:
            nx, ny, nz = nx / largest, ny / largest, nz / largest
        denom = nx * dx + ny * dy + nz * dz
        size = np.sqrt(nx * nx + ny * ny + nz * nz) * np.sqrt(dx * dx + dy * dy + dz * dz)
        if abs(denom) > 1e-9 * size:
            t = (nx * (corners[f, 0, 0] - origins[r, 0]) + ny * (corners[f, 0, 1] - origins[r, 1])
                 + nz * (corners[f, 0, 2] - origins[r, 2])) / denom
            out[h, 0] = origins[r, 0] + t * dx
            out[h, 1] = origins[r, 1] + t * dy
            out[h, 2] = origins[r, 2] + t * dz
        else:
            bu = np.float64(u[h])
            bv = np.float64(v[h])
            for a in range(3):
                out[h, a] = (1.0 - bu - bv) * corners[f, 0, a] + bu * corners[f, 1, a] + bv * corners[f, 2, a]
