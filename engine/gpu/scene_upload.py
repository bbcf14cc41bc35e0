"""The scene's triangles and BVH on the device, uploaded once per scene (or per animation frame).

The BVH is the one ``engine.core.bvh`` builds for the CPU, in the same flat layout (node boxes
bmin/bmax f32[N,3], first/count i32[N], prim i32[P]); the GPU traversal reads it as it is.
Triangle arrays keep their CPU shapes, so the shared watertight test (``engine.core.triangle``)
reads them with the same indexing on both targets.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.gpu.device import require_cuda


def upload(array: np.ndarray, dtype=None):
    """A C-contiguous device copy of ``array`` (an empty array becomes one row of zeros, since
    CUDA cannot allocate zero bytes and kernels check the logical count instead)."""
    cuda = require_cuda()
    host = np.ascontiguousarray(array, dtype=dtype or array.dtype)
    if host.size == 0:
        host = np.zeros((1,) + host.shape[1:], host.dtype)
    return cuda.to_device(host)


@dataclass
class DeviceTriangles:
    """T triangles on the device. vec: f32[4,T,3] the stack of v0, v1, v2, ng (f32[T,3] views of
    it: one argument carries all four to a kernel); material: i32[T]; normals
    f32[T,3,3] and uvs f32[T,3,2] (one zero row when the scene has none: ``has_normals`` and
    ``has_uvs`` say); magnitude f32[T] (``engine.core.offset.triangle_magnitudes``)."""

    vec: object
    material: object
    normals: object
    uvs: object
    magnitude: object
    count: int
    has_normals: bool
    has_uvs: bool

    @classmethod
    def from_host(cls, tris, magnitude: np.ndarray) -> "DeviceTriangles":
        vec = upload(np.stack([tris.v0, tris.v1, tris.v2, tris.ng]).astype(np.float32))
        return cls(vec, upload(tris.material, np.int32), upload(tris.normals, np.float32),
                   upload(tris.uvs, np.float32), upload(magnitude, np.float32), int(tris.v0.shape[0]),
                   bool(tris.normals.shape[0] > 0), bool(tris.uvs.shape[0] > 0))

    def __post_init__(self):
        # Views of the stack, made once (a view made per launch costs host time every frame).
        self.v0, self.v1, self.v2, self.ng = (self.vec[k] for k in range(4))

    def fits(self, tris) -> bool:
        """True when ``tris`` can be copied into these arrays (same count, same attributes)."""
        return (self.count == tris.v0.shape[0] and self.has_normals == (tris.normals.shape[0] > 0)
                and self.has_uvs == (tris.uvs.shape[0] > 0))

    def update(self, tris, magnitude: np.ndarray) -> None:
        """Copy moved triangles (an animation's next frame) into the arrays, in place, so every
        prepared launch that holds them stays valid."""
        self.vec.copy_to_device(np.stack([tris.v0, tris.v1, tris.v2, tris.ng]).astype(np.float32))
        self.material.copy_to_device(np.ascontiguousarray(tris.material, np.int32))
        if self.has_normals:
            self.normals.copy_to_device(np.ascontiguousarray(tris.normals, np.float32))
        if self.has_uvs:
            self.uvs.copy_to_device(np.ascontiguousarray(tris.uvs, np.float32))
        self.magnitude.copy_to_device(np.ascontiguousarray(magnitude, np.float32))


def child_box_table(bvh) -> np.ndarray:
    """f32[N,12]: for each inner node, its left child's box (min xyz, max xyz) then its right
    child's; zeros for leaves. Both boxes a node's walk tests come from one 48-byte row."""
    inner = np.flatnonzero(bvh.count == 0)
    left = bvh.first[inner]
    table = np.zeros((bvh.bmin.shape[0], 12), np.float32)
    table[inner, 0:3], table[inner, 3:6] = bvh.bmin[left], bvh.bmax[left]
    table[inner, 6:9], table[inner, 9:12] = bvh.bmin[left + 1], bvh.bmax[left + 1]
    return table


def _leaf_corners(bvh, tris) -> np.ndarray:
    """f32[3,P,3]: the corners of triangle prim[i] at row i (leaf order)."""
    return np.stack([tris.v0[bvh.prim], tris.v1[bvh.prim], tris.v2[bvh.prim]]).astype(np.float32)


def _root_row(bvh) -> np.ndarray:
    return np.concatenate([bvh.bmin[0], bvh.bmax[0]]).astype(np.float32)[None, :]


@dataclass
class DeviceBVH:
    """``engine.core.types.BVH`` on the device, laid out for a per-ray walk.

    child_boxes f32[N,12] (``child_box_table``); links i32[N,2]: (first, count) of each node as
    the CPU tree has them; prim i32[P]; leaf_tris f32[3,P,3]: the corners v0, v1, v2 of
    triangle prim[i] at row i, so a leaf's triangles are read from consecutive rows; root_row
    f32[1,6] the root's box (min xyz, max xyz); depth (host int). host_bvh: the host tree it
    holds (the device ``wide`` traversal collapses it), host_prim: that tree's ``prim``.
    """

    child_boxes: object
    links: object
    prim: object
    leaf_tris: object
    root_row: object
    depth: int

    @classmethod
    def from_host(cls, bvh, tris) -> "DeviceBVH":
        links = np.stack([bvh.first, bvh.count], axis=1).astype(np.int32)
        made = cls(upload(child_box_table(bvh)), upload(links), upload(bvh.prim, np.int32),
                   upload(_leaf_corners(bvh, tris)), upload(_root_row(bvh)), int(bvh.depth))
        made.host_prim = bvh.prim
        made.host_bvh = bvh
        return made

    def same_topology(self, bvh) -> bool:
        """True for a refit of the uploaded tree: the same node links and primitive order (a
        refit keeps the build's ``prim`` array, ``engine.core.bvh_refit``)."""
        return bvh.prim is self.host_prim

    def __post_init__(self):
        self.v0, self.v1, self.v2 = (self.leaf_tris[k] for k in range(3))
        self.host_prim = None
        self.host_bvh = None
