"""Run under numba's CUDA simulator (in its own process): the device refit of an uploaded tree
against the CPU refit of the same tree (``engine.core.bvh_refit``) for moved triangles, array
for array. Prints one JSON object (``tests/test_gpu_frame.py`` checks it)."""
from __future__ import annotations

import json

import numpy as np


def main() -> dict:
    from engine.core.bvh import build_bvh
    from engine.core.bvh_refit import refit_bvh
    from engine.core.offset import triangle_magnitudes
    from engine.gpu.refit import DeviceRefit
    from engine.gpu.scene_upload import DeviceBVH, DeviceTriangles
    from scenes.catalog import load_named

    tris = load_named("whitted", {"checks": 2, "subdivisions": 1}).triangles
    bvh = build_bvh(tris)
    device_tris = DeviceTriangles.from_host(tris, triangle_magnitudes(tris))
    device_bvh = DeviceBVH.from_host(bvh, tris)
    refit = DeviceRefit(bvh, device_bvh)
    rng = np.random.default_rng(1)
    result = {"triangles": int(tris.v0.shape[0]), "equal": []}
    for step in range(2):  # twice: the second refit starts from the first's boxes
        shift = (rng.normal(size=(tris.v0.shape[0], 3)) * 0.3).astype(np.float32)
        tris = tris._replace(v0=(tris.v0 + shift).astype(np.float32), v1=(tris.v1 + shift).astype(np.float32),
                             v2=(tris.v2 + 1.5 * shift).astype(np.float32))
        device_tris.update(tris, triangle_magnitudes(tris))
        refit.refit(device_tris)
        want = DeviceBVH.from_host(refit_bvh(bvh, tris), tris)
        result["equal"].append({name: bool(np.array_equal(getattr(device_bvh, name).copy_to_host(),
                                                          getattr(want, name).copy_to_host()))
                                for name in ("child_boxes", "root_row", "leaf_tris")})
    return result


if __name__ == "__main__":
    print(json.dumps(main()))
