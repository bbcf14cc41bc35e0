"""Robust secondary-ray origins: where a hit is, and how far to step off its surface.

Two sources of error put a naive origin on the wrong side of the surface it leaves:

* ``org + t * dir`` carries the rounding of ``t`` times the ray's length, which is on the order
  of the last digit of the coordinates it travelled through. ``hit_points`` instead evaluates
  the hit from the triangle's exact corners and the barycentrics in double precision: that
  point lies in the triangle's plane up to one float32 rounding of its own coordinates.
* The intersection kernel moves the triangle's corners to the ray origin in float32, so it
  decides the side of the plane only to within a few ulps of the *largest* coordinate
  involved, the triangle's corners included. A per-coordinate offset (Wald, "Ray Tracing
  Gems" ch. 6) is too small when the hit lies near zero on one axis of a large triangle (a
  floor at y = 0 with x, z in the hundreds).

So ``offset_origin`` steps along the geometric normal by ``OFFSET_SCALE`` times that largest
magnitude: 32 to 64 ulps of it, well above the 0.5-ulp rounding of the point and the kernel's
few-ulp translation error, and 4e-6 of the scene's extent, far below any visible gap. The
side is chosen by the caller: towards the incoming ray for reflections and shadow rays, away
from it for refraction.
"""
import numpy as np

#: Step off the surface, relative to the largest coordinate magnitude in play (2^-18).
OFFSET_SCALE = np.float32(2.0 ** -18)
#: Floor of that magnitude, for geometry that sits at the origin itself.
MIN_MAGNITUDE = np.float32(2.0 ** -40)


def hit_points(tris, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Hit points on triangles ``prim`` (i32[M]) at barycentrics u, v (f32[M]) -> f32[M,3].

    Evaluated in double from the exact corners and rounded once, so each point is within
    half an ulp per coordinate of the triangle's plane.
    """
    u = np.asarray(u, np.float64)[:, None]
    v = np.asarray(v, np.float64)[:, None]
    p = (1 - u - v) * tris.v0[prim].astype(np.float64) + u * tris.v1[prim] + v * tris.v2[prim]
    return p.astype(np.float32)


def triangle_magnitudes(tris) -> np.ndarray:
    """Largest |coordinate| among each triangle's corners -> f32[T] (computed once per scene)."""
    # Column by column: numpy's reduction along the short last axis of an (N, 3) array is slow
    # (12 ms for the kitchen, paid every animation frame); maxima are exact either way.
    m = np.abs(tris.v0[:, 0])
    for corner in (tris.v0, tris.v1, tris.v2):
        for axis in range(3):
            np.maximum(m, np.abs(corner[:, axis]), out=m)
    return m.astype(np.float32)


def coordinate_magnitude(tris, prim: np.ndarray, points: np.ndarray, corners: np.ndarray | None = None) -> np.ndarray:
    """Largest |coordinate| among each hit's triangle corners and the hit point -> f32[M].
    ``corners``: ``triangle_magnitudes(tris)`` when the caller keeps it (saves three gathers)."""
    if corners is None:
        corners = triangle_magnitudes(tris)
    return np.maximum(np.abs(points).max(axis=1), corners[prim]).astype(np.float32)


def offset_origin(points: np.ndarray, normals: np.ndarray, magnitude: np.ndarray | None = None) -> np.ndarray:
    """points f32[M,3], unit normals f32[M,3] (pointing to the side to leave towards),
    magnitude f32[M] (see ``coordinate_magnitude``; default: each point's own largest
    |coordinate|) -> f32[M,3] origins ``OFFSET_SCALE * magnitude`` off the surface."""
    p = np.ascontiguousarray(points, np.float32)
    n = np.asarray(normals, np.float32)
    if magnitude is None:
        magnitude = np.abs(p).max(axis=1)
    step = OFFSET_SCALE * np.maximum(np.asarray(magnitude, np.float32), MIN_MAGNITUDE)
    return (p + step[:, None] * n).astype(np.float32)
