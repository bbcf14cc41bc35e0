"""Runs ``engine.gpu.rayspace.DeviceRaySpace`` on numba's CUDA simulator (a child process of
tests/test_gpu_rayspace.py, which sets NUMBA_ENABLE_CUDASIM=1 for it alone).

    python tests/gpu_sim_rayspace_check.py CASES.npz OUT.npz

CASES.npz holds the scene (``tri_<field>`` for every ``Triangles`` field) and, for each case
``<name>_<key>``: org, dir f32[C,3], tmin, tmax f32[C], pixel i32[C], and a JSON ``<name>_spec``
(query "closest" | "occluded", n, width, height, light or null, pair_budget, shadow_grid,
secondary_grid, secondary, again: run the call a second time with the same tracer). OUT.npz gets the answers (``<name>_t/prim/u/v`` or ``<name>_occluded``,
the full output arrays, whose rows past n must keep their sentinel), ``<name>_grid_pixel`` (the
device's grid pixels of rays 0 .. n-1, for a case placed on the light or the direction grid) and
``<name>_report`` (JSON: stats, seconds, or the error raised; with ``again``, the second call's
answers ``<name>_again_<key>`` and its launches found prepared or not, ``again``).
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np

from tests.cudasim import prepare  # noqa: E402

prepare()   # before engine.gpu's kernels are imported: block size, stream grid, locked shared arrays
import engine.gpu.device as device  # noqa: E402
from engine.core.types import Triangles  # noqa: E402
from engine.gpu.rayspace import DeviceRaySpace  # noqa: E402
from engine.gpu.scene_upload import DeviceTriangles, upload  # noqa: E402

SENTINEL_T = np.float32(-7.0)
SENTINEL_PRIM = -7


def main(cases_path: str, out_path: str) -> None:
    cuda = device.require_cuda()
    data = np.load(cases_path)
    tris = Triangles(*(data[f"tri_{field}"] for field in Triangles._fields))
    dtris = DeviceTriangles.from_host(tris, np.ones(tris.v0.shape[0], np.float32))
    out = {}
    names = sorted(key[: -len("_spec")] for key in data.files if key.endswith("_spec"))
    for name in names:
        spec = json.loads(str(data[f"{name}_spec"]))
        rays = [upload(data[f"{name}_{key}"]) for key in ("org", "dir", "tmin", "tmax", "pixel")]
        size = data[f"{name}_tmin"].shape[0]
        grid = spec.get("shadow_grid", "light")
        secondary_grid = spec.get("secondary_grid", "direction")
        secondary = spec.get("secondary", False)
        tracer = DeviceRaySpace(dtris, tris, pair_budget=spec["pair_budget"], shadow_grid=grid,
                                secondary_grid=secondary_grid)
        report = {}
        clock = time.perf_counter()
        try:
            if spec["query"] == "closest":
                answers = {"t": np.full(size, SENTINEL_T), "prim": np.full(size, SENTINEL_PRIM, np.int32),
                           "u": np.full(size, SENTINEL_T), "v": np.full(size, SENTINEL_T)}
                initial = answers
                dev = {key: cuda.to_device(value) for key, value in answers.items()}
                tracer.closest(*rays, spec["n"], spec["width"], spec["height"], dev["t"], dev["prim"], dev["u"],
                               dev["v"], light=spec["light"], secondary=secondary)
            else:
                initial = {"occluded": np.full(size, 7, np.uint8)}
                dev = {"occluded": cuda.to_device(initial["occluded"])}
                tracer.occluded(*rays, spec["n"], spec["width"], spec["height"], dev["occluded"],
                                light=spec["light"])
            for key, array in dev.items():
                out[f"{name}_{key}"] = array.copy_to_host()
            placed = grid == "light" if spec["light"] is not None else secondary and secondary_grid == "direction"
            if placed and spec["n"]:
                out[f"{name}_grid_pixel"] = tracer.scratch.get("grid_pixel", spec["n"], np.int32).copy_to_host()
            report["stats"] = tracer.last
            if spec.get("again"):
                # The same call into the same answer arrays (as the next frame of a static view makes):
                # every launch should find itself prepared (the same views, the same sizes).
                hits, misses = tracer.scratch.launch.hits, tracer.scratch.launch.misses
                again = dev
                for key, array in again.items():  # back to the sentinels: the call must write it all again
                    array.copy_to_device(initial[key])
                if spec["query"] == "closest":
                    tracer.closest(*rays, spec["n"], spec["width"], spec["height"], again["t"], again["prim"],
                                   again["u"], again["v"], light=spec["light"], secondary=secondary)
                else:
                    tracer.occluded(*rays, spec["n"], spec["width"], spec["height"], again["occluded"],
                                    light=spec["light"])
                for key, array in again.items():
                    out[f"{name}_again_{key}"] = array.copy_to_host()
                report["again"] = {"hits": tracer.scratch.launch.hits - hits,
                                   "misses": tracer.scratch.launch.misses - misses, "first_misses": misses}
        except Exception as error:  # reported to the parent test, which decides
            report["error"] = f"{type(error).__name__}: {error}"
        report["seconds"] = time.perf_counter() - clock
        out[f"{name}_report"] = np.array(json.dumps(report))
    np.savez(out_path, **out)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
