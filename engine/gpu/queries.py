"""Ray queries on the GPU: the ``RayTracer(mesh, device="cuda")`` path of ``engine.api``.

Rays given as device arrays (numba, torch, CuPy: anything with ``__cuda_array_interface__``)
are traced where they are, without a host round trip, and the answers come back as device
arrays (numba ``DeviceNDArray``, which torch and CuPy take without a copy through the same
interface). Rays given as numpy arrays are checked as the CPU path checks them, copied to the
device once, and the answers come back as numpy arrays. The answers to torch or CuPy rays
live in memory from that library's own allocator (``answer_arrays``).

Device rays must be float32 (n, 3), C-contiguous; they are not scanned for NaN or infinity (a
pass over them would cost as much as the query), and a NaN ray simply misses.
"""
from __future__ import annotations

import numpy as np

from engine.core.errors import PacketrtError
from engine.core.offset import triangle_magnitudes
from engine.core.types import Hits
from engine.gpu.bvh_trace import DeviceBVHTraversal
from engine.gpu.device import BLOCK, blocks, on_device, require_cuda
from engine.gpu.fill import fill_array
from engine.gpu.scene_upload import DeviceBVH, DeviceTriangles, upload

cuda = require_cuda()


def answer_arrays(rays):
    """``new(n, dtype)``: a device array of max(n, 1) elements for a query's answers, from the
    allocator of the library the device rays came from (``rays``: the caller's origins, None
    for host rays) -- torch's caching allocator for torch tensors,
    CuPy's memory pool for CuPy arrays -- seen as a numba device array (which keeps the tensor
    alive). Elsewhere numba's own ``device_array``, a cudaMalloc per array (see the README's
    "The API on the GPU" for what each costs)."""
    library = type(rays).__module__.split(".")[0]
    if library == "torch":
        import torch

        dtypes = {np.dtype(np.float32): torch.float32, np.dtype(np.int32): torch.int32,
                  np.dtype(np.uint8): torch.uint8}

        def new(n, dtype):
            fresh = torch.empty(max(n, 1), dtype=dtypes[np.dtype(dtype)], device=rays.device)
            return cuda.as_cuda_array(fresh, sync=False)  # fresh memory: no stream work to wait for
        return new
    if library == "cupy":
        import cupy

        def new(n, dtype):
            with rays.device:
                return cuda.as_cuda_array(cupy.empty(max(n, 1), dtype), sync=False)
        return new
    return lambda n, dtype: cuda.device_array(max(n, 1), dtype)


class DeviceQueryError(PacketrtError):
    """Device rays of the wrong shape or type (a ValueError; the message names the argument)."""


class DeviceQueries:
    """Closest-hit and any-hit queries over one uploaded mesh and BVH (``bvh`` traversal)."""

    #: Scalar segment bounds kept filled on the device, per (ray count, value): a query's
    #: default tmin and tmax are not made again for the next query of the same size.
    KEPT_BOUNDS = 4

    def __init__(self, triangles, bvh):
        self.tris = DeviceTriangles.from_host(triangles, triangle_magnitudes(triangles))
        self.bvh = DeviceBVH.from_host(bvh, triangles)
        self.traversal = DeviceBVHTraversal(self.bvh, self.tris)
        self._filled = {}  # (n, f32 bits) -> device f32[n]; read only by the kernels

    def _rays(self, origins, directions, tmin, tmax, check):
        """(org, dirs, tmin, tmax device arrays, n, on_gpu) of the query's rays."""
        org, dirs = on_device(origins), on_device(directions)
        if org is None and dirs is None:
            o, d, lo, hi = check(origins, directions, tmin, tmax)
            n = o.shape[0]
            # Checked: a scalar bound is filled on the device like a device ray's, not uploaded.
            lo = self._bound("tmin", tmin, n, 0.0) if np.ndim(tmin) == 0 else upload(lo)
            hi = self._bound("tmax", tmax, n, np.inf) if np.ndim(tmax) == 0 else upload(hi)
            return upload(o), upload(d), lo, hi, n, False
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

    def _bound(self, name, value, n, default):
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
            # Filled on the device, once per size and value (at most KEPT_BOUNDS kept, 4 bytes
            # a ray each): a host array of n copies and its upload, or a fresh device array
            # each query, cost more than the walk (measured: the README's GPU section, "The API").
            key = (n, array.tobytes())
            filled = self._filled.get(key)
            if filled is None:
                filled = cuda.device_array(max(n, 1), np.float32)
                fill_array[blocks(n), BLOCK](filled, n, array[()])
                if len(self._filled) >= self.KEPT_BOUNDS:
                    self._filled.pop(next(iter(self._filled)))
                self._filled[key] = filled
            return filled
        if array.shape != (n,):
            raise DeviceQueryError(f"{name} must be a scalar or ({n},), got shape {array.shape}")
        return upload(array)

    def intersect(self, origins, directions, tmin, tmax, check) -> Hits:
        """Closest hits, on the device the rays came from (``check``: the host rays' checker)."""
        org, dirs, lo, hi, n, on_gpu = self._rays(origins, directions, tmin, tmax, check)
        new = answer_arrays(origins if on_gpu else None)  # host rays (torch CPU tensors too): numba's
        out = (new(n, np.float32), new(n, np.int32), new(n, np.float32), new(n, np.float32))
        if n:
            self.traversal.closest(org, dirs, lo, hi, None, n, 0, 0, *out)
        if on_gpu:
            return Hits(*(a[:n] for a in out))
        return Hits(*(a[:n].copy_to_host() for a in out))

    def occluded(self, origins, directions, tmin, tmax, check):
        """Any-hit flags: bool[n] on the host for host rays, u8[n] device array for device rays."""
        org, dirs, lo, hi, n, on_gpu = self._rays(origins, directions, tmin, tmax, check)
        flags = answer_arrays(origins if on_gpu else None)(n, np.uint8)
        if n:
            self.traversal.occluded(org, dirs, lo, hi, None, n, 0, 0, flags)
        return flags[:n] if on_gpu else flags[:n].copy_to_host().astype(bool)
