"""One definition of the per-ray math, compiled for the CPU and for the device.

The CPU kernels call small ``@njit(cache=True, inline="always")`` helpers (the watertight
triangle test, the slab test, the shading of one lane). ``device_twin(helper, **calls)`` makes
the same Python function a CUDA device function: it re-binds the helper's code to globals in
which the helpers *it* calls are replaced by their own twins (``calls``), then hands it to
``cuda.jit(device=True)``. Nothing is written twice, so the GPU image and the CPU image come
from the same expressions in the same order and precision.

A helper that calls numpy's scalar ufuncs (``np.sqrt``) gets them as ``math`` functions on the
device (``DEVICE_NUMPY``): numba's CUDA target has no numpy ufuncs.

Why not call the ``@njit`` dispatchers from device code directly: numba's simulator (the test
suite's GPU, ``NUMBA_ENABLE_CUDASIM=1``) hands kernels fake device arrays that CPU dispatchers
cannot unbox, and the re-bound Python function runs on both.
"""
from __future__ import annotations

import math
import types

import numpy as np

from engine.gpu.device import require_cuda, simulated


def _device_numpy() -> types.ModuleType:
    """numpy's namespace with its scalar ufuncs replaced by ``math`` functions: numba's CUDA
    target compiles ``math.sqrt`` but not ``np.sqrt``. On float32 they round the same way
    (libdevice's sqrtf is correctly rounded, as numpy's float32 sqrt is); the transcendental
    ones may differ in the last bit, which the CPU helpers that use them (the ray-space cones)
    absorb in their conservative slack."""
    module = types.ModuleType("device_numpy")
    module.__dict__.update(np.__dict__)
    module.__dict__.update(sqrt=math.sqrt, sin=math.sin, cos=math.cos, arctan2=math.atan2, arccos=math.acos,
                           arcsin=math.asin, floor=math.floor, abs=abs, minimum=min, maximum=max)
    return module


DEVICE_NUMPY = _device_numpy()


def device_twin(helper, **calls):
    """The CUDA device function of ``helper`` (an ``@njit`` dispatcher or a plain function),
    with each global name in ``calls`` bound to the given device function instead."""
    cuda = require_cuda()
    function = getattr(helper, "py_func", helper)
    scope = dict(function.__globals__)
    if scope.get("np") is np and not simulated():  # the simulator runs numpy itself
        scope["np"] = DEVICE_NUMPY
    scope.update(calls)
    clone = types.FunctionType(function.__code__, scope, function.__name__, function.__defaults__,
                               function.__closure__)
    clone.__doc__ = function.__doc__
    return cuda.jit(device=True)(clone)
