"""The mesh's own frame: geometry and rays re-expressed about the mesh's centre and scale.

float32 loses 0.06 units at 1e6 from the origin, so a mesh far from the origin (or far larger or
smaller than 1) is moved to its bounding-box centre and divided by its largest extent before its
corners are rounded to float32. Rays go through the same map in float64 (directions made unit),
so the float32 walk sees a mesh of size ~1 at the origin whatever the input. Answers come back
through ``locations`` in float64 from the float64 corners kept here.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from engine.core.triangle import HUGE_INV


class MeshFrame(NamedTuple):
    """A mesh in its local frame.

    center: f64[3], scale: float   local = (world - center) / scale.
    corners: f64[T,3,3]            world-space corners (for float64 locations).
    """

    center: np.ndarray
    scale: float
    corners: np.ndarray


def mesh_frame(vertices: np.ndarray, faces: np.ndarray) -> tuple[MeshFrame, np.ndarray]:
    """(MeshFrame, local vertices f64[V,3]) for vertices f64[V,3], faces i64[T,3]."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    center = (lo + hi) * 0.5
    extent = float((hi - lo).max())
    scale = extent if extent > 0 else 1.0
    local = (vertices - center) / scale
    return MeshFrame(center, scale, np.ascontiguousarray(vertices[faces])), local


@njit(cache=True, parallel=True)
def local_rays_kernel(origins, directions, order, center, scale, org, dirs, inv, valid):
    """Rays into the local frame, gathered into walk order (row k is input ray order[k]), so
    the walk reads its rays front to back.

    origins, directions: f64[n,3] world rays (any direction length). center: f64[3].
    Writes org, dirs, inv: f32[n,3] (local origin, unit direction, safe 1/dir) and valid: bool[n]
    (False for a NaN/inf component, a zero direction, or an origin too far out for float32;
    such rows are answered as misses).
    """
    for k in prange(origins.shape[0]):
        i = order[k]
        ok = True
        norm = 0.0
        for a in range(3):
            if not (np.isfinite(origins[i, a]) and np.isfinite(directions[i, a])):
                ok = False
            norm += directions[i, a] * directions[i, a]
        norm = np.sqrt(norm)
        if not (norm > 0.0 and np.isfinite(norm)):
            ok = False
        for a in range(3):
            o = (origins[i, a] - center[a]) / scale if ok else 0.0
            if abs(o) > 1e30:
                ok = False
        valid[k] = ok
        for a in range(3):
            if ok:
                org[k, a] = np.float32((origins[i, a] - center[a]) / scale)
                df = np.float32(directions[i, a] / norm)
                dirs[k, a] = df
                if df == 0:
                    inv[k, a] = np.float32(HUGE_INV) if not np.signbit(df) else -np.float32(HUGE_INV)
                else:
                    inv[k, a] = np.float32(1.0) / df
            else:
                org[k, a] = 0
                dirs[k, a] = 1 if a == 2 else 0
                inv[k, a] = HUGE_INV if a != 2 else 1


def local_rays(frame: MeshFrame, origins: np.ndarray, directions: np.ndarray, order: np.ndarray):
    """(org, dirs, inv f32[n,3], valid bool[n]) for f64 world rays, row k = input ray order[k]."""
    n = origins.shape[0]
    org = np.empty((n, 3), np.float32)
    dirs = np.empty((n, 3), np.float32)
    inv = np.empty((n, 3), np.float32)
    valid = np.empty(n, np.bool_)
    local_rays_kernel(origins, directions, order, frame.center, float(frame.scale), org, dirs, inv, valid)
    return org, dirs, inv, valid
