"""The final (ray, candidate triangle) tests of the device rayspace traversal.

The last stream holds (slot, triangle) pairs. Every pair gets the shared watertight test
(``engine.core.triangle.intersect_triangle``'s twin, with the ray's own [tmin, tmax]); the
closest hit per ray is found without sorting the pairs by ray, exactly and in any order:

1. ``nearest_t`` (per pair): t of the pair, kept; atomic min of t per ray;
2. ``nearest_prim`` (per pair): among the pairs whose t equals the ray's minimum, atomic min of
   the triangle index (the tie rule of ``closer``: smaller t, then smaller index);
3. ``merge_batch`` (per ray): the winner's (t, u, v) recomputed by the same test (the same
   inputs give the same bits) and merged with ``closer`` into the answer of earlier triangle
   batches; the batch's per-ray minima are reset for the next batch.

Occlusion is one kernel, ``any_hit``: a pair whose ray is not yet known occluded sets its flag.
"""
from __future__ import annotations

import numpy as np

from engine.core.triangle import closer, intersect_triangle, ray_shear
from engine.gpu.device import require_cuda
from engine.gpu.twin import device_twin

cuda = require_cuda()

_shear = device_twin(ray_shear)
_hit = device_twin(intersect_triangle)
_closer = device_twin(closer)

F32_INF = np.float32(np.inf)
NO_PRIM = np.int32(2**31 - 1)   # a batch's "no hit yet" (larger than every triangle index)


@cuda.jit(device=True)
def _test(org, dirs, tmin, tmax, v0, v1, v2, r, tri):
    """(t, u, v) of ray r against triangle tri: the CPU kernels' exact expressions."""
    kx, ky, kz, sx, sy, sz = _shear(dirs[r, 0], dirs[r, 1], dirs[r, 2])
    return _hit(org[r, kx], org[r, ky], org[r, kz], kx, ky, kz, sx, sy, sz, tmin[r], tmax[r], v0, v1, v2, tri)


@cuda.jit
def reset_answers(n, t_out, prim_out, u_out, v_out, best_t, best_prim):
    """Answers of rays 0 .. n-1 to misses; batch minima to empty."""
    r = cuda.grid(1)
    if r < n:
        t_out[r] = F32_INF
        prim_out[r] = -1
        u_out[r] = 0
        v_out[r] = 0
        best_t[r] = F32_INF
        best_prim[r] = NO_PRIM


@cuda.jit
def reset_flags(n, flags):
    r = cuda.grid(1)
    if r < n:
        flags[r] = 0


@cuda.jit
def nearest_t(slots, tris, n_pairs, slot_ray, org, dirs, tmin, tmax, v0, v1, v2, pair_t, best_t):
    p = cuda.grid(1)
    if p < n_pairs:
        r = slot_ray[slots[p]]
        t, _, _ = _test(org, dirs, tmin, tmax, v0, v1, v2, r, tris[p])
        pair_t[p] = t
        if t < F32_INF:
            cuda.atomic.min(best_t, r, t)


@cuda.jit
def nearest_prim(slots, tris, n_pairs, slot_ray, pair_t, best_t, best_prim):
    p = cuda.grid(1)
    if p < n_pairs:
        r = slot_ray[slots[p]]
        t = pair_t[p]
        if t < F32_INF and t == best_t[r]:
            cuda.atomic.min(best_prim, r, tris[p])


@cuda.jit
def merge_batch(n, org, dirs, tmin, tmax, v0, v1, v2, best_t, best_prim, t_out, prim_out, u_out, v_out):
    r = cuda.grid(1)
    if r < n:
        tri = best_prim[r]
        if tri != NO_PRIM:
            t, u, v = _test(org, dirs, tmin, tmax, v0, v1, v2, r, tri)
            if _closer(t, tri, t_out[r], prim_out[r]):
                t_out[r] = t
                prim_out[r] = tri
                u_out[r] = u
                v_out[r] = v
            best_t[r] = F32_INF
            best_prim[r] = NO_PRIM


@cuda.jit
def any_hit(slots, tris, n_pairs, slot_ray, org, dirs, tmin, tmax, v0, v1, v2, flags):
    p = cuda.grid(1)
    if p < n_pairs:
        r = slot_ray[slots[p]]
        if flags[r] == 0:
            t, _, _ = _test(org, dirs, tmin, tmax, v0, v1, v2, r, tris[p])
            if t < F32_INF:
                flags[r] = 1
