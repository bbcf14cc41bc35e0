"""``RayTracer(device="cuda")`` on a real GPU: host rays and device rays (torch, CuPy), checked
against the CPU API and timed.

On a GPU machine (after ``. tools/gpu_device_setup.sh``):

    python3 tools/gpu_api_check.py                       # bunny and kitchen, 1024² camera rays
    python3 tools/gpu_api_check.py --scene bunny --out api.json

For each scene: the camera's rays at ``--side``² and as many incoherent rays (origins in the
scene's box, uniform directions), traced by the CPU ``RayTracer`` (every core) and by the GPU
one given numpy arrays, torch tensors and CuPy arrays. It counts the rays whose triangle differs
from the CPU's, checks that the answers of device rays are device arrays that torch takes
without a copy (the same memory), and times each way of calling: median of ``--repeat`` calls,
each waited for, rays already where the caller holds them. The simulator tests
(``tests/test_gpu_frame.py``) check the answers on tiny scenes; this is the check with a real
driver, real torch and CuPy, and real sizes.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def camera_rays(scene, side: int):
    """(origins f32[n,3], directions f32[n,3]) of the scene's camera at side x side."""
    from engine.core.scratch import Scratch
    from engine.render.camera import camera_batch

    rays = camera_batch(scene, side, side, 8, Scratch().allocator("camera"))[0]
    return np.ascontiguousarray(rays.org, np.float32), np.ascontiguousarray(rays.dir, np.float32)


def incoherent_rays(scene, n: int, seed: int = 7):
    """n rays from uniform points of the scene's box in uniform directions."""
    rng = np.random.default_rng(seed)
    v = scene.triangles.v0
    lo, hi = v.min(axis=0), v.max(axis=0)
    origins = rng.uniform(lo, hi, size=(n, 3)).astype(np.float32)
    directions = rng.normal(size=(n, 3)).astype(np.float32)
    return origins, directions


def timed(call, repeat: int, wait) -> float:
    """Median seconds of ``call()`` followed by ``wait()``, after one untimed call."""
    call()
    wait()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        call()
        wait()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def check_scene(name: str, side: int, repeat: int) -> dict:
    import cupy
    import torch

    from engine.api import RayTracer
    from scenes.catalog import load_named

    scene = load_named(name)
    cpu = RayTracer(scene)
    gpu = RayTracer(scene, device="cuda")
    wait = torch.cuda.synchronize
    record = {"scene": name, "triangles": int(scene.n_triangles), "sets": []}
    for label, (org, dirs) in (("camera", camera_rays(scene, side)),
                               ("incoherent", incoherent_rays(scene, side * side))):
        n = org.shape[0]
        expected = cpu.intersect(org, dirs)
        host = gpu.intersect(org, dirs)
        t_org, t_dirs = torch.as_tensor(org, device="cuda"), torch.as_tensor(dirs, device="cuda")
        c_org, c_dirs = cupy.asarray(org), cupy.asarray(dirs)
        t_lo = torch.zeros(n, device="cuda", dtype=torch.float32)
        t_hi = torch.full((n,), float("inf"), device="cuda", dtype=torch.float32)
        on_torch = gpu.intersect(t_org, t_dirs)
        on_cupy = gpu.intersect(c_org, c_dirs)
        as_tensor = torch.as_tensor(on_torch.prim, device="cuda")
        zero_copy = as_tensor.data_ptr() == on_torch.prim.__cuda_array_interface__["data"][0]
        torch_prim = as_tensor.cpu().numpy()
        cupy_prim = cupy.asnumpy(cupy.asarray(on_cupy.prim))
        occluded_cpu = cpu.occluded(org, dirs, tmax=1.0)
        occluded_gpu = torch.as_tensor(gpu.occluded(t_org, t_dirs, tmax=1.0), device="cuda").cpu().numpy() != 0
        seconds = {
            "numpy in, numpy out": timed(lambda: gpu.intersect(org, dirs), repeat, wait),
            "torch in, device out": timed(lambda: gpu.intersect(t_org, t_dirs), repeat, wait),
            "torch in with torch tmin/tmax": timed(lambda: gpu.intersect(t_org, t_dirs, tmin=t_lo, tmax=t_hi),
                                                   repeat, wait),
            "cupy in, device out": timed(lambda: gpu.intersect(c_org, c_dirs), repeat, wait),
            "torch occluded, tmax 1": timed(lambda: gpu.occluded(t_org, t_dirs, tmax=1.0), repeat, wait),
            "cpu api, numpy": timed(lambda: cpu.intersect(org, dirs), max(3, repeat // 3), lambda: None),
        }
        differs = np.flatnonzero(host.prim != expected.prim)
        both = differs[(host.prim[differs] >= 0) & (expected.prim[differs] >= 0)]
        gap = np.abs(host.t[both] - expected.t[both]) / np.maximum(np.abs(expected.t[both]), 1e-30)
        row = {"rays": label, "count": n,
               "differing": {"both_hit": int(both.size), "one_misses": int(differs.size - both.size),
                             "same_t": int((gap == 0).sum()), "within_1e-6": int((gap <= 1e-6).sum()),
                             "largest_relative_t_gap": float(gap.max()) if gap.size else 0.0},
               "prim_differs": {"numpy": int((host.prim != expected.prim).sum()),
                                "torch": int((torch_prim != expected.prim).sum()),
                                "cupy": int((cupy_prim != expected.prim).sum())},
               "occluded_differs": int((occluded_gpu != occluded_cpu).sum()),
               "hits": int((expected.prim >= 0).sum()), "torch_zero_copy": bool(zero_copy),
               "ms": {k: 1e3 * v for k, v in seconds.items()},
               "grays_per_s": {k: n / v / 1e9 for k, v in seconds.items()}}
        record["sets"].append(row)
        print(f"{name} {label} {n:,} rays: prim differs numpy/torch/cupy {row['prim_differs']}, occluded differs "
              f"{row['occluded_differs']}, torch zero-copy {zero_copy}; differing: {row['differing']}")
        for k, v in seconds.items():
            print(f"  {k:32s} {1e3 * v:8.3f} ms  {n / v / 1e9:6.2f} Grays/s")
    return record


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", action="append", help="catalog scene (repeatable; default bunny and kitchen)")
    parser.add_argument("--side", type=int, default=1024, help="camera rays side (and side² incoherent rays)")
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--out", help="JSON of the results")
    args = parser.parse_args(argv)
    from engine.gpu.device import device_name

    results = {"device": device_name(),
               "scenes": [check_scene(s, args.side, args.repeat) for s in (args.scene or ["bunny", "bart-kitchen"])]}
    if args.out:
        from engine.core.atomic import write_json

        write_json(args.out, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
