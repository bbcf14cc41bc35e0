"""The shared kernel's own answer: every ray against every triangle, no hierarchy at all.

The reference for traversal tests that must not depend on what a BVH or a ray-space
hierarchy culls: a traversal is right when it returns exactly this.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from engine.core.triangle import F32_INF, closer, intersect_triangle, ray_shear


@njit(cache=True, parallel=True)
def brute_force(org, dirs, tmin, tmax, v0, v1, v2, out_t, out_prim):
    """Closest hit of every ray (org, dirs f32[R,3]; tmin, tmax f32[R]) over every triangle
    (v0, v1, v2 f32[T,3]) with the shared kernel and tie rule -> out_t f32[R], out_prim i32[R]."""
    for r in prange(org.shape[0]):
        best_t, best_prim = F32_INF, -1
        if tmin[r] <= tmax[r]:
            kx, ky, kz, sx, sy, sz = ray_shear(dirs[r, 0], dirs[r, 1], dirs[r, 2])
            for tri in range(v0.shape[0]):
                t, _, _ = intersect_triangle(org[r, kx], org[r, ky], org[r, kz], kx, ky, kz, sx, sy, sz,
                                             tmin[r], tmax[r], v0, v1, v2, tri)
                if t < F32_INF and closer(t, tri, best_t, best_prim):
                    best_t, best_prim = t, tri
        out_t[r] = best_t
        out_prim[r] = best_prim


def kernel_answer(rays, tris) -> tuple[np.ndarray, np.ndarray]:
    """(t f32[R], prim i32[R]) of ``brute_force`` for a RayBatch."""
    n = rays.org.shape[0]
    t = np.empty(n, np.float32)
    prim = np.empty(n, np.int32)
    brute_force(rays.org, rays.dir, rays.tmin, rays.tmax, tris.v0, tris.v1, tris.v2, t, prim)
    return t, prim
