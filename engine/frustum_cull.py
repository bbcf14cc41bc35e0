"""Frustum culling kernels shared by the packet traversals.

A packet's frustum (``engine.types.Frusta``: four planes (nx, ny, nz, d), a point p inside when
n.p + d >= 0) bounds every ray of the packet over the part of it that can meet geometry. The
builders (``frusta/``) already widen the planes by a margin that covers float32 rounding here
and in the watertight triangle test, so these tests are plain evaluations:

- ``load_frustum``: copy packet k's planes into a local f32[16] in SoA order (nx[4], ny[4],
  nz[4], d[4]) so the 4-plane loops below vectorise;
- ``frustum_misses_box``: the box lies entirely outside one plane (its corner farthest along
  the plane normal is outside), so no ray of the packet can hit anything in it;
- ``frustum_misses_triangle``: all three corners lie outside one plane.

Both are conservative only: "False" never means that some ray hits.
"""
from __future__ import annotations

import numpy as np
from numba import njit

F32_ZERO = np.float32(0.0)


@njit(cache=True)
def load_frustum(planes, valid, k, fr):
    """Copy packet k's planes (f32[K,4,4]) into fr (f32[16]); False when valid[k] is False."""
    if not valid[k]:
        return False
    for p in range(4):
        fr[p] = planes[k, p, 0]
        fr[4 + p] = planes[k, p, 1]
        fr[8 + p] = planes[k, p, 2]
        fr[12 + p] = planes[k, p, 3]
    return True


@njit(cache=True)
def frustum_misses_box(fr, bmin, bmax, node):
    """True when box ``node`` (bmin, bmax: f32[N,3]) is outside one of the planes in fr."""
    b0x = bmin[node, 0]
    b0y = bmin[node, 1]
    b0z = bmin[node, 2]
    b1x = bmax[node, 0]
    b1y = bmax[node, 1]
    b1z = bmax[node, 2]
    outside = False
    for p in range(4):
        nx = fr[p]
        ny = fr[4 + p]
        nz = fr[8 + p]
        # The box corner farthest along n: the per-axis max of the two products.
        s = max(nx * b0x, nx * b1x) + max(ny * b0y, ny * b1y) + max(nz * b0z, nz * b1z) + fr[12 + p]
        outside |= s < F32_ZERO
    return outside


@njit(cache=True)
def frustum_misses_triangle(fr, v0, v1, v2, tri):
    """True when triangle ``tri`` (corners v0, v1, v2: f32[T,3]) is outside one plane in fr."""
    outside = False
    for p in range(4):
        nx = fr[p]
        ny = fr[4 + p]
        nz = fr[8 + p]
        d = fr[12 + p]
        s0 = nx * v0[tri, 0] + ny * v0[tri, 1] + nz * v0[tri, 2]
        s1 = nx * v1[tri, 0] + ny * v1[tri, 1] + nz * v1[tri, 2]
        s2 = nx * v2[tri, 0] + ny * v2[tri, 1] + nz * v2[tri, 2]
        outside |= max(s0, max(s1, s2)) + d < F32_ZERO
    return outside
