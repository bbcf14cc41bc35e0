"""Type and lower every GPU kernel for a real GPU, on a machine without one.

numba's CUDA simulator (what ``make test`` runs the GPU code on) executes kernels as Python, so a
kernel that numba cannot type -- an int32 and an int64 unified in a loop, a local array whose shape
is not a constant, a numpy call the CUDA target lacks -- passes every simulator test and fails
only on a lent GPU, whose time is short. This check finds those here, in two child processes:

1. ``--record OUT.json`` (under ``NUMBA_ENABLE_CUDASIM=1``): runs small GPU workloads on the
   simulator -- a 5 x 4 frame with ``bvh`` and two with ``rayspace`` (secondary rays by pixel and by
   direction), the
   ``RayTracer(device="cuda")`` queries and the device refit, GPU side only -- and records every
   kernel launch's argument types (numba types of the arrays and scalars it was given);
2. ``--lower IN.json`` (numba's real CUDA target, no GPU): compiles each recorded (kernel,
   argument types) through numba's CUDA front end to LLVM IR for compute capability 9.0 (the
   H100/H200): typing, lowering and every device function it calls. Only the last step, NVVM's
   machine code, needs the CUDA toolkit's libdevice and is not run.

    python tools/gpu_lower_check.py                 # both steps; exit 1 if a kernel fails to lower
    python tools/gpu_lower_check.py --json out.json # also write the per-kernel report

``tests/test_gpu_lower_check.py`` runs it. It uses two numba-cuda internals (the device query of
``numba.cuda.dispatcher`` and ``numba.cuda.compiler.compile_cuda``); where they have moved it says
so and exits 2.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys
import tempfile
import types as pytypes
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The compute capability lowered for (H100 and H200: 9.0).
CC = (9, 0)


# -- step 1: record launches on the simulator ------------------------------------------------

def _describe(value):
    """A JSON description of a kernel argument's numba type."""
    import numba
    import numpy as np

    array = getattr(value, "_ary", value)  # the simulator's device arrays wrap a numpy array
    if isinstance(array, np.ndarray):
        kind = numba.typeof(array)
        return ["array", str(array.dtype), array.ndim, kind.layout]
    return ["scalar", str(numba.typeof(value))]


def _workloads() -> None:
    """Every device kernel, launched once on the simulator over a tiny scene (GPU side only)."""
    import numpy as np

    from engine.api import RayTracer
    from engine.core.bvh import build_bvh
    from engine.core.offset import triangle_magnitudes
    from engine.gpu.frame import GpuWhittedRenderer
    from engine.gpu.refit import DeviceRefit
    from engine.gpu.scene_upload import DeviceBVH, DeviceTriangles
    from engine.render.config import Config, PerKind, RenderConfig
    from scenes.catalog import load_named

    scene = load_named("whitted", {"checks": 2, "subdivisions": 0})
    for traversal, depth, options in (("bvh", 3, ()), ("wide", 3, ()), ("rayspace", 2, ()),
                                      ("rayspace", 2, (("rayspace", (("secondary_grid", "pixel"),)),))):
        config = Config(render=RenderConfig(width=5, height=4, max_depth=depth, packet=4, device="cuda"),
                        traversal=PerKind(*[traversal] * 4), frustum=PerKind("none", "none", "none", "none"),
                        options=options)
        GpuWhittedRenderer(scene, config).render()
    tracer = RayTracer(scene, device="cuda")
    org = np.tile(np.array([[0.0, 1.0, 6.0]], np.float32), (8, 1))
    d = np.tile(np.array([[0.1, -0.2, -1.0]], np.float32), (8, 1))
    tracer.intersect(org, d)
    tracer.occluded(org, d)
    from numba import cuda

    tracer.intersect(cuda.to_device(org), cuda.to_device(d))  # device rays: bounds filled there
    tris = scene.triangles
    bvh = build_bvh(tris)
    device_tris = DeviceTriangles.from_host(tris, triangle_magnitudes(tris))
    DeviceRefit(bvh, DeviceBVH.from_host(bvh, tris)).refit(device_tris)


def record(out: str) -> int:
    sys.path[:0] = [str(ROOT), str(ROOT / "tests")]
    from tests.cudasim import prepare

    prepare()
    from numba.cuda.simulator import kernel as simulated

    launches = {}
    original = simulated.FakeCUDAKernel.__call__

    def call(self, *args):
        if not self._device and not simulated._kernel_context:
            key = (self.fn.__module__, self.fn.__qualname__, json.dumps([_describe(a) for a in args]))
            launches[key] = launches.get(key, 0) + 1
        return original(self, *args)

    simulated.FakeCUDAKernel.__call__ = call
    _workloads()
    rows = [{"module": m, "kernel": k, "args": json.loads(a), "launches": n} for (m, k, a), n in sorted(launches.items())]
    from engine.core.atomic import write_json

    write_json(out, rows, "kernel launches")   # through a temporary file and a rename
    return 0


