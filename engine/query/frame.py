"""The mesh's own frame: geometry and rays re-expressed about the mesh's centre and scale.

float32 loses 0.06 units at 1e6 from the origin, so a mesh far from the origin (or far larger or
smaller than 1) is moved to its bounding-box centre and divided by its largest extent before its
corners are rounded to float32. Rays go through the same map in float64 (directions made unit),
so the float32 walk sees a mesh of size ~1 at the origin whatever the input (``local_ray``,
inlined into every query kernel, so no float32 copy of the rays is made). Answers come back
through ``locations`` in float64 from the float64 corners kept here.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

F32_0, F32_1 = np.float32(0.0), np.float32(1.0)
#: A ray whose origin lies this many mesh sizes (``MeshFrame.scale``) or more from the mesh's
#: centre is a miss: float32 holds such an origin, but no hit distance along it keeps a digit of
#: the mesh's size.
FAR_ORIGIN = 1e30


class MeshFrame(NamedTuple):
    """A mesh in its local frame.

    center: f64[3], scale: float   local = (world - center) / scale.
    corners: f64[T,3,3]            world-space corners (for float64 locations).
    lo, hi: f64[3]                 the mesh's box in the local frame.
    """

    center: np.ndarray
    scale: float
    corners: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def mesh_frame(vertices: np.ndarray, faces: np.ndarray) -> tuple[MeshFrame, np.ndarray]:
    """(MeshFrame, local vertices f64[V,3]) for vertices f64[V,3], faces i64[T,3]. The centre
    and scale are those of the vertices the faces use, as trimesh's ``mesh.bounds``: one stray
    vertex 1e7 sizes away shrank the mesh below float32's resolution in the local frame."""
    corners = vertices[faces.reshape(-1)] if faces.size else vertices
    lo, hi = (corners.min(axis=0), corners.max(axis=0)) if len(corners) else (np.zeros(3), np.zeros(3))
    center = (lo + hi) * 0.5
    extent = float((hi - lo).max())
    scale = extent if extent > 0 else 1.0
    local = (vertices - center) / scale
    unused = np.ones(len(vertices), np.bool_)
    unused[faces.reshape(-1)] = False
    local[unused] = 0.0  # a stray vertex, however far or NaN, is in no triangle: kept out of every check
    used = local[faces.reshape(-1)]
    frame = MeshFrame(center, scale, np.ascontiguousarray(vertices[faces]), used.min(axis=0), used.max(axis=0))
    return frame, local


@njit(cache=True, inline="always")
def local_ray(origins, directions, i, center, scale):
    """(ok, ox, oy, oz, dx, dy, dz): input ray i (origins, directions: f64[n,3], any direction
    length) in the local frame, f32, unit direction. ok is False for a NaN/inf component, a zero
    or overflowing direction, or an origin too far out for float32: such a ray is a miss."""
    norm = np.sqrt(directions[i, 0] ** 2 + directions[i, 1] ** 2 + directions[i, 2] ** 2)
    ok = norm > 0.0 and np.isfinite(norm)
    lx = (origins[i, 0] - center[0]) / scale
    ly = (origins[i, 1] - center[1]) / scale
    lz = (origins[i, 2] - center[2]) / scale
    ok = ok and abs(lx) < FAR_ORIGIN and abs(ly) < FAR_ORIGIN and abs(lz) < FAR_ORIGIN  # False for NaN too
    if not ok:
        return False, F32_0, F32_0, F32_0, F32_0, F32_0, F32_1
    return (True, np.float32(lx), np.float32(ly), np.float32(lz), np.float32(directions[i, 0] / norm),
            np.float32(directions[i, 1] / norm), np.float32(directions[i, 2] / norm))
