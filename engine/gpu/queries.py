"""Ray queries on the GPU: the ``RayTracer(mesh, device="cuda")`` path of ``engine.api``.

Rays given as device arrays (numba, torch, CuPy: anything with ``__cuda_array_interface__``)
are traced where they are, without a host round trip, and the answers come back as device
arrays (numba ``DeviceNDArray``, which torch and CuPy take without a copy through the same
interface). Rays given as numpy arrays are checked as the CPU path checks them, copied to the
device once, and the answers come back as numpy arrays.

Device rays must be float32 (n, 3), C-contiguous; they are not scanned for NaN or infinity (a
pass over them would cost as much as the query), and a NaN ray simply misses.
"""
from __future__ import annotations

import numpy as np

from engine.core.errors import PacketrtError
from engine.core.offset import triangle_magnitudes
from engine.core.types import Hits
from engine.gpu.bvh_trace import DeviceBVHTraversal
from engine.gpu.device import on_device, require_cuda
from engine.gpu.scene_upload import DeviceBVH, DeviceTriangles, upload

cuda = require_cuda()


class DeviceQueryError(PacketrtError):
    """Device rays of the wrong shape or type (a ValueError; the message names the argument)."""


class DeviceQueries:
    """Closest-hit and any-hit queries over one uploaded mesh and BVH (``bvh`` traversal)."""

    def __init__(self, triangles, bvh):
        self.tris = DeviceTriangles.from_host(triangles, triangle_magnitudes(triangles))
        self.bvh = DeviceBVH.from_host(bvh, triangles)
        self.traversal = DeviceBVHTraversal(self.bvh, self.tris)

    def _rays(self, origins, directions, tmin, tmax, check):
        """(org, dirs, tmin, tmax device arrays, n, on_gpu) of the query's rays."""
        org, dirs = on_device(origins), on_device(directions)
        if org is None and dirs is None:
            o, d, lo, hi = check(origins, directions, tmin, tmax)
            return upload(o), upload(d), upload(lo), upload(hi), o.shape[0], False
        if org is None or dirs is None:
            raise DeviceQueryError("origins and directions must both be device arrays or both host arrays")
        for name, array in (("origins", org), ("directions", dirs)):
            if array.dtype != np.float32 or array.ndim != 2 or array.shape[1] != 3 or not array.is_c_contiguous():
                raise DeviceQueryError(f"{name} on the device must be C-contiguous float32 (n, 3), got "
                                       f"{array.dtype} {tuple(array.shape)}")
        n = org.shape[0]
        if dirs.shape[0] != n:
            raise DeviceQueryError(f"directions has {dirs.shape[0]} rows, origins {n}")
        return org, dirs, self._bound("tmin", tmin, n, 0.0), self._bound("tmax", tmax, n, np.inf), n, True

    @staticmethod
    def _bound(name, value, n, default):
        """A device f32[n] segment bound from a scalar, a host array or a device array."""
        if value is None:
            value = default
        held = on_device(value)
        if held is not None:
            if held.dtype != np.float32 or held.shape != (n,):
                raise DeviceQueryError(f"{name} on the device must be float32 ({n},), got {held.dtype} "
                                       f"{tuple(held.shape)}")
            return held
        array = np.asarray(value, np.float32)
        if array.ndim == 0:
            array = np.full(n, array, np.float32)
        if array.shape != (n,):
            raise DeviceQueryError(f"{name} must be a scalar or ({n},), got shape {array.shape}")
        return upload(array)

    def intersect(self, origins, directions, tmin, tmax, check) -> Hits:
        """Closest hits, on the device the rays came from (``check``: the host rays' checker)."""
        org, dirs, lo, hi, n, on_gpu = self._rays(origins, directions, tmin, tmax, check)
        out = (cuda.device_array(max(n, 1), np.float32), cuda.device_array(max(n, 1), np.int32),
               cuda.device_array(max(n, 1), np.float32), cuda.device_array(max(n, 1), np.float32))
        if n:
            self.traversal.closest(org, dirs, lo, hi, None, n, 0, 0, *out)
        if on_gpu:
            return Hits(*(a[:n] for a in out))
        return Hits(*(a[:n].copy_to_host() for a in out))

    def occluded(self, origins, directions, tmin, tmax, check):
        """Any-hit flags: bool[n] on the host for host rays, u8[n] device array for device rays."""
        org, dirs, lo, hi, n, on_gpu = self._rays(origins, directions, tmin, tmax, check)
        flags = cuda.device_array(max(n, 1), np.uint8)
        if n:
            self.traversal.occluded(org, dirs, lo, hi, None, n, 0, 0, flags)
        return flags[:n] if on_gpu else flags[:n].copy_to_host().astype(bool)
