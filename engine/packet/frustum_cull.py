"""Frustum culling kernels shared by the packet traversals.

A packet's frustum (``engine.core.types.Frusta``: four planes (nx, ny, nz, d), a point p inside when
n.p + d >= 0) bounds every ray of the packet over the part of it that can meet geometry. The
builders (``frusta/``) already widen the planes by a margin that covers float32 rounding here
and in the watertight triangle test, so these tests are plain evaluations:

- ``load_frustum``: copy packet k's planes into a local f32[16] in SoA order (nx[4], ny[4],
  nz[4], d[4]) so the tests below handle the four planes as one vector (``engine.packet.simd4``);
- ``frustum_misses_box``: the box lies entirely outside one plane (its corner farthest along
  the plane normal is outside), so no ray of the packet can hit anything in it;
- ``frustum_misses_triangle``: all three corners lie outside one plane.

Both are conservative only: "False" never means that some ray hits.
"""
from __future__ import annotations

from numba import njit

from engine.packet.simd4 import planes4_box, planes4_triangle


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
def frustum_misses_box(fr, box):
    """True when ``box`` (x0, y0, z0, x1, y1, z1) is outside one of the planes in fr: the box
    corner farthest along the plane normal is outside it."""
    return planes4_box(fr, box[0], box[1], box[2], box[3], box[4], box[5])


@njit(cache=True, inline="always")
def frustum_misses_triangle(fr, v0, v1, v2, tri):
    """True when triangle ``tri`` (corners v0, v1, v2: f32[T,3]) is outside one plane in fr."""
    return planes4_triangle(fr, v0[tri, 0], v0[tri, 1], v0[tri, 2], v1[tri, 0], v1[tri, 1], v1[tri, 2],
                            v2[tri, 0], v2[tri, 1], v2[tri, 2])
