"""Run under numba's CUDA simulator (in its own process): ``RayTracer(device="cuda")`` against
the CPU ``RayTracer`` on host rays and on device rays. Prints one JSON object
(``tests/test_gpu_frame.py`` checks it)."""
from __future__ import annotations

import json

import numpy as np


def main() -> dict:
    from numba import cuda

    from engine.api import RayTracer
    from engine.core.errors import PacketrtError
    from scenes.catalog import load_named

    scene = load_named("whitted", {"checks": 2, "subdivisions": 0})
    cpu = RayTracer(scene, "single", "none")
    gpu = RayTracer(scene, device="cuda")
    rng = np.random.default_rng(3)
    org = np.tile(np.array([[0.0, 1.0, 6.0]], np.float32), (60, 1))
    d = (rng.random((60, 3)) - 0.5).astype(np.float32)
    d[:, 2] = -1
    tmax = np.where(rng.random(60) < 0.3, 3.0, np.inf).astype(np.float32)
    want = cpu.intersect(org, d, tmax=tmax)
    host = gpu.intersect(org, d, tmax=tmax)
    device = gpu.intersect(cuda.to_device(org), cuda.to_device(d), tmax=cuda.to_device(tmax))
    # Scalar bounds of device (and host) rays are filled on the device and kept per (count, value): the
    # same answers on the first and a repeated query, for several sizes, the keep bounded.
    dev_org, dev_d = cuda.to_device(org), cuda.to_device(d)
    scalar_equal = []
    for count, bound in ((60, 3.0), (60, 3.0), (30, 3.0), (60, np.inf), (45, 2.5), (20, 3.0), (60, 3.0)):
        got = gpu.intersect(dev_org[:count], dev_d[:count], tmax=bound)
        expected = cpu.intersect(org[:count], d[:count], tmax=bound)
        scalar_equal.append(all(np.array_equal(a.copy_to_host(), b) for a, b in zip(got, expected)))
        on_host = gpu.intersect(org[:count], d[:count], tmax=bound)  # host rays: the same filled bounds
        scalar_equal.append(all(np.array_equal(a, b) for a, b in zip(on_host, expected)))
        scalar_equal.append(bool(np.array_equal(gpu.occluded(dev_org[:count], dev_d[:count], tmin=0.5,
                                                             tmax=bound).copy_to_host() != 0,
                                                cpu.occluded(org[:count], d[:count], tmin=0.5, tmax=bound))))
    kept = len(gpu.device_queries._filled)
    # trimesh's names answer numpy arrays of trimesh's dtypes for device rays too (the device
    # answers have no astype and no comparisons on a real GPU).
    trimesh_names = []
    for name in ("intersects_first", "intersects_any", "intersects_id", "intersects_location"):
        on_device_rays = getattr(gpu, name)(cuda.to_device(org), cuda.to_device(d))
        on_cpu = getattr(cpu, name)(org, d)
        if not isinstance(on_cpu, tuple):
            on_device_rays, on_cpu = (on_device_rays,), (on_cpu,)
        trimesh_names.append(all(type(a) is np.ndarray and a.dtype == b.dtype and np.allclose(a, b)
                                 for a, b in zip(on_device_rays, on_cpu)))

    class HostTensor:
        """Host rays from a library named torch (a CPU tensor): answered as numpy rays are."""

        __module__ = "torch.fake"

        def __init__(self, array):
            self.array = array

        def __array__(self, dtype=None, copy=None):
            return self.array if dtype is None else self.array.astype(dtype)

    from_host_tensor = gpu.intersect(HostTensor(org), HostTensor(d), tmax=tmax)
    host_tensor_equal = all(np.array_equal(a, b) for a, b in zip(from_host_tensor, want)) and \
        bool(np.array_equal(gpu.occluded(HostTensor(org), HostTensor(d), tmax=tmax),
                            cpu.occluded(org, d, tmax=tmax)))
    errors = []
    for bad in (lambda: gpu.intersect(cuda.to_device(org.astype(np.float64)), cuda.to_device(d)),
                lambda: gpu.intersect(cuda.to_device(org), d),
                lambda: RayTracer(scene, "embree", device="cuda")):
        try:
            bad()
            errors.append("accepted")
        except PacketrtError as error:
            errors.append(type(error).__name__)
    image_gpu, stats = gpu.render({"render": {"width": 9, "height": 7}})
    image_cpu, _ = cpu.render({"render": {"width": 9, "height": 7}})
    # The device's own traversal name in a config that does not repeat the device (it was checked
    # as a CPU config first: "unknown traversal 'bvh'").
    named_bvh, named_stats = gpu.render({"render": {"width": 9, "height": 7}, "traversal": {"primary": "bvh"}})
    return {"hits": int((want.prim >= 0).sum()),
            "host_equal": all(np.array_equal(a, b) for a, b in zip(want, host)),
            "host_types": [type(a).__name__ for a in host],
            "device_equal": all(np.array_equal(a.copy_to_host(), b) for a, b in zip(device, want)),
            "device_stays_on_device": not isinstance(device.t, np.ndarray),
            "occluded_equal": bool(np.array_equal(gpu.occluded(org, d, tmax=tmax), cpu.occluded(org, d, tmax=tmax))),
            "scalar_bounds_equal": scalar_equal, "bounds_kept": kept, "host_tensor_equal": host_tensor_equal,
            "errors": errors, "render_difference": float(np.abs(image_gpu - image_cpu).max()),
            "render_device": stats["config"]["render"]["device"], "trimesh_names": trimesh_names,
            "counters_from": gpu.render({"render": {"width": 9, "height": 7}}, counters=True)[1]["counters_from"],
            "bvh_named_difference": float(np.abs(named_bvh - image_cpu).max()),
            "bvh_named_traversal": named_stats["config"]["traversal"]["primary"]}


if __name__ == "__main__":
    print(json.dumps(main()))