# -- step 2: type and lower each recorded kernel ------------------------------------------------

def _numba_type(description):
    import numba
    import numpy as np
    from numba.core import types

    if description[0] == "array":
        _, dtype, ndim, layout = description
        return types.Array(numba.from_dtype(np.dtype(dtype)), ndim, layout)
    return getattr(types, description[1])


def lower(source: str, report: str | None) -> int:
    from numba import cuda
    from numba.core import types

    try:
        import numba.cuda.dispatcher as dispatcher
        from numba.cuda.compiler import compile_cuda
    except ImportError as error:
        print(f"gpu_lower_check: numba-cuda's compiler is not where this check looks ({error})", file=sys.stderr)
        return 2
    if not hasattr(dispatcher, "get_current_device"):
        print("gpu_lower_check: numba.cuda.dispatcher.get_current_device is gone (a newer numba-cuda): "
              "the check cannot pose as a GPU", file=sys.stderr)
        return 2
    # Pose as a device of compute capability CC: device functions ask the current device for it.
    dispatcher.get_current_device = lambda: pytypes.SimpleNamespace(compute_capability=CC)
    sys.path.insert(0, str(ROOT))
    import engine.gpu.device as device

    device.require_cuda = lambda: cuda    # the kernels' modules import without a GPU
    rows = json.loads(Path(source).read_text())
    results, failed = [], 0
    for row in rows:
        name = f"{row['module']}.{row['kernel']}"
        entry = {"kernel": name, "args": row["args"], "launches": row["launches"]}
        try:
            target = importlib.import_module(row["module"])
            for part in row["kernel"].split("."):
                target = getattr(target, part)
            function = getattr(target, "py_func", None)
            if function is None:
                raise TypeError(f"{name} is not a numba CUDA kernel here ({type(target).__name__})")
            argtypes = tuple(_numba_type(d) for d in row["args"])
            result = compile_cuda(function, types.void, argtypes, cc=CC, nvvm_options={"opt": 3})
            entry["llvm_ir_chars"] = len(result.library.get_llvm_str())
        except Exception as error:  # noqa: BLE001 - every failure is reported, kernel by kernel
            failed += 1
            entry["error"] = f"{type(error).__name__}: {str(error).strip().splitlines()[0] if str(error) else ''}"
            print(f"FAILED {name}{tuple(row['args'])}: {entry['error']}", file=sys.stderr)
        results.append(entry)
    kernels = len({r["kernel"] for r in results})
    print(f"gpu_lower_check: {len(results)} launch signatures of {kernels} kernels lowered for sm_{CC[0]}{CC[1]}, "
          f"{failed} failed")
    if report:
        from engine.core.atomic import write_json

        write_json(report, results, "lowering report")
    return 1 if failed else 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--record", metavar="OUT", help="step 1 only (run under NUMBA_ENABLE_CUDASIM=1)")
    parser.add_argument("--lower", metavar="IN", help="step 2 only")
    parser.add_argument("--json", metavar="REPORT", help="write the per-kernel report here")
    args = parser.parse_args(argv)
    try:
        return _run(args)
    except (OSError, ValueError) as error:  # an unwritable --json path (PacketrtError), a full disk: one line
        print(f"gpu_lower_check: {error}", file=sys.stderr)
        return 2


def _run(args) -> int:
    if args.record:
        return record(args.record)
    if args.lower:
        return lower(args.lower, args.json)
    with tempfile.TemporaryDirectory() as folder:
        launches = os.path.join(folder, "launches.json")
        env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "PYTHONPATH": str(ROOT)}
        done = subprocess.run([sys.executable, __file__, "--record", launches], env=env, cwd=ROOT,
                              capture_output=True, text=True)
        if done.returncode != 0:
            print(f"gpu_lower_check: recording on the simulator failed:\n{done.stderr[-3000:]}", file=sys.stderr)
            return 2
        env = {k: v for k, v in env.items() if k != "NUMBA_ENABLE_CUDASIM"}
        done = subprocess.run([sys.executable, __file__, "--lower", launches]
                              + (["--json", args.json] if args.json else []), env=env, cwd=ROOT)
        return done.returncode


if __name__ == "__main__":
    sys.exit(main())
