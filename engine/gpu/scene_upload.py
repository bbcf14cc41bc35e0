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


@dataclass
class DeviceBVH:
    """``engine.core.types.BVH`` on the device: bmin, bmax f32[N,3]; first, count i32[N];
    prim i32[P]; depth (host int: the traversal stack holds depth + 2 entries)."""

    bmin: object
    bmax: object
    first: object
    count: object
    prim: object
    depth: int

    @classmethod
    def from_host(cls, bvh) -> "DeviceBVH":
        return cls(upload(bvh.bmin, np.float32), upload(bvh.bmax, np.float32), upload(bvh.first, np.int32),
                   upload(bvh.count, np.int32), upload(bvh.prim, np.int32), int(bvh.depth))

    def refit_from(self, bvh) -> None:
        """Copy a refitted tree's boxes (same topology) into the uploaded arrays."""
        self.bmin.copy_to_device(np.ascontiguousarray(bvh.bmin, np.float32))
        self.bmax.copy_to_device(np.ascontiguousarray(bvh.bmax, np.float32))
